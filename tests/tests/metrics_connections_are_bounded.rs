//! The metrics port cannot be held by silent connections: each one is closed once the header-read
//! timeout (10 s) passes, at most 64 are served at once (more wait in the listen backlog, taking
//! no descriptor of the server's), and a scrape that comes in while the cap is full is served
//! once a slot frees.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use spoofwatch_tests::start_server;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// The endpoint's cap on connections served at once.
const MAX_CONNECTIONS: usize = 64;
/// The endpoint's header-read timeout.
const HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);
/// Slack for a debug build on two shared cores.
const SLACK: Duration = Duration::from_secs(5);

/// Waits until the server closes `stream` (EOF or reset); anything it sends first (a 408) is read
/// and ignored.
async fn closed_by_the_server(mut stream: TcpStream) -> Instant {
    let mut buffer = [0u8; 1024];
    loop {
        match stream.read(&mut buffer).await {
            Ok(0) | Err(_) => return Instant::now(),
            Ok(_) => continue,
        }
    }
}

/// A one-request scrape (`Connection: close`); returns the status line.
async fn scrape(addr: SocketAddr) -> String {
    let mut stream = TcpStream::connect(addr)
        .await
        .expect("connect for a scrape");
    stream
        .write_all(b"GET /metrics HTTP/1.1\r\nHost: metrics\r\nConnection: close\r\n\r\n")
        .await
        .expect("send the request");
    let mut response = Vec::new();
    stream
        .read_to_end(&mut response)
        .await
        .expect("read the response");
    let text = String::from_utf8_lossy(&response);
    text.lines().next().unwrap_or_default().to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_connections_are_closed_and_a_scrape_gets_through() {
    let (_dir, server, clients) = start_server(|config| {
        config.metrics_listen = Some(SocketAddr::from(([127, 0, 0, 1], 0)));
    })
    .await;
    let addr = server.metrics_addr().expect("a metrics address");
    assert!(scrape(addr).await.starts_with("HTTP/1.1 200"));

    let opened = Instant::now();
    let mut silent = Vec::new();
    for _ in 0..MAX_CONNECTIONS + 6 {
        let stream = TcpStream::connect(addr).await.expect("connect silently");
        silent.push(tokio::spawn(closed_by_the_server(stream)));
    }
    // Comes in with the cap full: served once the first silent connections time out.
    let scraped = tokio::time::timeout(HEADER_READ_TIMEOUT + SLACK, scrape(addr))
        .await
        .expect("the scrape is served once the silent connections time out");
    assert!(scraped.starts_with("HTTP/1.1 200"), "{scraped}");

    // The first 64 within the timeout; those that waited in the backlog within another.
    for (i, closed) in silent.into_iter().enumerate() {
        let closed = tokio::time::timeout(2 * (HEADER_READ_TIMEOUT + SLACK), closed)
            .await
            .unwrap_or_else(|_| panic!("silent connection {i} was never closed"))
            .expect("the reader ends");
        if i < MAX_CONNECTIONS {
            assert!(
                closed - opened <= HEADER_READ_TIMEOUT + SLACK,
                "connection {i} closed after {:?}",
                closed - opened
            );
        }
    }
    assert!(scrape(addr).await.starts_with("HTTP/1.1 200"));
    drop(clients);
    server.stop().await;
}
