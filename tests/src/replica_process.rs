//! A server process for the tests that kill one: the `spoofwatch-test-replica` binary on a given
//! database, listening on a free port, its log kept drained, killed with SIGKILL when dropped.
//!
//! Owns starting and killing that process. Must not decide what a test does with it.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use crate::{Clients, Connection};

/// A generous bound for a debug binary on shared cores to say where it listens.
const STARTUP_BOUND: Duration = Duration::from_secs(60);

/// A running server process.
pub struct ReplicaProcess {
    child: Child,
    pub addr: SocketAddr,
    /// Its log lines, kept drained.
    _log: mpsc::Receiver<String>,
}

impl ReplicaProcess {
    /// Starts `binary` (a test's `env!("CARGO_BIN_EXE_spoofwatch-test-replica")`) on `database`
    /// as `instance`, and waits until it logs where it listens.
    pub fn start(binary: &str, database: &str, instance: &str) -> ReplicaProcess {
        let mut child = Command::new(binary)
            .args(["--listen", "127.0.0.1:0", "--database", database])
            .args(["--instance-id", instance])
            .env("SPOOFWATCH_LOG", "info")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("the server process starts");
        let stderr = child.stderr.take().expect("stderr is piped");
        let (tx, log) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                let _ = tx.send(line);
            }
        });
        let deadline = Instant::now() + STARTUP_BOUND;
        let port = loop {
            let line = log
                .recv_timeout(deadline.saturating_duration_since(Instant::now()))
                .expect("the server logs where it listens");
            if let Some(port) = listening_port(&line) {
                break port;
            }
        };
        ReplicaProcess {
            child,
            addr: SocketAddr::from(([127, 0, 0, 1], port)),
            _log: log,
        }
    }

    /// Clients connected to it directly.
    pub async fn clients(&self) -> Clients {
        let connection = Connection::connect(format!("http://{}", self.addr), None)
            .await
            .expect("connect to the server process");
        Clients::new(connection)
    }
}

impl Drop for ReplicaProcess {
    fn drop(&mut self) {
        // `Child::kill` is SIGKILL: a test's kill -9, and the clean-up otherwise.
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The port of the "listening addr=127.0.0.1:PORT" log line (colour codes ignored).
fn listening_port(line: &str) -> Option<u16> {
    if !line.contains("listening") {
        return None;
    }
    let rest = &line[line.find("127.0.0.1:")? + "127.0.0.1:".len()..];
    rest.chars()
        .take_while(char::is_ascii_digit)
        .collect::<String>()
        .parse()
        .ok()
}
