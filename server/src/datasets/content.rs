//! A dataset's bytes held as pieces of at most [`PIECE_BYTES`]. An upload grows a piece at a time,
//! never by copying what it already holds into a larger buffer, so a dataset costs its own size
//! once; the store keeps one row per piece, and parsers read the pieces in order.
//!
//! Owns the piece layout. Must not parse CSV nor touch the store.

use std::io::{self, Read, Write};

/// The size of every piece but the last.
pub const PIECE_BYTES: usize = 1 << 20;

/// Dataset bytes: the concatenation of `pieces`, in order.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Content {
    pieces: Vec<Vec<u8>>,
    len: usize,
}

impl Content {
    /// Content made of stored pieces (of any sizes), in order.
    pub fn from_pieces(pieces: Vec<Vec<u8>>) -> Self {
        let len = pieces.iter().map(Vec::len).sum();
        Self { pieces, len }
    }

    /// Appends `bytes`, filling the last piece before starting another.
    pub fn extend(&mut self, mut bytes: &[u8]) {
        while !bytes.is_empty() {
            let piece = match self.pieces.last_mut() {
                Some(piece) if piece.len() < PIECE_BYTES => piece,
                _ => {
                    // Allocated at full size once, so appending never reallocates and copies.
                    self.pieces.push(Vec::with_capacity(PIECE_BYTES));
                    self.pieces.last_mut().expect("just pushed")
                }
            };
            let taken = bytes.len().min(PIECE_BYTES - piece.len());
            piece.extend_from_slice(&bytes[..taken]);
            self.len += taken;
            bytes = &bytes[taken..];
        }
    }

    /// Gives back the unused room of the last piece (call when nothing more will be appended).
    pub fn finish(mut self) -> Self {
        if let Some(last) = self.pieces.last_mut() {
            last.shrink_to_fit();
        }
        self
    }

    /// Length in bytes.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether there are no bytes.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The pieces, for the store.
    pub fn into_pieces(self) -> Vec<Vec<u8>> {
        self.pieces
    }

    /// Reads the bytes in order.
    pub fn reader(&self) -> impl Read + '_ {
        PiecesReader {
            rest: &self.pieces,
            current: &[],
        }
    }

    /// Lower-case hex SHA-256 of the bytes.
    pub fn sha256_hex(&self) -> String {
        crate::identity::sha256_hex_of_pieces(self.pieces.iter().map(Vec::as_slice))
    }
}

impl Write for Content {
    fn write(&mut self, bytes: &[u8]) -> io::Result<usize> {
        self.extend(bytes);
        Ok(bytes.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// [`Content::reader`]: the current piece's unread part, then the pieces after it.
struct PiecesReader<'a> {
    rest: &'a [Vec<u8>],
    current: &'a [u8],
}

impl Read for PiecesReader<'_> {
    fn read(&mut self, out: &mut [u8]) -> io::Result<usize> {
        while self.current.is_empty() {
            let Some((next, rest)) = self.rest.split_first() else {
                return Ok(0);
            };
            self.current = next;
            self.rest = rest;
        }
        self.current.read(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_are_kept_in_full_pieces_and_read_back_in_order() {
        let bytes: Vec<u8> = (0..(2 * PIECE_BYTES + 300))
            .map(|i| (i % 251) as u8)
            .collect();
        let mut content = Content::default();
        // Odd-sized appends that straddle piece boundaries.
        for chunk in bytes.chunks(PIECE_BYTES / 3 + 7) {
            content.extend(chunk);
        }
        let content = content.finish();
        assert_eq!(content.len(), bytes.len());
        let mut read_back = Vec::new();
        content.reader().read_to_end(&mut read_back).expect("read");
        assert_eq!(read_back, bytes);
        assert_eq!(content.sha256_hex(), crate::identity::sha256_hex(&bytes));
        let pieces = content.into_pieces();
        let sizes: Vec<usize> = pieces.iter().map(Vec::len).collect();
        assert_eq!(sizes, [PIECE_BYTES, PIECE_BYTES, 300]);
    }

    #[test]
    fn stored_pieces_of_any_size_read_as_one_stream() {
        let content = Content::from_pieces(vec![b"ab".to_vec(), Vec::new(), b"cde".to_vec()]);
        assert_eq!(content.len(), 5);
        let mut text = String::new();
        content.reader().read_to_string(&mut text).expect("read");
        assert_eq!(text, "abcde");
        assert!(Content::default().is_empty());
        assert_eq!(
            Content::default().sha256_hex(),
            "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
        );
    }
}
