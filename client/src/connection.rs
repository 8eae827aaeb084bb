//! A typed connection to a Spoofwatch server: one HTTP/2 channel, an optional bearer token on every
//! request, and accessors for each service's generated client. It must not know what the calls
//! mean: streams live in `detect_stream`, commands in the binary.

use std::time::Duration;

use spoofwatch_proto::longrunning::operations_client::OperationsClient;
use spoofwatch_proto::v1::alarm_service_client::AlarmServiceClient;
use spoofwatch_proto::v1::dataset_service_client::DatasetServiceClient;
use spoofwatch_proto::v1::detection_service_client::DetectionServiceClient;
use spoofwatch_proto::v1::model_service_client::ModelServiceClient;
use spoofwatch_proto::v1::training_service_client::TrainingServiceClient;
use tonic::metadata::AsciiMetadataValue;
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};
use tonic::{Request, Status};
use tonic_health::pb::health_client::HealthClient;

use crate::error::{ClientError, error_chain};

/// Default server address of every remote command.
pub const DEFAULT_SERVER_URL: &str = "http://127.0.0.1:50051";
/// How long establishing the connection may take before the command gives up.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// Largest reply accepted. Model exports arrive in chunks of at most 1 MiB, but artifacts (and with
/// them single messages such as lists of models) may grow, so leave ample room over tonic's 4 MiB.
pub const MAX_DECODING_MESSAGE_BYTES: usize = 64 << 20;

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
                if token.is_empty() || !token.chars().all(|c| c.is_ascii_graphic()) {
                    return Err(ClientError::InvalidToken);
                }
                let mut value = AsciiMetadataValue::try_from(format!("Bearer {token}"))
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

/// A connection to one Spoofwatch server. Cheap to clone: clones share the HTTP/2 connection.
#[derive(Clone, Debug)]
pub struct Connection {
    url: String,
    channel: Channel,
    auth: BearerAuth,
}

impl Connection {
    /// Connects to `url` (e.g. `http://127.0.0.1:50051`) within [`CONNECT_TIMEOUT`]; with a `token`,
    /// every request carries `authorization: Bearer <token>`.
    pub async fn connect(
        url: impl Into<String>,
        token: Option<String>,
    ) -> Result<Connection, ClientError> {
        let url = url.into();
        let auth = BearerAuth::new(token.as_deref())?;
        let endpoint = Endpoint::from_shared(url.clone())
            .map_err(|e| ClientError::InvalidUrl {
                url: url.clone(),
                reason: error_chain(&e),
            })?
            .connect_timeout(CONNECT_TIMEOUT)
            .tcp_nodelay(true);
        let channel = endpoint.connect().await.map_err(|e| ClientError::Connect {
            url: url.clone(),
            reason: error_chain(&e),
        })?;
        Ok(Self { url, channel, auth })
    }

    /// The server URL this connection was made to.
    pub fn url(&self) -> &str {
        &self.url
    }

    fn channel(&self) -> AuthenticatedChannel {
        InterceptedService::new(self.channel.clone(), self.auth.clone())
    }

    /// A generated client over this connection that accepts replies up to
    /// [`MAX_DECODING_MESSAGE_BYTES`].
    fn limited<C>(
        &self,
        new: impl FnOnce(AuthenticatedChannel) -> C,
        max_decoding_message_size: impl FnOnce(C, usize) -> C,
    ) -> C {
        max_decoding_message_size(new(self.channel()), MAX_DECODING_MESSAGE_BYTES)
    }

    /// The DetectionService client (streaming and unary detection, sessions).
    pub fn detection(&self) -> DetectionServiceClient<AuthenticatedChannel> {
        self.limited(
            DetectionServiceClient::new,
            DetectionServiceClient::max_decoding_message_size,
        )
    }

    /// The ModelService client (registry, export/import).
    pub fn models(&self) -> ModelServiceClient<AuthenticatedChannel> {
        self.limited(
            ModelServiceClient::new,
            ModelServiceClient::max_decoding_message_size,
        )
    }

    /// The DatasetService client (upload, import, list, delete).
    pub fn datasets(&self) -> DatasetServiceClient<AuthenticatedChannel> {
        self.limited(
            DatasetServiceClient::new,
            DatasetServiceClient::max_decoding_message_size,
        )
    }

    /// The TrainingService client (create jobs, watch their progress).
    pub fn training(&self) -> TrainingServiceClient<AuthenticatedChannel> {
        self.limited(
            TrainingServiceClient::new,
            TrainingServiceClient::max_decoding_message_size,
        )
    }

    /// The google.longrunning.Operations client (get, list, cancel, delete, wait for jobs).
    pub fn operations(&self) -> OperationsClient<AuthenticatedChannel> {
        self.limited(
            OperationsClient::new,
            OperationsClient::max_decoding_message_size,
        )
    }

    /// The AlarmService client (list stored alarms, watch onsets and ends).
    pub fn alarms(&self) -> AlarmServiceClient<AuthenticatedChannel> {
        self.limited(
            AlarmServiceClient::new,
            AlarmServiceClient::max_decoding_message_size,
        )
    }

    /// The grpc.health.v1 client.
    pub fn health(&self) -> HealthClient<AuthenticatedChannel> {
        HealthClient::new(self.channel())
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

    #[tokio::test]
    async fn an_unparsable_url_is_reported_as_such() {
        let error = Connection::connect("not a url", None)
            .await
            .expect_err("must fail");
        assert!(matches!(error, ClientError::InvalidUrl { .. }), "{error}");
    }
}
