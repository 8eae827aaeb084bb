//! The attacks a fleet fit injects into its own attack-free drives: the training mix
//! ([`crate::scenario::training_attack`]) into pieces of its fit and validation drives, and the
//! detection grid, each kind with both levels' deadlines, into pieces of its test drives.
//!
//! An early attack starts 10–60 s into a session (its piece stands alone); a late one meets a warm
//! vehicle (its piece follows the drive's rows before it as warm-up).
//!
//! Owns where the attacks go and the grid. Must not run the detector or score anything.

use serde::{Deserialize, Serialize};

use crate::rng::Rng;
use crate::sample::Track;
use crate::scenario::{
    AttackKind, AttackSpec, InjectedTrack, Piece, ScenarioError, inject, pieces, training_attack,
    with_warmup,
};

/// Length of the pieces drives are cut into (s).
pub const PIECE_S: f64 = 300.0;
/// Warm-up rows before a late attack's piece (s of the drive before it).
pub const WARMUP_S: f64 = 600.0;
/// Onset of a test attack: early, into a fresh session; late, into a warm one (s into the piece).
pub const EARLY_ONSET_S: f64 = 15.0;
pub const LATE_ONSET_S: f64 = 60.0;
/// Length of a test attack (s), within its piece.
pub const TEST_ATTACK_S: f64 = 120.0;
/// Most attacks injected into the test part: a small test part carries every kind of the grid on
/// each of its pieces, a large one a kind per piece (bounds the scoring time of a large fleet's fit).
pub const MAX_TEST_ATTACKS: usize = 800;
/// The drive goes on at least this long after a training attack (s).
const AFTER_ATTACK_S: f64 = 20.0;

/// One kind of the detection grid and its deadlines (s from the attack's first row).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GridKind {
    pub kind: AttackKind,
    pub warning_within_s: f64,
    pub critical_within_s: f64,
}

/// The detection grid of the report: jumps of 20 m and more, frozen fixes and hops within 10 s
/// (hops 15 s) at both levels; ramps of 0.5, 1 and 2 m/s within 60, 30 and 30 s as warnings and
/// 90, 45 and 45 s as critical alarms.
pub fn detection_grid() -> Vec<GridKind> {
    let at_once = |kind, within_s| GridKind {
        kind,
        warning_within_s: within_s,
        critical_within_s: within_s,
    };
    let ramp = |velocity_mps, warning_within_s, critical_within_s| GridKind {
        kind: AttackKind::RampDrift { velocity_mps },
        warning_within_s,
        critical_within_s,
    };
    vec![
        at_once(AttackKind::Jump { offset_m: 20.0 }, 10.0),
        at_once(AttackKind::Jump { offset_m: 50.0 }, 10.0),
        at_once(AttackKind::Jump { offset_m: 500.0 }, 10.0),
        at_once(AttackKind::FrozenPosition, 10.0),
        at_once(
            AttackKind::Hopping {
                offset_m: 200.0,
                hold_s: 5.0,
            },
            15.0,
        ),
        ramp(0.5, 60.0, 90.0),
        ramp(1.0, 30.0, 45.0),
        ramp(2.0, 30.0, 45.0),
    ]
}

/// A test drive with one attack of the grid.
#[derive(Clone, Debug)]
pub struct TestAttack {
    /// The attacked track (warm-up rows first for a late attack).
    pub track: Track,
    /// Index into [`detection_grid`].
    pub grid_index: usize,
    pub early: bool,
    /// Rows of the attack in `track`.
    pub first_row: usize,
    pub last_row: usize,
}

/// Copies of pieces of `drives`, one random attack of the training mix in each (a third early), for
/// training or validation; at most `max_pieces`, spread over the drives.
pub fn training_injections(
    drives: &[Track],
    seed: u64,
    max_pieces: usize,
) -> Result<Vec<Track>, ScenarioError> {
    let all = pieces(drives, PIECE_S, WARMUP_S);
    let step = all.len().div_ceil(max_pieces.max(1)).max(1);
    let mut out = Vec::new();
    for (i, piece) in all.iter().enumerate().step_by(step) {
        let mut rng = Rng::seed_from_u64(seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let early = rng.below(3) == 0;
        let onset_s = if early {
            rng.uniform_range(10.0, 60.0)
        } else {
            rng.uniform_range(30.0, 120.0)
        }
        .round();
        let kind = training_attack(&mut rng, early);
        let longest = piece_seconds(piece) - onset_s - AFTER_ATTACK_S;
        let duration_s = rng.uniform_range(60.0, 180.0).round().min(longest);
        if duration_s < 10.0 {
            continue;
        }
        let attack = AttackSpec {
            kind,
            direction_deg: rng.uniform_range(0.0, 360.0).floor(),
            onset_s,
            duration_s,
            seed: Some(seed),
        };
        let injected = inject(&piece.base, &attack)?;
        out.push(joined(piece, injected, early).0);
    }
    Ok(out)
}

/// The detection grid injected into pieces of `drives`, each piece into `c` copies of itself, where
/// `c` is as many kinds of the grid as [`MAX_TEST_ATTACKS`] leaves room for (at least one, at most
/// the whole grid): attack j (piece ⌊j / c⌋) carries grid kind j mod the grid's size, early on even
/// passes through the grid and late on odd ones, in a random direction. A test part of a few
/// pieces so still tries every kind; with `c` = 1, piece k carries kind k mod the grid's size.
pub fn test_injections(drives: &[Track], seed: u64) -> Result<Vec<TestAttack>, ScenarioError> {
    let grid = detection_grid();
    let pieces = pieces(drives, PIECE_S, WARMUP_S);
    let copies = copies_per_piece(pieces.len(), grid.len());
    let mut out = Vec::new();
    let attacks = pieces
        .iter()
        .flat_map(|piece| std::iter::repeat_n(piece, copies));
    for (i, piece) in attacks.enumerate() {
        let grid_index = i % grid.len();
        let early = (i / grid.len()).is_multiple_of(2) || piece.warmup.is_empty();
        let onset_s = if early { EARLY_ONSET_S } else { LATE_ONSET_S };
        let mut rng = Rng::seed_from_u64(seed ^ (i as u64).wrapping_mul(0xD1B5_4A32_D192_ED03));
        let attack = AttackSpec {
            kind: grid[grid_index].kind,
            direction_deg: rng.uniform_range(0.0, 360.0).floor(),
            onset_s,
            duration_s: TEST_ATTACK_S.min(piece_seconds(piece) - onset_s - 1.0),
            seed: Some(seed),
        };
        let injected = inject(&piece.base, &attack)?;
        let (track, offset) = joined(piece, injected.clone(), early);
        out.push(TestAttack {
            track,
            grid_index,
            early,
            first_row: injected.first_attack_row + offset,
            last_row: injected.last_attack_row + offset,
        });
    }
    Ok(out)
}

/// How many kinds of a grid of `kinds` each of `pieces` test pieces carries.
fn copies_per_piece(pieces: usize, kinds: usize) -> usize {
    (MAX_TEST_ATTACKS / pieces.max(1)).clamp(1, kinds.max(1))
}

fn piece_seconds(piece: &Piece) -> f64 {
    match (piece.base.records.first(), piece.base.records.last()) {
        (Some(first), Some(last)) => last.sample.timestamp_s - first.sample.timestamp_s,
        _ => 0.0,
    }
}

/// The injected piece, after its warm-up rows when the attack is late; and how many rows those are.
fn joined(piece: &Piece, injected: InjectedTrack, early: bool) -> (Track, usize) {
    if early {
        (injected.track, 0)
    } else {
        (
            with_warmup(&piece.warmup, injected.track),
            piece.warmup.len(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::{DriveSpec, simulate_drive};

    fn drive(seconds: f64, seed: u64) -> Track {
        let spec = DriveSpec {
            duration_s: seconds,
            seed,
            ..DriveSpec::default()
        };
        let mut track = simulate_drive(&spec, "car").expect("drive");
        for r in &mut track.records {
            r.label = Some(false);
        }
        track
    }

    #[test]
    fn test_attacks_cover_the_grid_early_and_late_with_their_rows_labelled() {
        // 10 pieces of 300 s at 1 Hz, each carrying every kind of the grid: early on even pieces,
        // late (after warm-up rows) on odd ones.
        let attacks = test_injections(&[drive(3_001.0, 5)], 9).expect("injected");
        let grid = detection_grid().len();
        assert_eq!(attacks.len(), 10 * grid);
        for (i, attack) in attacks.iter().enumerate() {
            assert_eq!(attack.grid_index, i % grid);
            let piece = i / grid;
            assert_eq!(attack.early, piece.is_multiple_of(2), "{i}");
            // Every copy of a piece is the same driving.
            let first = &attacks[piece * grid].track.records;
            assert_eq!(attack.track.records.len(), first.len(), "{i}");
            assert_eq!(
                attack.track.records[0].sample.timestamp_s,
                first[0].sample.timestamp_s
            );
            let rows = &attack.track.records;
            assert!(
                rows[attack.first_row..=attack.last_row]
                    .iter()
                    .all(|r| r.label == Some(true))
            );
            assert!(
                rows[..attack.first_row]
                    .iter()
                    .all(|r| r.label != Some(true))
            );
            let onset = rows[attack.first_row].sample.timestamp_s;
            let start = rows
                .iter()
                .find(|r| !r.warmup)
                .expect("piece")
                .sample
                .timestamp_s;
            let expected = if attack.early {
                EARLY_ONSET_S
            } else {
                LATE_ONSET_S
            };
            assert!(
                (onset - start - expected).abs() <= 1.0,
                "{i}: {}",
                onset - start
            );
        }
        assert!(
            attacks[grid..]
                .iter()
                .any(|a| !a.early && a.track.records[0].warmup)
        );
    }

    #[test]
    fn a_large_test_part_carries_fewer_kinds_per_piece_within_the_bound() {
        assert_eq!(copies_per_piece(0, 8), 8);
        assert_eq!(copies_per_piece(10, 8), 8);
        assert_eq!(copies_per_piece(100, 8), 8);
        assert_eq!(copies_per_piece(101, 8), 7);
        assert_eq!(copies_per_piece(400, 8), 2);
        assert_eq!(copies_per_piece(401, 8), 1);
        assert_eq!(copies_per_piece(5_000, 8), 1, "at least one kind per piece");
        for pieces in [1, 99, 101, 333, 800] {
            assert!(pieces * copies_per_piece(pieces, 8) <= MAX_TEST_ATTACKS.max(pieces));
        }
    }

    #[test]
    fn training_injections_are_bounded_and_attacked() {
        let tracks = [drive(3_001.0, 6)];
        let all = training_injections(&tracks, 3, 100).expect("injected");
        assert_eq!(all.len(), 10);
        assert!(
            all.iter()
                .all(|t| t.records.iter().any(|r| r.label == Some(true)))
        );
        let few = training_injections(&tracks, 3, 4).expect("injected");
        assert_eq!(few.len(), 4, "every third piece of ten");
        assert_eq!(
            all,
            training_injections(&tracks, 3, 100).expect("again"),
            "seeded"
        );
    }
}
