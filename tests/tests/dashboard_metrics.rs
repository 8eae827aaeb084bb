//! What operators plug in names only metrics the server exports: every `spoofwatch_*` metric in the
//! Grafana dashboard (`deploy/grafana/*.json`) and the Prometheus rules (`deploy/prometheus/*.rules.yml`)
//! must appear in a real scrape of a server that has scored a drive, raised an alarm and stored it,
//! with a candidate model shadowing the vehicle (the shadow's metrics).
//! A histogram counts under its `_bucket`, `_sum` and `_count` series as well as its family name.
//! Every label value they select with `label="value"` (the alarm metrics' `severity`, the store
//! faults' `kind`) must be one the scrape carries for that metric.
//!
//! One server in this file: the metrics recorder is per process (see `metrics_endpoint.rs`).

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use spoofwatch_proto::v1;
use spoofwatch_tests::{
    REPLY_TIMEOUT, artifact_with_critical_level, import_model, scrape, start_server,
    stream_frozen_fix_drive,
};

/// The deploy files whose metric names are checked: the dashboards and the rules (not their unit
/// tests, whose series are made up on purpose).
fn deploy_files() -> Vec<PathBuf> {
    let deploy = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy");
    let mut files = Vec::new();
    for (dir, suffix) in [("grafana", ".json"), ("prometheus", ".rules.yml")] {
        for entry in std::fs::read_dir(deploy.join(dir)).expect("the deploy directory") {
            let path = entry.expect("a directory entry").path();
            if path.to_string_lossy().ends_with(suffix) {
                files.push(path);
            }
        }
    }
    files.sort();
    files
}

/// Every `spoofwatch_<name>` token of `text` (recording rules, `spoofwatch:…`, are not metrics).
fn metric_names(text: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let mut rest = text;
    while let Some(start) = rest.find("spoofwatch_") {
        let preceded_by_word = rest[..start]
            .chars()
            .next_back()
            .is_some_and(|c| c.is_ascii_alphanumeric() || c == '_');
        let tail = &rest[start..];
        let len = tail
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(tail.len());
        if !preceded_by_word {
            names.insert(tail[..len].to_string());
        }
        rest = &tail[len..];
    }
    names
}

/// Every `label="value"` matcher of `text` on a `spoofwatch_*` metric, as (metric, label, value):
/// the labels the server sets (not `job` or `instance`, which Prometheus adds), and fixed values
/// only (not a dashboard's `$variable`, nor `=~` or `!=` matchers). Quotes escaped in JSON count.
fn label_matchers(text: &str) -> BTreeSet<(String, String, String)> {
    let text = text.replace("\\\"", "\"");
    let mut matchers = BTreeSet::new();
    for name in metric_names(&text) {
        let opening = format!("{name}{{");
        for (start, _) in text.match_indices(&opening) {
            let selector = &text[start + opening.len()..];
            let selector = &selector[..selector.find('}').unwrap_or(selector.len())];
            for matcher in selector.split(',') {
                let Some((label, value)) = matcher.trim().split_once('=') else {
                    continue;
                };
                let label = label.trim();
                let fixed = value.starts_with('"') && !value.contains('$');
                if fixed && !label.ends_with('!') && !["job", "instance"].contains(&label) {
                    let value = value.trim_matches('"').to_string();
                    matchers.insert((name.clone(), label.to_string(), value));
                }
            }
        }
    }
    matchers
}

/// The series names a scrape exports: every sample's name, and each histogram family's name.
fn exported_names(exposition: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    for line in exposition.lines() {
        if let Some(declaration) = line.strip_prefix("# TYPE ") {
            let mut words = declaration.split_whitespace();
            if let (Some(name), Some("histogram" | "summary")) = (words.next(), words.next()) {
                names.insert(name.to_string());
            }
        } else if !line.starts_with('#') && !line.trim().is_empty() {
            let end = line.find(['{', ' ']).unwrap_or(line.len());
            names.insert(line[..end].to_string());
        }
    }
    names
}

#[test]
fn names_are_found_in_queries() {
    let names = metric_names(
        r#"sum(rate(spoofwatch_alarm_onsets_total{job=~"$job"}[5m])) / spoofwatch:x:y
           histogram_quantile(0.99, rate(spoofwatch_db_operation_duration_seconds_bucket[1m])) my_spoofwatch_x"#,
    );
    assert_eq!(
        names.into_iter().collect::<Vec<_>>(),
        [
            "spoofwatch_alarm_onsets_total",
            "spoofwatch_db_operation_duration_seconds_bucket"
        ]
    );
    let matchers = label_matchers(
        r#"sum(increase(spoofwatch_a_total{severity="critical"}[5m])) spoofwatch_b{job="x", kind!="y"}
           "expr": "sum(spoofwatch_c{job=~\"$job\", severity=\"warning\", rpc=~\"$rpc\"})""#,
    );
    let expected = [
        ("spoofwatch_a_total", "severity", "critical"),
        ("spoofwatch_c", "severity", "warning"),
    ]
    .map(|(m, l, v)| (m.to_string(), l.to_string(), v.to_string()));
    assert_eq!(matchers.into_iter().collect::<Vec<_>>(), expected);
    let exported = exported_names(
        "# TYPE spoofwatch_h histogram\nspoofwatch_h_bucket{le=\"1\"} 2\nspoofwatch_g 1\n",
    );
    assert_eq!(
        exported.into_iter().collect::<Vec<_>>(),
        ["spoofwatch_g", "spoofwatch_h", "spoofwatch_h_bucket"]
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_metric_of_the_dashboard_and_the_rules_is_exported() {
    let files = deploy_files();
    assert!(
        files
            .iter()
            .any(|f| f.extension().is_some_and(|e| e == "json")),
        "a Grafana dashboard under deploy/grafana: {files:?}"
    );
    assert!(
        files
            .iter()
            .any(|f| f.to_string_lossy().ends_with(".rules.yml")),
        "Prometheus rules under deploy/prometheus: {files:?}"
    );

    let (_dir, server, mut clients) = start_server(|config| {
        config.metrics_listen = Some(SocketAddr::from(([127, 0, 0, 1], 0)));
    })
    .await;
    let metrics = server.metrics_addr().expect("a metrics listener");
    // A candidate shadows every vehicle: its worker scores the drive beside the live model.
    let candidate = import_model(&mut clients, artifact_with_critical_level(), "candidate").await;
    clients
        .models
        .start_shadow(v1::StartShadowRequest {
            model: candidate.name,
            scope: Some(v1::start_shadow_request::Scope::AllVehicles(true)),
        })
        .await
        .expect("StartShadow");
    // A frozen fix raises an alarm; its events and the session's snapshots are stored in the
    // background, which records the database write histogram.
    let episodes = stream_frozen_fix_drive(&clients, "dash-1").await;
    assert!(!episodes.is_empty(), "the frozen fix raises an alarm");
    let deadline = Instant::now() + REPLY_TIMEOUT;
    let (exported, exposition) = loop {
        let exposition = scrape(metrics).await;
        let exported = exported_names(&exposition);
        if exported.contains("spoofwatch_db_operation_duration_seconds")
            && exported.contains("spoofwatch_shadow_batch_scoring_seconds")
        {
            break (exported, exposition);
        }
        assert!(
            Instant::now() < deadline,
            "the alarm write and the shadow's scoring are recorded: {exported:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    server.stop().await;

    let mut missing = Vec::new();
    for file in &files {
        let text = std::fs::read_to_string(file).expect("a deploy file");
        let used = metric_names(&text);
        assert!(!used.is_empty(), "{} names no metric", file.display());
        for name in used {
            if !exported.contains(&name) {
                missing.push(format!("{}: {name}", file.display()));
            }
        }
        for (name, label, value) in label_matchers(&text) {
            let series = format!("{name}{{");
            let pair = format!("{label}=\"{value}\"");
            let carried = exposition
                .lines()
                .any(|line| line.starts_with(&series) && line.contains(&pair));
            if !carried {
                missing.push(format!("{}: {name}{{{pair}}}", file.display()));
            }
        }
    }
    assert!(
        missing.is_empty(),
        "metrics named in deploy files but not exported by the server:\n{}\nexported: {exported:#?}",
        missing.join("\n")
    );
}
