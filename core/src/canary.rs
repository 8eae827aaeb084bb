//! The canary drive: a fixed synthetic drive that every model artifact must get through with only
//! finite probabilities in [0, 1] before it is accepted (`docs/detector.md` §5.1). The range checks on
//! an artifact's values are meant to make a bad output impossible; the canary runs the real streaming
//! [`Detector`] to prove it for the artifact at hand, so a value the checks missed is refused at import
//! instead of blinding detection later.
//!
//! Owns the canary drive, the check, and the artifact's public ways in and out
//! ([`ModelArtifact::from_slice`], [`ModelArtifact::read`], [`ModelArtifact::write`],
//! [`ModelArtifact::to_vec`], [`ModelArtifact::validate`]): each runs the field checks of
//! [`crate::model::artifact`] and then the canary, so no path into or out of the registry skips it.
//! They live here because the canary needs the detector, which needs the artifact. Must not parse
//! artifacts nor choose what they may hold (that is [`crate::model::artifact`]).

use std::io::{Read, Write};
use std::sync::Arc;

use crate::detector::Detector;
use crate::geo::displace_fix;
use crate::model::artifact::{ArtifactError, ModelArtifact};
use crate::sample::{Sample, readable};

/// Samples in the canary drive (1 Hz): the attack starts after the drift calibration's 240 s warm-up
/// (which waits while an offset anchor is frozen), so every drift channel is switched on, and it is
/// still only a few milliseconds of model steps.
pub const CANARY_SAMPLES: usize = 360;

/// Where the canary drive starts (degrees).
const START: (f64, f64) = (48.137, 11.575);
/// Onboard speed (m/s) and heading (degrees clockwise from north).
const SPEED_MPS: f64 = 12.0;
const HEADING_DEG: f64 = 60.0;
/// The spoofer's cross-track drag from this sample on (m/s), then a jump and a frozen fix.
const DRIFT_START: usize = 250;
const DRIFT_MPS: f64 = 1.5;
const JUMP_AT: usize = 320;
const JUMP_M: f64 = 300.0;
const FROZEN: std::ops::Range<usize> = 335..342;
/// A 3 s gap in the timestamps after this sample (a dropped second of data).
const GAP_AFTER: usize = 345;

/// The canary drive: a straight line at constant speed with a small deterministic wobble on the fix,
/// then a slow cross-track drift, a jump, a frozen fix and a gap, so that every evidence channel moves.
pub fn canary_drive() -> Vec<Sample> {
    let heading = HEADING_DEG.to_radians();
    let (along_e, along_n) = (heading.sin(), heading.cos());
    let mut samples: Vec<Sample> = Vec::with_capacity(CANARY_SAMPLES);
    for k in 0..CANARY_SAMPLES {
        let t = k as f64 + if k > GAP_AFTER { 3.0 } else { 0.0 };
        let travelled = SPEED_MPS * t;
        let wobble = [0.6 * (0.9 * t).sin(), 0.4 * (1.3 * t).cos()];
        let drag = DRIFT_MPS * (k.saturating_sub(DRIFT_START) as f64);
        let jump = if k >= JUMP_AT { JUMP_M } else { 0.0 };
        // The drag and the jump are across the track (to the right of the heading).
        let cross = drag + jump;
        let east = travelled * along_e + wobble[0] + cross * along_n;
        let north = travelled * along_n + wobble[1] - cross * along_e;
        let (latitude, longitude) = displace_fix(START.0, START.1, east, north);
        let mut sample = Sample::new(t, latitude, longitude, SPEED_MPS, HEADING_DEG);
        if FROZEN.contains(&k)
            && let Some(previous) = samples.last()
        {
            sample.latitude_deg = previous.latitude_deg;
            sample.longitude_deg = previous.longitude_deg;
        }
        samples.push(sample);
    }
    samples
}

/// The first canary sample whose probability is not a number in [0, 1].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CanaryFailure {
    /// Index into [`canary_drive`].
    pub sample: usize,
    /// The probability the detector produced there.
    pub probability: f64,
}

/// Runs a fresh streaming detector with `artifact` over the canary drive.
pub fn check(artifact: Arc<ModelArtifact>) -> Result<(), CanaryFailure> {
    let mut detector = Detector::new(artifact);
    for (sample, record) in canary_drive().iter().enumerate() {
        let probability = detector.step(record, false).probability;
        if !(0.0..=1.0).contains(&probability) {
            return Err(CanaryFailure {
                sample,
                probability,
            });
        }
    }
    Ok(())
}

impl ModelArtifact {
    /// Reads and validates an artifact (see [`ModelArtifact::from_slice`]).
    pub fn read<R: Read>(mut reader: R) -> Result<Self, ArtifactError> {
        let mut bytes = Vec::new();
        reader.read_to_end(&mut bytes)?;
        Self::from_slice(&bytes)
    }

    /// Parses and validates an artifact: JSON syntax, then the schema version (before anything else,
    /// so a newer artifact gets a clear message instead of a field-level parse error), then every
    /// field's type, then every value's range ([`ModelArtifact::validate`], canary drive included).
    pub fn from_slice(bytes: &[u8]) -> Result<Self, ArtifactError> {
        let artifact = Self::parse(bytes)?;
        artifact.validate()?;
        Ok(artifact)
    }

    /// Writes the artifact as pretty JSON (after [`ModelArtifact::validate`]: what is written reads).
    pub fn write<W: Write>(&self, writer: W) -> Result<(), ArtifactError> {
        self.validate()?;
        self.write_json(writer)
    }

    /// The artifact as JSON bytes.
    pub fn to_vec(&self) -> Result<Vec<u8>, ArtifactError> {
        let mut out = Vec::new();
        self.write(&mut out)?;
        Ok(out)
    }

    /// Checks every value is in its documented range (`docs/detector.md` §5.1) and the parts fit
    /// together, then runs the canary drive, which must yield only finite probabilities in [0, 1].
    /// A few milliseconds, so it runs on every read and write: no path into the registry skips it.
    pub fn validate(&self) -> Result<(), ArtifactError> {
        self.check_fields()?;
        check(Arc::new(self.clone())).map_err(|failure| {
            ArtifactError::field_error(
                "model",
                format!(
                    "the canary drive yields probability {} at sample {}; every probability must \
                     be finite and in [0, 1]",
                    readable(failure.probability),
                    failure.sample
                ),
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bundled() -> ModelArtifact {
        ModelArtifact::from_slice(include_bytes!("../../models/default.json"))
            .expect("the bundled model loads")
    }

    #[test]
    fn the_drive_is_fixed_and_moves_every_evidence_channel() {
        let drive = canary_drive();
        assert_eq!(drive.len(), CANARY_SAMPLES);
        assert_eq!(drive, canary_drive());
        assert!(drive.iter().all(|s| s.violations().is_empty()));
        let artifact = Arc::new(bundled());
        let mut detector = Detector::new(Arc::clone(&artifact));
        let features: Vec<_> = drive
            .iter()
            .map(|s| detector.step(s, false).features)
            .collect();
        for channel in 0..artifact.schema().feature_count() {
            let first = features[0][channel];
            assert!(
                features.iter().any(|f| f[channel] != first),
                "channel {channel} never moves"
            );
        }
    }

    #[test]
    fn a_model_that_yields_nan_fails_at_the_first_sample() {
        let mut artifact = bundled();
        artifact.model.params_mut().tensors_mut()[0].1.data_mut()[0] = f64::NAN;
        let failure = check(Arc::new(artifact)).expect_err("NaN weights");
        assert_eq!(failure.sample, 0);
        assert!(failure.probability.is_nan());
        assert_eq!(check(Arc::new(bundled())), Ok(()));
    }
}
