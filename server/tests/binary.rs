//! Issue 4, test 7: the real `spoofwatch-server` binary starts on a free port with a fresh
//! database, serves a Detect call, and exits cleanly (code 0) on SIGTERM.
#![cfg(unix)]

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::detection_service_client::DetectionServiceClient;
use tonic::transport::Channel;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

/// Generous bounds for a debug binary on shared cores.
const STARTUP_BOUND: Duration = Duration::from_secs(60);
const EXIT_BOUND: Duration = Duration::from_secs(20);

/// Kills the child if the test fails before it exits by itself.
struct ServerProcess(Child);

impl Drop for ServerProcess {
    fn drop(&mut self) {
        if let Ok(None) = self.0.try_wait() {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

/// Forwards the child's stderr lines to a channel (and keeps the pipe drained).
fn stderr_lines(child: &mut Child) -> mpsc::Receiver<String> {
    let stderr = child.stderr.take().expect("stderr is piped");
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// The port in the "listening" log line (`... listening addr=127.0.0.1:PORT ...`), ignoring any
/// colour codes around the field.
fn listening_port(line: &str) -> Option<u16> {
    if !line.contains("listening") {
        return None;
    }
    let rest = &line[line.find("127.0.0.1:")? + "127.0.0.1:".len()..];
    let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
    digits.parse().ok()
}

async fn wait_until_serving(addr: SocketAddr) -> Channel {
    let deadline = Instant::now() + STARTUP_BOUND;
    loop {
        if let Ok(channel) = Channel::from_shared(format!("http://{addr}"))
            .expect("a valid URI")
            .connect()
            .await
        {
            let status = HealthClient::new(channel.clone())
                .check(HealthCheckRequest {
                    service: String::new(),
                })
                .await
                .map(|r| r.into_inner().status);
            if matches!(status, Ok(s) if s == ServingStatus::Serving as i32) {
                return channel;
            }
        }
        assert!(
            Instant::now() < deadline,
            "the binary did not become SERVING"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn sample(t: f64) -> v1::Sample {
    v1::Sample {
        timestamp_s: t,
        latitude_deg: 32.23 + t * 1e-5,
        longitude_deg: -110.91,
        speed_mps: 1.1,
        heading_deg: 0.0,
        ..v1::Sample::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_binary_serves_and_exits_cleanly_on_sigterm() {
    let dir = tempfile::tempdir().expect("temp dir");
    let database = dir.path().join("binary.db");
    let child = Command::new(env!("CARGO_BIN_EXE_spoofwatch-server"))
        // A clean environment: no SPOOFWATCH_* settings of the caller leak in (e.g. an auth token).
        .env_clear()
        .env("SPOOFWATCH_LOG", "info")
        .env("NO_COLOR", "1")
        .args([
            "--listen",
            "127.0.0.1:0",
            "--shutdown-grace-secs",
            "2",
            "--database",
        ])
        .arg(&database)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the server binary starts");
    let mut server = ServerProcess(child);
    let lines = stderr_lines(&mut server.0);
    let deadline = Instant::now() + STARTUP_BOUND;
    let port = loop {
        let remaining = deadline.saturating_duration_since(Instant::now());
        let line = lines
            .recv_timeout(remaining)
            .expect("the binary logs its listening address");
        if let Some(port) = listening_port(&line) {
            break port;
        }
    };
    let addr = SocketAddr::from(([127, 0, 0, 1], port));

    let channel = wait_until_serving(addr).await;
    let response = DetectionServiceClient::new(channel)
        .detect(v1::DetectRequest {
            samples: (0..5).map(|i| sample(f64::from(i))).collect(),
            ..v1::DetectRequest::default()
        })
        .await
        .expect("Detect works against the binary")
        .into_inner();
    assert_eq!(response.detections.len(), 5);
    assert_eq!(response.model, "models/default");
    assert!(
        response
            .detections
            .iter()
            .all(|d| (0.0..=1.0).contains(&d.probability))
    );

    let pid = server.0.id().to_string();
    let killed = Command::new("kill")
        .args(["-TERM", &pid])
        .status()
        .expect("kill runs");
    assert!(killed.success());
    let deadline = Instant::now() + EXIT_BOUND;
    let status = loop {
        if let Some(status) = server.0.try_wait().expect("the child can be waited for") {
            break status;
        }
        assert!(
            Instant::now() < deadline,
            "the binary did not exit after SIGTERM"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(status.code(), Some(0), "clean exit on SIGTERM: {status:?}");
    // The reader thread ends at EOF (the child has exited), which disconnects the channel.
    let mut log = Vec::new();
    while let Ok(line) = lines.recv_timeout(EXIT_BOUND) {
        log.push(line);
    }
    assert!(
        log.iter().any(|l| l.contains("server stopped")),
        "the shutdown is logged: {log:?}"
    );
    assert!(database.is_file(), "the database file was created");
}
