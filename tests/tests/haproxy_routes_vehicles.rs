//! The shipped HAProxy configuration (`deploy/haproxy/spoofwatch.cfg`, unchanged: addresses come
//! from its environment variables) in front of two real replicas: its gRPC health check passes
//! (L7OK), every vehicle's streams land on exactly one replica and always the same one (consistent
//! hashing on the `x-vehicle-id` header the client sends), and when one replica stops, HAProxy takes
//! it out and its vehicles are served by the other through the balancer.
//!
//! Needs a real HAProxy (Debian's 2.6): `SPOOFWATCH_HAPROXY` names the binary (`.ci/run` installs
//! it and sets the variable, with `SPOOFWATCH_REQUIRE_HAPROXY=1` so that a missing one fails
//! there); without it the test is skipped with a message.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, Connection, DetectStream, REPLY_TIMEOUT, TestServer, normal_drive, start_server,
    track_samples,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// The replicas' names in the configuration.
const REPLICAS: [&str; 2] = ["replica-1", "replica-2"];
/// Vehicles streamed through the balancer.
const VEHICLES: usize = 12;
/// Longest wait for HAProxy to see a replica's state change.
const STATE_TIMEOUT: Duration = Duration::from_secs(30);

/// The HAProxy binary, or why the test cannot run.
fn haproxy() -> Result<PathBuf, String> {
    let Some(path) = std::env::var_os("SPOOFWATCH_HAPROXY").filter(|v| !v.is_empty()) else {
        return Err("SPOOFWATCH_HAPROXY is not set (apt-get install haproxy; point it at /usr/sbin/haproxy)".into());
    };
    let path = PathBuf::from(path);
    match Command::new(&path).arg("-v").output() {
        Ok(output) if output.status.success() => Ok(path),
        Ok(output) => Err(format!(
            "{} -v failed: {}",
            path.display(),
            String::from_utf8_lossy(&output.stderr)
        )),
        Err(e) => Err(format!("cannot run {}: {e}", path.display())),
    }
}

/// A running HAProxy with the shipped configuration; killed when dropped.
struct Balancer {
    child: Child,
    addr: String,
    admin_socket: PathBuf,
    log: PathBuf,
}

impl Balancer {
    /// Starts `haproxy -db -f deploy/haproxy/spoofwatch.cfg` on a free loopback port in front of
    /// `replicas`, with its runtime API and log in `dir`.
    fn start(haproxy: &Path, dir: &Path, replicas: [&TestServer; 2]) -> Balancer {
        let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/haproxy/spoofwatch.cfg");
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        let addr = format!("127.0.0.1:{port}");
        let admin_socket = dir.join("haproxy.sock");
        let log = dir.join("haproxy.log");
        let output = std::fs::File::create(&log).expect("the log file");
        let child = Command::new(haproxy)
            .arg("-db")
            .arg("-f")
            .arg(&config)
            .env("SPOOFWATCH_LB_LISTEN", &addr)
            .env("SPOOFWATCH_REPLICA_1", replicas[0].addr.to_string())
            .env("SPOOFWATCH_REPLICA_2", replicas[1].addr.to_string())
            .env("SPOOFWATCH_LB_ADMIN_SOCKET", &admin_socket)
            .stdin(Stdio::null())
            .stdout(output.try_clone().expect("the log file"))
            .stderr(output)
            .spawn()
            .expect("haproxy starts");
        Balancer {
            child,
            addr,
            admin_socket,
            log,
        }
    }

    /// Each replica's `status` and `check_status` columns of `show stat` (e.g. `UP`, `L7OK`);
    /// empty while the runtime API is not up yet.
    async fn replica_states(&self) -> BTreeMap<String, (String, String)> {
        let Ok(mut socket) = tokio::net::UnixStream::connect(&self.admin_socket).await else {
            return BTreeMap::new();
        };
        let mut csv = String::new();
        if socket.write_all(b"show stat\n").await.is_err()
            || socket.read_to_string(&mut csv).await.is_err()
        {
            return BTreeMap::new();
        }
        let mut lines = csv.lines();
        let header: Vec<&str> = lines
            .next()
            .unwrap_or_default()
            .trim_start_matches("# ")
            .split(',')
            .collect();
        let column = |name: &str| header.iter().position(|h| *h == name);
        let (Some(server), Some(status), Some(check)) =
            (column("svname"), column("status"), column("check_status"))
        else {
            return BTreeMap::new();
        };
        lines
            .map(|line| line.split(',').collect::<Vec<_>>())
            .filter(|fields| fields.len() > check && REPLICAS.contains(&fields[server]))
            .map(|f| {
                (
                    f[server].to_string(),
                    (f[status].to_string(), f[check].to_string()),
                )
            })
            .collect()
    }

    /// Polls the runtime API until `replica` has `status` (and, if given, `check_status`).
    async fn wait_for(&self, replica: &str, status: &str, check: Option<&str>) {
        let deadline = tokio::time::Instant::now() + STATE_TIMEOUT;
        loop {
            let states = self.replica_states().await;
            if let Some((s, c)) = states.get(replica)
                && s == status
                && check.is_none_or(|check| c == check)
            {
                return;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "{replica} never became {status} {check:?}: {states:?}\nHAProxy log:\n{}",
                self.log_text()
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Balancer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Streams `samples` (seq from `first_seq`) for `vehicle` through `connection` on one stream
/// opened with `reset`; returns its SessionAccepted.
async fn stream(
    connection: &Connection,
    vehicle: &str,
    reset: bool,
    first_seq: u64,
    samples: &[v1::Sample],
) -> v1::SessionAccepted {
    let (stream, accepted) = DetectStream::start(connection, vehicle, "", reset)
        .await
        .unwrap_or_else(|e| panic!("{vehicle}: the stream opens through the balancer: {e}"));
    let mut stream = stream.with_reply_timeout(REPLY_TIMEOUT);
    for (k, batch) in samples.chunks(5).enumerate() {
        let detections = stream
            .detect(first_seq + k as u64, batch.to_vec())
            .await
            .unwrap_or_else(|e| panic!("{vehicle}: detections through the balancer: {e}"));
        assert_eq!(detections.len(), batch.len());
    }
    stream.finish().await.expect("the stream ends cleanly");
    accepted
}

/// The vehicle ids with a session on the replica behind `clients`.
async fn sessions_on(clients: &Clients) -> Vec<String> {
    clients
        .detection
        .clone()
        .list_sessions(v1::ListSessionsRequest::default())
        .await
        .expect("ListSessions")
        .into_inner()
        .sessions
        .into_iter()
        .map(|s| s.vehicle_id)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn haproxy_pins_each_vehicle_to_one_replica_and_fails_over_when_it_stops() {
    let haproxy = match haproxy() {
        Ok(path) => path,
        Err(why) if std::env::var_os("SPOOFWATCH_REQUIRE_HAPROXY").is_some_and(|v| v == "1") => {
            panic!("SPOOFWATCH_REQUIRE_HAPROXY=1 but no usable HAProxy: {why}")
        }
        Err(why) => {
            eprintln!("skipped: {why}");
            return;
        }
    };
    let (_dir_1, server_1, clients_1) = start_server(|_| {}).await;
    let (_dir_2, server_2, clients_2) = start_server(|_| {}).await;
    let lb_dir = tempfile::tempdir().expect("temp dir");
    let balancer = Balancer::start(&haproxy, lb_dir.path(), [&server_1, &server_2]);
    for replica in REPLICAS {
        // L7OK: the gRPC health check saw SERVING.
        balancer.wait_for(replica, "UP", Some("L7OK")).await;
    }
    let lb_url = format!("http://{}", balancer.addr);
    let through_lb = Connection::connect(lb_url.clone(), None)
        .await
        .expect("connect to the balancer");

    let vehicles: Vec<(String, Vec<v1::Sample>)> = (0..VEHICLES)
        .map(|k| {
            let id = format!("car-{k:02}");
            let samples = track_samples(&normal_drive(&id, 39.0, 40 + k as u64));
            (id, samples)
        })
        .collect();
    for (id, samples) in &vehicles {
        stream(&through_lb, id, true, 1, &samples[..20]).await;
    }
    let on_1 = sessions_on(&clients_1).await;
    let on_2 = sessions_on(&clients_2).await;
    for (id, _) in &vehicles {
        assert!(
            on_1.contains(id) ^ on_2.contains(id),
            "{id} is on exactly one replica: {on_1:?} / {on_2:?}"
        );
    }
    assert!(
        !on_1.is_empty() && !on_2.is_empty(),
        "the vehicles are spread over both replicas: {on_1:?} / {on_2:?}"
    );

    // Again, in the reverse order and over a new connection to the balancer: every vehicle finds
    // its session (resumed with its 20 samples), so it landed on the same replica.
    let again = Connection::connect(lb_url.clone(), None)
        .await
        .expect("connect to the balancer");
    for (id, samples) in vehicles.iter().rev() {
        let accepted = stream(&again, id, false, 5, &samples[20..30]).await;
        assert!(
            accepted.resumed && accepted.samples_seen == 20,
            "{id}: {accepted:?}"
        );
    }
    assert_eq!(sessions_on(&clients_1).await, on_1);
    assert_eq!(sessions_on(&clients_2).await, on_2);

    // The replica holding car-00 stops; HAProxy takes it out and its vehicles move to the other.
    let lost_index = if on_1.contains(&vehicles[0].0) { 0 } else { 1 };
    let mut servers = [Some(server_1), Some(server_2)];
    let mut clients = [Some(clients_1), Some(clients_2)];
    let placement = [on_1, on_2];
    let (lost, kept) = (&placement[lost_index], &placement[1 - lost_index]);
    clients[lost_index] = None;
    let stopped = servers[lost_index].take().expect("the replica to stop");
    stopped.stop().await;
    balancer.wait_for(REPLICAS[lost_index], "DOWN", None).await;
    for (id, samples) in &vehicles {
        let accepted = stream(&again, id, false, 7, &samples[30..]).await;
        if kept.contains(id) {
            assert!(
                accepted.resumed && accepted.samples_seen == 30,
                "{id} stays on its replica: {accepted:?}"
            );
        }
    }
    let survivor_clients = clients[1 - lost_index]
        .take()
        .expect("the remaining replica");
    let now_on_survivor = sessions_on(&survivor_clients).await;
    for id in lost.iter().chain(kept) {
        assert!(
            now_on_survivor.contains(id),
            "{id} is served by the remaining replica: {now_on_survivor:?}"
        );
    }
    drop((through_lb, again, survivor_clients));
    drop(balancer);
    let survivor = servers[1 - lost_index]
        .take()
        .expect("the remaining replica");
    survivor.stop().await;
}
