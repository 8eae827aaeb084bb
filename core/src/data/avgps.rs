//! AV-GPS dataset files (their columns and time formats: `docs/getting-started.md`, "Data formats"):
//! one vehicle per file, time from the clock
//! with a Run Time fallback, trajectory breaks by the reference's boundary rule.
//!
//! Owns the AV-GPS column mapping. Must not validate samples beyond parsing (that is `sample.rs`).

use std::io::Read;

use super::timefmt::{parse_clock_time, parse_date, parse_duration};
use super::{DataError, Table, parse_flag, parse_measurement};
use crate::evidence::{MAX_BACKWARD_S, MAX_GAP_S};
use crate::sample::{Record, Sample};

/// Columns whose presence identifies an AV-GPS file.
pub const REQUIRED_COLUMNS: [&str; 5] = [
    "GPS Latitude",
    "GPS Longitude",
    "Velocity (m/s)",
    "Heading (deg)",
    "Run Time",
];

const SECONDS_PER_DAY: f64 = 86_400.0;

/// Column indices of the fields we read. The heading is `Heading (deg)`, never `Yaw (deg)`
/// (Yaw = Heading − 180° in these files).
struct Columns {
    latitude: usize,
    longitude: usize,
    speed: usize,
    heading: usize,
    run_time: usize,
    hobbs: Option<usize>,
    clock_time: Option<usize>,
    clock_date: Option<usize>,
    label: Option<usize>,
    comparator: Option<usize>,
}

impl Columns {
    /// `None` when a required column is absent (the caller checked already).
    fn find(table: &Table<'_>) -> Option<Self> {
        Some(Self {
            latitude: table.column("GPS Latitude")?,
            longitude: table.column("GPS Longitude")?,
            speed: table.column("Velocity (m/s)")?,
            heading: table.column("Heading (deg)")?,
            run_time: table.column("Run Time")?,
            hobbs: table.column("Hobbs"),
            clock_time: table.column("Clock Time"),
            clock_date: table.column("Clock Date"),
            label: table.column("Data Type"),
            comparator: table.column("EKF Detector"),
        })
    }
}

/// The time fields of one row (seconds; `None` when empty).
#[derive(Clone, Copy, Debug)]
struct RowTimes {
    run_time: Option<f64>,
    hobbs: Option<f64>,
    /// Clock Date + Clock Time, only when both are present.
    clock: Option<f64>,
    date: Option<i64>,
}

/// Reads the records of an AV-GPS file (its single vehicle's), handing each to `on_record` in
/// file order.
pub(super) fn read_records<R: Read>(
    csv: &mut csv::Reader<R>,
    table: &Table<'_>,
    on_record: &mut dyn FnMut(Record),
) -> Result<(), DataError> {
    let columns = Columns::find(table).ok_or_else(|| DataError::UnknownFormat {
        file: table.source.to_string(),
        detail: "not an AV-GPS header".into(),
    })?;
    let mut row = csv::StringRecord::new();
    let mut previous: Option<RowTimes> = None;
    let mut timestamp = 0.0;
    while let Some(line) = table.next_row(csv, &mut row)? {
        let field = |index: usize| row.get(index).unwrap_or("");
        let optional = |index: Option<usize>| index.map_or("", field);
        let err = |index: usize, problem: String| table.field_error(line, index, problem);
        let err_opt = |index: Option<usize>, problem: String| err(index.unwrap_or(0), problem);

        let measurement = |index: usize| parse_measurement(field(index)).map_err(|p| err(index, p));
        let sample_fields = [
            measurement(columns.latitude)?,
            measurement(columns.longitude)?,
            measurement(columns.speed)?,
            measurement(columns.heading)?,
        ];
        let times = RowTimes {
            run_time: parse_duration(field(columns.run_time))
                .map_err(|p| err(columns.run_time, p))?,
            hobbs: parse_duration(optional(columns.hobbs))
                .map_err(|p| err_opt(columns.hobbs, p))?,
            clock: None,
            date: parse_date(optional(columns.clock_date))
                .map_err(|p| err_opt(columns.clock_date, p))?,
        };
        let time_of_day = parse_clock_time(optional(columns.clock_time))
            .map_err(|p| err_opt(columns.clock_time, p))?;
        let times = RowTimes {
            clock: times
                .date
                .zip(time_of_day)
                .map(|(day, seconds)| day as f64 * SECONDS_PER_DAY + seconds),
            ..times
        };
        let label = parse_flag(optional(columns.label)).map_err(|p| err_opt(columns.label, p))?;
        let comparator_alarm =
            parse_flag(optional(columns.comparator)).map_err(|p| err_opt(columns.comparator, p))?;

        let (trajectory_break, delta_t) = boundary_and_delta(previous.as_ref(), &times);
        // The reference's cumulative time: an undefined δ adds nothing.
        if delta_t.is_finite() {
            timestamp += delta_t;
        }
        let [latitude, longitude, speed, heading] = sample_fields;
        on_record(Record {
            sample: Sample::new(timestamp, latitude, longitude, speed, heading),
            label,
            comparator_alarm,
            line,
            trajectory_break,
            warmup: false,
        });
        previous = Some(times);
    }
    Ok(())
}

/// `a − b`, NaN when either is missing.
fn difference(a: Option<f64>, b: Option<f64>) -> f64 {
    a.zip(b).map_or(f64::NAN, |(a, b)| a - b)
}

/// The reference's segment boundary (§1.5) and δ_t (§1.4) of a row against the previous FILE row.
/// Comparisons with NaN are false, so missing fields never create a boundary by themselves.
fn boundary_and_delta(previous: Option<&RowTimes>, current: &RowTimes) -> (bool, f64) {
    let Some(previous) = previous else {
        return (true, f64::NAN);
    };
    let d_run = difference(current.run_time, previous.run_time);
    let d_hobbs = difference(current.hobbs, previous.hobbs);
    let d_clock = difference(current.clock, previous.clock);
    let date_change = matches!((current.date, previous.date), (Some(c), Some(p)) if c != p);
    let reset = d_run < -MAX_BACKWARD_S || d_hobbs < -MAX_BACKWARD_S || d_clock < -MAX_BACKWARD_S;
    let gap = d_run > MAX_GAP_S || d_clock > MAX_GAP_S;
    let delta_t = if d_clock > 0.0 {
        d_clock
    } else if d_run > 0.0 {
        d_run
    } else {
        f64::NAN
    };
    (date_change || reset || gap, delta_t)
}
