//! Server configuration: flags with `SPOOFWATCH_*` environment fallbacks, and [`Config::default`]
//! with the same defaults but no environment. Each default value is written once, in [`defaults`].
//! This module only describes configuration; it must not act on it.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use crate::incidents::settings::IncidentSettings;
pub use crate::incidents::settings::IncidentTimeline;

/// The default of every setting, shared by clap's `default_value_t` and [`Config::default`].
pub mod defaults {
    use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4};

    use spoofwatch_proto::wire::limits;

    pub const LISTEN: SocketAddr = SocketAddr::V4(SocketAddrV4::new(Ipv4Addr::LOCALHOST, 50051));
    pub const DATABASE: &str = "spoofwatch.db";
    pub const MAX_SESSIONS: usize = 100_000;
    /// Half the table: no one token or certificate can fill it.
    pub const MAX_SESSIONS_PER_IDENTITY: usize = 50_000;
    /// HTTP/2 streams one connection may have open at once (a fleet gateway multiplexes its
    /// vehicles' streams over few connections; beyond this it opens another).
    pub const MAX_STREAMS_PER_CONNECTION: u32 = 1_024;
    /// Room for four uploads of the largest dataset accepted at once.
    pub const UPLOAD_MEMORY_MIB: u32 = 1_024;
    pub const SESSION_IDLE_SECS: u64 = 900;
    pub const MAX_BATCH_SAMPLES: usize = limits::MAX_BATCH_SAMPLES;
    pub const MAX_MESSAGE_BYTES: usize = limits::MAX_MESSAGE_BYTES;
    pub const MAX_RUNNING_JOBS: usize = 1;
    /// The datasets of four of the largest jobs' worth of input read at once.
    pub const JOB_INPUT_MIB: u32 = 1_024;
    pub const MAX_PENDING_JOBS: usize = 16;
    pub const SHUTDOWN_GRACE_SECS: u64 = 10;
    pub const HANDSHAKE_TIMEOUT_SECS: u64 = 10;
    /// Five minutes: a vehicle sends every second or so, and the HTTP/2 keepalive already notices
    /// dead peers; this ends live connections that merely stopped talking.
    pub const STREAM_IDLE_SECS: u64 = 300;
    /// Room for about 370 artifacts the size of the bundled model (0.7 MB), or 16 of the largest
    /// importable (`limits::MAX_ARTIFACT_BYTES`).
    pub const MODEL_CACHE_BYTES: usize = 256 << 20;
    pub const LOG_FORMAT: super::LogFormat = super::LogFormat::Text;
    /// Ten minutes of a 1 Hz vehicle, or a minute: what a crashed process's vehicles resend.
    pub const SNAPSHOT_EVERY_SAMPLES: u64 = 600;
    pub const SNAPSHOT_EVERY_SECS: u64 = 60;
    /// A day: a vehicle parked overnight loses its calibration, one back from lunch keeps it.
    pub const SNAPSHOT_TTL_SECS: u64 = 86_400;
    /// About the range of a spoofer on the ground (tens of km for a strong one, a few for most).
    pub const INCIDENT_RADIUS_KM: f64 = 10.0;
    pub const INCIDENT_WINDOW_SECS: u64 = 300;
    pub const INCIDENT_MIN_VEHICLES: u32 = 3;
    pub const INCIDENT_MIN_SOURCES: u32 = 2;
    pub const INCIDENT_MAX_PER_SOURCE: u32 = 3;
    pub const INCIDENT_QUIET_SECS: u64 = 600;
    pub const INCIDENT_TIMELINE: super::IncidentTimeline = super::IncidentTimeline::Wall;
    pub const INCIDENT_PRIOR: bool = true;
}

/// How the server binary writes its log lines to stderr.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines (coloured only on a terminal).
    Text,
    /// One JSON object per line, the event's fields at the top level.
    Json,
}

/// Everything the server needs to start.
#[derive(Clone, Debug, clap::Parser)]
#[command(
    name = "spoofwatch-server",
    version,
    about = "Spoofwatch GNSS-spoofing detection gRPC service"
)]
pub struct Config {
    /// Address to listen on.
    #[arg(long, env = "SPOOFWATCH_LISTEN", default_value_t = defaults::LISTEN)]
    pub listen: SocketAddr,
    /// Database: a SQLite file path or sqlite:// URL (created if missing), or a postgres:// URL of
    /// an existing PostgreSQL database that replicas share; migrated on start.
    #[arg(long, env = "SPOOFWATCH_DATABASE", default_value = defaults::DATABASE)]
    pub database: String,
    /// This server's name among replicas sharing a database: it owns the jobs it admits. Default:
    /// the host name. Replicas on one host need distinct names; a restart under the same name fails
    /// at once the jobs its previous run left (others fail once their lease expires).
    #[arg(long, env = "SPOOFWATCH_INSTANCE_ID", value_parser = parse_instance_id)]
    pub instance_id: Option<String>,
    /// Most MiB the database may grow to; beyond it writes fail RESOURCE_EXHAUSTED until deletions
    /// free space (detection and alarms in memory go on). Unset: only the disk limits it.
    #[arg(long, env = "SPOOFWATCH_DATABASE_MAX_MIB", value_parser = clap::value_parser!(u64).range(1..=16_777_216))]
    pub database_max_mib: Option<u64>,
    /// Directory ImportDataset may read CSV files from (nothing outside it). Unset: imports refused.
    #[arg(long, env = "SPOOFWATCH_DATA_DIR")]
    pub data_dir: Option<PathBuf>,
    /// Most vehicle sessions held in memory.
    #[arg(long, env = "SPOOFWATCH_MAX_SESSIONS", default_value_t = defaults::MAX_SESSIONS)]
    pub max_sessions: usize,
    /// Most sessions one identity (a bearer token or client certificate; every caller of a server
    /// without either is one) may hold; beyond it its new vehicles are refused RESOURCE_EXHAUSTED.
    #[arg(long, env = "SPOOFWATCH_MAX_SESSIONS_PER_IDENTITY", default_value_t = defaults::MAX_SESSIONS_PER_IDENTITY)]
    pub max_sessions_per_identity: usize,
    /// HTTP/2 streams one connection may have open at once (calls beyond it wait for a free one).
    #[arg(long, env = "SPOOFWATCH_MAX_STREAMS_PER_CONNECTION", default_value_t = defaults::MAX_STREAMS_PER_CONNECTION,
          value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    pub max_streams_per_connection: u32,
    /// MiB of upload data that all UploadDataset calls together may hold in memory while they
    /// arrive; an upload that would exceed it is refused RESOURCE_EXHAUSTED (retry later).
    #[arg(long, env = "SPOOFWATCH_UPLOAD_MEMORY_MIB", default_value_t = defaults::UPLOAD_MEMORY_MIB,
          value_parser = clap::value_parser!(u32).range(1..=1_048_576))]
    pub upload_memory_mib: u32,
    /// Seconds after which a session without a stream is evicted.
    #[arg(long, env = "SPOOFWATCH_SESSION_IDLE_SECS", default_value_t = defaults::SESSION_IDLE_SECS)]
    pub session_idle_secs: u64,
    /// Most samples in one batch.
    #[arg(long, env = "SPOOFWATCH_MAX_BATCH_SAMPLES", default_value_t = defaults::MAX_BATCH_SAMPLES)]
    pub max_batch_samples: usize,
    /// Largest gRPC message accepted (bytes).
    #[arg(long, env = "SPOOFWATCH_MAX_MESSAGE_BYTES", default_value_t = defaults::MAX_MESSAGE_BYTES)]
    pub max_message_bytes: usize,
    /// Training/evaluation jobs running at once (the rest queue).
    #[arg(long, env = "SPOOFWATCH_MAX_RUNNING_JOBS", default_value_t = defaults::MAX_RUNNING_JOBS)]
    pub max_running_jobs: usize,
    /// Jobs queued or running at once; more are refused.
    #[arg(long, env = "SPOOFWATCH_MAX_PENDING_JOBS", default_value_t = defaults::MAX_PENDING_JOBS)]
    pub max_pending_jobs: usize,
    /// MiB of stored dataset input that running jobs together may read (a job holds its datasets'
    /// records in memory while it runs); a job waits for room, and one whose datasets alone hold
    /// more is refused INVALID_ARGUMENT.
    #[arg(long, env = "SPOOFWATCH_JOB_INPUT_MIB", default_value_t = defaults::JOB_INPUT_MIB,
          value_parser = clap::value_parser!(u32).range(1..=1_048_576))]
    pub job_input_mib: u32,
    /// Bytes of parsed model artifacts kept in memory besides the active model (least recently used
    /// evicted first; sized by the serialised artifact).
    #[arg(long, env = "SPOOFWATCH_MODEL_CACHE_BYTES", default_value_t = defaults::MODEL_CACHE_BYTES)]
    pub model_cache_bytes: usize,
    /// Seconds the shutdown waits for streams and jobs before closing anyway.
    #[arg(long, env = "SPOOFWATCH_SHUTDOWN_GRACE_SECS", default_value_t = defaults::SHUTDOWN_GRACE_SECS)]
    pub shutdown_grace_secs: u64,
    /// Seconds a new connection has to send the HTTP/2 preface (with TLS: to complete the TLS
    /// handshake) before it is closed.
    #[arg(long, env = "SPOOFWATCH_HANDSHAKE_TIMEOUT_SECS", default_value_t = defaults::HANDSHAKE_TIMEOUT_SECS,
          value_parser = clap::value_parser!(u64).range(1..=300))]
    pub handshake_timeout_secs: u64,
    /// The admin bearer token, from the environment only (`SPOOFWATCH_AUTH_TOKEN`): a command-line
    /// argument would show in every process listing. Prefer --auth-token-file.
    #[arg(skip = std::env::var("SPOOFWATCH_AUTH_TOKEN").ok())]
    pub auth_token: Option<String>,
    /// A file holding the admin bearer token (`authorization: Bearer <token>` on every call except
    /// health and reflection); re-read within seconds when it changes.
    #[arg(long, env = "SPOOFWATCH_AUTH_TOKEN_FILE")]
    pub auth_token_file: Option<PathBuf>,
    /// The roles file: which client certificates and tokens act as vehicle, gateway, operator or
    /// admin, and which are revoked; re-read within seconds when it changes.
    #[arg(long, env = "SPOOFWATCH_ROLES_FILE")]
    pub roles_file: Option<PathBuf>,
    /// Serve Prometheus metrics at `GET /metrics` on this address (its own listener, no token).
    /// Unset: no metrics are collected.
    #[arg(long, env = "SPOOFWATCH_METRICS_LISTEN")]
    pub metrics_listen: Option<SocketAddr>,
    /// Log line format on stderr.
    #[arg(long, env = "SPOOFWATCH_LOG_FORMAT", value_enum, default_value_t = defaults::LOG_FORMAT)]
    pub log_format: LogFormat,
    /// TLS certificate chain (PEM), server certificate first. With --tls-key, the server speaks
    /// only TLS.
    #[arg(long, env = "SPOOFWATCH_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// TLS private key (PEM: PKCS#8, PKCS#1 or SEC1) of --tls-cert.
    #[arg(long, env = "SPOOFWATCH_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// CA certificate(s) (PEM) that client certificates must be signed by (mutual TLS): clients
    /// without such a certificate are refused during the handshake.
    #[arg(long, env = "SPOOFWATCH_TLS_CLIENT_CA", requires = "tls_cert")]
    pub tls_client_ca: Option<PathBuf>,
    /// Seconds a StreamDetect, StreamDetectFleet or upload stream may send nothing before the
    /// server ends it with DEADLINE_EXCEEDED (the session stays resumable).
    #[arg(long, env = "SPOOFWATCH_STREAM_IDLE_SECS", default_value_t = defaults::STREAM_IDLE_SECS,
          value_parser = clap::value_parser!(u64).range(1..=86_400))]
    pub stream_idle_secs: u64,
    /// Snapshot a session (for hand-off to another replica or a restart) after this many samples
    /// since its last snapshot; 0: only by time. Sessions are also snapshotted when their stream
    /// ends, on eviction, at shutdown and with every alarm onset or end.
    #[arg(long, env = "SPOOFWATCH_SNAPSHOT_EVERY_SAMPLES", default_value_t = defaults::SNAPSHOT_EVERY_SAMPLES)]
    pub snapshot_every_samples: u64,
    /// Snapshot a session at its first batch this many seconds after its last snapshot.
    #[arg(long, env = "SPOOFWATCH_SNAPSHOT_EVERY_SECS", default_value_t = defaults::SNAPSHOT_EVERY_SECS,
          value_parser = clap::value_parser!(u64).range(1..=86_400))]
    pub snapshot_every_secs: u64,
    /// Seconds a stored session snapshot is kept without being rewritten (its vehicle gone); then
    /// it is deleted and the alarm it held open ends. Must exceed --session-idle-secs and
    /// --snapshot-every-secs.
    #[arg(long, env = "SPOOFWATCH_SNAPSHOT_TTL_SECS", default_value_t = defaults::SNAPSHOT_TTL_SECS,
          value_parser = clap::value_parser!(u64).range(60..=31_536_000))]
    pub snapshot_ttl_secs: u64,
    /// Area incidents: vehicles whose true positions are within this many km of each other, whose
    /// alarms start within --incident-window-secs and agree on one false position, translation or
    /// drift, are one incident (0.1 to 200 km).
    #[arg(long, env = "SPOOFWATCH_INCIDENT_RADIUS_KM", default_value_t = defaults::INCIDENT_RADIUS_KM)]
    pub incident_radius_km: f64,
    /// Seconds within which the alarm onsets that open an incident must start.
    #[arg(long, env = "SPOOFWATCH_INCIDENT_WINDOW_SECS", default_value_t = defaults::INCIDENT_WINDOW_SECS,
          value_parser = clap::value_parser!(u64).range(1..=3_600))]
    pub incident_window_secs: u64,
    /// Vehicles that must agree before an incident opens.
    #[arg(long, env = "SPOOFWATCH_INCIDENT_MIN_VEHICLES", default_value_t = defaults::INCIDENT_MIN_VEHICLES,
          value_parser = clap::value_parser!(u32).range(2..=1_000))]
    pub incident_min_vehicles: u32,
    /// Independent sources the agreeing vehicles' alarms must come from before an incident opens
    /// (1 to --incident-min-vehicles): a source is a credential (a vehicle's, a gateway's, a
    /// token's), or each vehicle of a gateway the roles file says forwards independent receivers,
    /// or each vehicle of a server without identities. Whoever holds one credential cannot open an
    /// incident alone, however many vehicle ids it streams for.
    #[arg(long, env = "SPOOFWATCH_INCIDENT_MIN_SOURCES", default_value_t = defaults::INCIDENT_MIN_SOURCES,
          value_parser = clap::value_parser!(u32).range(1..=1_000))]
    pub incident_min_sources: u32,
    /// Open incidents one source (see --incident-min-sources) may take part in at once: beyond it
    /// its alarms still alarm, but join no other incident and open none.
    #[arg(long, env = "SPOOFWATCH_INCIDENT_MAX_PER_SOURCE", default_value_t = defaults::INCIDENT_MAX_PER_SOURCE,
          value_parser = clap::value_parser!(u32).range(1..=1_000))]
    pub incident_max_per_source: u32,
    /// An incident ends once none of its vehicles has had an open alarm for this many seconds.
    #[arg(long, env = "SPOOFWATCH_INCIDENT_QUIET_SECS", default_value_t = defaults::INCIDENT_QUIET_SECS,
          value_parser = clap::value_parser!(u64).range(0..=86_400))]
    pub incident_quiet_secs: u64,
    /// The clock that places alarms in time for incidents: `wall` (the servers' clock at onset and
    /// end: live fleets) or `samples` (the vehicles' sample times: replays of recordings whose
    /// vehicles share one clock).
    #[arg(long, env = "SPOOFWATCH_INCIDENT_TIMELINE", value_enum, default_value_t = defaults::INCIDENT_TIMELINE)]
    pub incident_timeline: IncidentTimeline,
    /// Whether a sample inside an open incident's area is scored with the area prior: the incident
    /// counts as the receiver's spoofing flag does (a displaced fix held for 1 s alarms at once), and
    /// p̂ ≥ θ alarms after 2 s instead of the model's T_on. `false` scores every vehicle on its own
    /// evidence alone.
    #[arg(long, env = "SPOOFWATCH_INCIDENT_PRIOR", default_value_t = defaults::INCIDENT_PRIOR,
          action = clap::ArgAction::Set)]
    pub incident_prior: bool,
}

/// An instance id: 1–128 visible ASCII characters (it is stored with every job and logged).
pub fn parse_instance_id(text: &str) -> Result<String, String> {
    if text.is_empty() || text.len() > 128 || !text.bytes().all(|b| b.is_ascii_graphic()) {
        return Err("must be 1 to 128 visible ASCII characters, without spaces".into());
    }
    Ok(text.to_string())
}

/// The defaults, without reading the environment (no data directory, no auth token).
impl Default for Config {
    fn default() -> Self {
        Self {
            listen: defaults::LISTEN,
            database: defaults::DATABASE.to_string(),
            database_max_mib: None,
            instance_id: None,
            data_dir: None,
            max_sessions: defaults::MAX_SESSIONS,
            max_sessions_per_identity: defaults::MAX_SESSIONS_PER_IDENTITY,
            max_streams_per_connection: defaults::MAX_STREAMS_PER_CONNECTION,
            upload_memory_mib: defaults::UPLOAD_MEMORY_MIB,
            session_idle_secs: defaults::SESSION_IDLE_SECS,
            max_batch_samples: defaults::MAX_BATCH_SAMPLES,
            max_message_bytes: defaults::MAX_MESSAGE_BYTES,
            max_running_jobs: defaults::MAX_RUNNING_JOBS,
            job_input_mib: defaults::JOB_INPUT_MIB,
            max_pending_jobs: defaults::MAX_PENDING_JOBS,
            model_cache_bytes: defaults::MODEL_CACHE_BYTES,
            shutdown_grace_secs: defaults::SHUTDOWN_GRACE_SECS,
            handshake_timeout_secs: defaults::HANDSHAKE_TIMEOUT_SECS,
            auth_token: None,
            auth_token_file: None,
            roles_file: None,
            metrics_listen: None,
            log_format: defaults::LOG_FORMAT,
            tls_cert: None,
            tls_key: None,
            tls_client_ca: None,
            stream_idle_secs: defaults::STREAM_IDLE_SECS,
            snapshot_every_samples: defaults::SNAPSHOT_EVERY_SAMPLES,
            snapshot_every_secs: defaults::SNAPSHOT_EVERY_SECS,
            snapshot_ttl_secs: defaults::SNAPSHOT_TTL_SECS,
            incident_radius_km: defaults::INCIDENT_RADIUS_KM,
            incident_window_secs: defaults::INCIDENT_WINDOW_SECS,
            incident_min_vehicles: defaults::INCIDENT_MIN_VEHICLES,
            incident_min_sources: defaults::INCIDENT_MIN_SOURCES,
            incident_max_per_source: defaults::INCIDENT_MAX_PER_SOURCE,
            incident_quiet_secs: defaults::INCIDENT_QUIET_SECS,
            incident_timeline: defaults::INCIDENT_TIMELINE,
            incident_prior: defaults::INCIDENT_PRIOR,
        }
    }
}

impl Config {
    /// The defaults with this database (tests, the demo).
    pub fn with_database(database: impl Into<String>) -> Self {
        Self {
            database: database.into(),
            ..Self::default()
        }
    }

    /// The instance id: the configured one, else the host name (else "spoofwatch").
    pub fn instance(&self) -> String {
        self.instance_id.clone().unwrap_or_else(|| {
            let name = rustix::system::uname();
            let host = name.nodename().to_string_lossy();
            if host.is_empty() {
                "spoofwatch".to_string()
            } else {
                host.into_owned()
            }
        })
    }

    /// The database size limit in bytes.
    pub fn database_max_bytes(&self) -> Option<u64> {
        self.database_max_mib.map(|mib| mib * 1024 * 1024)
    }

    /// The snapshot policy; `Err` names the flag when the TTL would expire the snapshots of
    /// sessions still held in memory.
    pub fn snapshot_policy(&self) -> Result<crate::detection::SnapshotPolicy, String> {
        let shortest = self.session_idle_secs.max(self.snapshot_every_secs);
        if self.snapshot_ttl_secs <= shortest {
            return Err(format!(
                "--snapshot-ttl-secs {} must exceed --session-idle-secs and --snapshot-every-secs \
                 ({shortest}): a snapshot could expire while its session is still held",
                self.snapshot_ttl_secs
            ));
        }
        Ok(crate::detection::SnapshotPolicy {
            every_samples: self.snapshot_every_samples,
            every: Duration::from_secs(self.snapshot_every_secs),
            ttl: Duration::from_secs(self.snapshot_ttl_secs),
        })
    }

    /// How incidents are correlated; the error names the flag out of range.
    pub fn incident_settings(&self) -> Result<IncidentSettings, String> {
        if !(0.1..=200.0).contains(&self.incident_radius_km) {
            return Err(format!(
                "--incident-radius-km must be finite and in [0.1, 200] km, got {}",
                self.incident_radius_km
            ));
        }
        let area = spoofwatch_core::incident::AreaConfig {
            radius_m: self.incident_radius_km * 1_000.0,
            window_s: self.incident_window_secs as f64,
            min_vehicles: self.incident_min_vehicles,
            min_sources: self.incident_min_sources,
            max_incidents_per_source: self.incident_max_per_source,
            quiet_s: self.incident_quiet_secs as f64,
            ..spoofwatch_core::incident::AreaConfig::default()
        };
        if let Err((field, reason)) = area.validate() {
            let flag = match field {
                "window_s" => "--incident-window-secs",
                "min_vehicles" => "--incident-min-vehicles",
                "min_sources" => "--incident-min-sources",
                "max_incidents_per_source" => "--incident-max-per-source",
                "quiet_s" => "--incident-quiet-secs",
                other => other,
            };
            return Err(format!("{flag}: {reason}"));
        }
        Ok(IncidentSettings {
            area,
            timeline: self.incident_timeline,
            prior: self.incident_prior,
        })
    }

    pub fn session_idle(&self) -> Duration {
        Duration::from_secs(self.session_idle_secs)
    }

    pub fn shutdown_grace(&self) -> Duration {
        Duration::from_secs(self.shutdown_grace_secs)
    }

    pub fn handshake_timeout(&self) -> Duration {
        Duration::from_secs(self.handshake_timeout_secs)
    }

    pub fn stream_idle(&self) -> Duration {
        Duration::from_secs(self.stream_idle_secs)
    }
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[test]
    fn default_matches_the_command_line_defaults() {
        let parsed = Config::try_parse_from(["spoofwatch-server"]).expect("no flags");
        let default = Config::default();
        // Environment fallbacks may set these on a developer machine; the rest must agree.
        if std::env::vars().all(|(k, _)| !k.starts_with("SPOOFWATCH_")) {
            assert_eq!(format!("{parsed:?}"), format!("{default:?}"));
        }
        assert_eq!(default.listen.to_string(), "127.0.0.1:50051");
        assert_eq!(default.metrics_listen, None, "metrics are off by default");
        assert_eq!(default.log_format, LogFormat::Text);
    }

    #[test]
    fn metrics_and_log_format_flags_parse() {
        let parsed = Config::try_parse_from([
            "spoofwatch-server",
            "--metrics-listen",
            "0.0.0.0:9464",
            "--log-format",
            "json",
        ])
        .expect("valid flags");
        assert_eq!(
            parsed.metrics_listen,
            Some("0.0.0.0:9464".parse().expect("an address"))
        );
        assert_eq!(parsed.log_format, LogFormat::Json);
        assert!(Config::try_parse_from(["spoofwatch-server", "--log-format", "xml"]).is_err());
    }

    #[test]
    fn the_token_is_never_a_command_line_argument() {
        // It would show in every process listing: only the environment or a file carry it.
        assert!(Config::try_parse_from(["spoofwatch-server", "--auth-token", "s3cret"]).is_err());
        let parsed = Config::try_parse_from(["spoofwatch-server", "--auth-token-file", "t.txt"])
            .expect("a token file");
        assert_eq!(parsed.auth_token_file, Some(PathBuf::from("t.txt")));
    }

    #[test]
    fn a_tls_certificate_and_key_go_together_and_mtls_needs_both() {
        let parse = |args: &[&str]| {
            Config::try_parse_from(std::iter::once("spoofwatch-server").chain(args.iter().copied()))
        };
        assert!(parse(&["--tls-cert", "c.pem"]).is_err());
        assert!(parse(&["--tls-key", "k.pem"]).is_err());
        assert!(parse(&["--tls-client-ca", "ca.pem"]).is_err());
        let parsed = parse(&[
            "--tls-cert",
            "c.pem",
            "--tls-key",
            "k.pem",
            "--tls-client-ca",
            "ca.pem",
        ])
        .expect("complete TLS flags");
        assert_eq!(parsed.tls_client_ca, Some(PathBuf::from("ca.pem")));
        assert!(parse(&["--stream-idle-secs", "0"]).is_err());
    }
}
