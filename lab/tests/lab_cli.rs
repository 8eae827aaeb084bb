//! The `spoofwatch-lab` commands, run as a user would (the real binary, real files): `evaluate
//! --plot`, `cusum`, the experiments and their figures, and `bench` against its in-process server.

use std::path::Path;
use std::process::{Command, Output};

use clap::Parser;
use spoofwatch_client::cli::{self, Cli};
use spoofwatch_core::testdata::{AVGPS_DIR_VAR, data_file};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_spoofwatch-lab"))
        .args(args)
        .env_remove("CI")
        .output()
        .expect("the spoofwatch-lab binary runs")
}

fn lab(args: &[&str]) -> Output {
    let output = run(args);
    assert!(
        output.status.success(),
        "spoofwatch-lab {args:?} failed:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

/// Runs `spoofwatch-lab` expecting it to refuse; returns what it said on standard error.
fn lab_refuses(args: &[&str]) -> String {
    let output = run(args);
    assert!(
        !output.status.success(),
        "spoofwatch-lab {args:?} succeeded"
    );
    String::from_utf8_lossy(&output.stderr).into_owned()
}

fn stdout(output: &Output) -> String {
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn path(dir: &Path, name: &str) -> String {
    dir.join(name).display().to_string()
}

/// `spoofwatch scenario simulate --out <out> <options>`, through the client library's command line
/// (the operator's binary belongs to another package).
fn simulate(out: &str, options: &[&str]) {
    let args = [
        &["spoofwatch", "scenario", "simulate", "--out", out],
        options,
    ]
    .concat();
    let parsed = Cli::try_parse_from(args).expect("valid simulate arguments");
    cli::run(parsed).expect("the drives are simulated");
}

/// The legend and title texts of an SVG figure (trimmed), after checking that it parses.
fn svg_texts(file: &str) -> Vec<String> {
    let svg = std::fs::read_to_string(file).expect("the figure is written");
    let doc = roxmltree::Document::parse(&svg).expect("the figure is well-formed XML");
    doc.descendants()
        .filter(|n| n.is_element() && n.tag_name().name() == "text")
        .map(|n| n.text().unwrap_or_default().trim().to_string())
        .collect()
}

#[test]
fn evaluate_plots_the_trace_of_a_chosen_vehicle() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = path(dir.path(), "drives.csv");
    simulate(
        &data,
        &[
            "--vehicles",
            "2",
            "--duration",
            "300",
            "--seed",
            "7",
            "--attack",
            "frozen",
            "--onset",
            "150",
            "--attack-duration",
            "100",
        ],
    );
    let vehicles: Vec<String> = spoofwatch_core::data::read_path(Path::new(&data))
        .expect("readable")
        .tracks
        .into_iter()
        .map(|t| t.vehicle_id)
        .collect();
    assert_eq!(vehicles.len(), 2);
    // The bundled v3 model: no training needed, and its evidence has the drift and offset channels.
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/../models/default.json");

    let first = path(dir.path(), "first.svg");
    let printed = stdout(&lab(&[
        "evaluate", "--model", model, "--data", &data, "--plot", &first,
    ]));
    assert!(
        printed.contains(&format!("trace figure written to {first}")),
        "{printed}"
    );
    let texts = svg_texts(&first);
    assert!(
        texts.iter().any(|t| t.starts_with(&vehicles[0])),
        "{texts:?}"
    );
    for legend in [
        "ground truth: spoofed",
        "confirmed alarm",
        "p̂ (spoofing probability)",
        "ln(1 + ‖η‖) (whitened residual)",
        "ã = ln(1 + a)",
        "ln(1 + drift statistic)",
        "ln(1 + stale fix s)",
        "ln(1 + NIS fast)",
        "ln(1 + NIS slow)",
        "ln(1 + held s)",
        "‖o‖ slow anchor (m)",
        "5σ gate (m)",
        // The frozen feed, named by the detections' explanation.
        "why: the dominant evidence of each detection",
        "frozen fix",
    ] {
        assert!(texts.iter().any(|t| t == legend), "{legend}: {texts:?}");
    }
    assert!(texts.iter().any(|t| t.starts_with("θ = ")), "{texts:?}");
    // Simulated telemetry has no detector verdict of its own.
    assert!(!texts.iter().any(|t| t == "EKF Detector"), "{texts:?}");

    let second = path(dir.path(), "second.svg");
    let plot = [
        "evaluate",
        "--model",
        model,
        "--data",
        &data,
        "--plot",
        &second,
        "--plot-vehicle",
    ];
    lab(&[&plot[..], &[vehicles[1].as_str()]].concat());
    assert!(
        svg_texts(&second)
            .iter()
            .any(|t| t.starts_with(&vehicles[1]))
    );

    let stderr = lab_refuses(&[&plot[..], &["nobody"]].concat());
    assert!(
        stderr.contains("\"nobody\"")
            && stderr.contains(&vehicles[0])
            && stderr.contains(&vehicles[1]),
        "{stderr}"
    );
}

#[test]
fn cusum_and_the_bundled_model_on_the_av_gps_data() {
    let (Some(d2), Some(d3)) = (
        data_file(AVGPS_DIR_VAR, "AV-GPS-Dataset-2.csv"),
        data_file(AVGPS_DIR_VAR, "AV-GPS-Dataset-3.csv"),
    ) else {
        return;
    };
    let (d2, d3) = (d2.display().to_string(), d3.display().to_string());
    let cusum = stdout(&lab(&["cusum", "--train", &d2, "--data", &d3]));
    assert!(cusum.contains("CUSUM: mu_e ="), "{cusum}");
    assert!(cusum.contains("| data |"), "{cusum}");

    // The committed paper-schema model (`models/paper.json`) reproduces its documented Dataset-3 scores (`docs/experiments.md`).
    let bundled = concat!(env!("CARGO_MANIFEST_DIR"), "/../models/paper.json");
    let dir = tempfile::tempdir().expect("tempdir");
    let json = path(dir.path(), "d3.json");
    let plot = path(dir.path(), "d3.svg");
    lab(&[
        "evaluate", "--model", bundled, "--data", &d3, "--json", &json, "--plot", &plot,
    ]);
    // The case-study figure: Dataset-3 carries AV-GPS's own detector, drawn against the truth.
    let texts = svg_texts(&plot);
    assert!(texts.iter().any(|t| t == "EKF Detector"), "{texts:?}");
    assert!(texts.iter().any(|t| t == "θ = 0.90"), "{texts:?}");
    let metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("valid");
    let overall = &metrics["overall"];
    assert_eq!(overall["events"], 2);
    assert_eq!(overall["detected_events"], 2);
    assert_eq!(overall["false_alarm_rows"], 29);
    assert_eq!(overall["false_alarm_events"], 2);
    assert_eq!(overall["delays_s"], serde_json::json!([33.0, 50.0]));
}

/// Runs `spoofwatch-lab experiment <name> --data-dir <AV-GPS dir> --out <temp dir> <args>` and returns the
/// output directory with its `report.json`; `None` (test skipped) without the AV-GPS data.
fn run_experiment(name: &str, args: &[&str]) -> Option<(tempfile::TempDir, serde_json::Value)> {
    let d2 = data_file(AVGPS_DIR_VAR, "AV-GPS-Dataset-2.csv")?;
    let data_dir = d2.parent().expect("a directory").display().to_string();
    let out = tempfile::tempdir().expect("tempdir");
    let out_dir = out.path().display().to_string();
    let mut command = vec![
        "experiment",
        name,
        "--data-dir",
        &data_dir,
        "--out",
        &out_dir,
    ];
    command.extend(args);
    lab(&command);
    let report = serde_json::from_str(
        &std::fs::read_to_string(out.path().join("report.json")).expect("report.json"),
    )
    .expect("valid json");
    Some((out, report))
}

#[test]
fn the_av_gps_experiment_runs_end_to_end() {
    let args = ["--epochs", "1", "--no-ablations", "--seeds", "2"];
    let Some((out, report)) = run_experiment("av-gps", &args) else {
        return;
    };
    // HO-LLN in both schemas and every baseline, each trained with both seeds.
    let compared: Vec<&str> = report["compared"]
        .as_array()
        .expect("compared detectors")
        .iter()
        .filter_map(|n| n.as_str())
        .collect();
    let mut expected = vec!["HO-LLN (ξ paper)", "HO-LLN (ξ v2)"];
    for schema in ["paper", "v2"] {
        for learner in ["XGBoost-style trees", "MLP", "LSTM", "GRU"] {
            expected.push(Box::leak(
                format!("{learner} (ξ {schema})").into_boxed_str(),
            ));
        }
    }
    expected.push("GPS-IDS trees (AV-GPS columns)");
    assert_eq!(compared, expected);
    assert_eq!(report["seeds"], serde_json::json!([42, 43]));
    let variants = report["variants"].as_array().expect("trained models");
    for name in &compared {
        let seeds: Vec<&serde_json::Value> = variants
            .iter()
            .filter(|v| v["name"] == *name)
            .map(|v| &v["seed"])
            .collect();
        assert_eq!(seeds, [42, 43], "{name}");
    }
    let markdown = std::fs::read_to_string(out.path().join("report.md")).expect("report.md");
    assert!(
        markdown.contains("mean ± std over 2 seed(s) (42, 43)"),
        "{markdown}"
    );
    // The figures report.md links: the Dataset-3 case study and the training curves of every model.
    let dir = out.path().display().to_string();
    let case_study = svg_texts(&format!("{dir}/case-study-dataset3.svg"));
    for series in ["p̂", "truth", "EKF Detector"] {
        assert!(
            case_study.iter().any(|t| t.contains(series)),
            "{series}: {case_study:?}"
        );
    }
    let curves = svg_texts(&format!("{dir}/training-curves.svg"));
    let trees = svg_texts(&format!("{dir}/training-curves-trees.svg"));
    for name in &compared {
        let figure = if name.contains("trees") {
            &trees
        } else {
            &curves
        };
        assert!(figure.iter().any(|t| t == name), "{name}: {figure:?}");
    }
    for key in ["dataset2_test", "dataset3", "ekf_dataset3"] {
        for field in [
            "auroc",
            "auprc",
            "f1",
            "precision",
            "recall",
            "fpr",
            "adr",
            "mean_delay_s",
            "false_alarm_rows",
            "false_alarm_events",
        ] {
            assert!(report[key].get(field).is_some(), "{key}.{field} missing");
        }
    }
    assert_eq!(
        report["ekf_dataset3"]["delays_s"],
        serde_json::json!([22.0, 29.0])
    );
    assert!(report["operating_point"]["theta"].is_number());
    assert_eq!(report["seed"], 42);
    assert!(out.path().join("report.md").is_file() && out.path().join("model.json").is_file());
}

#[test]
fn the_subtle_experiment_reports_every_detector_within_the_budget() {
    let bundled = concat!(env!("CARGO_MANIFEST_DIR"), "/../models/default.json");
    let args = [
        "--epochs",
        "1",
        "--drives",
        "2",
        "--repeats",
        "1",
        "--clean-drives",
        "2",
        "--also",
        bundled,
    ];
    let Some((out, report)) = run_experiment("subtle", &args) else {
        return;
    };
    assert_eq!(report["false_alarm_budget_per_hour"], 1.0);
    let detectors = report["detectors"].as_array().expect("detector rows");
    let names: Vec<&str> = detectors
        .iter()
        .filter_map(|d| d["name"].as_str())
        .collect();
    let mut expected = vec!["HO-LLN v2", "HO-LLN paper"];
    for schema in ["v2", "paper"] {
        for learner in ["XGBoost-style trees", "MLP", "LSTM", "GRU"] {
            expected.push(Box::leak(
                format!("{learner} (ξ {schema})").into_boxed_str(),
            ));
        }
    }
    expected.extend([bundled, "directional GLR", "CUSUM"]);
    assert_eq!(names, expected);
    for d in detectors {
        assert!(d["false_alarms_per_hour"].is_number(), "{d}");
        assert!(d.get("smallest_ramp_mps_within_60s").is_some(), "{d}");
        // A detector either has a budgeted operating point and was tested on every attack kind, or
        // says it has none.
        let attacks = d["attacks"].as_array().expect("attack rows");
        if d["operating_point"].is_null() {
            assert!(attacks.is_empty());
        } else {
            for family in ["ramp_drift", "frozen_position", "jump", "hopping"] {
                assert!(
                    attacks.iter().any(|a| a["family"] == family),
                    "{family}: {d}"
                );
            }
            assert!(attacks.iter().all(|a| a["events"] == 1), "{d}");
        }
    }
    let markdown = std::fs::read_to_string(out.path().join("report.md")).expect("report.md");
    assert!(markdown.contains("smallest ramp within 30 s"));
    // One frontier curve per detector with a budgeted operating point.
    let dir = out.path().display().to_string();
    for figure in ["frontier-ramps.svg", "frontier-accelerating.svg"] {
        let texts = svg_texts(&format!("{dir}/{figure}"));
        for d in detectors.iter().filter(|d| !d["operating_point"].is_null()) {
            let name = d["name"].as_str().expect("name");
            assert!(
                texts.iter().any(|t| t == name),
                "{figure}: {name}: {texts:?}"
            );
        }
    }
}

#[test]
fn the_dataset2_ramp_experiment_cross_validates_over_the_normal_trajectories() {
    let bundled = concat!(env!("CARGO_MANIFEST_DIR"), "/../models/default.json");
    let args = ["--epochs", "1", "--drives", "2", "--also", bundled];
    let Some((_out, report)) = run_experiment("subtle-d2", &args) else {
        return;
    };
    // Dataset-2 has two normal trajectories of 10+ minutes: one fold each; per fold the fold's
    // model, the bundled default at its own operating point, the GLR and CUSUM.
    let folds = report["folds"].as_array().expect("folds");
    assert_eq!(folds.len(), 2);
    for fold in folds {
        assert!(
            fold["attacks_per_magnitude"].as_u64().expect("count") >= 10,
            "{fold}"
        );
        let detectors = fold["detectors"].as_array().expect("detectors");
        let names: Vec<&str> = detectors
            .iter()
            .filter_map(|d| d["name"].as_str())
            .collect();
        assert_eq!(names, ["HO-LLN v2", bundled, "directional GLR", "CUSUM"]);
        assert!(detectors[1]["operating_point"]["lifecycle"].is_object());
        for d in detectors {
            let attacks = d["attacks"].as_array().expect("attack rows");
            if !d["operating_point"].is_null() {
                // One row per ramp velocity, each over every onset; coverage is a share.
                assert_eq!(attacks.len(), 4, "{d}");
                for a in attacks {
                    assert_eq!(a["events"], fold["attacks_per_magnitude"]);
                    let coverage = a["coverage"].as_f64();
                    assert!(coverage.is_none_or(|c| (0.0..=1.0).contains(&c)), "{a}");
                }
            }
        }
    }
}

/// The data rows (vehicles, per message, …, errors) of `bench`'s results table.
fn bench_rows(output: &str) -> Vec<Vec<String>> {
    output
        .lines()
        .filter(|l| {
            l.starts_with("| ")
                && l.split('|')
                    .nth(1)
                    .is_some_and(|c| c.trim().parse::<u32>().is_ok())
        })
        .map(|l| {
            l.split('|')
                .map(|c| c.trim().to_string())
                .filter(|c| !c.is_empty())
                .collect()
        })
        .collect()
}

#[test]
fn bench_drives_one_stream_per_vehicle_or_gateway_streams_without_errors() {
    for (per_message, spread) in [("1", "streams"), ("1", "connections"), ("10", "streams")] {
        let output = stdout(&lab(&[
            "bench",
            "--spread",
            spread,
            "--streams",
            "25",
            "--batch",
            "2",
            "--seconds",
            "1",
            "--rate",
            "500",
            "--sessions",
            "0",
            "--vehicles-per-message",
            per_message,
        ]));
        let rows = bench_rows(&output);
        assert_eq!(rows.len(), 1, "{output}");
        let row = &rows[0];
        assert_eq!(
            (row[0].as_str(), row[1].as_str()),
            ("25", per_message),
            "{output}"
        );
        assert_eq!(
            row.last().map(String::as_str),
            Some("0"),
            "no errors: {output}"
        );
        let messages: u64 = row[4].parse().expect("a message count");
        assert!(messages > 0, "{output}");
    }
}

#[test]
fn bench_hands_every_vehicle_over_from_its_snapshot() {
    // The phase fails unless every vehicle resumes on the second server at its last seq.
    let output = stdout(&lab(&[
        "bench",
        "--handoff",
        "12",
        "--handoff-concurrency",
        "4",
        "--batch",
        "3",
    ]));
    let vehicles_in = |label: &str| {
        output
            .lines()
            .find(|l| l.starts_with(&format!("| {label} |")))
            .and_then(|l| l.split('|').nth(2))
            .map(|c| c.trim().to_string())
    };
    assert_eq!(
        vehicles_in("from the snapshot").as_deref(),
        Some("12"),
        "{output}"
    );
    assert_eq!(
        vehicles_in("fresh (never seen)").as_deref(),
        Some("12"),
        "{output}"
    );
}
