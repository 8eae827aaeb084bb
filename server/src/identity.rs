//! Fresh ids and content digests for stored resources (models, datasets, jobs). Owns nothing else:
//! no storage, no naming (resource names are `spoofwatch_proto::wire::names`).

/// A fresh short random id (48 bits of a v4 UUID, hex).
pub fn new_id() -> String {
    uuid::Uuid::new_v4().simple().to_string()[..12].to_string()
}

/// Lower-case hex SHA-256 of stored blobs (models, datasets).
pub fn sha256_hex(bytes: &[u8]) -> String {
    sha256_hex_of_pieces([bytes])
}

/// Lower-case hex SHA-256 of the concatenation of `pieces`.
pub fn sha256_hex_of_pieces<'a>(pieces: impl IntoIterator<Item = &'a [u8]>) -> String {
    use sha2::{Digest, Sha256};
    let mut hasher = Sha256::new();
    for piece in pieces {
        hasher.update(piece);
    }
    hasher
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}
