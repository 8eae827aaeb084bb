//! The flags that say where a server is and how to reach it (address, token, TLS files, gzip),
//! shared by every command that talks to one. Owns only the flags and the connection they make.

use std::path::PathBuf;

use anyhow::Result;

use crate::connection::{ConnectOptions, Connection, DEFAULT_SERVER_ADDRESS};

/// Where the server is and how to authenticate. The flags are global: they may follow a
/// subcommand (`spoofwatch models list --server …`).
#[derive(Debug, Clone, clap::Args)]
pub struct ServerArgs {
    /// Spoofwatch server: a URL (`http://…`, `https://…`) or `host:port` (https when a TLS flag is
    /// given, else http).
    #[arg(long, global = true, env = "SPOOFWATCH_SERVER", default_value = DEFAULT_SERVER_ADDRESS)]
    pub server: String,
    /// Bearer token sent as `authorization: Bearer <token>` with every request.
    #[arg(long, global = true, env = "SPOOFWATCH_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    #[command(flatten)]
    pub transport: TransportArgs,
}

/// A server that `demo` and `bench` may be given: without one the operator's binary refuses and
/// the research binary starts one in-process.
#[derive(Debug, Clone, clap::Args)]
pub struct OptionalServerArgs {
    /// Run against this server; without it `spoofwatch-lab` starts one in-process (temporary
    /// database). Deliberately not read from SPOOFWATCH_SERVER.
    #[arg(long)]
    pub server: Option<String>,
    /// Bearer token for --server.
    #[arg(long, env = "SPOOFWATCH_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    #[command(flatten)]
    pub transport: TransportArgs,
}

impl OptionalServerArgs {
    /// Connection options for --server.
    pub fn options(&self) -> ConnectOptions {
        self.transport.options(self.token.clone())
    }
}

/// TLS files and compression of a connection (shared by every command that takes `--server`).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct TransportArgs {
    /// CA certificate(s) (PEM) to trust for the server; without it `https://` trusts the
    /// built-in web PKI roots (Mozilla's).
    #[arg(long, global = true, env = "SPOOFWATCH_CA_CERT")]
    pub ca_cert: Option<PathBuf>,
    /// Client certificate (PEM) for a server that requires mutual TLS; needs --client-key.
    #[arg(
        long,
        global = true,
        env = "SPOOFWATCH_CLIENT_CERT",
        requires = "client_key"
    )]
    pub client_cert: Option<PathBuf>,
    /// Private key (PEM) of --client-cert.
    #[arg(
        long,
        global = true,
        env = "SPOOFWATCH_CLIENT_KEY",
        requires = "client_cert"
    )]
    pub client_key: Option<PathBuf>,
    /// Compress requests with gzip and ask for gzip replies (for slow links; costs CPU).
    #[arg(long, global = true)]
    pub gzip: bool,
}

impl TransportArgs {
    /// Connection options with these files and `token`.
    pub fn options(&self, token: Option<String>) -> ConnectOptions {
        ConnectOptions {
            token,
            ca_cert: self.ca_cert.clone(),
            client_cert: self.client_cert.clone(),
            client_key: self.client_key.clone(),
            gzip: self.gzip,
        }
    }
}

impl ServerArgs {
    /// Connects (within the connect timeout).
    pub async fn connect(&self) -> Result<Connection> {
        let options = self.transport.options(self.token.clone());
        Ok(Connection::connect_with(&self.server, &options).await?)
    }

    /// Connections for `streams` concurrent streams, at most `per_connection` on each.
    pub async fn connect_pool(
        &self,
        streams: usize,
        per_connection: usize,
    ) -> Result<Vec<Connection>> {
        let options = self.transport.options(self.token.clone());
        Ok(Connection::pool(&self.server, &options, streams, per_connection).await?)
    }
}
