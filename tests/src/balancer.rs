//! The shipped HAProxy configuration (`deploy/haproxy/spoofwatch.cfg`, unchanged: addresses come
//! from its environment variables) run for real in front of two replicas, and its runtime API's
//! view of them.
//!
//! Needs a real HAProxy (Debian's 2.6): `SPOOFWATCH_HAPROXY` names the binary (`.ci/run` installs
//! it and sets the variable, with `SPOOFWATCH_REQUIRE_HAPROXY=1` so that a missing one fails
//! there); without it the tests that need it are skipped with a message.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// The replicas' names in the configuration.
pub const REPLICAS: [&str; 2] = ["replica-1", "replica-2"];
/// Longest wait for HAProxy to see a replica's state change.
pub const STATE_TIMEOUT: Duration = Duration::from_secs(30);

/// The HAProxy binary, or why the test cannot run.
fn find_haproxy() -> Result<PathBuf, String> {
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

/// The HAProxy binary; `None` (the test is skipped, with a message) when there is none, unless
/// `SPOOFWATCH_REQUIRE_HAPROXY=1`, which makes a missing one a failure.
pub fn haproxy() -> Option<PathBuf> {
    match find_haproxy() {
        Ok(path) => Some(path),
        Err(why) if std::env::var_os("SPOOFWATCH_REQUIRE_HAPROXY").is_some_and(|v| v == "1") => {
            panic!("SPOOFWATCH_REQUIRE_HAPROXY=1 but no usable HAProxy: {why}")
        }
        Err(why) => {
            eprintln!("skipped: {why}");
            None
        }
    }
}

/// A running HAProxy with the shipped configuration; killed when dropped.
pub struct Balancer {
    child: Child,
    /// Where clients connect (`127.0.0.1:PORT`).
    pub addr: String,
    admin_socket: PathBuf,
    log: PathBuf,
}

impl Balancer {
    /// Starts `haproxy -db -f deploy/haproxy/spoofwatch.cfg` on a free loopback port in front of
    /// `replicas`, with its runtime API and log in `dir`.
    pub fn start(haproxy: &Path, dir: &Path, replicas: [SocketAddr; 2]) -> Balancer {
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
            .env("SPOOFWATCH_REPLICA_1", replicas[0].to_string())
            .env("SPOOFWATCH_REPLICA_2", replicas[1].to_string())
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
    pub async fn wait_for(&self, replica: &str, status: &str, check: Option<&str>) {
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

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Balancer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
