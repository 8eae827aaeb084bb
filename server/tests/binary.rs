//! The real `spoofwatch-server` binary: it starts on a free port with a fresh database, serves,
//! exits cleanly (code 0) on SIGTERM, recovers after a crash, loses no alarm to another process
//! reading its database file, and holds a large upload within twice its size in memory.
#![cfg(unix)]

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use spoofwatch_core::data::telemetry::write_tracks;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{AttackKind, AttackSpec, DriveSpec, inject, simulate_drive};
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::dataset_service_client::DatasetServiceClient;
use spoofwatch_proto::v1::detection_service_client::DetectionServiceClient;
use spoofwatch_proto::v1::training_service_client::TrainingServiceClient;
use spoofwatch_server::store::{AlarmEventRow, Store};
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
        // Keep reading after the receiver is gone: a full pipe would block the server's logging.
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line);
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

/// A running server binary on a free loopback port.
struct Running {
    process: ServerProcess,
    addr: SocketAddr,
    log: mpsc::Receiver<String>,
}

/// Starts the binary on `database` and waits for its listening address (from its log).
fn spawn_server(database: &Path) -> Running {
    spawn_server_with(database, &[]).0
}

/// [`spawn_server`] with extra flags; also returns the log lines read up to the listening address.
fn spawn_server_with(database: &Path, flags: &[&str]) -> (Running, Vec<String>) {
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
        .arg(database)
        .args(flags)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the server binary starts");
    let mut process = ServerProcess(child);
    let log = stderr_lines(&mut process.0);
    let deadline = Instant::now() + STARTUP_BOUND;
    let mut startup = Vec::new();
    let port = loop {
        let remaining = deadline.saturating_duration_since(Instant::now());
        let line = log
            .recv_timeout(remaining)
            .expect("the binary logs its listening address");
        let port = listening_port(&line);
        startup.push(line);
        if let Some(port) = port {
            break port;
        }
    };
    let running = Running {
        process,
        addr: SocketAddr::from(([127, 0, 0, 1], port)),
        log,
    };
    (running, startup)
}

/// Sends `signal` (e.g. `-TERM`) to the child and waits for its exit status.
async fn signal_and_wait(process: &mut ServerProcess, signal: &str) -> std::process::ExitStatus {
    let pid = process.0.id().to_string();
    let sent = Command::new("kill")
        .args([signal, &pid])
        .status()
        .expect("kill runs");
    assert!(sent.success());
    let deadline = Instant::now() + EXIT_BOUND;
    loop {
        if let Some(status) = process.0.try_wait().expect("the child can be waited for") {
            return status;
        }
        assert!(
            Instant::now() < deadline,
            "the binary did not exit after kill {signal}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_binary_serves_and_exits_cleanly_on_sigterm() {
    let dir = tempfile::tempdir().expect("temp dir");
    let database = dir.path().join("binary.db");
    let Running {
        process: mut server,
        addr,
        log: lines,
    } = spawn_server(&database);

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

    let status = signal_and_wait(&mut server, "-TERM").await;
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

/// Three 300 s simulated drives at 1 Hz, one with a ramp attack spanning the training and
/// validation parts of the chronological split, as a telemetry CSV.
fn small_fleet_csv() -> Vec<u8> {
    let ramp = AttackKind::RampDrift { velocity_mps: 1.5 };
    let tracks = vec![
        drive("crash-0", 300.0, 1, None),
        drive("crash-1", 300.0, 2, Some((ramp, 150.0, 100.0))),
        drive("crash-2", 300.0, 3, None),
    ];
    let mut csv = Vec::new();
    write_tracks(&mut csv, &tracks).expect("the tracks serialise");
    csv
}

/// A simulated drive, optionally with an attack (kind, onset, duration).
fn drive(
    vehicle_id: &str,
    seconds: f64,
    seed: u64,
    attack: Option<(AttackKind, f64, f64)>,
) -> Track {
    let spec = DriveSpec {
        duration_s: seconds,
        seed,
        ..DriveSpec::default()
    };
    let track = simulate_drive(&spec, vehicle_id).expect("a valid drive");
    let Some((kind, onset_s, duration_s)) = attack else {
        return track;
    };
    let attack = AttackSpec {
        kind,
        direction_deg: 90.0,
        onset_s,
        duration_s,
        seed: Some(seed),
    };
    let mut injected = inject(&track, &attack).expect("a valid attack").track;
    injected.vehicle_id = vehicle_id.to_string();
    injected
}

fn to_proto(sample: &spoofwatch_core::sample::Sample) -> v1::Sample {
    v1::Sample {
        timestamp_s: sample.timestamp_s,
        latitude_deg: sample.latitude_deg,
        longitude_deg: sample.longitude_deg,
        speed_mps: sample.speed_mps,
        heading_deg: sample.heading_deg,
        ..v1::Sample::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_crash_the_running_job_is_failed_and_open_alarms_are_closed() {
    use spoofwatch_proto::longrunning;
    use v1::upload_dataset_request::Kind;
    let dir = tempfile::tempdir().expect("temp dir");
    let database = dir.path().join("crash.db");
    let Running {
        process: mut server,
        addr,
        ..
    } = spawn_server(&database);
    let channel = wait_until_serving(addr).await;
    let messages = [
        Kind::Header(v1::UploadDatasetHeader {
            display_name: "crash fleet".into(),
        }),
        Kind::CsvChunk(small_fleet_csv()),
    ]
    .map(|kind| v1::UploadDatasetRequest { kind: Some(kind) });
    let dataset = DatasetServiceClient::new(channel.clone())
        .upload_dataset(tokio_stream::iter(messages))
        .await
        .expect("the upload is accepted")
        .into_inner();
    let job = TrainingServiceClient::new(channel.clone())
        .create_training_job(v1::CreateTrainingJobRequest {
            datasets: vec![dataset.name],
            spec: Some(v1::TrainingSpec {
                max_epochs: 200,
                // 210 s training parts are too short for the v2 drift channels' 120 s scale.
                feature_schema: "paper".into(),
                ..v1::TrainingSpec::default()
            }),
            ..v1::CreateTrainingJobRequest::default()
        })
        .await
        .expect("the training job is accepted")
        .into_inner();
    let mut watch = TrainingServiceClient::new(channel.clone())
        .watch_job(v1::WatchJobRequest {
            name: job.name.clone(),
        })
        .await
        .expect("WatchJob is accepted")
        .into_inner();
    loop {
        let update = watch
            .message()
            .await
            .expect("the watch works")
            .expect("the job is still going");
        if update.state == v1::JobState::Running as i32 {
            break;
        }
    }

    // A drive whose GNSS fix freezes from 100 s on: the server is killed while the alarm it
    // raised is open.
    let attacked = drive(
        "crash-car",
        240.0,
        21,
        Some((AttackKind::FrozenPosition, 100.0, 130.0)),
    );
    let mut detection = DetectionServiceClient::new(channel.clone());
    let mut alarming = false;
    for chunk in attacked.records.chunks(10) {
        let response = detection
            .detect(v1::DetectRequest {
                vehicle_id: "crash-car".into(),
                samples: chunk.iter().map(|r| to_proto(&r.sample)).collect(),
                ..v1::DetectRequest::default()
            })
            .await
            .expect("Detect works")
            .into_inner();
        alarming = response.detections.last().is_some_and(|d| d.alarm);
        if alarming {
            break;
        }
    }
    assert!(alarming, "the frozen fix raised an alarm");
    drop((watch, detection, channel));
    // The onset is stored, and the session snapshot taken with it holds the alarm open, before the
    // kill: what the writer had not stored yet is lost in a crash by design.
    let store = open_store(&database).await;
    let deadline = Instant::now() + Duration::from_secs(10);
    let onset = loop {
        let events = crash_car_alarms(&store).await;
        let snapshot = store.load_snapshot("crash-car").await.expect("snapshot");
        if let ([event], Some(snapshot)) = (events.as_slice(), &snapshot)
            && snapshot.open_alarm_id == Some(event.id)
        {
            break event.clone();
        }
        assert!(
            Instant::now() < deadline,
            "stored: {events:?}, {snapshot:?}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    store.close().await;
    assert!(onset.is_open());

    let status = signal_and_wait(&mut server, "-KILL").await;
    assert_eq!(status.code(), None, "killed by a signal");

    // First restart: the running job fails; the alarm stays open, as its session snapshot holds
    // it (the vehicle may resume on any replica and continue it).
    let Running {
        process: mut restarted,
        addr,
        ..
    } = spawn_server(&database);
    let channel = wait_until_serving(addr).await;
    let operation = longrunning::operations_client::OperationsClient::new(channel.clone())
        .get_operation(longrunning::GetOperationRequest {
            name: job.name.clone(),
        })
        .await
        .expect("the job is still known")
        .into_inner();
    assert!(operation.done, "nothing is left running after a restart");
    let Some(longrunning::operation::Result::Error(error)) = &operation.result else {
        panic!("an interrupted job ends with an error: {operation:?}");
    };
    assert_eq!(error.code, tonic::Code::Aborted as i32);
    assert!(error.message.contains("restarted"), "{}", error.message);
    drop(channel);
    assert_eq!(
        signal_and_wait(&mut restarted, "-TERM").await.code(),
        Some(0)
    );
    let store = open_store(&database).await;
    let events = crash_car_alarms(&store).await;
    assert_eq!(
        events,
        std::slice::from_ref(&onset),
        "a held alarm stays open"
    );

    // Second restart, as after a crash that came before the snapshot was stored: no snapshot holds
    // the alarm, so the start ends it, without an end sample.
    assert_eq!(
        store
            .delete_snapshots_of_model(&onset.model_id)
            .await
            .expect("the snapshot is deleted"),
        1
    );
    store.close().await;
    let Running {
        process: mut restarted,
        addr,
        ..
    } = spawn_server(&database);
    drop(wait_until_serving(addr).await);
    assert_eq!(
        signal_and_wait(&mut restarted, "-TERM").await.code(),
        Some(0)
    );
    let store = open_store(&database).await;
    let events = crash_car_alarms(&store).await;
    store.close().await;
    let [closed] = events.as_slice() else {
        panic!("one alarm: {events:?}");
    };
    assert_eq!(closed.id, onset.id);
    assert!(!closed.is_open(), "the restart ended it: {closed:?}");
    assert_eq!(closed.end_timestamp_s, None, "no end sample: {closed:?}");
}

/// The store of the server's database file, opened beside (or after) the server.
async fn open_store(database: &Path) -> Store {
    Store::open(&database.display().to_string())
        .await
        .expect("the database opens")
}

/// The stored alarms of the crash test's vehicle, newest first.
async fn crash_car_alarms(store: &Store) -> Vec<AlarmEventRow> {
    store
        .list_alarm_events(Some("crash-car"), 100)
        .await
        .expect("alarm events")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_binary_survives_a_closed_stderr() {
    let dir = tempfile::tempdir().expect("temp dir");
    // The log cannot tell the port here, so probe a free one (the tiny reuse race is acceptable).
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let child = Command::new(env!("CARGO_BIN_EXE_spoofwatch-server"))
        .env_clear()
        .env("SPOOFWATCH_LOG", "info")
        .args(["--listen", &format!("127.0.0.1:{port}"), "--database"])
        .arg(dir.path().join("closed-stderr.db"))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the server binary starts");
    let mut server = ServerProcess(child);
    // Every log line the server writes from now on fails with EPIPE.
    drop(server.0.stderr.take());

    let channel = wait_until_serving(SocketAddr::from(([127, 0, 0, 1], port))).await;
    let response = DetectionServiceClient::new(channel)
        .detect(v1::DetectRequest {
            samples: (0..3).map(|i| sample(f64::from(i))).collect(),
            ..v1::DetectRequest::default()
        })
        .await
        .expect("Detect works although logging fails")
        .into_inner();
    assert_eq!(response.detections.len(), 3);
    let status = signal_and_wait(&mut server, "-TERM").await;
    assert_eq!(status.code(), Some(0), "clean exit: {status:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn json_logs_are_one_object_per_line_with_top_level_fields() {
    let dir = tempfile::tempdir().expect("temp dir");
    let database = dir.path().join("json-logs.db");
    let (
        Running {
            process: mut server,
            addr,
            log: lines,
        },
        mut log,
    ) = spawn_server_with(
        &database,
        &["--log-format", "json", "--metrics-listen", "127.0.0.1:0"],
    );
    wait_until_serving(addr).await;
    let status = signal_and_wait(&mut server, "-TERM").await;
    assert_eq!(status.code(), Some(0), "clean exit on SIGTERM: {status:?}");
    while let Ok(line) = lines.recv_timeout(EXIT_BOUND) {
        log.push(line);
    }

    let events: Vec<serde_json::Value> = log
        .iter()
        .map(|line| {
            serde_json::from_str(line).unwrap_or_else(|e| panic!("not a JSON line ({e}): {line}"))
        })
        .collect();
    for event in &events {
        for key in ["timestamp", "level", "target", "message"] {
            assert!(event[key].is_string(), "{key} missing in {event}");
        }
    }
    let message = |text: &str| {
        events
            .iter()
            .find(|e| e["message"] == text)
            .unwrap_or_else(|| panic!("no {text:?} line in {log:?}"))
    };
    let listening = message("spoofwatch-server listening");
    assert_eq!(listening["addr"], addr.to_string(), "fields are top-level");
    assert_eq!(listening["level"], "INFO");
    let metrics = message("metrics listening (GET /metrics)");
    assert!(
        metrics["addr"]
            .as_str()
            .is_some_and(|a| a.starts_with("127.0.0.1:")),
        "{metrics}"
    );
    message("server stopped");
}

/// One field of `/proc/PID/status`, in KiB (`VmRSS`, `VmHWM`).
fn memory_kib(pid: u32, field: &str) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("process status");
    status
        .lines()
        .find_map(|line| line.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|rest| rest.split_whitespace().next()?.parse().ok())
        .unwrap_or_else(|| panic!("no {field} in the process status"))
}

/// A telemetry CSV of just under `size` bytes: 1,000 vehicles at 1 Hz.
fn telemetry_csv(size: usize) -> Vec<u8> {
    let mut csv = b"vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,label\n".to_vec();
    for n in 0.. {
        let (vehicle, t) = (n % 1000, n / 1000);
        let row = format!(
            "vehicle-{vehicle:04},{},{:.7},{:.7},10.5,{}.5,{}\n",
            1_700_000_000 + t,
            32.2 + f64::from(vehicle) * 1e-3 + f64::from(t) * 1e-5,
            -110.9 + f64::from(t) * 1e-5,
            (n * 7) % 360,
            u8::from(t > 1500)
        );
        if csv.len() + row.len() > size {
            break;
        }
        csv.extend_from_slice(row.as_bytes());
    }
    csv
}

/// The server's whole resident memory peaks within twice the size of a 128 MiB CSV upload: the
/// upload is held once, in pieces, and only counted while it is checked, never built as tracks.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_128_mib_csv_upload_peaks_within_twice_its_size() {
    use v1::upload_dataset_request::Kind;
    let dir = tempfile::tempdir().expect("temp dir");
    let Running {
        process: mut server,
        addr,
        ..
    } = spawn_server(&dir.path().join("upload.db"));
    let channel = wait_until_serving(addr).await;
    let csv = telemetry_csv(128 << 20);
    let messages: Vec<v1::UploadDatasetRequest> =
        std::iter::once(Kind::Header(v1::UploadDatasetHeader::default()))
            .chain(
                csv.chunks(1 << 20)
                    .map(|chunk| Kind::CsvChunk(chunk.to_vec())),
            )
            .map(|kind| v1::UploadDatasetRequest { kind: Some(kind) })
            .collect();
    let dataset = DatasetServiceClient::new(channel)
        .upload_dataset(tokio_stream::iter(messages))
        .await
        .expect("the upload is stored")
        .into_inner();
    assert_eq!(dataset.size_bytes, csv.len() as u64);
    assert_eq!(dataset.vehicles, 1000);
    let peak_kib = memory_kib(server.0.id(), "VmHWM");
    let upload_kib = csv.len() as u64 / 1024;
    assert!(
        peak_kib <= 2 * upload_kib,
        "the server's resident memory peaked at {peak_kib} KiB for an upload of {upload_kib} KiB"
    );
    assert!(signal_and_wait(&mut server, "-TERM").await.success());
}

/// Another process reading the database file while the server stores bursts of alarm onsets (a
/// `sqlite3` shell, a backup, a monitoring script) must not take the write-ahead log from under
/// it: a reader that opens, reads and closes the file deletes the log whenever the server holds
/// no lock on it, and the server then writes into a deleted file. Every onset the clients were
/// shown is readable by other processes, still stored after a `kill -9`, and a restarted server
/// stores more. The reader is Python's `sqlite3` module, a SQLite client of its own, as the
/// `sqlite3` shell would be.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stray_reader_of_the_database_loses_no_alarm() {
    const VEHICLES: usize = 60;
    const BURSTS: usize = 4;
    let dir = tempfile::tempdir().expect("temp dir");
    let database = dir.path().join("stray-reader.db");
    let Running {
        process: mut server,
        addr,
        ..
    } = spawn_server(&database);
    let channel = wait_until_serving(addr).await;
    let reader = StrayReader::start(&database);

    // Each burst: every vehicle drives up to its frozen fix, then all send the frozen part at
    // once. Between bursts the server goes idle, and the reader reads alone.
    let attacked = drive(
        "stray",
        160.0,
        31,
        Some((AttackKind::FrozenPosition, 100.0, 60.0)),
    );
    let (before, during): (Vec<_>, Vec<_>) = attacked
        .records
        .iter()
        .map(|r| to_proto(&r.sample))
        .partition(|s| s.timestamp_s < 100.0);
    let mut shown = 0;
    for burst in 0..BURSTS {
        let vehicles: Vec<String> = (0..VEHICLES)
            .map(|v| format!("stray-{burst}-{v}"))
            .collect();
        for part in [&before, &during] {
            let mut calls = tokio::task::JoinSet::new();
            for vehicle in &vehicles {
                let mut detection = DetectionServiceClient::new(channel.clone());
                let request = v1::DetectRequest {
                    vehicle_id: vehicle.clone(),
                    samples: part.clone(),
                    ..v1::DetectRequest::default()
                };
                calls.spawn(async move { detection.detect(request).await });
            }
            while let Some(call) = calls.join_next().await {
                let response = call.expect("the call ran").expect("Detect works");
                shown += response
                    .into_inner()
                    .detections
                    .iter()
                    .filter(|d| d.alarm_onset)
                    .count();
            }
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    assert!(
        shown >= VEHICLES * BURSTS,
        "every frozen fix alarmed: {shown}"
    );

    // Another process sees every onset shown, while the stray reader still reads.
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let store = open_store(&database).await;
        let stored = stored_onsets(&store).await;
        store.close().await;
        if stored == shown {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "{stored} of {shown} onsets shown are visible to other processes"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let reads = reader.stop();
    assert!(reads > 10, "the stray reader read {reads} times");

    let status = signal_and_wait(&mut server, "-KILL").await;
    assert_eq!(status.code(), None, "killed by a signal");
    let store = open_store(&database).await;
    assert_eq!(stored_onsets(&store).await, shown, "stored after the kill");
    store.close().await;

    // Nothing is wedged: a restarted server stores a new alarm.
    let Running {
        process: mut restarted,
        addr,
        ..
    } = spawn_server(&database);
    let mut detection = DetectionServiceClient::new(wait_until_serving(addr).await);
    let samples = attacked.records.iter().map(|r| to_proto(&r.sample));
    let onsets = detection
        .detect(v1::DetectRequest {
            vehicle_id: "after-the-kill".into(),
            samples: samples.collect(),
            ..v1::DetectRequest::default()
        })
        .await
        .expect("Detect works after the restart")
        .into_inner()
        .detections
        .iter()
        .filter(|d| d.alarm_onset)
        .count();
    assert!(onsets >= 1, "the frozen fix alarmed after the restart");
    drop(detection);
    assert_eq!(
        signal_and_wait(&mut restarted, "-TERM").await.code(),
        Some(0)
    );
    let store = open_store(&database).await;
    assert_eq!(stored_onsets(&store).await, shown + onsets);
    store.close().await;
}

/// A Python process that opens the database with its own SQLite, reads and closes it, every 2 ms,
/// until told to stop.
struct StrayReader {
    process: ServerProcess,
    stop_file: PathBuf,
}

impl StrayReader {
    const SCRIPT: &str = "\
import os, sqlite3, sys, time
database, stop_file = sys.argv[1], sys.argv[2]
reads = 0
while not os.path.exists(stop_file):
    try:
        connection = sqlite3.connect(database, timeout=0.1)
        connection.execute('SELECT count(*) FROM alarm_events').fetchone()
        connection.close()
        reads += 1
    except sqlite3.Error:
        pass  # a busy or locked file is part of sharing it: try again
    time.sleep(0.002)
print(reads)
";

    fn start(database: &Path) -> StrayReader {
        let stop_file = database.with_extension("stop-reading");
        let child = Command::new("python3")
            .args(["-c", Self::SCRIPT])
            .arg(database)
            .arg(&stop_file)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .spawn()
            .expect("python3 runs (the stray reader)");
        StrayReader {
            process: ServerProcess(child),
            stop_file,
        }
    }

    /// Stops the reader; returns how many times it read.
    fn stop(mut self) -> usize {
        std::fs::write(&self.stop_file, b"").expect("the stop file is written");
        let mut out = String::new();
        std::io::Read::read_to_string(
            self.process.0.stdout.as_mut().expect("stdout is piped"),
            &mut out,
        )
        .expect("the reader's count");
        assert!(self.process.0.wait().expect("waited").success());
        out.trim().parse().expect("a count")
    }
}

/// How many alarm onsets the database holds.
async fn stored_onsets(store: &Store) -> usize {
    store
        .list_alarm_events(None, 100_000)
        .await
        .expect("alarm events")
        .len()
}
