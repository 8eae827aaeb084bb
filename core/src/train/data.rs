//! From labelled tracks to model-ready sequences (SPEC §4, §9): chronological splitting, trajectory
//! boundaries, the evidence fit (Σ̂, μ_e, scaler) and the per-trajectory [`Sequence`]s.
//!
//! Everything here reuses the streaming evidence builder, so training sees exactly what serving
//! computes. Must not train, score or choose anything (that is [`super::detector`]).

use std::ops::Range;

use crate::evidence::{EvidenceBuilder, EvidenceFit, EvidenceParams, Features, build_track};
use crate::geo::Projection;
use crate::sample::{Record, Track};
use crate::train::Sequence;
use crate::train::spec::SplitFractions;

/// Chronological train/validation/test parts of a set of tracks.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ChronologicalSplit {
    pub train: Vec<Track>,
    pub validation: Vec<Track>,
    pub test: Vec<Track>,
}

/// Row ranges of the trajectories the evidence builder finds in `records` (gaps, backward time,
/// source breaks). The statistics do not influence segmentation, so any parameters do.
pub fn trajectory_ranges(records: &[Record]) -> Vec<Range<usize>> {
    let mut builder = EvidenceBuilder::new(segmentation_params());
    let mut ranges: Vec<Range<usize>> = Vec::new();
    for (i, record) in records.iter().enumerate() {
        if builder
            .push(&record.sample, record.trajectory_break)
            .trajectory_start
        {
            ranges.push(i..i + 1);
        } else if let Some(last) = ranges.last_mut() {
            last.end = i + 1;
        }
    }
    ranges
}

/// Parameters for passes that only need trajectory boundaries, ν and residuals.
fn segmentation_params() -> EvidenceParams {
    EvidenceParams::unnormalised(Projection::default())
}

/// Splits every trajectory of every track chronologically into train/validation/test sub-trajectories.
/// Each part becomes its own track (`<vehicle>/t<k>/<part>`), so its first row starts a trajectory.
pub fn split_chronologically(tracks: &[Track], fractions: SplitFractions) -> ChronologicalSplit {
    split_with_warmup(tracks, fractions, 0.0)
}

/// [`split_chronologically`], each validation and test part preceded by the rows of its trajectory
/// in the `warmup_s` seconds before it, marked [`Record::warmup`]: the part is scored as the
/// continuation of its vehicle's stream that it was, with the per-vehicle state (levels, misfit)
/// those rows taught, rather than as a fresh session.
pub fn split_with_warmup(
    tracks: &[Track],
    fractions: SplitFractions,
    warmup_s: f64,
) -> ChronologicalSplit {
    let mut split = ChronologicalSplit::default();
    for track in tracks {
        for (k, range) in trajectory_ranges(&track.records).into_iter().enumerate() {
            let rows = &track.records[range];
            let n = rows.len();
            let n_train = ((n as f64) * fractions.train).round() as usize;
            let n_val = ((n as f64) * fractions.validation).round() as usize;
            let n_train = n_train.min(n);
            let n_val = n_val.min(n - n_train);
            let parts = [
                (&mut split.train, 0..n_train, "train"),
                (&mut split.validation, n_train..n_train + n_val, "val"),
                (&mut split.test, n_train + n_val..n, "test"),
            ];
            for (out, part, name) in parts {
                if part.is_empty() {
                    continue;
                }
                let start_s = rows[part.start].sample.timestamp_s;
                let warmup = rows[..part.start]
                    .iter()
                    .rev()
                    .take_while(|r| start_s - r.sample.timestamp_s < warmup_s)
                    .count();
                let mut records = rows[part.start - warmup..part.end].to_vec();
                for record in &mut records[..warmup] {
                    record.warmup = true;
                }
                records[0].trajectory_break = true;
                out.push(Track {
                    vehicle_id: format!("{}/t{k}/{name}", track.vehicle_id),
                    records,
                });
            }
        }
    }
    split
}

/// Normal rows within this many seconds after an attack's last row leave the loss (unless
/// [`Ablation::no_exit_mask`](crate::model::Ablation)): the spoofer's exit (the fix returning to the
/// truth) is a jump labelled normal, and the evidence of the attack fades over seconds.
pub const EXIT_MASK_S: f64 = 10.0;

/// Model-ready sequences, one per trajectory (unlabelled rows count as normal only if labelled;
/// callers pass labelled data for training). With `mask_exits`, the normal rows within
/// [`EXIT_MASK_S`] after an attacked row are marked invalid, so they enter neither loss nor metrics;
/// so are warm-up rows ([`Record::warmup`]), which only carry the state forward.
pub fn sequences(fit: &EvidenceFit, tracks: &[Track], mask_exits: bool) -> Vec<Sequence> {
    let mut out = Vec::new();
    for track in tracks {
        let evidence = build_track(&fit.params, &track.records);
        let mut current: Option<Sequence> = None;
        let mut last_attack_s = f64::NEG_INFINITY;
        for (e, record) in evidence.iter().zip(&track.records) {
            let time = record.sample.timestamp_s;
            let label = record.label.unwrap_or(false);
            if label {
                last_attack_s = time;
            }
            let exit =
                mask_exits && !label && (0.0..=EXIT_MASK_S).contains(&(time - last_attack_s));
            if e.trajectory_start {
                out.extend(current.take());
            }
            let seq = current.get_or_insert_with(Sequence::default);
            let features: Features = fit.scaler.transform(e);
            seq.features.push(features);
            seq.deltas.push(e.delta_t);
            seq.labels.push(label);
            seq.valid.push(e.valid && !exit && !record.warmup);
        }
        out.extend(current);
    }
    out
}
