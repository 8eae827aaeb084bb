//! The offline `spoofwatch` commands, run as a user would (the real binary, real files).

use std::path::Path;
use std::process::{Command, Output};

use spoofwatch_core::sample::Sample;
use spoofwatch_core::scenario::{
    DriveDistribution, DriveSpec, FleetTruth, RegionalAttack, generate_fleet, simulate_drive,
};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_spoofwatch"))
        .args(args)
        .env_remove("CI")
        .output()
        .expect("the spoofwatch binary runs")
}

fn spoofwatch(args: &[&str]) -> Output {
    let output = run(args);
    assert!(
        output.status.success(),
        "spoofwatch {args:?} failed:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

/// Runs `spoofwatch` expecting it to refuse; returns what it said on standard error.
fn spoofwatch_refuses(args: &[&str]) -> String {
    let output = run(args);
    assert!(!output.status.success(), "spoofwatch {args:?} succeeded");
    String::from_utf8_lossy(&output.stderr).into_owned()
}

fn stdout(output: &Output) -> String {
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn path(dir: &Path, name: &str) -> String {
    dir.join(name).display().to_string()
}

/// `spoofwatch scenario simulate --out <out> <options>`.
fn simulate(out: &str, options: &[&str]) {
    spoofwatch(&[&["scenario", "simulate", "--out", out], options].concat());
}

#[test]
fn simulate_train_evaluate_and_evidence_work_together() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (train, val, test, model) = (
        path(dir.path(), "train.csv"),
        path(dir.path(), "val.csv"),
        path(dir.path(), "test.csv"),
        path(dir.path(), "model.json"),
    );
    for (file, seed) in [(&train, "1"), (&val, "50"), (&test, "90")] {
        simulate(
            file,
            &[
                "--vehicles",
                "2",
                "--duration",
                "400",
                "--seed",
                seed,
                "--attack",
                "frozen",
                "--onset",
                "150",
                "--attack-duration",
                "120",
            ],
        );
    }
    let csv = std::fs::read_to_string(&train).expect("written");
    assert!(csv.starts_with("vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,label"));
    assert_eq!(csv.lines().count(), 1 + 2 * 401);

    // The v2 evidence keeps this plumbing test quick on short drives; the default (v3) is trained
    // end to end by the fleet-fit job test.
    let trained = stdout(&spoofwatch(&[
        "train", "--data", &train, "--val", &val, "--out", &model, "--epochs", "3", "--schema",
        "v2",
    ]));
    assert!(trained.contains("operating point"), "{trained}");
    assert!(trained.contains("| validation |"), "{trained}");

    let json = path(dir.path(), "metrics.json");
    let rows = path(dir.path(), "rows.csv");
    let evaluated = stdout(&spoofwatch(&[
        "evaluate", "--model", &model, "--data", &test, "--json", &json, "--rows", &rows,
    ]));
    assert!(evaluated.contains("| overall |"), "{evaluated}");
    // One row per (attacked) vehicle besides the overall one.
    assert!(
        evaluated.contains("| sim0#frozen") && evaluated.contains("| sim1#frozen"),
        "{evaluated}"
    );
    let metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("valid json");
    assert_eq!(metrics["overall"]["events"], 2);
    assert_eq!(
        std::fs::read_to_string(&rows)
            .expect("rows")
            .lines()
            .count(),
        1 + 2 * 401
    );

    // Evidence with the model's statistics: one row per input row, ν = 0 on each trajectory start.
    let evidence = stdout(&spoofwatch(&[
        "evidence", "--data", &test, "--stats", &model,
    ]));
    let lines: Vec<&str> = evidence.lines().collect();
    assert_eq!(lines.len(), 1 + 2 * 401);
    assert!(lines[0].starts_with("vehicle_id,line,trajectory,delta_t,nu,r_e,r_n,eta_e"));
    let first: Vec<&str> = lines[1].split(',').collect();
    assert!(first[0].starts_with("sim0#frozen"), "{}", lines[1]);
    assert_eq!(&first[1..5], ["2", "0", "NaN", "0"], "{}", lines[1]);
}

#[test]
fn simulated_drives_take_a_rate_and_realistic_ones_round_trip_through_the_reader() {
    let dir = tempfile::tempdir().expect("tempdir");
    let ten_hz = path(dir.path(), "ten-hz.csv");
    simulate(&ten_hz, &["--duration", "30", "--rate", "10"]);
    let csv = std::fs::read_to_string(&ten_hz).expect("written");
    assert_eq!(csv.lines().count(), 1 + 301);

    let realistic = path(dir.path(), "realistic.csv");
    simulate(
        &realistic,
        &[
            "--vehicles",
            "4",
            "--duration",
            "900",
            "--seed",
            "3",
            "--realistic",
        ],
    );
    let read = spoofwatch_core::data::read_path(Path::new(&realistic)).expect("readable");
    assert_eq!(read.tracks.len(), 4);
    let distribution = DriveDistribution::realistic();
    let mut vehicles_with_gaps = 0;
    for (k, track) in (3..).zip(&read.tracks) {
        let spec = DriveSpec {
            duration_s: 900.0,
            ..distribution.draw(k)
        };
        let simulated = simulate_drive(&spec, &format!("sim{}", k - 3)).expect("a drawn spec");
        assert_eq!(track.vehicle_id, simulated.vehicle_id);
        let samples = |t: &spoofwatch_core::sample::Track| -> Vec<Sample> {
            t.records.iter().map(|r| r.sample).collect()
        };
        // Bit for bit: the CSV writes shortest round-trip floats.
        assert_eq!(samples(track), samples(&simulated), "{}", track.vehicle_id);
        assert!(track.records.iter().all(|r| r.label == Some(false)));
        if track.records.len() < spec.sample_count() {
            vehicles_with_gaps += 1;
        }
    }
    assert!(
        vehicles_with_gaps > 0,
        "seeds 3–6 include drives with outages"
    );

    let stderr = spoofwatch_refuses(&[
        "scenario",
        "simulate",
        "--out",
        &realistic,
        "--realistic",
        "--rate",
        "10",
    ]);
    assert!(
        stderr.contains("--realistic") && stderr.contains("--rate"),
        "{stderr}"
    );
}

#[test]
fn a_fleet_scene_writes_labelled_telemetry_and_its_ground_truth() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (csv, json) = (
        path(dir.path(), "scene.csv"),
        path(dir.path(), "truth.json"),
    );
    let options = [
        "--vehicles",
        "12",
        "--pass-through",
        "4",
        "--area-m",
        "6000",
        "--duration",
        "300",
        "--rate",
        "5",
        "--radius-m",
        "700",
        "--start",
        "60",
        "--attack-duration",
        "180",
        "--attack",
        "position",
        "--false-lat",
        "32.3",
        "--false-lon",
        "-110.8",
        "--seed",
        "5",
    ];
    let output = spoofwatch(
        &[
            &["scenario", "fleet", "--out", &csv, "--truth", &json],
            &options[..],
        ]
        .concat(),
    );
    let said = String::from_utf8_lossy(&output.stderr);
    assert!(
        said.contains("wrote 12 vehicles") && said.contains("4 vehicles captured"),
        "{said}"
    );

    let truth: FleetTruth = serde_json::from_str(&std::fs::read_to_string(&json).expect("written"))
        .expect("the ground truth");
    let spoofer = truth.spec.spoofer;
    assert_eq!(
        (spoofer.lat_deg, spoofer.lon_deg),
        (32.23, -110.91),
        "the area's centre"
    );
    assert_eq!(
        (spoofer.radius_m, spoofer.start_s, spoofer.duration_s),
        (700.0, 60.0, 180.0)
    );
    assert_eq!(
        spoofer.attack,
        RegionalAttack::Position {
            lat_deg: 32.3,
            lon_deg: -110.8
        }
    );
    assert_eq!((truth.spec.vehicles, truth.spec.rate_hz), (12, 5.0));
    assert_eq!(truth.captured_vehicles, 4);
    assert_eq!(
        truth.vehicles.iter().filter(|v| v.routed_through).count(),
        4
    );

    let read = spoofwatch_core::data::read_path(Path::new(&csv)).expect("readable");
    assert_eq!(read.tracks.len(), 12);
    // The file is the core's scene bit for bit (the CSV writes shortest round-trip floats).
    let scene = generate_fleet(&truth.spec).expect("the recorded spec");
    let samples = |t: &spoofwatch_core::sample::Track| -> Vec<(Sample, Option<bool>)> {
        t.records.iter().map(|r| (r.sample, r.label)).collect()
    };
    let mut reported_lat = Vec::new();
    for ((track, expected), vehicle) in read.tracks.iter().zip(&scene.tracks).zip(&truth.vehicles) {
        assert_eq!(track.vehicle_id, vehicle.vehicle_id);
        assert_eq!(samples(track), samples(expected), "{}", track.vehicle_id);
        let spoofed: Vec<&Sample> = track
            .records
            .iter()
            .filter(|r| r.label == Some(true))
            .map(|r| &r.sample)
            .collect();
        assert_eq!(
            vehicle.captured,
            !spoofed.is_empty(),
            "{}",
            track.vehicle_id
        );
        assert_eq!(
            vehicle.captures.iter().map(|c| c.rows).sum::<usize>(),
            spoofed.len()
        );
        reported_lat.extend(spoofed.iter().map(|s| s.latitude_deg));
    }
    assert_eq!(reported_lat.len(), truth.spoofed_rows);
    // Every captured receiver reports the false position (metre-level noise: 1e-4° is 11 m).
    reported_lat.sort_by(f64::total_cmp);
    let median = reported_lat[reported_lat.len() / 2];
    assert!((median - 32.3).abs() < 1e-4, "{median}");

    let stderr = spoofwatch_refuses(&[
        "scenario",
        "fleet",
        "--out",
        &csv,
        "--truth",
        &json,
        "--attack",
        "translation",
        "--east-mps",
        "1",
    ]);
    assert!(stderr.contains("--east-mps"), "{stderr}");
    let stderr = spoofwatch_refuses(&[
        "scenario",
        "fleet",
        "--out",
        &csv,
        "--truth",
        &json,
        "--vehicles",
        "12",
        "--pass-through",
        "13",
    ]);
    assert!(
        stderr.contains("--pass-through") && stderr.contains("pass_through"),
        "{stderr}"
    );
}

#[test]
fn bad_input_names_file_line_and_column() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = path(dir.path(), "bad.csv");
    std::fs::write(
        &file,
        "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg\nv,0,32.2,-110.9,1,0\nv,1,abc,-110.9,1,0\n",
    )
    .expect("write");
    let stderr = spoofwatch_refuses(&["evidence", "--data", &file]);
    assert!(stderr.contains("bad.csv:3"), "{stderr}");
    assert!(stderr.contains("latitude"), "{stderr}");
}

#[test]
fn demo_and_bench_without_a_server_name_the_research_binary() {
    for command in ["demo", "bench"] {
        let stderr = spoofwatch_refuses(&[command]);
        assert!(
            stderr.contains("--server") && stderr.contains(&format!("spoofwatch-lab {command}")),
            "{stderr}"
        );
    }
}
