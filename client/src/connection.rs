//! A typed connection to a Spoofwatch server: one HTTP/2 channel (plaintext, TLS or mutual TLS), an
//! optional bearer token on every request, optional gzip, and accessors for each service's
//! generated client. It must not know what the calls mean: streams live in `detect_stream`,
//! retries in `retry`, commands in the binary.

use std::path::{Path, PathBuf};
use std::time::Duration;

use spoofwatch_proto::longrunning::operations_client::OperationsClient;
use spoofwatch_proto::pem;
use spoofwatch_proto::v1::alarm_service_client::AlarmServiceClient;
use spoofwatch_proto::v1::dataset_service_client::DatasetServiceClient;
use spoofwatch_proto::v1::detection_service_client::DetectionServiceClient;
use spoofwatch_proto::v1::model_service_client::ModelServiceClient;
use spoofwatch_proto::v1::training_service_client::TrainingServiceClient;
use tonic::codec::CompressionEncoding;
use tonic::metadata::AsciiMetadataValue;
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};
use tonic::{Request, Status};
use tonic_health::pb::health_client::HealthClient;

use crate::error::{ClientError, error_chain};

/// Default server address of every remote command (`http://`, or `https://` with TLS files).
pub const DEFAULT_SERVER_ADDRESS: &str = "127.0.0.1:50051";
/// How long establishing the connection may take before the command gives up.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// Largest reply accepted. Model exports arrive in chunks of at most 1 MiB, but artifacts (and with
/// them single messages such as lists of models) may grow, so leave ample room over tonic's 4 MiB.
pub const MAX_DECODING_MESSAGE_BYTES: usize = 64 << 20;

/// The `authorization` header value for `token`: `Bearer <token>`. [`ClientError::InvalidToken`]
/// for an empty token or one with characters a header cannot carry.
pub fn bearer_value(token: &str) -> Result<String, ClientError> {
    if token.is_empty() || !token.chars().all(|c| c.is_ascii_graphic()) {
        return Err(ClientError::InvalidToken);
    }
    Ok(format!("Bearer {token}"))
}

/// Adds `authorization: Bearer <token>` to every request when a token is configured.
#[derive(Clone, Debug, Default)]
pub struct BearerAuth {
    header: Option<AsciiMetadataValue>,
}

impl BearerAuth {
    /// An interceptor for `token` (`None`: requests go out unchanged).
    pub fn new(token: Option<&str>) -> Result<Self, ClientError> {
        let header = match token {
            None => None,
            Some(token) => {
                let mut value = AsciiMetadataValue::try_from(bearer_value(token)?)
                    .map_err(|_| ClientError::InvalidToken)?;
                // Keeps the token out of Debug output and logs.
                value.set_sensitive(true);
                Some(value)
            }
        };
        Ok(Self { header })
    }
}

impl Interceptor for BearerAuth {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(header) = &self.header {
            request
                .metadata_mut()
                .insert("authorization", header.clone());
        }
        Ok(request)
    }
}

/// The channel every generated client of a [`Connection`] uses.
pub type AuthenticatedChannel = InterceptedService<Channel, BearerAuth>;

/// How to connect besides the address: authentication, TLS files, compression.
#[derive(Clone, Debug, Default)]
pub struct ConnectOptions {
    /// Sent as `authorization: Bearer <token>` with every request.
    pub token: Option<String>,
    /// CA certificate(s) (PEM) to trust for the server, instead of the built-in web PKI roots.
    pub ca_cert: Option<PathBuf>,
    /// Client certificate chain (PEM) for mutual TLS; needs `client_key`.
    pub client_cert: Option<PathBuf>,
    /// Private key (PEM) of `client_cert`.
    pub client_key: Option<PathBuf>,
    /// Compress requests with gzip and ask for gzip replies (worth it on slow links only: it costs
    /// CPU on both ends).
    pub gzip: bool,
}

impl ConnectOptions {
    /// Options with only a bearer token.
    pub fn with_token(token: Option<String>) -> Self {
        Self {
            token,
            ..Self::default()
        }
    }

    /// Whether a TLS file is given (then a bare `host:port` means `https://`).
    pub fn wants_tls(&self) -> bool {
        self.ca_cert.is_some() || self.client_cert.is_some() || self.client_key.is_some()
    }
}

/// A server address as a URL: `host:port` gets `https://` when `tls`, else `http://`; a URL with a
/// scheme is kept as it is.
pub fn server_url(address: &str, tls: bool) -> String {
    let address = address.trim();
    if address.contains("://") {
        address.to_string()
    } else if tls {
        format!("https://{address}")
    } else {
        format!("http://{address}")
    }
}

/// A connection to one Spoofwatch server. Cheap to clone: clones share the HTTP/2 connection.
#[derive(Clone, Debug)]
pub struct Connection {
    url: String,
    channel: Channel,
    auth: BearerAuth,
    gzip: bool,
}

/// A generated client over `$connection`'s channel that accepts replies up to
/// [`MAX_DECODING_MESSAGE_BYTES`] and uses gzip when the connection does.
macro_rules! client {
    ($connection:expr, $client:ident) => {{
        let client = $client::new($connection.channel())
            .max_decoding_message_size(MAX_DECODING_MESSAGE_BYTES);
        if $connection.gzip {
            client
                .send_compressed(CompressionEncoding::Gzip)
                .accept_compressed(CompressionEncoding::Gzip)
        } else {
            client
        }
    }};
}

impl Connection {
    /// Connects to `url` (e.g. `http://127.0.0.1:50051`) within [`CONNECT_TIMEOUT`]; with a `token`,
    /// every request carries `authorization: Bearer <token>`.
    pub async fn connect(
        url: impl Into<String>,
        token: Option<String>,
    ) -> Result<Connection, ClientError> {
        Self::connect_with(&url.into(), &ConnectOptions::with_token(token)).await
    }

    /// Enough connections to `address` for `streams` concurrent streams with at most
    /// `per_connection` on each (at least one connection).
    pub async fn pool(
        address: &str,
        options: &ConnectOptions,
        streams: usize,
        per_connection: usize,
    ) -> Result<Vec<Connection>, ClientError> {
        let count = streams.div_ceil(per_connection.max(1)).max(1);
        let mut pool = Vec::with_capacity(count);
        for _ in 0..count {
            pool.push(Self::connect_with(address, options).await?);
        }
        Ok(pool)
    }

    /// Connects to `address` (a URL, or `host:port`: see [`server_url`]) with `options` within
    /// [`CONNECT_TIMEOUT`] (TCP, then again for the TLS handshake). `https://` uses TLS, trusting
    /// `options.ca_cert` or else the built-in web PKI roots.
    pub async fn connect_with(
        address: &str,
        options: &ConnectOptions,
    ) -> Result<Connection, ClientError> {
        let url = server_url(address, options.wants_tls());
        let auth = BearerAuth::new(options.token.as_deref())?;
        let mut endpoint = Endpoint::from_shared(url.clone())
            .map_err(|e| ClientError::InvalidUrl {
                url: url.clone(),
                reason: error_chain(&e),
            })?
            .connect_timeout(CONNECT_TIMEOUT)
            .tcp_nodelay(true);
        if url.starts_with("https://") {
            endpoint =
                endpoint
                    .tls_config(client_tls(options)?)
                    .map_err(|e| ClientError::InvalidUrl {
                        url: url.clone(),
                        reason: error_chain(&e),
                    })?;
        } else if options.wants_tls() {
            return Err(ClientError::InvalidOption {
                option: "--ca-cert/--client-cert/--client-key",
                reason: format!("TLS files need an https:// server URL, not {url}"),
            });
        }
        let channel = endpoint.connect().await.map_err(|e| ClientError::Connect {
            url: url.clone(),
            reason: error_chain(&e),
        })?;
        Ok(Self {
            url,
            channel,
            auth,
            gzip: options.gzip,
        })
    }

    /// The server URL this connection was made to.
    pub fn url(&self) -> &str {
        &self.url
    }

    fn channel(&self) -> AuthenticatedChannel {
        InterceptedService::new(self.channel.clone(), self.auth.clone())
    }

    /// The DetectionService client (streaming and unary detection, sessions).
    pub fn detection(&self) -> DetectionServiceClient<AuthenticatedChannel> {
        client!(self, DetectionServiceClient)
    }

    /// The ModelService client (registry, export/import).
    pub fn models(&self) -> ModelServiceClient<AuthenticatedChannel> {
        client!(self, ModelServiceClient)
    }

    /// The DatasetService client (upload, import, list, delete).
    pub fn datasets(&self) -> DatasetServiceClient<AuthenticatedChannel> {
        client!(self, DatasetServiceClient)
    }

    /// The TrainingService client (create jobs, watch their progress).
    pub fn training(&self) -> TrainingServiceClient<AuthenticatedChannel> {
        client!(self, TrainingServiceClient)
    }

    /// The google.longrunning.Operations client (get, list, cancel, delete, wait for jobs).
    pub fn operations(&self) -> OperationsClient<AuthenticatedChannel> {
        client!(self, OperationsClient)
    }

    /// The AlarmService client (list stored alarms, watch onsets and ends).
    pub fn alarms(&self) -> AlarmServiceClient<AuthenticatedChannel> {
        client!(self, AlarmServiceClient)
    }

    /// The grpc.health.v1 client.
    pub fn health(&self) -> HealthClient<AuthenticatedChannel> {
        client!(self, HealthClient)
    }

    /// Polls the overall health of the server at `address` every 50 ms (connecting again each time)
    /// until it reports SERVING; [`ClientError::Timeout`] once `bound` has passed. For a server that
    /// was just started: its port may accept connections before its database is open.
    pub async fn wait_until_serving(
        address: &str,
        options: &ConnectOptions,
        bound: Duration,
    ) -> Result<(), ClientError> {
        use tonic_health::pb::HealthCheckRequest;
        use tonic_health::pb::health_check_response::ServingStatus;
        let deadline = tokio::time::Instant::now() + bound;
        loop {
            if let Ok(connection) = Connection::connect_with(address, options).await {
                let status = connection
                    .health()
                    .check(HealthCheckRequest::default())
                    .await
                    .map(|r| r.into_inner().status);
                if matches!(status, Ok(s) if s == ServingStatus::Serving as i32) {
                    return Ok(());
                }
            }
            if tokio::time::Instant::now() >= deadline {
                return Err(ClientError::Timeout {
                    context: format!("waiting for {address} to report SERVING"),
                    after: bound,
                });
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

/// The TLS settings of `options`, with every file read and checked (named in the error).
fn client_tls(options: &ConnectOptions) -> Result<ClientTlsConfig, ClientError> {
    let tls = ClientTlsConfig::new().timeout(CONNECT_TIMEOUT);
    let tls = match &options.ca_cert {
        Some(ca) => tls.ca_certificate(Certificate::from_pem(certificates_pem("--ca-cert", ca)?)),
        None => tls.with_webpki_roots(),
    };
    match (&options.client_cert, &options.client_key) {
        (None, None) => Ok(tls),
        (Some(cert), Some(key)) => Ok(tls.identity(Identity::from_pem(
            certificates_pem("--client-cert", cert)?,
            key_pem("--client-key", key)?,
        ))),
        (Some(_), None) | (None, Some(_)) => Err(ClientError::InvalidOption {
            option: "--client-cert/--client-key",
            reason: "give both (a client certificate and its private key) or neither".into(),
        }),
    }
}

/// The bytes of a PEM file holding at least one certificate.
fn certificates_pem(option: &'static str, path: &Path) -> Result<Vec<u8>, ClientError> {
    pem::certificates(path).map_err(|reason| tls_file_error(option, path, reason))
}

/// The bytes of a PEM file holding a private key.
fn key_pem(option: &'static str, path: &Path) -> Result<Vec<u8>, ClientError> {
    pem::private_key(path).map_err(|reason| tls_file_error(option, path, reason))
}

fn tls_file_error(option: &'static str, path: &Path, reason: impl Into<String>) -> ClientError {
    ClientError::TlsFile {
        option,
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn authorization(auth: &mut BearerAuth) -> Option<String> {
        let request = auth
            .call(Request::new(()))
            .expect("the interceptor never fails");
        request
            .metadata()
            .get("authorization")
            .map(|v| v.to_str().expect("ascii").to_string())
    }

    #[test]
    fn a_token_is_sent_as_a_bearer_authorization_header() {
        let mut auth = BearerAuth::new(Some("s3cret-token")).expect("valid token");
        assert_eq!(
            authorization(&mut auth).as_deref(),
            Some("Bearer s3cret-token")
        );
    }

    #[test]
    fn without_a_token_no_header_is_added() {
        let mut auth = BearerAuth::new(None).expect("no token");
        assert_eq!(authorization(&mut auth), None);
    }

    #[test]
    fn tokens_that_cannot_be_a_header_are_refused() {
        for token in ["", "two words", "line\nbreak", "caf\u{e9}"] {
            assert!(
                matches!(BearerAuth::new(Some(token)), Err(ClientError::InvalidToken)),
                "{token:?}"
            );
        }
    }

    #[test]
    fn a_bare_address_gets_a_scheme_and_a_url_keeps_its_own() {
        assert_eq!(
            server_url("127.0.0.1:50051", false),
            "http://127.0.0.1:50051"
        );
        assert_eq!(
            server_url("fleet.example:443", true),
            "https://fleet.example:443"
        );
        assert_eq!(server_url("https://h:1", false), "https://h:1");
        assert_eq!(server_url("http://h:1", true), "http://h:1");
    }

    #[tokio::test]
    async fn tls_files_with_a_plaintext_url_or_half_a_client_pair_are_refused() {
        let options = ConnectOptions {
            ca_cert: Some("ca.pem".into()),
            ..ConnectOptions::default()
        };
        let error = Connection::connect_with("http://127.0.0.1:1", &options)
            .await
            .expect_err("TLS files with http://");
        assert!(
            matches!(error, ClientError::InvalidOption { .. }),
            "{error}"
        );
        let options = ConnectOptions {
            client_cert: Some("c.pem".into()),
            ..ConnectOptions::default()
        };
        let error = Connection::connect_with("https://127.0.0.1:1", &options)
            .await
            .expect_err("a certificate without its key");
        assert!(
            matches!(error, ClientError::InvalidOption { .. }),
            "{error}"
        );
        let options = ConnectOptions {
            ca_cert: Some("/nonexistent/ca.pem".into()),
            ..ConnectOptions::default()
        };
        let error = Connection::connect_with("127.0.0.1:1", &options)
            .await
            .expect_err("an unreadable CA file");
        assert!(
            error
                .to_string()
                .starts_with("--ca-cert /nonexistent/ca.pem: cannot read"),
            "{error}"
        );
    }

    #[tokio::test]
    async fn an_unparsable_url_is_reported_as_such() {
        let error = Connection::connect("not a url", None)
            .await
            .expect_err("must fail");
        assert!(matches!(error, ClientError::InvalidUrl { .. }), "{error}");
    }
}
