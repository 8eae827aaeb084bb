//! What a fleet fit may learn from: the recordings' attack-free drives, checked, and split by time
//! into fit, validation and test parts that never share a drive.
//!
//! A drive is one trajectory of one vehicle (the evidence builder's segmentation: gaps, backward
//! time and source breaks end one), cut further wherever rows are labelled attacked, so that only
//! attack-free driving is used; unlabelled rows count as attack-free, the recordings being the
//! fleet's normal service. A drive longer than [`MAX_DRIVE_S`] is cut into equal consecutive
//! segments, each a drive of its own that starts a session: so a fleet of few, long recordings
//! still splits by time (a later segment of a drive may test what its earlier ones fitted, never
//! the same minutes).
//!
//! Owns the checks (with the field each refusal names) and the split. Must not fit, inject or train.

use std::collections::BTreeSet;

use crate::sample::{Record, Track};
use crate::train::data::trajectory_ranges;

/// Least attack-free driving a fit accepts (h): below it the validation part cannot hold the
/// warning budget of one false alarm per vehicle-hour.
pub const MIN_DRIVING_HOURS: f64 = 1.0;
/// Least vehicles: a prior fitted on one vehicle describes that vehicle, not a fleet.
pub const MIN_VEHICLES: usize = 2;
/// A row is moving when the onboard speed is at least this (m/s).
pub const MOVING_MPS: f64 = 0.5;
/// Drives shorter than this (s) are left out: too short for the calibration or the anchors.
pub const MIN_DRIVE_S: f64 = 60.0;
/// Drives longer than this (s) are cut into equal segments no longer than it.
pub const MAX_DRIVE_S: f64 = 1_200.0;
/// Shares of the attack-free time given to the fit and validation parts; the rest is the test.
pub const FIT_SHARE: f64 = 0.6;
pub const VALIDATION_SHARE: f64 = 0.2;
/// Rates closer than this share are the same nominal rate.
const RATE_TOLERANCE: f64 = 0.1;

/// Why recordings cannot support a fleet fit; each names the request field at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitDataError {
    #[error("no rows where the vehicle moves (onboard speed ≥ {MOVING_MPS} m/s)")]
    NoMovingRows,
    #[error(
        "{hours:.2} h of attack-free driving; a fleet fit needs at least \
         {MIN_DRIVING_HOURS} h"
    )]
    TooLittleDriving { hours: f64 },
    #[error(
        "the recordings hold {found} vehicle ({vehicles}); a fleet fit needs at least \
         {MIN_VEHICLES}, so that its priors describe a fleet and not one vehicle"
    )]
    TooFewVehicles { found: usize, vehicles: String },
    #[error("{claimed} Hz was claimed, but the drives are sampled at {found} Hz")]
    RateMismatch { claimed: f64, found: String },
    #[error(
        "{drives} attack-free drive(s) of at least {MIN_DRIVE_S} s; the fit, validation \
         and test parts need one each, never sharing a drive"
    )]
    TooFewDrives { drives: usize },
    #[error("{0}")]
    Validation(String),
}

impl FitDataError {
    /// The request field at fault.
    pub fn field(&self) -> &'static str {
        match self {
            Self::RateMismatch { .. } => "fleet_fit.sample_rate_hz",
            Self::Validation(_) => "validation_datasets",
            _ => "datasets",
        }
    }
}

/// One attack-free drive.
#[derive(Clone, Debug, PartialEq)]
pub struct Drive {
    pub vehicle_id: String,
    /// Its rows, the first starting a trajectory, every one labelled attack-free.
    pub track: Track,
    pub start_s: f64,
    pub duration_s: f64,
    /// Its nominal sample rate (Hz): 1 / the median step, rounded to 0.1 Hz.
    pub rate_hz: f64,
}

impl Drive {
    pub fn hours(&self) -> f64 {
        self.duration_s / 3_600.0
    }
}

/// The fleet's drives, split.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FleetSplit {
    pub fit: Vec<Drive>,
    pub validation: Vec<Drive>,
    pub test: Vec<Drive>,
}

/// Every attack-free drive of `tracks` lasting at least [`MIN_DRIVE_S`], in the order found.
pub fn drives(tracks: &[Track]) -> Vec<Drive> {
    let mut out = Vec::new();
    for track in tracks {
        for range in trajectory_ranges(&track.records) {
            let rows = &track.records[range];
            for run in rows.split(|r| r.label == Some(true)) {
                for segment in segments(run) {
                    if let Some(drive) = drive(&track.vehicle_id, segment, out.len()) {
                        out.push(drive);
                    }
                }
            }
        }
    }
    out
}

/// `rows` cut into ⌈duration / [`MAX_DRIVE_S`]⌉ consecutive segments of equal duration.
fn segments(rows: &[Record]) -> Vec<&[Record]> {
    let (Some(first), Some(last)) = (rows.first(), rows.last()) else {
        return Vec::new();
    };
    let t0 = first.sample.timestamp_s;
    let duration = last.sample.timestamp_s - t0;
    let count = (duration / MAX_DRIVE_S).ceil().max(1.0);
    let length = duration / count;
    let mut out = Vec::new();
    let mut start = 0;
    for k in 1..count as usize {
        let cut = t0 + length * k as f64;
        let end = start + rows[start..].partition_point(|r| r.sample.timestamp_s < cut);
        out.push(&rows[start..end]);
        start = end;
    }
    out.push(&rows[start..]);
    out
}

fn drive(vehicle_id: &str, rows: &[Record], index: usize) -> Option<Drive> {
    let (first, last) = (rows.first()?, rows.last()?);
    let duration_s = last.sample.timestamp_s - first.sample.timestamp_s;
    if duration_s.is_nan() || duration_s < MIN_DRIVE_S {
        return None;
    }
    let mut steps: Vec<f64> = rows
        .windows(2)
        .map(|w| w[1].sample.timestamp_s - w[0].sample.timestamp_s)
        .filter(|d| d.is_finite() && *d > 0.0)
        .collect();
    steps.sort_unstable_by(f64::total_cmp);
    let median_step = *steps.get(steps.len() / 2)?;
    let mut records = rows.to_vec();
    for record in &mut records {
        record.label = Some(false);
        record.trajectory_break = false;
        record.warmup = false;
    }
    records[0].trajectory_break = true;
    Some(Drive {
        vehicle_id: vehicle_id.to_string(),
        track: Track {
            vehicle_id: format!("{vehicle_id}/drive{index}"),
            records,
        },
        start_s: first.sample.timestamp_s,
        duration_s,
        rate_hz: (10.0 / median_step).round() / 10.0,
    })
}

/// The nominal rates of `drives`, each once (drives within [`RATE_TOLERANCE`] of a rate share it).
pub fn rates(drives: &[Drive]) -> Vec<f64> {
    let mut found: Vec<f64> = Vec::new();
    for drive in drives {
        if !found
            .iter()
            .any(|r| (drive.rate_hz - r).abs() <= RATE_TOLERANCE * r)
        {
            found.push(drive.rate_hz);
        }
    }
    found.sort_unstable_by(f64::total_cmp);
    found
}

/// Refuses recordings that cannot support a fit: no moving rows, less than
/// [`MIN_DRIVING_HOURS`] of attack-free driving, fewer than [`MIN_VEHICLES`] vehicles, or a claimed
/// sample rate the drives do not have.
pub fn check(
    tracks: &[Track],
    drives: &[Drive],
    claimed_rate_hz: Option<f64>,
) -> Result<(), FitDataError> {
    let moving = tracks
        .iter()
        .flat_map(|t| &t.records)
        .any(|r| r.label != Some(true) && r.sample.speed_mps.abs() >= MOVING_MPS);
    if !moving {
        return Err(FitDataError::NoMovingRows);
    }
    let hours: f64 = drives.iter().map(Drive::hours).sum();
    if hours < MIN_DRIVING_HOURS {
        return Err(FitDataError::TooLittleDriving { hours });
    }
    let vehicles: BTreeSet<&str> = drives.iter().map(|d| d.vehicle_id.as_str()).collect();
    if vehicles.len() < MIN_VEHICLES {
        return Err(FitDataError::TooFewVehicles {
            found: vehicles.len(),
            vehicles: vehicles.into_iter().collect::<Vec<_>>().join(", "),
        });
    }
    if let Some(claimed) = claimed_rate_hz {
        let found = rates(drives);
        if found
            .iter()
            .any(|r| (r - claimed).abs() > RATE_TOLERANCE * claimed)
        {
            return Err(FitDataError::RateMismatch {
                claimed,
                found: found
                    .iter()
                    .map(|r| format!("{r}"))
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        }
    }
    Ok(())
}

/// Splits `drives` by time: in order of start (then vehicle), a drive whose midpoint falls in the
/// first [`FIT_SHARE`] of the fleet's attack-free time is a fit drive, in the next
/// [`VALIDATION_SHARE`] a validation drive, else a test drive. With `validation` given, those are
/// the validation part and the recordings are split into fit and test alone, in the same
/// proportion. Every part must hold a drive.
pub fn split(mut drives: Vec<Drive>, validation: Vec<Drive>) -> Result<FleetSplit, FitDataError> {
    drives.sort_by(|a, b| {
        a.start_s
            .total_cmp(&b.start_s)
            .then_with(|| a.vehicle_id.cmp(&b.vehicle_id))
    });
    let count = drives.len();
    let total: f64 = drives.iter().map(|d| d.duration_s).sum();
    let explicit = !validation.is_empty();
    let fit_share = if explicit {
        FIT_SHARE / (1.0 - VALIDATION_SHARE)
    } else {
        FIT_SHARE
    };
    let mut parts = FleetSplit {
        validation,
        ..FleetSplit::default()
    };
    let mut elapsed = 0.0;
    for drive in drives {
        let midpoint = (elapsed + 0.5 * drive.duration_s) / total;
        elapsed += drive.duration_s;
        if midpoint < fit_share {
            parts.fit.push(drive);
        } else if !explicit && midpoint < FIT_SHARE + VALIDATION_SHARE {
            parts.validation.push(drive);
        } else {
            parts.test.push(drive);
        }
    }
    if parts.fit.is_empty() || parts.validation.is_empty() || parts.test.is_empty() {
        return Err(FitDataError::TooFewDrives { drives: count });
    }
    Ok(parts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::{DriveSpec, simulate_drive};

    fn drive_of(vehicle: &str, start_s: f64, seconds: f64, rate_hz: f64, seed: u64) -> Track {
        let spec = DriveSpec {
            duration_s: seconds,
            rate_hz,
            seed,
            ..DriveSpec::default()
        };
        let mut track = simulate_drive(&spec, vehicle).expect("valid drive");
        for record in &mut track.records {
            record.sample.timestamp_s += start_s;
            record.label = None;
        }
        track
    }

    #[test]
    fn drives_are_cut_at_attacked_rows_and_labelled_attack_free() {
        let mut track = drive_of("car-1", 0.0, 600.0, 1.0, 3);
        for record in &mut track.records[200..230] {
            record.label = Some(true);
        }
        let found = drives(&[track]);
        assert_eq!(found.len(), 2, "before and after the attack");
        assert_eq!(found[0].track.records.len(), 200);
        assert_eq!(found[1].track.records.len(), 601 - 230);
        for drive in &found {
            assert!(drive.track.records[0].trajectory_break);
            assert!(drive.track.records.iter().all(|r| r.label == Some(false)));
            assert_eq!(drive.rate_hz, 1.0);
        }
    }

    #[test]
    fn a_long_drive_is_cut_into_equal_segments_that_start_sessions() {
        let found = drives(&[drive_of("car-1", 0.0, 3_000.0, 1.0, 4)]);
        // 3000 s: three segments of 1000 s (rows 0..1000, 1000..2000, 2000..=3000).
        let lengths: Vec<usize> = found.iter().map(|d| d.track.records.len()).collect();
        assert_eq!(lengths, [1000, 1000, 1001]);
        assert_eq!(found[1].start_s, 1000.0);
        assert!(found.iter().all(|d| d.track.records[0].trajectory_break));
        assert!(found.iter().all(|d| d.vehicle_id == "car-1"));
    }

    #[test]
    fn the_checks_name_what_the_recordings_lack() {
        let one = vec![drive_of("car-1", 0.0, 4_000.0, 1.0, 1)];
        assert!(matches!(
            check(&one, &drives(&one), None),
            Err(FitDataError::TooFewVehicles { found: 1, .. })
        ));
        let short = vec![
            drive_of("car-1", 0.0, 900.0, 1.0, 1),
            drive_of("car-2", 0.0, 900.0, 1.0, 2),
        ];
        assert!(matches!(
            check(&short, &drives(&short), None),
            Err(FitDataError::TooLittleDriving { .. })
        ));
        let mixed = vec![
            drive_of("car-1", 0.0, 2_000.0, 1.0, 1),
            drive_of("car-2", 0.0, 2_000.0, 5.0, 2),
        ];
        let error = check(&mixed, &drives(&mixed), Some(1.0)).expect_err("5 Hz found");
        assert_eq!(error.field(), "fleet_fit.sample_rate_hz");
        assert!(error.to_string().contains("1, 5"), "{error}");
        assert_eq!(check(&mixed, &drives(&mixed), None), Ok(()));
        let mut still = mixed.clone();
        for record in still.iter_mut().flat_map(|t| &mut t.records) {
            record.sample.speed_mps = 0.0;
        }
        assert_eq!(
            check(&still, &drives(&still), None),
            Err(FitDataError::NoMovingRows)
        );
    }

    #[test]
    fn the_split_follows_time_and_never_shares_a_drive() {
        let tracks: Vec<Track> = (0..10)
            .map(|i| drive_of(&format!("car-{}", i % 3), 1_000.0 * i as f64, 600.0, 1.0, i))
            .collect();
        let parts = split(drives(&tracks), Vec::new()).expect("ten drives");
        assert_eq!(
            (parts.fit.len(), parts.validation.len(), parts.test.len()),
            (6, 2, 2)
        );
        let last_fit = parts.fit.iter().map(|d| d.start_s).fold(0.0, f64::max);
        assert!(parts.validation.iter().all(|d| d.start_s > last_fit));
        let last_validation = parts
            .validation
            .iter()
            .map(|d| d.start_s)
            .fold(0.0, f64::max);
        assert!(parts.test.iter().all(|d| d.start_s > last_validation));

        let given = drives(&[drive_of("car-9", 0.0, 600.0, 1.0, 99)]);
        let parts = split(drives(&tracks), given).expect("explicit validation");
        assert_eq!(parts.validation.len(), 1);
        assert_eq!(parts.fit.len() + parts.test.len(), 10);
        assert_eq!(
            parts.fit.len(),
            7,
            "three quarters of the time, by midpoint"
        );

        assert_eq!(
            split(drives(&tracks[..2]), Vec::new()),
            Err(FitDataError::TooFewDrives { drives: 2 })
        );
    }
}
