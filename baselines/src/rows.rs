//! What every baseline sees: one table of rows (features, label, ν, trajectory, time) built with
//! HO-LLN's own evidence pass, so trajectories, ν and the metrics' rows are exactly HO-LLN's.

use std::ops::Range;

use spoofwatch_core::data::NumericColumns;
use spoofwatch_core::evaluation::trajectory_key;
use spoofwatch_core::evidence::EvidenceFit;
use spoofwatch_core::evidence::{FeatureSchema, build_track};
use spoofwatch_core::metrics::ScoredRow;
use spoofwatch_core::sample::Track;
use spoofwatch_core::train::ClassWeights;

use crate::common::BaselineError;

/// The AV-GPS columns of the GPS-IDS-style row: the vehicle's own dynamics and the receiver's
/// quality figures, as a per-row classifier would read them. Left out on purpose: the label
/// (`Data Type`), the `EKF Detector` column, every time column (`Run Time`, `Hobbs`, `Clock Time`,
/// `Clock Date`) and every absolute-position or route-progress column (latitude, longitude, MGRS,
/// positions, altitudes, distances, mission index, waypoint headings), which would identify the
/// place and time of the recording rather than the attack.
pub const GPS_IDS_COLUMNS: [&str; 19] = [
    "Roll (deg)",
    "Pitch (deg)",
    "Heading (deg)",
    "Yaw (deg)",
    "Yaw Rate (deg/s)",
    "Velocity (m/s)",
    "Steering Angle (deg)",
    "Throttle (%)",
    "GPS HDOP",
    "GPS VDOP",
    "GPS Course",
    "Satellite Locks",
    "Satellite Count",
    "Longitudinal Velocity (m/s)",
    "Lateral Velocity (m/s)",
    "Vertical Velocity (m/s)",
    "Longitudinal Vibration",
    "Lateral Vibration",
    "Vertical Vibration",
];

/// What a baseline reads per row.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Input {
    /// HO-LLN's scaled ξ_t in this schema.
    Evidence(FeatureSchema),
    /// The raw [`GPS_IDS_COLUMNS`] of the recording's file.
    Columns,
}

impl Input {
    /// Short name for reports.
    pub fn name(self) -> String {
        match self {
            Input::Evidence(schema) => format!("ξ {}", schema.name()),
            Input::Columns => "AV-GPS columns".into(),
        }
    }

    /// The evidence schema whose pass gives ν and the trajectories (the paper's for raw columns).
    pub fn schema(self) -> FeatureSchema {
        match self {
            Input::Evidence(schema) => schema,
            Input::Columns => FeatureSchema::Paper,
        }
    }

    /// Features per row.
    pub fn width(self) -> usize {
        match self {
            Input::Evidence(schema) => schema.feature_count(),
            Input::Columns => GPS_IDS_COLUMNS.len(),
        }
    }
}

/// Tracks to score or train on, with the raw columns of the file they were read from (needed by
/// [`Input::Columns`] only).
#[derive(Clone, Copy, Debug)]
pub struct Dataset<'a> {
    pub tracks: &'a [Track],
    pub columns: Option<&'a NumericColumns>,
}

impl<'a> Dataset<'a> {
    /// Tracks without raw columns.
    pub fn tracks(tracks: &'a [Track]) -> Self {
        Self {
            tracks,
            columns: None,
        }
    }
}

/// Rows of some tracks in track order, each trajectory contiguous.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RowTable {
    /// Metrics rows (the score is NaN until a baseline fills it).
    pub rows: Vec<ScoredRow>,
    /// Row-major features, `width` per row.
    pub features: Vec<f32>,
    pub width: usize,
    /// Row ranges of the trajectories.
    pub trajectories: Vec<Range<usize>>,
}

impl RowTable {
    /// Builds the table of `data` for `input`, with `fit`'s evidence parameters (and scaler).
    pub fn build(
        fit: &EvidenceFit,
        input: Input,
        data: Dataset<'_>,
    ) -> Result<Self, BaselineError> {
        let width = input.width();
        let mut table = RowTable {
            width,
            ..RowTable::default()
        };
        for (index, track) in data.tracks.iter().enumerate() {
            let evidence = build_track(&fit.params, &track.records);
            for (e, record) in evidence.iter().zip(&track.records) {
                let row = table.rows.len();
                if e.trajectory_start || row == 0 {
                    table.trajectories.push(row..row + 1);
                } else if let Some(last) = table.trajectories.last_mut() {
                    last.end = row + 1;
                }
                table.rows.push(ScoredRow {
                    trajectory: trajectory_key(index, e.trajectory),
                    time_s: record.sample.timestamp_s,
                    valid: e.valid,
                    label: record.label.unwrap_or(false),
                    score: f64::NAN,
                });
                match input {
                    Input::Evidence(_) => table
                        .features
                        .extend(fit.scaler.transform(e)[..width].iter().map(|&x| x as f32)),
                    Input::Columns => {
                        let columns = data.columns.ok_or(BaselineError::NoColumns)?;
                        let values = columns.at_line(record.line).ok_or_else(|| {
                            BaselineError::MissingRow {
                                vehicle: track.vehicle_id.clone(),
                                line: record.line,
                            }
                        })?;
                        table.features.extend(values.iter().map(|&x| x as f32));
                    }
                }
            }
        }
        Ok(table)
    }

    /// Features of row `i`.
    pub fn row(&self, i: usize) -> &[f32] {
        &self.features[i * self.width..(i + 1) * self.width]
    }

    /// Indices of the ν = 1 rows: the only rows in the loss and the metrics, as for HO-LLN.
    pub fn valid_rows(&self) -> Vec<usize> {
        (0..self.rows.len())
            .filter(|&i| self.rows[i].valid)
            .collect()
    }

    /// HO-LLN's class weights over the ν = 1 rows, clipped as in `TrainConfig`.
    pub fn class_weights(&self, min: f64, max: f64) -> Result<ClassWeights, BaselineError> {
        let spoofed = self.rows.iter().filter(|r| r.valid && r.label).count();
        let normal = self.rows.iter().filter(|r| r.valid && !r.label).count();
        ClassWeights::from_counts(normal, spoofed, min, max).ok_or(BaselineError::OneClass)
    }

    /// Loss weight of every row: α of its label where ν = 1, else 0.
    pub fn loss_weights(&self, weights: ClassWeights) -> Vec<f32> {
        self.rows
            .iter()
            .map(|r| {
                if r.valid {
                    weights.of(r.label) as f32
                } else {
                    0.0
                }
            })
            .collect()
    }
}
