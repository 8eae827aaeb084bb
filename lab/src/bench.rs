//! `spoofwatch-lab bench`: the operator's load benchmark (client library) against servers started
//! in this process; with `--server`, exactly `spoofwatch bench`. It owns only starting and stopping
//! those servers: one for the throughput and memory phases, two on one temporary SQLite database
//! for the hand-off phase.

use std::time::Duration;

use anyhow::{Context, Result};
use spoofwatch_client::cli::remote::bench::{self, Args};
use spoofwatch_client::connection::{ConnectOptions, Connection};
use spoofwatch_server::inprocess::InProcessServer;

pub async fn run(args: Args) -> Result<()> {
    if args.server.server.is_some() {
        bench::run(args).await
    } else if args.handoff > 0 {
        handoff_in_process(&args).await
    } else {
        load_in_process(&args).await
    }
}

/// Benchmarks a server started in this process (no token: it has none).
async fn load_in_process(args: &Args) -> Result<()> {
    let server = InProcessServer::start(|_| {}).await?;
    let url = server.url();
    println!(
        "in-process server on {url} (temporary database); client and server share this \
         process, so its CPU and memory numbers include the client"
    );
    let options = ConnectOptions::default();
    let result = bench::load(args, &url, options, Some(std::process::id())).await;
    server.shutdown().await?;
    result
}

/// The hand-off phase between two servers in this process on one temporary SQLite database.
async fn handoff_in_process(args: &Args) -> Result<()> {
    let first = InProcessServer::start(|_| {}).await?;
    // The second server may open the database only once the first has created it.
    Connection::wait_until_serving(
        &first.url(),
        &ConnectOptions::default(),
        Duration::from_secs(30),
    )
    .await?;
    let database = first
        .database_dir()
        .context("the in-process server has a temporary database")?
        .join("spoofwatch.db");
    let mut config = spoofwatch_server::Config::with_database(database.display().to_string());
    config.shutdown_grace_secs = 2;
    let second = InProcessServer::start_with(config).await?;
    println!(
        "two in-process servers on one temporary database ({}); they share this process's CPU",
        database.display()
    );
    let options = ConnectOptions::default();
    let result = bench::handoff(args, &first.url(), &second.url(), options).await;
    second.shutdown().await?;
    first.shutdown().await?;
    result
}
