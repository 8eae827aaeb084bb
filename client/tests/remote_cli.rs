//! The remote `spoofwatch` commands an operator uses, run as the real binary against an in-process
//! server: `sessions list|get|reset`, remote `evaluate`, and `models delete` ending sessions.

use std::process::Output;

use spoofwatch_server::inprocess::InProcessServer;

/// Runs the CLI against `server` off the async runtime (the server runs on it).
async fn spoofwatch(server: &InProcessServer, args: &[&str]) -> Output {
    let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_spoofwatch"));
    command
        .args(args)
        .env("SPOOFWATCH_SERVER", server.url())
        .env_remove("SPOOFWATCH_TOKEN")
        .env_remove("CI");
    tokio::task::spawn_blocking(move || command.output().expect("the spoofwatch binary runs"))
        .await
        .expect("the command's thread")
}

async fn succeeds(server: &InProcessServer, args: &[&str]) -> String {
    let output = spoofwatch(server, args).await;
    assert!(
        output.status.success(),
        "spoofwatch {args:?} failed:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_and_remote_evaluation_from_the_command_line() {
    let server = InProcessServer::start(|_| {}).await.expect("server starts");
    let dir = tempfile::tempdir().expect("tempdir");
    let drive = dir.path().join("drive.csv").display().to_string();
    succeeds(
        &server,
        &[
            "scenario",
            "simulate",
            "--out",
            &drive,
            "--duration",
            "240",
            "--seed",
            "3",
            "--attack",
            "frozen",
            "--onset",
            "100",
            "--attack-duration",
            "60",
        ],
    )
    .await;

    // A replay leaves one session per vehicle behind.
    succeeds(&server, &["detect", "--data", &drive, "--quiet"]).await;
    let listed = succeeds(&server, &["sessions", "list"]).await;
    let mut lines = listed.lines();
    assert!(
        lines.next().is_some_and(|h| h.starts_with("vehicle")),
        "{listed}"
    );
    let row = lines
        .next()
        .unwrap_or_else(|| panic!("one session: {listed}"));
    let vehicle = row
        .split_whitespace()
        .next()
        .expect("a vehicle id")
        .to_string();
    assert!(
        row.contains("models/default") && row.contains("241"),
        "{row}"
    );

    let got = succeeds(&server, &["sessions", "get", &vehicle]).await;
    assert!(got.contains("241 in 1 trajectories"), "{got}");
    let reset = succeeds(&server, &["sessions", "reset", &vehicle]).await;
    assert!(reset.contains("0 in 0 trajectories"), "{reset}");
    let missing = spoofwatch(&server, &["sessions", "get", "nobody"]).await;
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr).contains("NOT_FOUND"));

    // Remote evaluation: upload the drive, evaluate the active model on it, print its metrics.
    let uploaded = succeeds(&server, &["datasets", "upload", "--file", &drive]).await;
    let dataset = uploaded
        .split_whitespace()
        .find(|w| w.starts_with("datasets/"))
        .unwrap_or_else(|| panic!("the upload names its dataset: {uploaded}"))
        .to_string();
    let evaluated = succeeds(
        &server,
        &["evaluate", "--server", &server.url(), "--dataset", &dataset],
    )
    .await;
    assert!(
        evaluated.contains("evaluated models/default"),
        "{evaluated}"
    );
    assert!(
        evaluated.contains("AUROC") || evaluated.contains("auroc"),
        "{evaluated}"
    );
    // Offline flags do not mix with --server.
    let mixed = spoofwatch(
        &server,
        &[
            "evaluate",
            "--server",
            &server.url(),
            "--dataset",
            &dataset,
            "--data",
            &drive,
        ],
    )
    .await;
    assert!(!mixed.status.success());

    server.shutdown().await.expect("the server stops");
}
