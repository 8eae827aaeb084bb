//! The attacks injected into normal training (and validation) data of the experiments: which kinds,
//! how the tracks are cut before injection, and the injected copies. It owns only that training
//! mix, not the scenario generator (core's `scenario`).

use anyhow::{Context, Result};
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{
    AttackDuration, AttackKind, Piece, ScenarioPlan, generate, pieces, with_warmup,
};
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
