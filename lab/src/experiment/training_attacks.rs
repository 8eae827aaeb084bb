//! The attacks injected into normal training (and validation) data of the experiments: which kinds,
//! how the tracks are cut before injection, and the injected copies. It owns only that training
//! mix, not the scenario generator (core's `scenario`).

use anyhow::{Context, Result};
use spoofwatch_core::sample::{Record, Track};
use spoofwatch_core::scenario::{AttackDuration, AttackKind, ScenarioPlan, generate};
use spoofwatch_core::train::data::ChronologicalSplit;

/// Attacks injected into training (and, in the subtle experiment, validation) data: magnitudes a
/// metre-level GNSS/odometry residual can reveal, so the labels are learnable.
const TRAINING_KINDS: [AttackKind; 7] = [
    AttackKind::RampDrift { velocity_mps: 0.5 },
    AttackKind::RampDrift { velocity_mps: 1.0 },
    AttackKind::RampDrift { velocity_mps: 2.0 },
    AttackKind::AcceleratingDrift {
        acceleration_mps2: 0.05,
    },
    AttackKind::AcceleratingDrift {
        acceleration_mps2: 0.2,
    },
    AttackKind::FrozenPosition,
    AttackKind::Jump { offset_m: 30.0 },
];

/// Length of the pieces normal tracks are cut into before injection, and of each attack (s).
const TRAINING_PIECE_S: f64 = 300.0;
const TRAINING_ATTACK_S: f64 = 90.0;

/// One piece of a track and the rows that precede it as its warm-up.
struct Piece {
    base: Track,
    warmup: Vec<Record>,
}

/// Cuts tracks into consecutive pieces of about `piece_s` seconds (shorter remainders are dropped),
/// each with the track's rows of the `warmup_s` seconds before it, marked as warm-up. Rows that are
/// already warm-up rows are never cut into a piece.
fn pieces(tracks: &[Track], piece_s: f64, warmup_s: f64) -> Vec<Piece> {
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

/// Whether no row of `track` is labelled attacked.
pub fn is_normal(track: &Track) -> bool {
    track.records.iter().all(|r| r.label != Some(true))
}

/// Labelled copies of the normal tracks' pieces, every training attack kind injected into each piece
/// (random onset and direction), for training; each copy preceded by the `warmup_s` seconds of its
/// track before the piece as warm-up rows, so that the attack meets a warm per-vehicle state.
pub fn training_injections(tracks: &[Track], seed: u64, warmup_s: f64) -> Result<Vec<Track>> {
    let normal: Vec<Track> = tracks.iter().filter(|t| is_normal(t)).cloned().collect();
    let mut out = Vec::new();
    for (i, Piece { base, warmup }) in pieces(&normal, TRAINING_PIECE_S, warmup_s)
        .iter()
        .enumerate()
    {
        let plan = ScenarioPlan {
            kinds: TRAINING_KINDS.to_vec(),
            directions_deg: Vec::new(),
            duration: AttackDuration::Seconds(TRAINING_ATTACK_S),
            onset_s: None,
            margin_fraction: 0.15,
            repeats: 1,
            seed: seed.wrapping_add(i as u64),
        };
        let injected = generate(std::slice::from_ref(base), &plan)
            .with_context(|| format!("injecting a training attack into {}", base.vehicle_id))?;
        out.extend(injected.into_iter().map(|i| with_warmup(warmup, i.track)));
    }
    Ok(out)
}

/// `track` continuing from the warm-up rows `warmup` (the first of them starts the trajectory).
fn with_warmup(warmup: &[Record], mut track: Track) -> Track {
    if warmup.is_empty() {
        return track;
    }
    track.records[0].trajectory_break = false;
    let mut records = warmup.to_vec();
    records[0].trajectory_break = true;
    records.append(&mut track.records);
    Track { records, ..track }
}

/// `tracks` followed by copies of their normal pieces with injected subtle attacks (each after
/// `warmup_s` seconds of warm-up rows).
pub fn with_injections(tracks: &[Track], seed: u64, warmup_s: f64) -> Result<Vec<Track>> {
    Ok([
        tracks.to_vec(),
        training_injections(tracks, seed, warmup_s)?,
    ]
    .concat())
}

/// Training and validation tracks: Dataset-2's chronological training and validation parts with
/// injected attacks (left out with `simulated_only`; each injected piece after `warmup_s` seconds
/// of warm-up rows), each followed by its simulated mix.
pub fn recorded_and_simulated(
    split: &ChronologicalSplit,
    seed: u64,
    warmup_s: f64,
    simulated_only: bool,
    train_mix: Vec<Track>,
    validation_mix: Vec<Track>,
) -> Result<(Vec<Track>, Vec<Track>)> {
    let recorded = |tracks: &[Track], seed: u64| -> Result<Vec<Track>> {
        if simulated_only {
            Ok(Vec::new())
        } else {
            with_injections(tracks, seed, warmup_s)
        }
    };
    Ok((
        [recorded(&split.train, seed)?, train_mix].concat(),
        [recorded(&split.validation, seed ^ 0x5EED)?, validation_mix].concat(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use spoofwatch_core::scenario::{DriveSpec, simulate_drive};

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
