//! The remote commands an operator uses, run as a user would (the real binary) against an
//! in-process server that has just detected simulated drives with a frozen GNSS fix (replayed by
//! `spoofwatch detect`): `alarms list|watch`, `sessions list|get|reset` and remote `evaluate`.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::Duration;

use serde_json::Value;
use spoofwatch_server::inprocess::InProcessServer;

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_spoofwatch"))
        .args(args)
        .env_remove("SPOOFWATCH_SERVER")
        .env_remove("SPOOFWATCH_TOKEN")
        .output()
        .expect("the spoofwatch binary runs")
}

fn succeed(args: &[&str]) -> String {
    let output = run(args);
    assert!(
        output.status.success(),
        "spoofwatch {args:?} failed:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn json_lines(text: &str) -> Vec<Value> {
    text.lines()
        .map(|line| serde_json::from_str(line).expect("one JSON object per line"))
        .collect()
}

/// Two simulated 240 s drives whose fix freezes for 60 s from 100 s.
fn simulate(path: &Path) {
    succeed(&[
        "scenario",
        "simulate",
        "--out",
        &path.display().to_string(),
        "--vehicles",
        "2",
        "--duration",
        "240",
        "--seed",
        "21",
        "--attack",
        "frozen",
        "--onset",
        "100",
        "--attack-duration",
        "60",
    ]);
}

fn detect(url: &str, data: &Path) {
    succeed(&[
        "detect",
        "--server",
        url,
        "--data",
        &data.display().to_string(),
        "--batch",
        "20",
        "--quiet",
    ]);
}

/// A runtime, an in-process server on it, and the simulated drives (in a directory that must
/// outlive the test).
fn server_and_drives() -> (
    tokio::runtime::Runtime,
    InProcessServer,
    tempfile::TempDir,
    std::path::PathBuf,
) {
    let runtime = tokio::runtime::Runtime::new().expect("a runtime");
    let server = runtime
        .block_on(InProcessServer::start(|_| {}))
        .expect("the server starts");
    let dir = tempfile::tempdir().expect("temp dir");
    let drives = dir.path().join("drives.csv");
    simulate(&drives);
    (runtime, server, dir, drives)
}

#[test]
fn alarms_are_listed_and_watched_from_the_command_line() {
    let (runtime, server, _dir, drives) = server_and_drives();
    let url = server.url();

    // A watcher connected before the drives: it prints CAUGHT_UP, then the events as they happen.
    let mut watcher = Command::new(env!("CARGO_BIN_EXE_spoofwatch"))
        .args(["alarms", "watch", "--server", &url, "--count", "2"])
        .stdout(Stdio::piped())
        .spawn()
        .expect("the watcher starts");
    let mut lines = BufReader::new(watcher.stdout.take().expect("stdout")).lines();
    let first: Value =
        serde_json::from_str(&lines.next().expect("a line").expect("readable")).expect("JSON");
    assert_eq!(first["kind"], "caught_up");
    detect(&url, &drives);
    let live: Vec<Value> = lines
        .map(|line| serde_json::from_str(&line.expect("readable")).expect("JSON"))
        .collect();
    assert!(watcher.wait().expect("the watcher exits").success());
    assert_eq!(live.len(), 2, "--count 2: {live:?}");
    // The two vehicles are replayed at once: the first two events of the fleet, in cursor order.
    assert_eq!(live[0]["kind"], "onset");
    assert!(live[0]["cursor"].as_i64() < live[1]["cursor"].as_i64());

    // The writer stores in the background: list until both vehicles' alarms are stored and every
    // alarm is closed (one vehicle's may be stored well after the other's).
    let mut listed = Vec::new();
    for _ in 0..300 {
        listed = json_lines(&succeed(&[
            "alarms", "list", "--server", &url, "--state", "closed", "--json",
        ]));
        let all = json_lines(&succeed(&["alarms", "list", "--server", &url, "--json"]));
        let vehicles: std::collections::BTreeSet<&str> = listed
            .iter()
            .filter_map(|a| a["vehicle_id"].as_str())
            .collect();
        if vehicles.len() == 2 && listed.len() == all.len() {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(!listed.is_empty(), "the frozen fixes raised alarms");
    assert!(
        listed
            .iter()
            .all(|a| a["open"] == false && a["model"] == "models/default")
    );
    // The list is in id order and the watch in the order the onsets were stored; the two vehicles
    // run at once, so the first watched alarm is found by its id.
    let watched = &live[0]["alarm"];
    let stored = listed
        .iter()
        .find(|a| a["id"] == watched["id"])
        .expect("the first alarm watched is listed");
    assert_eq!(
        stored["onset_time"], watched["onset_time"],
        "the list and the watch agree on the first alarm watched"
    );

    let vehicle = listed[0]["vehicle_id"]
        .as_str()
        .expect("a vehicle id")
        .to_string();
    let of_vehicle = json_lines(&succeed(&[
        "alarms",
        "list",
        "--server",
        &url,
        "--vehicle",
        &vehicle,
        "--json",
    ]));
    assert!(!of_vehicle.is_empty());
    assert!(
        of_vehicle
            .iter()
            .all(|a| a["vehicle_id"] == vehicle.as_str())
    );
    assert_eq!(
        json_lines(&succeed(&[
            "alarms", "list", "--server", &url, "--limit", "1", "--json"
        ])),
        listed[..1]
    );
    let future = json_lines(&succeed(&[
        "alarms",
        "list",
        "--server",
        &url,
        "--since",
        "2999-01-01T00:00:00Z",
        "--json",
    ]));
    assert!(future.is_empty());
    let table = succeed(&["alarms", "list", "--server", &url]);
    let header: Vec<&str> = table
        .lines()
        .next()
        .unwrap_or_default()
        .split_whitespace()
        .collect();
    assert_eq!(header[..2], ["id", "vehicle"], "{table}");
    assert_eq!(table.lines().count(), 1 + listed.len(), "{table}");

    // Replay from cursor 0, then resume after the first event: the same events, one fewer. Each
    // ended alarm logged its onset and its end, and its escalation too when it turned critical
    // after it opened (one that opened critical escalated at its onset, in the same event).
    let events_logged = listed
        .iter()
        .map(|a| {
            2 + usize::from(a["escalated_timestamp_s"].as_f64() > a["onset_timestamp_s"].as_f64())
        })
        .sum::<usize>();
    let count = events_logged.to_string();
    let replayed = json_lines(&succeed(&[
        "alarms", "watch", "--server", &url, "--after", "0", "--count", &count,
    ]));
    assert_eq!(replayed.len(), events_logged);
    assert_eq!(replayed[..2], live[..]);
    let cursor = replayed[0]["cursor"].to_string();
    let resumed = json_lines(&succeed(&[
        "alarms",
        "watch",
        "--server",
        &url,
        "--after",
        &cursor,
        "--count",
        &(events_logged - 1).to_string(),
    ]));
    assert_eq!(resumed[..], replayed[1..]);
    let collected = json_lines(&succeed(&[
        "alarms",
        "watch",
        "--server",
        &url,
        "--after",
        &cursor,
        "--until-caught-up",
    ]));
    let (last, events) = collected.split_last().expect("at least caught_up");
    assert_eq!(last["kind"], "caught_up");
    assert_eq!(events, &replayed[1..]);

    // Refusals name the field; a refused watch does not retry.
    let refused = run(&["alarms", "list", "--server", &url, "--vehicle", "no spaces"]);
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        stderr.contains("INVALID_ARGUMENT") && stderr.contains("vehicle_id"),
        "{stderr}"
    );
    let refused = run(&[
        "alarms",
        "watch",
        "--server",
        &url,
        "--after",
        "999999999999999",
    ]);
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("after_cursor"), "{stderr}");

    runtime
        .block_on(server.shutdown())
        .expect("the server stops cleanly");
}

#[test]
fn sessions_and_remote_evaluation_from_the_command_line() {
    let (runtime, server, _dir, drives) = server_and_drives();
    let url = server.url();

    // The replay leaves one session per vehicle behind.
    detect(&url, &drives);
    let listed = succeed(&["sessions", "list", "--server", &url]);
    let rows: Vec<&str> = listed.lines().collect();
    assert!(rows[0].starts_with("vehicle"), "{listed}");
    assert_eq!(rows.len(), 3, "two vehicles: {listed}");
    assert!(
        rows[1].contains("models/default") && rows[1].contains("241"),
        "{listed}"
    );
    let vehicle = rows[1].split_whitespace().next().expect("a vehicle id");

    let got = succeed(&["sessions", "get", vehicle, "--server", &url]);
    assert!(got.contains("241 in 1 trajectories"), "{got}");
    let reset = succeed(&["sessions", "reset", vehicle, "--server", &url]);
    assert!(reset.contains("0 in 0 trajectories"), "{reset}");
    let missing = run(&["sessions", "get", "nobody", "--server", &url]);
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr).contains("NOT_FOUND"));

    // Remote evaluation: upload the drives, evaluate the active model on them, print its metrics.
    let drives = drives.display().to_string();
    let uploaded = succeed(&["datasets", "upload", "--file", &drives, "--server", &url]);
    let dataset = uploaded
        .split_whitespace()
        .find(|w| w.starts_with("datasets/"))
        .unwrap_or_else(|| panic!("the upload names its dataset: {uploaded}"));
    let evaluated = succeed(&["evaluate", "--server", &url, "--dataset", dataset]);
    assert!(
        evaluated.contains("evaluated models/default"),
        "{evaluated}"
    );
    assert!(evaluated.contains("AUROC"), "{evaluated}");
    // Offline inputs do not mix with --server.
    let mixed = run(&[
        "evaluate",
        "--server",
        &url,
        "--dataset",
        dataset,
        "--data",
        &drives,
    ]);
    assert!(!mixed.status.success());

    runtime
        .block_on(server.shutdown())
        .expect("the server stops");
}
