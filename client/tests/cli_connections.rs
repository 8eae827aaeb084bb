//! The CLI's connection flags against an in-process server: `--server host:port` (plaintext), and
//! over TLS `https://` with `--ca-cert`, `host:port` with `--ca-cert`, and the refusal of a server
//! whose CA is not trusted.

use std::path::Path;
use std::process::{Command, Output};

use rcgen::{BasicConstraints, CertificateParams, CertifiedIssuer, IsCa, KeyPair, KeyUsagePurpose};
use spoofwatch_server::inprocess::InProcessServer;

/// Runs `spoofwatch` off the async runtime (it blocks until the command ends).
async fn spoofwatch(args: Vec<String>) -> Output {
    tokio::task::spawn_blocking(move || {
        Command::new(env!("CARGO_BIN_EXE_spoofwatch"))
            .args(&args)
            .env_remove("SPOOFWATCH_SERVER")
            .env_remove("SPOOFWATCH_TOKEN")
            .env_remove("SPOOFWATCH_CA_CERT")
            .output()
            .expect("spoofwatch runs")
    })
    .await
    .expect("the command thread")
}

fn args(items: &[&str]) -> Vec<String> {
    items.iter().map(|s| s.to_string()).collect()
}

/// A CA (its certificate in `dir/ca.pem`) and a server certificate for 127.0.0.1 signed by it
/// (`server.pem`, `server-key.pem`).
fn write_ca_and_server_cert(dir: &Path) {
    let mut ca = CertificateParams::new(Vec::<String>::new()).expect("CA parameters");
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca.key_usages = vec![KeyUsagePurpose::KeyCertSign];
    let ca = CertifiedIssuer::self_signed(ca, KeyPair::generate().expect("key")).expect("CA");
    let key = KeyPair::generate().expect("key");
    let server = CertificateParams::new(vec!["127.0.0.1".to_string()])
        .expect("server parameters")
        .signed_by(&key, &ca)
        .expect("signed");
    std::fs::write(dir.join("ca.pem"), ca.pem()).expect("written");
    std::fs::write(dir.join("server.pem"), server.pem()).expect("written");
    std::fs::write(dir.join("server-key.pem"), key.serialize_pem()).expect("written");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_takes_a_bare_address() {
    let server = InProcessServer::start(|_| {}).await.expect("server starts");
    let output = spoofwatch(args(&["health", "--server", &server.addr().to_string()])).await;
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{output:?}");
    assert!(stdout.contains("SERVING"), "{stdout}");
    server.shutdown().await.expect("clean shutdown");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_over_tls_trusts_the_given_ca_only() {
    let dir = tempfile::tempdir().expect("temp dir");
    write_ca_and_server_cert(dir.path());
    let file = |name: &str| dir.path().join(name).display().to_string();
    let server = InProcessServer::start(|config| {
        config.tls_cert = Some(dir.path().join("server.pem"));
        config.tls_key = Some(dir.path().join("server-key.pem"));
    })
    .await
    .expect("server starts");
    let address = server.addr().to_string();
    let https = format!("https://{address}");

    for server_flag in [&https, &address] {
        let output = spoofwatch(args(&[
            "health",
            "--server",
            server_flag,
            "--ca-cert",
            &file("ca.pem"),
        ]))
        .await;
        assert!(output.status.success(), "{server_flag}: {output:?}");
        assert!(
            String::from_utf8_lossy(&output.stdout).contains(&format!("{https}: SERVING")),
            "{output:?}"
        );
    }
    // Without --ca-cert the built-in web roots do not know the test CA.
    let output = spoofwatch(args(&["health", "--server", &https])).await;
    assert!(!output.status.success(), "{output:?}");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("certificate"), "{stderr}");
    server.shutdown().await.expect("clean shutdown");
}
