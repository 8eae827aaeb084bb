//! The AV-GPS files read, segmented and validated: the row counts, trajectories and ν asserted
//! below are those of the shared data.
//! Needs SPOOFWATCH_AVGPS_DIR (skipped when unset).

use spoofwatch_core::data::{Format, read_path};
use spoofwatch_core::evidence::{EvidenceParams, build_track};
use spoofwatch_core::geo::Projection;
use spoofwatch_core::sample::Track;
use spoofwatch_core::testdata::{AVGPS_DIR_VAR, data_file};

fn read_track(name: &str) -> Option<Track> {
    let path = data_file(AVGPS_DIR_VAR, name)?;
    let recording = read_path(&path).expect("the AV-GPS file reads");
    assert_eq!(recording.format, Format::AvGps);
    assert_eq!(recording.tracks.len(), 1);
    recording.tracks.into_iter().next()
}

/// (first row, last row) of each trajectory, 0-based file rows, from the builder's own starts.
fn trajectory_ranges(track: &Track) -> (Vec<(usize, usize)>, Vec<bool>) {
    let params = EvidenceParams::new([[1.0, 0.0], [0.0, 1.0]], 0.0, Projection::default())
        .expect("valid params");
    let evidence = build_track(&params, &track.records);
    let mut ranges: Vec<(usize, usize)> = Vec::new();
    for (row, e) in evidence.iter().enumerate() {
        if e.trajectory_start {
            assert_eq!(e.trajectory as usize, ranges.len(), "row {row}");
            ranges.push((row, row));
        } else if let Some(last) = ranges.last_mut() {
            last.1 = row;
        }
    }
    (ranges, evidence.iter().map(|e| e.valid).collect())
}

fn label_counts(track: &Track) -> (usize, usize) {
    let normal = track
        .records
        .iter()
        .filter(|r| r.label == Some(false))
        .count();
    let attack = track
        .records
        .iter()
        .filter(|r| r.label == Some(true))
        .count();
    (normal, attack)
}

#[test]
fn dataset2_has_six_trajectories_and_6882_valid_rows() {
    let Some(track) = read_track("AV-GPS-Dataset-2.csv") else {
        return;
    };
    assert_eq!(track.vehicle_id, "AV-GPS-Dataset-2");
    assert_eq!(track.records.len(), 6890);
    assert_eq!(label_counts(&track), (5184, 1706));
    assert!(track.records.iter().all(|r| r.comparator_alarm.is_none()));
    assert_eq!(track.records[0].line, 2);
    assert_eq!(track.records[6889].line, 6891);

    let (ranges, valid) = trajectory_ranges(&track);
    assert_eq!(
        ranges,
        [
            (0, 170),
            (171, 177),
            (178, 388),
            (389, 1705),
            (1706, 3963),
            (3964, 6889)
        ]
    );
    // The source flags give the same starts (the builder detects nothing more, nothing less).
    let flagged: Vec<usize> = (0..track.records.len())
        .filter(|&i| track.records[i].trajectory_break)
        .collect();
    assert_eq!(flagged, [0, 171, 178, 389, 1706, 3964]);

    assert_eq!(valid.iter().filter(|&&v| v).count(), 6882);
    let invalid: Vec<usize> = (0..valid.len()).filter(|&i| !valid[i]).collect();
    // Six starts, row 3965 (previous clock missing, Run Time delta 0), row 3992 (duplicate clock).
    assert_eq!(invalid, [0, 171, 178, 389, 1706, 3964, 3965, 3992]);
    let valid_normal = (0..valid.len())
        .filter(|&i| valid[i] && track.records[i].label == Some(false))
        .count();
    assert_eq!(valid_normal, 5180);
}

#[test]
fn dataset3_is_one_trajectory_with_635_label_free_valid_rows() {
    let Some(track) = read_track("AV-GPS-Dataset-3.csv") else {
        return;
    };
    assert_eq!(track.records.len(), 636);
    assert_eq!(label_counts(&track), (231, 405));
    let ekf_ones = track
        .records
        .iter()
        .filter(|r| r.comparator_alarm == Some(true))
        .count();
    let ekf_zeros = track
        .records
        .iter()
        .filter(|r| r.comparator_alarm == Some(false))
        .count();
    assert_eq!((ekf_ones, ekf_zeros), (355, 281));

    let (ranges, valid) = trajectory_ranges(&track);
    assert_eq!(ranges, [(0, 635)]);
    // Label-free ν: only row 0 is invalid (the reference's legacy mode also drops row 323).
    assert_eq!(valid.iter().filter(|&&v| v).count(), 635);
    assert!(!valid[0] && valid[323]);
    // Label structure: normal 0–141, attack 142–322, normal 323–411, attack 412–635.
    let attack = |i: usize| track.records[i].label == Some(true);
    assert!(!attack(141) && attack(142) && attack(322) && !attack(323));
    assert!(!attack(411) && attack(412) && attack(635));
    // Row 1 takes δ = 1 from Run Time (row 0 has no clock); then the clock runs 10:55:59 → 11:06:37.
    assert_eq!(track.records[1].sample.timestamp_s, 1.0);
    assert_eq!(track.records[635].sample.timestamp_s, 1.0 + 638.0);
}
