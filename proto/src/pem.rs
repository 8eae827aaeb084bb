//! The TLS files both ends read at startup: a PEM file of certificates or of a private key, read
//! and checked before it is handed to tonic, so that a wrong file is named with why at once.
//!
//! Owns the reading and the checks and their reasons. Must not know the flags the files come from
//! or build a TLS configuration (each end wraps the reason in its own error, with its flag).

use std::path::Path;

use rustls_pki_types::pem::PemObject;
use rustls_pki_types::{CertificateDer, PrivateKeyDer};

/// The bytes of a PEM file holding at least one certificate; otherwise why not.
pub fn certificates(path: &Path) -> Result<Vec<u8>, String> {
    let pem = read(path)?;
    let mut count = 0;
    for item in CertificateDer::pem_slice_iter(&pem) {
        item.map_err(|e| format!("not valid PEM: {e}"))?;
        count += 1;
    }
    if count == 0 {
        return Err("holds no PEM certificate (-----BEGIN CERTIFICATE-----)".to_string());
    }
    Ok(pem)
}

/// The bytes of a PEM file holding a private key; otherwise why not.
pub fn private_key(path: &Path) -> Result<Vec<u8>, String> {
    let pem = read(path)?;
    PrivateKeyDer::from_pem_slice(&pem)
        .map_err(|e| format!("holds no usable PEM private key (PKCS#8, PKCS#1 or SEC1): {e}"))?;
    Ok(pem)
}

fn read(path: &Path) -> Result<Vec<u8>, String> {
    std::fs::read(path).map_err(|e| format!("cannot read: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_that_is_missing_or_not_pem_says_why() {
        let dir = std::env::temp_dir().join(format!("spoofwatch-pem-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("a directory");
        let not_pem = dir.join("not.pem");
        std::fs::write(&not_pem, "hello").expect("written");
        let missing = certificates(&dir.join("missing.pem")).expect_err("missing");
        assert!(missing.starts_with("cannot read: "), "{missing}");
        let no_certificate = certificates(&not_pem).expect_err("no certificate");
        assert!(
            no_certificate.starts_with("holds no PEM certificate"),
            "{no_certificate}"
        );
        let no_key = private_key(&not_pem).expect_err("no key");
        assert!(
            no_key.starts_with("holds no usable PEM private key"),
            "{no_key}"
        );
        std::fs::remove_dir_all(&dir).expect("removed");
    }
}
