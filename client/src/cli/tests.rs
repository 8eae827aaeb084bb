//! Argument parsing: the remote commands, `train`'s offline form, `scenario simulate --rate/--realistic`,
//! `scenario fleet`'s defaults and attacks; `incidents end|dismiss` and the closure they print.

use crate::connection::DEFAULT_SERVER_ADDRESS;
use clap::Parser;

use super::{Cli, Command, remote};

fn parse(args: &[&str]) -> Result<Command, clap::Error> {
    Cli::try_parse_from(std::iter::once("spoofwatch").chain(args.iter().copied()))
        .map(|c| c.command)
}

fn default_server() -> String {
    std::env::var("SPOOFWATCH_SERVER").unwrap_or_else(|_| DEFAULT_SERVER_ADDRESS.to_string())
}

#[test]
fn detect_has_documented_defaults() {
    let Ok(Command::Detect(args)) = parse(&["detect", "--data", "a.csv", "b.csv"]) else {
        panic!("detect must parse");
    };
    assert_eq!(args.data.len(), 2);
    assert_eq!(args.server.server, default_server());
    assert_eq!((args.rate, args.batch, args.quiet), (0.0, 1, false));
    assert_eq!((args.model, args.out), (None, None));
    assert_eq!(
        (args.reconnect_every, args.seed, args.summary),
        (0.0, 1, None)
    );
}

#[test]
fn detect_takes_every_option() {
    let Ok(Command::Detect(args)) = parse(&[
        "detect",
        "--server",
        "http://h:1",
        "--token",
        "t0k",
        "--data",
        "a.csv",
        "--rate",
        "20",
        "--batch",
        "50",
        "--model",
        "models/m",
        "--out",
        "rows.csv",
        "--quiet",
        "--reconnect-every",
        "300",
        "--seed",
        "9",
        "--summary",
        "fleet.json",
    ]) else {
        panic!("detect must parse");
    };
    assert_eq!((args.reconnect_every, args.seed), (300.0, 9));
    assert_eq!(
        args.summary.as_deref(),
        Some(std::path::Path::new("fleet.json"))
    );
    assert_eq!(args.server.server, "http://h:1");
    assert_eq!(args.server.token.as_deref(), Some("t0k"));
    assert_eq!((args.rate, args.batch, args.quiet), (20.0, 50, true));
    assert_eq!(args.model.as_deref(), Some("models/m"));
}

#[test]
fn detect_refuses_out_of_range_values() {
    for bad in [
        &["detect", "--data", "a.csv", "--batch", "0"][..],
        &["detect", "--data", "a.csv", "--batch", "1001"],
        &["detect", "--data", "a.csv", "--rate", "-1"],
        &["detect", "--data", "a.csv", "--rate", "inf"],
        &["detect", "--data", "a.csv", "--reconnect-every", "-5"],
        &["detect", "--data", "a.csv", "--reconnect-every", "nan"],
        &["detect"],
    ] {
        assert!(parse(bad).is_err(), "{bad:?}");
    }
}

#[test]
fn server_flags_may_follow_the_subcommand() {
    let Ok(Command::Models(args)) = parse(&["models", "list", "--server", "http://m:2"]) else {
        panic!("models list must parse");
    };
    assert_eq!(args.server.server, "http://m:2");
    assert!(matches!(args.command, remote::models::Command::List));
}

#[test]
fn model_and_dataset_subcommands_parse() {
    let Ok(Command::Models(args)) = parse(&[
        "models",
        "import",
        "--file",
        "m.json",
        "--name",
        "mine",
        "--activate",
    ]) else {
        panic!("models import must parse");
    };
    assert!(matches!(
        args.command,
        remote::models::Command::Import { activate: true, ref name, .. } if name.as_deref() == Some("mine")
    ));
    let Ok(Command::Models(args)) = parse(&["models", "export", "models/a", "--out", "a.json"])
    else {
        panic!("models export must parse");
    };
    assert!(
        matches!(args.command, remote::models::Command::Export { ref name, .. } if name == "models/a")
    );
    assert!(
        parse(&["models", "export", "models/a"]).is_err(),
        "--out is required"
    );

    let Ok(Command::Datasets(args)) =
        parse(&["datasets", "import", "--path", "AV-GPS-Dataset-2.csv"])
    else {
        panic!("datasets import must parse");
    };
    assert!(matches!(
        args.command,
        remote::datasets::Command::Import { ref path, name: None } if path == "AV-GPS-Dataset-2.csv"
    ));
    for ok in [
        &["datasets", "upload", "--file", "x.csv"][..],
        &["datasets", "list"],
        &["datasets", "get", "datasets/1"],
        &["datasets", "delete", "datasets/1"],
        &["models", "get", "m"],
        &["models", "activate", "m"],
        &["models", "delete", "m"],
        &["health"],
    ] {
        assert!(parse(ok).is_ok(), "{ok:?}");
    }
}

#[test]
fn jobs_subcommands_parse() {
    let Ok(Command::Jobs(args)) = parse(&["jobs", "wait", "operations/x", "--timeout", "3"]) else {
        panic!("jobs wait must parse");
    };
    assert!(matches!(
        args.command,
        remote::jobs::Command::Wait { ref name, timeout: Some(t) } if name == "operations/x" && t == 3.0
    ));
    let Ok(Command::Jobs(args)) =
        parse(&["jobs", "list", "--filter", "kind=training AND done=false"])
    else {
        panic!("jobs list must parse");
    };
    assert!(matches!(
        args.command,
        remote::jobs::Command::List { ref filter } if filter == "kind=training AND done=false"
    ));
    assert!(parse(&["jobs", "get", "operations/x"]).is_ok());
    assert!(parse(&["jobs", "cancel", "operations/x"]).is_ok());
    assert!(parse(&["jobs", "wait", "operations/x", "--timeout", "0"]).is_err());
}

#[test]
fn train_stays_offline_without_server() {
    let Ok(Command::Train(args)) = parse(&["train", "--data", "a.csv", "--out", "m.json"]) else {
        panic!("offline train must parse");
    };
    let debug = format!("{args:?}");
    assert!(debug.contains("server: None"), "{debug}");
    assert!(
        parse(&["train", "--data", "a.csv"]).is_err(),
        "--out is required offline"
    );
    assert!(
        parse(&["train", "--out", "m.json"]).is_err(),
        "--data is required offline"
    );
}

#[test]
fn train_with_server_is_remote_and_takes_datasets() {
    let parsed = parse(&[
        "train",
        "--server",
        "http://s:3",
        "--dataset",
        "datasets/a",
        "datasets/b",
        "--val-dataset",
        "datasets/v",
        "--epochs",
        "3",
        "--activate",
        "--name",
        "run1",
    ]);
    let Ok(Command::Train(args)) = parsed else {
        panic!("remote train must parse: {parsed:?}");
    };
    let debug = format!("{args:?}");
    for expected in [
        "server: Some(\"http://s:3\")",
        "datasets: [\"datasets/a\", \"datasets/b\"]",
        "val_datasets: [\"datasets/v\"]",
        "activate: true",
        "epochs: 3",
    ] {
        assert!(debug.contains(expected), "{expected} missing in {debug}");
    }
}

#[test]
fn train_modes_do_not_mix() {
    assert!(
        parse(&[
            "train",
            "--server",
            "http://s:3",
            "--dataset",
            "d",
            "--data",
            "a.csv"
        ])
        .is_err()
    );
    assert!(
        parse(&[
            "train",
            "--server",
            "http://s:3",
            "--dataset",
            "d",
            "--out",
            "m"
        ])
        .is_err()
    );
    assert!(parse(&["train", "--server", "http://s:3", "--val", "v.csv"]).is_err());
    // Remote-only flags without --server parse, and are refused by `train::run` before any work.
    let Ok(Command::Train(args)) =
        parse(&["train", "--dataset", "d", "--data", "a.csv", "--out", "m"])
    else {
        panic!("parses");
    };
    let error = super::train::run(args).expect_err("refused");
    assert_eq!(
        error.to_string(),
        "remote-training flags need --server: --dataset"
    );
}

#[test]
fn bench_has_documented_defaults_and_bounds() {
    let Ok(Command::Bench(args)) = parse(&["bench"]) else {
        panic!("bench must parse");
    };
    assert_eq!(args.streams, vec![1, 100, 1000]);
    assert_eq!((args.batch, args.seconds, args.sessions), (10, 5.0, 10_000));
    assert_eq!((args.server.server, args.server_pid), (None, None));

    let Ok(Command::Bench(args)) = parse(&[
        "bench",
        "--server",
        "http://b:4",
        "--server-pid",
        "42",
        "--streams",
        "2,20",
        "--batch",
        "5",
        "--seconds",
        "1.5",
        "--sessions",
        "0",
    ]) else {
        panic!("bench with options must parse");
    };
    assert_eq!(args.streams, vec![2, 20]);
    assert_eq!((args.batch, args.seconds, args.sessions), (5, 1.5, 0));
    assert_eq!(args.server_pid, Some(42));

    assert!(
        parse(&["bench", "--server-pid", "42"]).is_err(),
        "needs --server"
    );
    assert!(parse(&["bench", "--streams", "0"]).is_err());
    assert!(parse(&["bench", "--seconds", "0"]).is_err());
    assert!(parse(&["bench", "--batch", "1001"]).is_err());
    assert_eq!(
        args.vehicles_per_message, 1,
        "one stream per vehicle by default"
    );
    assert!(parse(&["bench", "--vehicles-per-message", "0"]).is_err());
    assert!(parse(&["bench", "--vehicles-per-message", "1001"]).is_err());
}

#[test]
fn demo_defaults_to_twenty_samples_per_second() {
    let Ok(Command::Demo(args)) = parse(&["demo"]) else {
        panic!("demo must parse");
    };
    assert_eq!(args.rate, 20.0);
    assert!(parse(&["demo", "--rate", "-2"]).is_err());
}

#[test]
fn scenario_simulate_takes_a_rate_or_realistic_drives_but_not_both() {
    let simulate = |extra: &[&str]| {
        let mut args = vec!["scenario", "simulate", "--out", "drives.csv"];
        args.extend_from_slice(extra);
        parse(&args)
    };
    assert!(simulate(&[]).is_ok());
    assert!(simulate(&["--rate", "10"]).is_ok());
    assert!(simulate(&["--realistic"]).is_ok());
    let err =
        simulate(&["--realistic", "--rate", "10"]).expect_err("the realistic draw sets the rate");
    assert_eq!(err.kind(), clap::error::ErrorKind::ArgumentConflict);
    assert!(err.to_string().contains("--rate"), "{err}");
}

#[test]
fn scenario_fleet_defaults_to_the_default_scene_and_maps_each_attack() {
    use spoofwatch_core::scenario::{FleetSpec, RegionalAttack};
    let fleet = |extra: &[&str]| {
        let mut args = vec!["scenario", "fleet", "--out", "s.csv", "--truth", "t.json"];
        args.extend_from_slice(extra);
        match parse(&args) {
            Ok(Command::Scenario(super::scenario::Command::Fleet(args))) => args.spec(),
            other => panic!("scenario fleet must parse: {other:?}"),
        }
    };
    assert_eq!(fleet(&[]).expect("the defaults"), FleetSpec::default());
    let attack = |extra: &[&str]| fleet(extra).expect("valid").spoofer.attack;
    assert_eq!(
        attack(&[
            "--attack",
            "position",
            "--false-lat",
            "-33.9",
            "--false-lon",
            "-70.6"
        ]),
        RegionalAttack::Position {
            lat_deg: -33.9,
            lon_deg: -70.6
        }
    );
    assert_eq!(
        attack(&["--attack", "translation", "--north-m", "-300"]),
        RegionalAttack::Translation {
            east_m: 0.0,
            north_m: -300.0
        }
    );
    assert_eq!(
        attack(&["--attack", "drift", "--north-mps", "0.5"]),
        RegionalAttack::Drift {
            east_mps: 0.0,
            north_mps: 0.5
        }
    );
    let spec = fleet(&[
        "--centre-lat",
        "-33.45",
        "--centre-lon",
        "-70.66",
        "--spoofer-lon",
        "-70.7",
    ])
    .expect("valid");
    assert_eq!(
        (spec.spoofer.lat_deg, spec.spoofer.lon_deg),
        (-33.45, -70.7),
        "an omitted spoofer coordinate is the area's centre"
    );
    let refused = |extra: &[&str]| fleet(extra).expect_err("refused").to_string();
    assert!(refused(&["--attack", "position", "--false-lat", "1"]).contains("--false-lon"));
    assert!(refused(&["--false-lat", "1"]).contains("--attack position"));
    assert!(refused(&["--attack", "translation"]).contains("--east-m"));
    let err = refused(&["--start", "3600"]);
    assert!(
        err.contains("--start") && err.contains("spoofer.start_s"),
        "{err}"
    );
    let err = refused(&["--attack", "drift", "--east-mps", "0"]);
    assert!(err.starts_with("--attack: "), "{err}");
}

#[test]
fn alarms_list_and_watch_take_their_filters() {
    let Ok(Command::Alarms(args)) = parse(&[
        "alarms",
        "list",
        "--vehicle",
        "car-1",
        "--model",
        "models/m",
        "--since",
        "2025-06-01T00:00:00Z",
        "--until",
        "2025-06-02T00:00:00Z",
        "--state",
        "open",
        "--limit",
        "5",
        "--json",
    ]) else {
        panic!("alarms list must parse");
    };
    let remote::alarms::Command::List(list) = args.command else {
        panic!("a list command");
    };
    let request = remote::alarms::list_request(&list);
    assert_eq!(
        (request.vehicle_id.as_str(), request.model.as_str()),
        ("car-1", "models/m")
    );
    assert_eq!(request.onset_after.map(|t| t.seconds), Some(1_748_736_000));
    assert_eq!(request.onset_before.map(|t| t.seconds), Some(1_748_822_400));
    assert_eq!(
        request.state,
        spoofwatch_proto::v1::AlarmStateFilter::Open as i32
    );
    assert_eq!((list.limit, list.json), (Some(5), true));

    let Ok(Command::Alarms(args)) = parse(&["alarms", "watch", "--after", "42"]) else {
        panic!("alarms watch must parse");
    };
    let remote::alarms::Command::Watch(watch) = args.command else {
        panic!("a watch command");
    };
    assert_eq!(
        (watch.after, watch.vehicle, watch.count),
        (Some(42), None, None)
    );
    assert_eq!(watch.reconnect_for, 300.0);
}

#[test]
fn alarms_refuse_bad_times_cursors_and_states() {
    for bad in [
        &["alarms", "list", "--since", "yesterday"][..],
        &["alarms", "list", "--state", "half"],
        &["alarms", "watch", "--after", "-1"],
        &["alarms", "watch", "--reconnect-for", "-1"],
        &["alarms", "watch", "--reconnect-for", "nan"],
    ] {
        assert!(parse(bad).is_err(), "{bad:?} must be refused");
    }
}

#[test]
fn incidents_end_and_dismiss_need_a_reason_and_print_the_closure() {
    for (verb, dismissing) in [("end", false), ("dismiss", true)] {
        let Ok(Command::Incidents(args)) = parse(&[
            "incidents",
            verb,
            "3",
            "--reason",
            "the jammer was switched off",
        ]) else {
            panic!("incidents {verb} must parse");
        };
        let (remote::incidents::Command::End(end) | remote::incidents::Command::Dismiss(end)) =
            &args.command
        else {
            panic!("an end or dismiss command");
        };
        assert_eq!(
            (end.id, end.reason.as_str()),
            (3, "the jammer was switched off")
        );
        assert_eq!(
            matches!(args.command, remote::incidents::Command::Dismiss(_)),
            dismissing
        );
        assert!(
            parse(&["incidents", verb, "3"]).is_err(),
            "incidents {verb} without a reason must be refused"
        );
    }

    use spoofwatch_proto::v1;
    let incident = v1::Incident {
        id: 3,
        closure: Some(v1::IncidentClosure {
            kind: v1::IncidentClosureKind::Dismissed as i32,
            reason: "fabricated".into(),
            closed_by: "admin token".into(),
            closed_time: Some(prost_types::Timestamp {
                seconds: 1_748_736_000,
                nanos: 0,
            }),
        }),
        ..v1::Incident::default()
    };
    let json = remote::incidents::incident_json(&incident);
    assert_eq!(json["closure"]["kind"], "dismissed");
    assert_eq!(json["closure"]["reason"], "fabricated");
    assert_eq!(json["closure"]["closed_by"], "admin token");
    assert_eq!(json["closure"]["closed_time"], "2025-06-01T00:00:00Z");
    let open = remote::incidents::incident_json(&v1::Incident::default());
    assert!(open["closure"].is_null());
}
