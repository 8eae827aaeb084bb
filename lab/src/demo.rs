//! `spoofwatch-lab demo`: the operator's demo drive (client library) against a server started in
//! this process on a temporary database; with `--server`, exactly `spoofwatch demo`. It owns only
//! the in-process server's start and stop.

use anyhow::Result;
use spoofwatch_client::cli::remote::demo::{self, Args, drive};
use spoofwatch_client::connection::ConnectOptions;
use spoofwatch_server::inprocess::InProcessServer;

pub async fn run(args: Args) -> Result<()> {
    if args.server.server.is_some() {
        return demo::run(args).await;
    }
    let (track, attack) = drive::scenario(args.seed, args.drift)?;
    let server = InProcessServer::start(|_| {}).await?;
    println!(
        "in-process server on {} (temporary database in {})",
        server.url(),
        server
            .database_dir()
            .unwrap_or(std::path::Path::new("?"))
            .display()
    );
    // The in-process server has no token and no TLS.
    let options = ConnectOptions::default();
    let result = drive::stream_drive(&server.url(), &options, &track, &attack, args.rate).await;
    server.shutdown().await?;
    println!("server stopped");
    result
}
