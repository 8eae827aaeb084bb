//! Reader checks on small hand-written files.

use super::telemetry::write_tracks;
use super::*;
use crate::sample::{Record, Sample};

const AVGPS_HEADER: &str = "Heading (deg),Yaw (deg),Velocity (m/s),Run Time,Hobbs,Clock Time,Clock Date,\
GPS Latitude,GPS Longitude,Data Type,EKF Detector";

fn avgps(rows: &[&str]) -> String {
    let mut text = String::from(AVGPS_HEADER);
    for row in rows {
        text.push_str("\r\n");
        text.push_str(row);
    }
    text.push_str("\r\n");
    text
}

fn read_str(text: &str, source: &str) -> Result<Recording, DataError> {
    read(text.as_bytes(), source)
}

#[test]
fn avgps_times_breaks_and_fields() {
    let text = avgps(&[
        // 0: no clock → δ NaN; first row is a break.
        "10,-170,1.5,0:00:00,15:03:55,,,32.23,-110.9,0,",
        // 1: clock missing on the previous row → Run Time fallback: δ = 1.
        "11,-169,1.6,0:00:01,15:03:55,10:55:59,5/24/2022,32.2301,-110.9,0,1",
        // 2: Δclock = 2 → δ = 2. Empty speed → NaN.
        "12,-168,,0:00:02,15:03:55,10:56:01,5/24/2022,32.2302,-110.9,1,1",
        // 3: Δclock = 0, ΔRunTime = 1 → δ = 1 (fallback).
        "13,-167,1.7,0:00:03,15:03:55,10:56:01,5/24/2022,nan,-110.9,1,0",
        // 4: Δclock = 7 → gap break, δ = 7.
        "14,-166,1.8,0:00:10,15:03:55,10:56:08,5/24/2022,32.2303,-110.9,1,0",
        // 5: Δclock 1, Run Time reset → break, δ = 1.
        "15,-165,1.9,0:00:00,15:03:55,10:56:09,5/24/2022,32.2304,-110.9,0,0",
        // 6: date change (clock goes back 3 days) → break, δ NaN (Δclock < 0, ΔRunTime 1 → 1!).
        "16,-164,2.0,0:00:01,15:03:55,10:56:10,5/21/2022,32.2305,-110.9,0,0",
        // 7: nothing changes in Run Time and the clock repeats → δ NaN, no break.
        "17,-163,2.1,0:00:01,15:03:55,10:56:10,5/21/2022,32.2306,-110.9,0,0",
        // 8: Hobbs goes back → break.
        "18,-162,2.2,0:00:02,15:03:50,10:56:11,5/21/2022,32.2307,-110.9,0,0",
    ]);
    let rec = read_str(&text, "D").expect("valid file");
    assert_eq!(rec.format, Format::AvGps);
    assert_eq!(rec.source, "D");
    assert_eq!(rec.tracks.len(), 1);
    let track = &rec.tracks[0];
    assert_eq!(track.vehicle_id, "D");
    let breaks: Vec<bool> = track.records.iter().map(|r| r.trajectory_break).collect();
    assert_eq!(
        breaks,
        [true, false, false, false, true, true, true, false, true]
    );
    // Cumulative δ with NaN as 0: 0, 1, 3, 4, 11, 12, 13 (ΔRunTime fallback), 13, 14.
    let times: Vec<f64> = track.records.iter().map(|r| r.sample.timestamp_s).collect();
    assert_eq!(times, [0.0, 1.0, 3.0, 4.0, 11.0, 12.0, 13.0, 13.0, 14.0]);
    let lines: Vec<u64> = track.records.iter().map(|r| r.line).collect();
    assert_eq!(lines, (2..=10).collect::<Vec<u64>>());
    let first = &track.records[0];
    assert_eq!(first.sample.heading_deg, 10.0, "Heading, not Yaw");
    assert_eq!(first.sample.speed_mps, 1.5);
    assert_eq!(
        (first.sample.latitude_deg, first.sample.longitude_deg),
        (32.23, -110.9)
    );
    assert_eq!((first.label, first.comparator_alarm), (Some(false), None));
    assert!(track.records[2].sample.speed_mps.is_nan());
    assert!(track.records[3].sample.latitude_deg.is_nan());
    assert_eq!(track.records[2].label, Some(true));
    assert_eq!(track.records[2].comparator_alarm, Some(true));
}

fn error_of(text: &str) -> String {
    read_str(text, "AV-GPS-Dataset-3.csv")
        .expect_err("malformed")
        .to_string()
}

#[test]
fn avgps_errors_name_file_line_and_column() {
    let ok = "10,-170,1.5,0:00:00,15:03:55,10:55:59,5/24/2022,32.23,-110.9,0,0";
    let msg = error_of(&avgps(&[
        ok,
        "10,-170,1.5,0:00:01,15:03:55,10:56:00,5/24/2022,abc,-110.9,0,0",
    ]));
    assert_eq!(
        msg,
        "AV-GPS-Dataset-3.csv:3: column \"GPS Latitude\": expected a number, got \"abc\""
    );
    let msg = error_of(&avgps(&[
        ok,
        ok,
        "10,-170,1.5,0:00:01,15:03:55,10:5x:00,5/24/2022,32.23,-110.9,0,0",
    ]));
    assert!(
        msg.starts_with("AV-GPS-Dataset-3.csv:4: column \"Clock Time\": expected a 24-hour time"),
        "{msg}"
    );
    let msg = error_of(&avgps(&[
        "10,-170,1.5,0:00:01,15:03:55,10:56:00,24/5/2022,32.23,-110.9,0,0",
    ]));
    assert!(
        msg.starts_with("AV-GPS-Dataset-3.csv:2: column \"Clock Date\""),
        "{msg}"
    );
    let msg = error_of(&avgps(&[
        "10,-170,1.5,1:00,15:03:55,10:56:00,5/24/2022,32.23,-110.9,0,0",
    ]));
    assert!(
        msg.starts_with("AV-GPS-Dataset-3.csv:2: column \"Run Time\""),
        "{msg}"
    );
    let msg = error_of(&avgps(&[
        "10,-170,1.5,0:00:01,15:03:55,10:56:00,5/24/2022,32.23,-110.9,2,0",
    ]));
    assert!(
        msg.starts_with("AV-GPS-Dataset-3.csv:2: column \"Data Type\""),
        "{msg}"
    );
    // A short row names the first missing column; a long one the last header column.
    let msg = error_of(&avgps(&[
        ok,
        "10,-170,1.5,0:00:01,15:03:55,10:56:00,5/24/2022",
    ]));
    assert_eq!(
        msg,
        "AV-GPS-Dataset-3.csv:3: column \"GPS Latitude\": missing: the row has 7 fields, the header 11"
    );
    let msg = error_of(&avgps(&[&format!("{ok},9")]));
    assert!(
        msg.starts_with("AV-GPS-Dataset-3.csv:2: the row has 12 fields")
            && msg.contains("\"EKF Detector\""),
        "{msg}"
    );
}

#[test]
fn unknown_and_empty_headers_are_errors() {
    let msg = read_str("a,b,latitude\n1,2,3\n", "x.csv")
        .expect_err("unknown")
        .to_string();
    assert!(
        msg.starts_with("x.csv: unrecognised header: not AV-GPS (missing \"GPS Latitude\""),
        "{msg}"
    );
    assert!(
        msg.contains("not telemetry (missing \"vehicle_id\", \"timestamp\""),
        "{msg}"
    );
    assert!(!msg.contains("\"latitude\""), "{msg}");
    let msg = read_str("", "empty.csv").expect_err("empty").to_string();
    assert_eq!(msg, "empty.csv: empty file (no header row)");
}

#[test]
fn io_errors_name_the_file() {
    let missing = std::path::Path::new("/nonexistent/dir/AV-GPS-Dataset-9.csv");
    let msg = read_path(missing).expect_err("missing file").to_string();
    assert!(
        msg.starts_with("/nonexistent/dir/AV-GPS-Dataset-9.csv: "),
        "{msg}"
    );
}

#[test]
fn read_path_names_the_avgps_vehicle_after_the_file_stem() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("AV-GPS-Dataset-7.csv");
    let ok = "10,-170,1.5,0:00:00,15:03:55,10:55:59,5/24/2022,32.23,-110.9,0,0";
    std::fs::write(&path, avgps(&[ok])).expect("write");
    let rec = read_path(&path).expect("valid");
    assert_eq!(rec.tracks[0].vehicle_id, "AV-GPS-Dataset-7");
    assert_eq!(rec.source, path.display().to_string());
}

#[test]
fn telemetry_interleaved_vehicles_any_column_order() {
    let text = "extra,heading_deg,speed_mps,label,longitude,latitude,timestamp,vehicle_id,position_std_m\n\
                x,90,1.5,0,-110.9,32.23,0,car-b,\n\
                y,91,1.6,1,-110.8,32.24,0,car-a,2.5\n\
                z,92,,,-110.9,32.23,1,car-b,nan\n\
                w,93,NaN,0,-110.8,32.24,1,car-a,\n";
    let rec = read_str(text, "fleet.csv").expect("valid");
    assert_eq!(rec.format, Format::Telemetry);
    let ids: Vec<&str> = rec.tracks.iter().map(|t| t.vehicle_id.as_str()).collect();
    assert_eq!(ids, ["car-b", "car-a"]);
    let b = &rec.tracks[0].records;
    assert_eq!(b.len(), 2);
    assert_eq!((b[0].line, b[1].line), (2, 4));
    assert_eq!(b[0].sample, Sample::new(0.0, 32.23, -110.9, 1.5, 90.0));
    assert!(b[1].sample.speed_mps.is_nan());
    assert_eq!((b[0].label, b[1].label), (Some(false), None));
    assert_eq!(b[1].sample.position_std_m, None);
    let a = &rec.tracks[1].records;
    assert_eq!(a[0].sample.position_std_m, Some(2.5));
    assert_eq!(a[0].sample.speed_std_mps, None);
    assert_eq!((a[0].label, a[0].line, a[1].line), (Some(true), 3, 5));
    assert!(a[1].sample.speed_mps.is_nan());
}

/// `summarize` counts what `read` would build, and fails with the very error `read` gives.
#[test]
fn a_summary_counts_what_read_builds() {
    let telemetry = "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,label\n\
                     car-b,0,32.23,-110.9,1.5,90,0\n\
                     car-a,0,32.24,-110.8,1.6,91,1\n\
                     car-b,1,32.23,-110.9,1.5,90,\n\
                     car-a,1,32.24,-110.8,1.6,91,1\n\
                     car-c,1,32.25,-110.8,1.6,91,0\n";
    assert_eq!(
        summarize(telemetry.as_bytes(), "fleet.csv").expect("valid"),
        Summary {
            format: Format::Telemetry,
            rows: 5,
            vehicles: 3,
            labelled_rows: 4,
            spoofed_rows: 2,
        }
    );
    let one_vehicle = avgps(&[
        "10,-170,1.5,0:00:00,15:03:55,,,32.23,-110.9,0,",
        "11,-169,1.6,0:00:01,15:03:55,10:55:59,5/24/2022,32.2301,-110.9,1,1",
        "12,-168,1.6,0:00:02,15:03:55,10:56:00,5/24/2022,32.2302,-110.9,,1",
    ]);
    assert_eq!(
        summarize(one_vehicle.as_bytes(), "D").expect("valid"),
        Summary {
            format: Format::AvGps,
            rows: 3,
            vehicles: 1,
            labelled_rows: 2,
            spoofed_rows: 1,
        }
    );
    // An AV-GPS file without rows is still its one vehicle, as `read` has it.
    let empty = avgps(&[]);
    assert_eq!(read_str(&empty, "E").expect("valid").tracks.len(), 1);
    assert_eq!(summarize(empty.as_bytes(), "E").expect("valid").vehicles, 1);
    let bad = "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg\n\
               v,0,32.23,-110.9,1.0,90\n\
               v,1,32.23,-110.9,fast,90\n";
    assert_eq!(
        summarize(bad.as_bytes(), "t.csv")
            .expect_err("bad")
            .to_string(),
        read_str(bad, "t.csv").expect_err("bad").to_string()
    );
}

#[test]
fn telemetry_errors_name_line_and_column() {
    let text = "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg\n\
                v,0,32.23,-110.9,1.0,90\n\
                v,1,32.23,-110.9,fast,90\n";
    let msg = read_str(text, "t.csv").expect_err("bad").to_string();
    assert_eq!(
        msg,
        "t.csv:3: column \"speed_mps\": expected a number, got \"fast\""
    );
    let text = "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,label\n\
                v,0,32.23,-110.9,1.0,90,yes\n";
    let msg = read_str(text, "t.csv").expect_err("bad label").to_string();
    assert!(msg.starts_with("t.csv:2: column \"label\""), "{msg}");
    let text = "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg\n\
                ,0,32.23,-110.9,1.0,90\n";
    let msg = read_str(text, "t.csv").expect_err("no id").to_string();
    assert_eq!(msg, "t.csv:2: column \"vehicle_id\": empty vehicle id");
}

#[test]
fn telemetry_round_trips_through_write_tracks() {
    let record = |t: f64, speed: f64, label: Option<bool>, line: u64| Record {
        sample: Sample::new(t, 32.231_495_4 + t * 1e-5, -110.907_963_1, speed, 359.5),
        label,
        comparator_alarm: None,
        line,
        trajectory_break: false,
        warmup: false,
    };
    let tracks = vec![
        Track {
            vehicle_id: "alpha".into(),
            records: vec![
                record(0.0, 1.25, Some(false), 2),
                record(1.0, 0.1 + 0.2, Some(true), 3),
            ],
        },
        Track {
            vehicle_id: "beta".into(),
            records: vec![record(0.5, 3.0, None, 4)],
        },
    ];
    let mut bytes = Vec::new();
    write_tracks(&mut bytes, &tracks).expect("write");
    let rec = read(bytes.as_slice(), "round-trip").expect("read back");
    assert_eq!(rec.format, Format::Telemetry);
    assert_eq!(rec.tracks, tracks);
    // NaN survives as NaN.
    let nan_track = vec![Track {
        vehicle_id: "n".into(),
        records: vec![record(0.0, f64::NAN, None, 2)],
    }];
    let mut bytes = Vec::new();
    write_tracks(&mut bytes, &nan_track).expect("write");
    let rec = read(bytes.as_slice(), "nan").expect("read back");
    assert!(rec.tracks[0].records[0].sample.speed_mps.is_nan());
    // Uncertainties, present or absent per sample, survive too.
    let mut uncertain = tracks.clone();
    uncertain[0].records[0].sample.position_std_m = Some(2.5);
    uncertain[0].records[1].sample.speed_std_mps = Some(0.125);
    uncertain[1].records[0].sample.heading_std_deg = Some(3.0);
    let mut bytes = Vec::new();
    write_tracks(&mut bytes, &uncertain).expect("write");
    let header = String::from_utf8_lossy(&bytes)
        .lines()
        .next()
        .map(str::to_owned);
    assert_eq!(
        header.as_deref(),
        Some(
            "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,label,position_std_m,speed_std_mps,heading_std_deg"
        )
    );
    let rec = read(bytes.as_slice(), "uncertain").expect("read back");
    assert_eq!(rec.tracks, uncertain);
}

#[test]
fn receiver_status_columns_read_names_and_numbers_and_round_trip() {
    use crate::sample::{JammingState, SpoofingState};
    let text = "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,spoofing_state,jamming_state,satellites_used,hdop\n\
                v,0,32.23,-110.9,1.0,90,none,ok,12,0.8\n\
                v,1,32.23,-110.9,1.0,90,2,3,,\n\
                v,2,32.23,-110.9,1.0,90,Multiple,,7,nan\n\
                v,3,32.23,-110.9,1.0,90,,warning,300,150\n";
    let recording = read_str(text, "r.csv").expect("valid");
    let samples: Vec<_> = recording.tracks[0]
        .records
        .iter()
        .map(|r| r.sample)
        .collect();
    let states: Vec<_> = samples
        .iter()
        .map(|s| (s.spoofing_state, s.jamming_state, s.satellites_used, s.hdop))
        .collect();
    assert_eq!(
        states,
        [
            (SpoofingState::None, JammingState::Ok, Some(12), Some(0.8)),
            (SpoofingState::Indicated, JammingState::Critical, None, None),
            (
                SpoofingState::Multiple,
                JammingState::Unknown,
                Some(7),
                None
            ),
            // Out of range, but parsed: the API's validation refuses it, no evidence reads it.
            (
                SpoofingState::Unknown,
                JammingState::Warning,
                Some(300),
                Some(150.0)
            ),
        ]
    );
    let mut bytes = Vec::new();
    write_tracks(&mut bytes, &recording.tracks).expect("write");
    let written = String::from_utf8_lossy(&bytes).into_owned();
    assert!(
        written.starts_with(
            "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,spoofing_state,jamming_state,satellites_used,hdop\n\
             v,0,32.23,-110.9,1,90,none,ok,12,0.8\n"
        ),
        "{written}"
    );
    assert_eq!(
        read(bytes.as_slice(), "again").expect("read back").tracks,
        recording.tracks
    );

    for (cell, expected) in [
        (
            "spoofed",
            "expected unknown, none, indicated, multiple, 0 to 3 or empty, got \"spoofed\"",
        ),
        ("4", "expected a state number 0 to 3, got 4"),
    ] {
        let text = format!(
            "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,spoofing_state\n\
             v,0,32.23,-110.9,1.0,90,{cell}\n"
        );
        let msg = read_str(&text, "t.csv").expect_err("bad state").to_string();
        assert_eq!(
            msg,
            format!("t.csv:2: column \"spoofing_state\": {expected}")
        );
    }
    let text = "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,satellites_used\n\
                v,0,32.23,-110.9,1.0,90,-1\n";
    let msg = read_str(text, "t.csv")
        .expect_err("negative count")
        .to_string();
    assert!(
        msg.starts_with("t.csv:2: column \"satellites_used\": expected a whole number"),
        "{msg}"
    );
}

#[test]
fn numeric_columns_are_keyed_by_the_lines_of_the_track_rows() {
    let text = avgps(&[
        "10,-170,1.5,0:00:00,15:03:55,10:55:59,5/24/2022,32.23,-110.9,0,",
        "11,,1.6,0:00:01,15:03:55,10:56:00,5/24/2022,32.2301,-110.9,0,1",
        "12,-168,nan,0:00:02,15:03:55,10:56:01,5/24/2022,32.2302,-110.9,1,1",
    ]);
    let track = &read_str(&text, "D").expect("valid file").tracks[0];
    let columns = read_numeric_columns(text.as_bytes(), "D", &["Velocity (m/s)", "Yaw (deg)"])
        .expect("both columns exist");
    assert_eq!(columns.names, ["Velocity (m/s)", "Yaw (deg)"]);
    for (record, expected_velocity) in track.records.iter().zip([1.5, 1.6, f64::NAN]) {
        let values = columns
            .at_line(record.line)
            .expect("every track row has its columns");
        assert_eq!(values[0].to_bits(), expected_velocity.to_bits());
    }
    assert!(columns.at_line(track.records[1].line).expect("row 2")[1].is_nan());
    assert_eq!(columns.at_line(1), None, "the header is not a row");

    let missing = read_numeric_columns(text.as_bytes(), "D", &["Satellite Count"]);
    assert!(
        matches!(&missing, Err(DataError::UnknownFormat { detail, .. }) if detail.contains("\"Satellite Count\"")),
        "{missing:?}"
    );
    let bad = avgps(&["10,-170,fast,0:00:00,15:03:55,10:55:59,5/24/2022,32.23,-110.9,0,"]);
    let error = read_numeric_columns(bad.as_bytes(), "D", &["Velocity (m/s)"]);
    assert!(
        matches!(&error, Err(DataError::Field { line: 2, column, .. }) if column == "Velocity (m/s)"),
        "{error:?}"
    );
}
