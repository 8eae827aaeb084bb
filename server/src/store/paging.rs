//! Keyset pagination over `(created_at, id)`, newest first, with opaque page tokens.
//!
//! Keyset (rather than offset) pages stay correct while rows are inserted or deleted between calls:
//! the token names the last row returned and the next page starts strictly after it. This module
//! owns the token format and the one way a listing query is cut into a page ([`PagePlan`]: a
//! listing binds its cursor and `LIMIT`, then [`PagePlan::finish`] cuts the rows);
//! it must not know any table.

use super::StoreError;

/// Page size used when a request asks for 0.
pub const DEFAULT_PAGE_SIZE: u32 = 50;

/// Larger requested page sizes are lowered to this.
pub const MAX_PAGE_SIZE: u32 = 500;

/// Which page of a listing to return.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PageRequest {
    /// Maximum rows to return; 0 means [`DEFAULT_PAGE_SIZE`], values above [`MAX_PAGE_SIZE`] are capped.
    pub page_size: u32,
    /// The `next_page_token` of the previous page, or `None` for the first page.
    pub page_token: Option<String>,
}

impl PageRequest {
    /// The first page with `page_size` rows at most.
    pub fn first(page_size: u32) -> PageRequest {
        PageRequest {
            page_size,
            page_token: None,
        }
    }

    /// The page following the one that returned `token`.
    pub fn after(page_size: u32, token: impl Into<String>) -> PageRequest {
        PageRequest {
            page_size,
            page_token: Some(token.into()),
        }
    }

    /// The effective page size after applying the default and the cap.
    pub fn effective_size(&self) -> u32 {
        match self.page_size {
            0 => DEFAULT_PAGE_SIZE,
            size => size.min(MAX_PAGE_SIZE),
        }
    }
}

/// One page of a listing.
#[derive(Debug, Clone, PartialEq)]
pub struct Page<T> {
    /// The rows, newest first.
    pub items: Vec<T>,
    /// Token for the next page, `None` on the last page.
    pub next_page_token: Option<String>,
}

/// The keyset position a page starts after: `(created_at, id)` of the previous page's last row.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Cursor {
    pub(crate) created_at_ms: i64,
    pub(crate) id: String,
}

/// A decoded request: how many rows to fetch and where to start.
pub(crate) struct PagePlan {
    /// Rows to return.
    pub(crate) size: u32,
    /// Start strictly after this position; `None` for the first page.
    pub(crate) cursor: Option<Cursor>,
}

impl PagePlan {
    /// Decodes `request` for the listing named `listing` (tokens from another listing are rejected).
    pub(crate) fn new(
        listing: &'static str,
        request: &PageRequest,
    ) -> Result<PagePlan, StoreError> {
        let cursor = match request.page_token.as_deref() {
            None | Some("") => None,
            Some(token) => Some(decode_token(listing, token)?),
        };
        Ok(PagePlan {
            size: request.effective_size(),
            cursor,
        })
    }

    /// `LIMIT` to bind: one extra row reveals whether another page follows.
    pub(crate) fn fetch_limit(&self) -> i64 {
        i64::from(self.size) + 1
    }

    /// Cursor `created_at` to bind (NULL on the first page).
    pub(crate) fn after_created_at(&self) -> Option<i64> {
        self.cursor.as_ref().map(|cursor| cursor.created_at_ms)
    }

    /// Cursor id to bind (NULL on the first page).
    pub(crate) fn after_id(&self) -> Option<&str> {
        self.cursor.as_ref().map(|cursor| cursor.id.as_str())
    }

    /// Cuts the fetched rows (at most `fetch_limit`) down to a page and makes its next-page token.
    pub(crate) fn finish<T>(
        &self,
        listing: &'static str,
        mut rows: Vec<T>,
        key: impl Fn(&T) -> (i64, &str),
    ) -> Page<T> {
        let size = usize::try_from(self.size).unwrap_or(usize::MAX);
        let has_more = rows.len() > size;
        rows.truncate(size);
        let next_page_token = match rows.last() {
            Some(last) if has_more => {
                let (created_at_ms, id) = key(last);
                Some(encode_token(listing, created_at_ms, id))
            }
            _ => None,
        };
        Page {
            items: rows,
            next_page_token,
        }
    }
}

/// Token layout before hex encoding: `v1|<listing>|<created_at_ms>|<id>`. Hex keeps it opaque and
/// URL-safe without another dependency; ids may contain any character, so `id` comes last.
fn encode_token(listing: &str, created_at_ms: i64, id: &str) -> String {
    let plain = format!("v1|{listing}|{created_at_ms}|{id}");
    plain.bytes().map(|byte| format!("{byte:02x}")).collect()
}

fn decode_token(listing: &str, token: &str) -> Result<Cursor, StoreError> {
    let bytes = hex_decode(token).ok_or(StoreError::InvalidPageToken)?;
    let plain = String::from_utf8(bytes).map_err(|_| StoreError::InvalidPageToken)?;
    let mut parts = plain.splitn(4, '|');
    let (Some("v1"), Some(token_listing), Some(created_at), Some(id)) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(StoreError::InvalidPageToken);
    };
    if token_listing != listing {
        return Err(StoreError::InvalidPageToken);
    }
    let created_at_ms = created_at
        .parse::<i64>()
        .map_err(|_| StoreError::InvalidPageToken)?;
    Ok(Cursor {
        created_at_ms,
        id: id.to_owned(),
    })
}

fn hex_decode(text: &str) -> Option<Vec<u8>> {
    if !text.len().is_multiple_of(2) {
        return None;
    }
    text.as_bytes()
        .chunks(2)
        .map(|pair| {
            let high = char::from(pair[0]).to_digit(16)?;
            let low = char::from(pair[1]).to_digit(16)?;
            u8::try_from(high * 16 + low).ok()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn token_round_trips_ids_with_separators() {
        let token = encode_token("models", 1_700_000_000_123, "a|b c/é");
        let cursor = decode_token("models", &token).expect("own token decodes");
        assert_eq!(
            cursor,
            Cursor {
                created_at_ms: 1_700_000_000_123,
                id: "a|b c/é".to_owned()
            }
        );
    }

    #[test]
    fn token_from_another_listing_is_rejected() {
        let token = encode_token("jobs", 5, "x");
        assert!(matches!(
            decode_token("models", &token),
            Err(StoreError::InvalidPageToken)
        ));
    }

    #[test]
    fn malformed_tokens_are_rejected() {
        for token in ["zz", "abc", "7631", &encode_token("models", 1, "x")[2..]] {
            assert!(
                matches!(
                    decode_token("models", token),
                    Err(StoreError::InvalidPageToken)
                ),
                "token {token:?} should be rejected"
            );
        }
        let not_a_number: String = "v1|models|12x|id"
            .bytes()
            .map(|byte| format!("{byte:02x}"))
            .collect();
        assert!(matches!(
            decode_token("models", &not_a_number),
            Err(StoreError::InvalidPageToken)
        ));
    }

    #[test]
    fn page_size_defaults_and_caps() {
        assert_eq!(PageRequest::first(0).effective_size(), DEFAULT_PAGE_SIZE);
        assert_eq!(PageRequest::first(7).effective_size(), 7);
        assert_eq!(PageRequest::first(100_000).effective_size(), MAX_PAGE_SIZE);
    }
}
