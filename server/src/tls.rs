//! The server's TLS settings: the certificate, key and optional client CA the configuration names,
//! read and parsed once at startup, so that a wrong or unreadable file is reported by its flag and
//! path before the server takes a connection. tonic does the handshakes (also on the vetted
//! connections of `incoming`), bounded by the handshake timeout.

use std::path::{Path, PathBuf};

use spoofwatch_proto::pem;
use tonic::transport::{Certificate, Identity, Server, ServerTlsConfig};

use crate::config::Config;
use crate::error_chain::error_chain;

/// Why the TLS settings cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// Only one of certificate and key is configured.
    #[error("--tls-cert and --tls-key go together: {given} is set, {missing} is not")]
    Incomplete {
        given: &'static str,
        missing: &'static str,
    },
    /// A client CA without a server certificate (mutual TLS needs TLS).
    #[error("--tls-client-ca needs --tls-cert and --tls-key")]
    ClientCaWithoutTls,
    /// A file cannot be read or holds no usable PEM item.
    #[error("{flag} {}: {reason}", path.display())]
    File {
        flag: &'static str,
        path: PathBuf,
        reason: String,
    },
    /// rustls refused the combination (e.g. the key does not belong to the certificate).
    #[error("--tls-cert/--tls-key: {0}")]
    Refused(String),
}

/// What the server speaks, for the startup log.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Transport {
    Plaintext,
    Tls,
    MutualTls,
}

impl Transport {
    pub fn as_str(self) -> &'static str {
        match self {
            Transport::Plaintext => "plaintext (no TLS)",
            Transport::Tls => "TLS",
            Transport::MutualTls => "mutual TLS (client certificates required)",
        }
    }
}

/// `server` speaking TLS as `config` says (unchanged for plaintext). tonic runs the handshakes on
/// the vetted connections, each bounded by the handshake timeout.
pub fn configure(server: Server, config: &Config) -> Result<Server, TlsError> {
    match server_tls(config)? {
        None => Ok(server),
        Some(tls) => server
            .tls_config(tls)
            .map_err(|e| TlsError::Refused(error_chain(&e))),
    }
}

/// The TLS configuration of `config` (`None`: plaintext), with every file read and checked.
pub fn server_tls(config: &Config) -> Result<Option<ServerTlsConfig>, TlsError> {
    let (cert, key) = match (&config.tls_cert, &config.tls_key) {
        (None, None) if config.tls_client_ca.is_some() => return Err(TlsError::ClientCaWithoutTls),
        (None, None) => return Ok(None),
        (Some(_), None) => {
            return Err(TlsError::Incomplete {
                given: "--tls-cert",
                missing: "--tls-key",
            });
        }
        (None, Some(_)) => {
            return Err(TlsError::Incomplete {
                given: "--tls-key",
                missing: "--tls-cert",
            });
        }
        (Some(cert), Some(key)) => (cert, key),
    };
    let cert_pem = certificates_pem("--tls-cert", cert)?;
    let key_pem = key_pem("--tls-key", key)?;
    let mut tls = ServerTlsConfig::new()
        .identity(Identity::from_pem(cert_pem, key_pem))
        .timeout(config.handshake_timeout());
    if let Some(ca) = &config.tls_client_ca {
        tls = tls.client_ca_root(Certificate::from_pem(certificates_pem(
            "--tls-client-ca",
            ca,
        )?));
    }
    Ok(Some(tls))
}

/// What `config` makes the server speak.
pub fn transport(config: &Config) -> Transport {
    match (&config.tls_cert, &config.tls_client_ca) {
        (None, _) => Transport::Plaintext,
        (Some(_), None) => Transport::Tls,
        (Some(_), Some(_)) => Transport::MutualTls,
    }
}

/// The bytes of a PEM file holding at least one certificate.
fn certificates_pem(flag: &'static str, path: &Path) -> Result<Vec<u8>, TlsError> {
    pem::certificates(path).map_err(|reason| file_error(flag, path, reason))
}

/// The bytes of a PEM file holding a private key.
fn key_pem(flag: &'static str, path: &Path) -> Result<Vec<u8>, TlsError> {
    pem::private_key(path).map_err(|reason| file_error(flag, path, reason))
}

fn file_error(flag: &'static str, path: &Path, reason: impl Into<String>) -> TlsError {
    TlsError::File {
        flag,
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(cert: Option<&Path>, key: Option<&Path>, ca: Option<&Path>) -> Config {
        Config {
            tls_cert: cert.map(Path::to_path_buf),
            tls_key: key.map(Path::to_path_buf),
            tls_client_ca: ca.map(Path::to_path_buf),
            ..Config::default()
        }
    }

    #[test]
    fn without_files_the_server_is_plaintext_and_half_a_pair_is_refused() {
        let none = config(None, None, None);
        assert!(matches!(server_tls(&none), Ok(None)));
        assert_eq!(transport(&none), Transport::Plaintext);
        let cert_only = config(Some(Path::new("c.pem")), None, None);
        assert!(matches!(
            server_tls(&cert_only),
            Err(TlsError::Incomplete { .. })
        ));
        let ca_only = config(None, None, Some(Path::new("ca.pem")));
        assert!(matches!(
            server_tls(&ca_only),
            Err(TlsError::ClientCaWithoutTls)
        ));
    }

    #[test]
    fn an_unreadable_or_wrong_file_is_named_with_its_flag() {
        let dir = tempfile::tempdir().expect("temp dir");
        let missing = dir.path().join("missing.pem");
        let not_pem = dir.path().join("not.pem");
        std::fs::write(&not_pem, "hello").expect("written");
        let error = server_tls(&config(Some(&missing), Some(&not_pem), None))
            .expect_err("missing certificate file");
        let text = error.to_string();
        assert!(
            text.starts_with("--tls-cert ") && text.contains("missing.pem"),
            "{text}"
        );
        assert!(text.contains("cannot read"), "{text}");

        let error = server_tls(&config(Some(&not_pem), Some(&not_pem), None))
            .expect_err("no certificate in the file");
        assert!(
            error.to_string().contains("holds no PEM certificate"),
            "{error}"
        );
    }
}
