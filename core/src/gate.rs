//! A fixed residual gate, as autopilots check GNSS against odometry (PX4-style): alarm when GNSS and
//! the onboard motion disagree by more than 5 m in one step, or by more than 5 m summed over the
//! last 10 s, and that has held for 1 s. Nothing is fitted: it is the floor every learned detector
//! must beat, at the false-alarm rate it happens to have.
//!
//! Owns the gate and its scoring over tracks. Must not choose operating points or train.

use std::collections::VecDeque;

use serde::{Deserialize, Serialize};

use crate::evaluation::{Scored, trajectory_key};
use crate::evidence::{EvidenceParams, build_track};
use crate::geo::Projection;
use crate::metrics::ScoredRow;
use crate::sample::Track;

/// The gate's limits.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResidualGate {
    /// Largest one-step disagreement (m).
    pub step_m: f64,
    /// Largest disagreement summed over `window_s` (m).
    pub window_m: f64,
    pub window_s: f64,
    /// How long a trip must hold before it alarms (s).
    pub hold_s: f64,
}

impl Default for ResidualGate {
    /// 5 m in one step or 5 m over 10 s, held 1 s.
    fn default() -> Self {
        Self {
            step_m: 5.0,
            window_m: 5.0,
            window_s: 10.0,
            hold_s: 1.0,
        }
    }
}

impl ResidualGate {
    /// Scores every track (a fresh gate per track): the score is the larger of the one-step and the
    /// windowed disagreement, each over its limit (≥ 1 trips); the alarm is a trip held `hold_s`.
    pub fn score_tracks(&self, tracks: &[Track], projection: Projection) -> Scored {
        let params = EvidenceParams::unnormalised(projection);
        let mut scored = Scored::default();
        for (index, track) in tracks.iter().enumerate() {
            let mut window: VecDeque<(f64, [f64; 2])> = VecDeque::new();
            let mut sum = [0.0; 2];
            let mut tripped_since: Option<f64> = None;
            for (record, e) in track
                .records
                .iter()
                .zip(build_track(&params, &track.records))
            {
                let time = record.sample.timestamp_s;
                if e.trajectory_start {
                    window.clear();
                    sum = [0.0; 2];
                    tripped_since = None;
                }
                let mut score = 0.0;
                if e.valid {
                    window.push_back((time, e.residual));
                    sum = [sum[0] + e.residual[0], sum[1] + e.residual[1]];
                    while window
                        .front()
                        .is_some_and(|(t, _)| time - t >= self.window_s)
                    {
                        if let Some((_, old)) = window.pop_front() {
                            sum = [sum[0] - old[0], sum[1] - old[1]];
                        }
                    }
                    let step = e.residual[0].hypot(e.residual[1]) / self.step_m;
                    let windowed = sum[0].hypot(sum[1]) / self.window_m;
                    score = step.max(windowed);
                    if score > 1.0 {
                        tripped_since.get_or_insert(time);
                    } else {
                        tripped_since = None;
                    }
                }
                let alarm = tripped_since.is_some_and(|since| time - since + 1e-6 >= self.hold_s);
                if record.warmup {
                    continue;
                }
                scored.rows.push(ScoredRow {
                    trajectory: trajectory_key(index, e.trajectory),
                    time_s: time,
                    valid: e.valid,
                    label: record.label.unwrap_or(false),
                    score,
                });
                scored.alarms.push(alarm);
            }
        }
        scored
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::{Record, Sample};

    /// A vehicle driving north at 10 m/s at 1 Hz whose fix jumps 8 m east at `jump_row` and stays.
    fn track(jump_row: usize) -> Track {
        let metres_per_degree = crate::geo::EQUIRECTANGULAR_RADIUS_M.to_radians();
        let records = (0..40)
            .map(|i| {
                let east = if i >= jump_row { 8.0 } else { 0.0 };
                Record {
                    sample: Sample::new(
                        i as f64,
                        10.0 * i as f64 / metres_per_degree,
                        east / metres_per_degree,
                        10.0,
                        0.0,
                    ),
                    label: Some(i >= jump_row),
                    comparator_alarm: None,
                    line: i as u64 + 2,
                    trajectory_break: false,
                    warmup: false,
                }
            })
            .collect();
        Track {
            vehicle_id: "v".into(),
            records,
        }
    }

    #[test]
    fn a_held_jump_alarms_one_second_later_and_clears_when_the_window_forgets_it() {
        let scored =
            ResidualGate::default().score_tracks(&[track(10)], Projection::Equirectangular);
        let alarmed: Vec<usize> = (0..40).filter(|&i| scored.alarms[i]).collect();
        // Tripped at row 10 (8 m step, 8 m summed); held 1 s at row 11; the 10 s window still holds
        // the step until row 19 (the step leaves it when 10 s have passed).
        assert_eq!(alarmed, (11..=19).collect::<Vec<_>>());
        assert!((scored.rows[10].score - 1.6).abs() < 1e-6);
    }
}
