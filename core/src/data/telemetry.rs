//! The plain telemetry CSV: `vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg[,label]`,
//! with optional uncertainty columns and the receiver's status (`spoofing_state`, `jamming_state`,
//! `satellites_used`, `hdop`).
//!
//! The receiver states are read by name (`unknown`, `none`, `indicated`, `multiple`; `unknown`,
//! `ok`, `warning`, `critical`; any case) or by their u-blox/PX4 number (0–3, the same for both
//! sources); an empty cell is `unknown`. The writer writes names.
//!
//! Owns the telemetry CSV column mapping. Must not validate samples beyond parsing.

use std::io::{Read, Write};

use super::{DataError, Table, parse_flag, parse_measurement};
use crate::sample::{JammingState, ReceiverState, Record, Sample, SpoofingState, Track};

/// Required columns, in the order the writer emits them.
pub const REQUIRED_COLUMNS: [&str; 6] = [
    "vehicle_id",
    "timestamp",
    "latitude",
    "longitude",
    "speed_mps",
    "heading_deg",
];

/// Optional columns the reader recognises (others are ignored).
pub const OPTIONAL_COLUMNS: [&str; 4] = [
    "label",
    "position_std_m",
    "speed_std_mps",
    "heading_std_deg",
];

/// Optional columns of the receiver's status, in the order the writer emits them.
pub const RECEIVER_COLUMNS: [&str; 4] =
    ["spoofing_state", "jamming_state", "satellites_used", "hdop"];

/// Column indices of the fields we read.
struct Columns {
    vehicle_id: usize,
    measurements: [usize; 5],
    label: Option<usize>,
    stds: [Option<usize>; 3],
    receiver: [Option<usize>; 4],
}

/// A receiver state by name or u-blox/PX4 number; empty is `unknown`.
fn parse_state<S: ReceiverState>(text: &str) -> Result<S, String> {
    let text = text.trim();
    if text.is_empty() {
        return Ok(S::default());
    }
    let known = || {
        let names: Vec<&str> = S::NAMED.iter().map(|(_, name)| *name).collect();
        names.join(", ")
    };
    match text.parse::<i64>() {
        Ok(number) => S::from_code(number)
            .ok_or_else(|| format!("expected a state number 0 to 3, got {number}")),
        Err(_) => S::from_name(text)
            .ok_or_else(|| format!("expected {}, 0 to 3 or empty, got \"{text}\"", known())),
    }
}

/// A satellite count: a whole non-negative number, or empty.
fn parse_count(text: &str) -> Result<Option<u32>, String> {
    let text = text.trim();
    if text.is_empty() {
        return Ok(None);
    }
    text.parse::<u32>()
        .map(Some)
        .map_err(|_| format!("expected a whole number of satellites or empty, got \"{text}\""))
}

/// Reads the rows of a telemetry CSV, handing each record and its vehicle id to `on_record` in row
/// order. Empty or `nan` numeric fields become NaN (the sample is then invalid, ν = 0); empty
/// uncertainty fields are absent.
pub(super) fn read_records<R: Read>(
    csv: &mut csv::Reader<R>,
    table: &Table<'_>,
    on_record: &mut dyn FnMut(&str, Record),
) -> Result<(), DataError> {
    let find = |name: &str| {
        table.column(name).ok_or_else(|| DataError::UnknownFormat {
            file: table.source.to_string(),
            detail: format!("missing column \"{name}\""),
        })
    };
    let columns = Columns {
        vehicle_id: find("vehicle_id")?,
        measurements: [
            find("timestamp")?,
            find("latitude")?,
            find("longitude")?,
            find("speed_mps")?,
            find("heading_deg")?,
        ],
        label: table.column("label"),
        stds: [
            table.column("position_std_m"),
            table.column("speed_std_mps"),
            table.column("heading_std_deg"),
        ],
        receiver: RECEIVER_COLUMNS.map(|name| table.column(name)),
    };
    let mut row = csv::StringRecord::new();
    while let Some(line) = table.next_row(csv, &mut row)? {
        let field = |index: usize| row.get(index).unwrap_or("");
        let err = |index: usize, problem: String| table.field_error(line, index, problem);

        let vehicle_id = field(columns.vehicle_id).trim();
        if vehicle_id.is_empty() {
            return Err(err(columns.vehicle_id, "empty vehicle id".into()));
        }
        let mut values = [0.0; 5];
        for (value, &index) in values.iter_mut().zip(&columns.measurements) {
            *value = parse_measurement(field(index)).map_err(|p| err(index, p))?;
        }
        let [timestamp, latitude, longitude, speed, heading] = values;
        let mut sample = Sample::new(timestamp, latitude, longitude, speed, heading);
        let mut stds = [None; 3];
        for (std, index) in stds.iter_mut().zip(columns.stds) {
            if let Some(index) = index {
                let value = parse_measurement(field(index)).map_err(|p| err(index, p))?;
                *std = (!value.is_nan()).then_some(value);
            }
        }
        [
            sample.position_std_m,
            sample.speed_std_mps,
            sample.heading_std_deg,
        ] = stds;
        let [spoofing, jamming, satellites, hdop] = columns.receiver;
        if let Some(index) = spoofing {
            sample.spoofing_state =
                parse_state::<SpoofingState>(field(index)).map_err(|p| err(index, p))?;
        }
        if let Some(index) = jamming {
            sample.jamming_state =
                parse_state::<JammingState>(field(index)).map_err(|p| err(index, p))?;
        }
        if let Some(index) = satellites {
            sample.satellites_used = parse_count(field(index)).map_err(|p| err(index, p))?;
        }
        if let Some(index) = hdop {
            let value = parse_measurement(field(index)).map_err(|p| err(index, p))?;
            sample.hdop = (!value.is_nan()).then_some(value);
        }
        let label = match columns.label {
            Some(index) => parse_flag(field(index)).map_err(|p| err(index, p))?,
            None => None,
        };

        on_record(
            vehicle_id,
            Record {
                sample,
                label,
                comparator_alarm: None,
                line,
                trajectory_break: false,
                warmup: false,
            },
        );
    }
    Ok(())
}

/// Writes tracks in the telemetry format, with a `label` column when any record is labelled, the
/// three uncertainty columns when any sample carries one, and the four receiver columns when any
/// sample carries a receiver status (an absent value, or an unknown state, is an empty cell).
/// Vehicles are written one after another; floats use Rust's shortest round-trip form.
pub fn write_tracks<W: Write>(writer: W, tracks: &[Track]) -> csv::Result<()> {
    let records = || tracks.iter().flat_map(|t| &t.records);
    let labelled = records().any(|r| r.label.is_some());
    let uncertain = records().any(|r| uncertainties(&r.sample).iter().any(Option::is_some));
    let receiver = records().any(|r| r.sample.has_receiver_status());
    let mut out = csv::Writer::from_writer(writer);
    let mut header: Vec<&str> = REQUIRED_COLUMNS.to_vec();
    if labelled {
        header.push("label");
    }
    if uncertain {
        header.extend(&OPTIONAL_COLUMNS[1..]);
    }
    if receiver {
        header.extend(&RECEIVER_COLUMNS);
    }
    out.write_record(&header)?;
    for track in tracks {
        for record in &track.records {
            let s = &record.sample;
            let mut row = vec![
                track.vehicle_id.clone(),
                s.timestamp_s.to_string(),
                s.latitude_deg.to_string(),
                s.longitude_deg.to_string(),
                s.speed_mps.to_string(),
                s.heading_deg.to_string(),
            ];
            if labelled {
                row.push(match record.label {
                    Some(true) => "1".into(),
                    Some(false) => "0".into(),
                    None => String::new(),
                });
            }
            if uncertain {
                row.extend(
                    uncertainties(s).map(|std| std.map_or_else(String::new, |v| v.to_string())),
                );
            }
            if receiver {
                row.extend(receiver_cells(s));
            }
            out.write_record(&row)?;
        }
    }
    out.flush()?;
    Ok(())
}

/// A sample's optional uncertainties in the order of [`OPTIONAL_COLUMNS`]`[1..]`.
fn uncertainties(sample: &Sample) -> [Option<f64>; 3] {
    [
        sample.position_std_m,
        sample.speed_std_mps,
        sample.heading_std_deg,
    ]
}

/// A sample's receiver status in the order of [`RECEIVER_COLUMNS`].
fn receiver_cells(sample: &Sample) -> [String; 4] {
    let state = |name: &str, unknown: bool| {
        if unknown {
            String::new()
        } else {
            name.to_string()
        }
    };
    [
        state(
            sample.spoofing_state.name(),
            sample.spoofing_state == SpoofingState::Unknown,
        ),
        state(
            sample.jamming_state.name(),
            sample.jamming_state == JammingState::Unknown,
        ),
        sample
            .satellites_used
            .map_or_else(String::new, |n| n.to_string()),
        sample.hdop.map_or_else(String::new, |v| v.to_string()),
    ]
}
