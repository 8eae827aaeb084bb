//! Fresh ids and content digests for stored resources (models, datasets, jobs). Owns nothing else:
//! no storage, no naming (resource names are `spoofwatch_proto::wire::names`).

/// A fresh short random id (48 bits of a v4 UUID, hex).
pub fn new_id() -> String {
    uuid::Uuid::new_v4().simple().to_string()[..12].to_string()
}

/// Lower-case hex SHA-256 of stored blobs (models, datasets).
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::{Digest, Sha256};
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}
