//! Cutting recorded or simulated tracks into pieces to inject attacks into: each piece with the rows
//! of its track before it as warm-up, so that an attack injected into it meets a warm per-vehicle
//! state, and the injected copy joined back to those rows.
//!
//! Owns the cutting and the joining. Must not draw or inject attacks (the callers do, with
//! [`super::generate`] or [`super::inject`]).

use crate::sample::{Record, Track};

/// One piece of a track and the rows that precede it as its warm-up.
pub struct Piece {
    pub base: Track,
    pub warmup: Vec<Record>,
}

/// Cuts tracks into consecutive pieces of about `piece_s` seconds (shorter remainders are dropped),
/// each with the track's rows of the `warmup_s` seconds before it, marked as warm-up. Rows that are
/// already warm-up rows are never cut into a piece.
pub fn pieces(tracks: &[Track], piece_s: f64, warmup_s: f64) -> Vec<Piece> {
    let mut out = Vec::new();
    for track in tracks {
        let records = &track.records;
        let Some(mut start) = records.iter().position(|r| !r.warmup) else {
            continue;
        };
        for (i, r) in records.iter().enumerate().skip(start) {
            let t0 = records[start].sample.timestamp_s;
            if r.sample.timestamp_s - t0 < piece_s {
                continue;
            }
            let warmup_rows = records[..start]
                .iter()
                .rev()
                .take_while(|w| t0 - w.sample.timestamp_s < warmup_s)
                .count();
            let mut warmup = records[start - warmup_rows..start].to_vec();
            for w in &mut warmup {
                w.warmup = true;
            }
            let mut base = records[start..i].to_vec();
            base[0].trajectory_break = true;
            out.push(Piece {
                base: Track {
                    vehicle_id: format!("{}@{}", track.vehicle_id, out.len()),
                    records: base,
                },
                warmup,
            });
            start = i;
        }
    }
    out
}

/// `track` continuing from the warm-up rows `warmup` (the first of them starts the trajectory).
pub fn with_warmup(warmup: &[Record], mut track: Track) -> Track {
    if warmup.is_empty() {
        return track;
    }
    track.records[0].trajectory_break = false;
    let mut records = warmup.to_vec();
    records[0].trajectory_break = true;
    records.append(&mut track.records);
    Track { records, ..track }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::{DriveSpec, simulate_drive};

    fn track(seconds: f64) -> Track {
        let spec = DriveSpec {
            duration_s: seconds,
            seed: 4,
            ..DriveSpec::default()
        };
        simulate_drive(&spec, "piece").expect("valid drive")
    }

    #[test]
    fn pieces_carry_the_rows_before_them_as_warm_up_and_never_cut_warm_up_rows() {
        let mut whole = track(999.0); // 1000 rows at 1 Hz
        for record in &mut whole.records[..100] {
            record.warmup = true;
        }
        let cut = pieces(std::slice::from_ref(&whole), 300.0, 150.5);
        // Rows 100..1000: two whole pieces of 300 s; the last 299 s are too short.
        let starts: Vec<u64> = cut.iter().map(|p| p.base.records[0].line).collect();
        assert_eq!(starts, [101, 401]);
        assert!(cut.iter().all(|p| p.base.records.len() == 300));
        let warm: Vec<usize> = cut.iter().map(|p| p.warmup.len()).collect();
        assert_eq!(warm, [100, 150]);
        assert!(cut.iter().all(|p| p.warmup.iter().all(|r| r.warmup)));
        assert!(cut.iter().all(|p| p.base.records.iter().all(|r| !r.warmup)));
        assert_eq!(cut[1].warmup[0].line, 251);

        let joined = with_warmup(&cut[1].warmup, cut[1].base.clone());
        assert_eq!(joined.records.len(), 450);
        assert!(joined.records[0].trajectory_break);
        assert!(!joined.records[150].trajectory_break && !joined.records[150].warmup);

        // Without warm-up the pieces are cut as they always were.
        let plain = pieces(&[track(999.0)], 300.0, 0.0);
        assert_eq!(plain.len(), 3);
        assert!(plain.iter().all(|p| p.warmup.is_empty()));
        assert!(plain.iter().all(|p| p.base.records[0].trajectory_break));
    }
}
