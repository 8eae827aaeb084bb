//! Recorded data: AV-GPS CSVs and the plain telemetry CSV, told apart by their header (SPEC §2–3).
//!
//! Owns reading recorded files into tracks. Must not compute evidence or labels beyond what the files
//! say.

pub mod avgps;
pub mod telemetry;
mod timefmt;

use std::collections::{HashMap, HashSet};
use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use crate::sample::{Record, Track};

/// Which CSV dialect a recording came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// An AV-GPS dataset file (one vehicle, one track).
    AvGps,
    /// The plain telemetry CSV of [`telemetry::REQUIRED_COLUMNS`] (any number of vehicles).
    Telemetry,
}

/// The tracks read from one source.
#[derive(Clone, Debug, PartialEq)]
pub struct Recording {
    /// The file (or the name given to [`read`]) the tracks came from.
    pub source: String,
    /// The detected dialect.
    pub format: Format,
    /// One track per vehicle, in order of first appearance.
    pub tracks: Vec<Track>,
}

/// Why a recording could not be read. Every message names the source; row problems also the
/// 1-based line and the column.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// The file could not be opened or read.
    #[error("{file}: {source}")]
    Io {
        /// The file.
        file: String,
        /// The underlying error.
        source: std::io::Error,
    },
    /// There is no header row.
    #[error("{file}: empty file (no header row)")]
    Empty {
        /// The file.
        file: String,
    },
    /// The header matches neither format.
    #[error("{file}: unrecognised header: {detail}")]
    UnknownFormat {
        /// The file.
        file: String,
        /// Which columns each format is missing.
        detail: String,
    },
    /// One field of a row is malformed (or missing from a short row).
    #[error("{file}:{line}: column \"{column}\": {problem}")]
    Field {
        /// The file.
        file: String,
        /// 1-based line of the row.
        line: u64,
        /// The header name of the column.
        column: String,
        /// What is wrong.
        problem: String,
    },
    /// A row is malformed as a whole (too many fields, invalid UTF-8, ...).
    #[error("{file}:{line}: {problem}")]
    Row {
        /// The file.
        file: String,
        /// 1-based line of the row.
        line: u64,
        /// What is wrong.
        problem: String,
    },
}

/// Reads a recording from a file; the AV-GPS vehicle id is the file stem.
pub fn read_path(path: &Path) -> Result<Recording, DataError> {
    let file_name = path.display().to_string();
    let file = File::open(path).map_err(|source| DataError::Io {
        file: file_name.clone(),
        source,
    })?;
    let vehicle_id = path
        .file_stem()
        .map_or_else(|| file_name.clone(), |s| s.to_string_lossy().into_owned());
    read_named(file, &file_name, &vehicle_id)
}

/// Reads a recording from any reader; `source` names it in errors and is the AV-GPS vehicle id.
pub fn read<R: Read>(reader: R, source: &str) -> Result<Recording, DataError> {
    read_named(reader, source, source)
}

fn read_named<R: Read>(reader: R, source: &str, vehicle_id: &str) -> Result<Recording, DataError> {
    let mut tracks: Vec<Track> = Vec::new();
    let mut track_of_vehicle: HashMap<String, usize> = HashMap::new();
    let format = visit(reader, source, vehicle_id, &mut |vehicle, record| {
        let track = match track_of_vehicle.get(vehicle) {
            Some(&index) => index,
            None => {
                track_of_vehicle.insert(vehicle.to_string(), tracks.len());
                tracks.push(Track {
                    vehicle_id: vehicle.to_string(),
                    records: Vec::new(),
                });
                tracks.len() - 1
            }
        };
        tracks[track].records.push(record);
    })?;
    if format == Format::AvGps && tracks.is_empty() {
        // An AV-GPS file is one vehicle's track, even with no rows.
        tracks.push(Track {
            vehicle_id: vehicle_id.to_string(),
            records: Vec::new(),
        });
    }
    Ok(Recording {
        source: source.to_string(),
        format,
        tracks,
    })
}

/// What a recording holds, counted while it is read: no record is kept, so summarising a large
/// upload costs the memory of its distinct vehicle ids only.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Summary {
    /// The detected dialect.
    pub format: Format,
    /// Data rows (samples).
    pub rows: u64,
    /// Distinct vehicles (an AV-GPS file is always one).
    pub vehicles: u64,
    /// Rows carrying a spoofing label.
    pub labelled_rows: u64,
    /// Labelled rows marked spoofed.
    pub spoofed_rows: u64,
}

/// Reads a recording as [`read`] does, with the same errors, but only counts it.
pub fn summarize<R: Read>(reader: R, source: &str) -> Result<Summary, DataError> {
    let mut vehicles: HashSet<String> = HashSet::new();
    let (mut rows, mut labelled_rows, mut spoofed_rows) = (0, 0, 0);
    let format = visit(reader, source, source, &mut |vehicle, record| {
        rows += 1;
        labelled_rows += u64::from(record.label.is_some());
        spoofed_rows += u64::from(record.label == Some(true));
        if !vehicles.contains(vehicle) {
            vehicles.insert(vehicle.to_string());
        }
    })?;
    Ok(Summary {
        format,
        rows,
        vehicles: match format {
            Format::AvGps => 1,
            Format::Telemetry => vehicles.len() as u64,
        },
        labelled_rows,
        spoofed_rows,
    })
}

/// Reads every row of either format, handing each record and its vehicle id to `on_record` in
/// file order (an AV-GPS file's records all belong to `vehicle_id`).
fn visit<R: Read>(
    reader: R,
    source: &str,
    vehicle_id: &str,
    on_record: &mut dyn FnMut(&str, Record),
) -> Result<Format, DataError> {
    let (mut csv, header, crlf) = open_csv(reader, source)?;
    let table = Table {
        source,
        header: &header,
        crlf,
    };
    let missing_avgps = missing_columns(&header, &avgps::REQUIRED_COLUMNS);
    let missing_telemetry = missing_columns(&header, &telemetry::REQUIRED_COLUMNS);
    if missing_avgps.is_empty() {
        avgps::read_records(&mut csv, &table, &mut |record| {
            on_record(vehicle_id, record)
        })?;
        Ok(Format::AvGps)
    } else if missing_telemetry.is_empty() {
        telemetry::read_records(&mut csv, &table, on_record)?;
        Ok(Format::Telemetry)
    } else {
        Err(DataError::UnknownFormat {
            file: source.to_string(),
            detail: format!(
                "not AV-GPS (missing {}) and not telemetry (missing {})",
                missing_avgps.join(", "),
                missing_telemetry.join(", ")
            ),
        })
    }
}

/// A CSV reader past its header, the trimmed header names and whether lines end in CRLF.
type OpenCsv<R> = (csv::Reader<BufReader<R>>, Vec<String>, bool);

/// Opens `reader` as a CSV with a header row (a BOM and surrounding spaces are trimmed from names).
fn open_csv<R: Read>(reader: R, source: &str) -> Result<OpenCsv<R>, DataError> {
    let mut reader = BufReader::with_capacity(1 << 16, reader);
    let first_chunk = reader.fill_buf().map_err(|source_error| DataError::Io {
        file: source.to_string(),
        source: source_error,
    })?;
    let crlf = uses_crlf(first_chunk);
    let mut csv = csv::ReaderBuilder::new()
        .has_headers(true)
        // Field counts are checked per row so the error can name the line and column.
        .flexible(true)
        .from_reader(reader);
    let header: Vec<String> = csv
        .headers()
        .map_err(|e| csv_error(source, e, 0))?
        .iter()
        .map(|name| name.trim_start_matches('\u{feff}').trim().to_string())
        .collect();
    if header.iter().all(|name| name.is_empty()) {
        return Err(DataError::Empty {
            file: source.to_string(),
        });
    }
    Ok((csv, header, crlf))
}

/// Numeric columns of a recorded file, row by row, keyed by the rows' 1-based source lines (the
/// [`Record::line`](crate::sample::Record::line)s of the tracks read from the same file).
#[derive(Clone, Debug, PartialEq)]
pub struct NumericColumns {
    /// The column names, in the order of each row's values.
    pub names: Vec<String>,
    /// (line, values) per data row; an empty or `nan` field is NaN.
    pub rows: Vec<(u64, Vec<f64>)>,
}

impl NumericColumns {
    /// The values of the row at `line`, if the file has it.
    pub fn at_line(&self, line: u64) -> Option<&[f64]> {
        self.rows
            .binary_search_by_key(&line, |(l, _)| *l)
            .ok()
            .map(|i| self.rows[i].1.as_slice())
    }
}

/// Reads the columns `names` (exact header names) of every row of a CSV. A missing column is an
/// [`DataError::UnknownFormat`] naming it; a non-numeric field a [`DataError::Field`].
pub fn read_numeric_columns<R: Read>(
    reader: R,
    source: &str,
    names: &[&str],
) -> Result<NumericColumns, DataError> {
    let (mut csv, header, crlf) = open_csv(reader, source)?;
    let table = Table {
        source,
        header: &header,
        crlf,
    };
    let missing = missing_columns(&header, names);
    if !missing.is_empty() {
        return Err(DataError::UnknownFormat {
            file: source.to_string(),
            detail: format!("missing {}", missing.join(", ")),
        });
    }
    let indices: Vec<usize> = names.iter().filter_map(|n| table.column(n)).collect();
    let mut rows = Vec::new();
    let mut record = csv::StringRecord::new();
    while let Some(line) = table.next_row(&mut csv, &mut record)? {
        let values = indices
            .iter()
            .map(|&i| parse_measurement(&record[i]).map_err(|p| table.field_error(line, i, p)))
            .collect::<Result<Vec<f64>, DataError>>()?;
        rows.push((line, values));
    }
    Ok(NumericColumns {
        names: names.iter().map(|n| n.to_string()).collect(),
        rows,
    })
}

/// The required names absent from `header`, quoted.
fn missing_columns(header: &[String], required: &[&str]) -> Vec<String> {
    required
        .iter()
        .filter(|name| !header.iter().any(|h| h == *name))
        .map(|name| format!("\"{name}\""))
        .collect()
}

/// Whether the first line ends in CRLF. The csv crate reports a CRLF row's line one too low (the
/// row "starts" at the previous line's `\n`), so line numbers are corrected for such files.
fn uses_crlf(first_chunk: &[u8]) -> bool {
    first_chunk
        .iter()
        .position(|&b| b == b'\n')
        .is_some_and(|end| end > 0 && first_chunk[end - 1] == b'\r')
}

/// The source name and header, for column lookups and precise errors.
pub(crate) struct Table<'a> {
    pub source: &'a str,
    pub header: &'a [String],
    /// The file's lines end in CRLF (see [`uses_crlf`]).
    pub crlf: bool,
}

impl Table<'_> {
    /// Index of a column by exact (trimmed) name.
    pub fn column(&self, name: &str) -> Option<usize> {
        self.header.iter().position(|h| h == name)
    }

    /// An error about one field.
    pub fn field_error(&self, line: u64, column: usize, problem: String) -> DataError {
        DataError::Field {
            file: self.source.to_string(),
            line,
            column: self.header.get(column).cloned().unwrap_or_default(),
            problem,
        }
    }

    /// Reads the next data row into `record`; `Ok(None)` at the end. Checks the field count.
    pub fn next_row<R: Read>(
        &self,
        csv: &mut csv::Reader<R>,
        record: &mut csv::StringRecord,
    ) -> Result<Option<u64>, DataError> {
        if !csv
            .read_record(record)
            .map_err(|e| csv_error(self.source, e, u64::from(self.crlf)))?
        {
            return Ok(None);
        }
        let reported = record.position().map_or(0, csv::Position::line);
        let line = reported + u64::from(self.crlf);
        let (found, expected) = (record.len(), self.header.len());
        if found < expected {
            return Err(self.field_error(
                line,
                found,
                format!("missing: the row has {found} fields, the header {expected}"),
            ));
        }
        if found > expected {
            return Err(DataError::Row {
                file: self.source.to_string(),
                line,
                problem: format!(
                    "the row has {found} fields, the header {expected} (extra fields after column \"{}\")",
                    self.header.last().map_or("", String::as_str)
                ),
            });
        }
        Ok(Some(line))
    }
}

/// Maps a csv error to an I/O error naming the file, or a row error naming the line.
fn csv_error(source: &str, error: csv::Error, line_offset: u64) -> DataError {
    let line = error.position().map_or(0, csv::Position::line) + line_offset;
    let problem = error.to_string();
    match error.into_kind() {
        csv::ErrorKind::Io(io) => DataError::Io {
            file: source.to_string(),
            source: io,
        },
        _ => DataError::Row {
            file: source.to_string(),
            line,
            problem,
        },
    }
}

/// A measurement: empty or `nan` (any case) is NaN (the sample becomes invalid, ν = 0); any other
/// text that is not a number is an error.
pub(crate) fn parse_measurement(text: &str) -> Result<f64, String> {
    let text = text.trim();
    if text.is_empty() || text.eq_ignore_ascii_case("nan") {
        return Ok(f64::NAN);
    }
    text.parse::<f64>()
        .map_err(|_| format!("expected a number, got \"{text}\""))
}

/// A 0/1 flag (label, comparator alarm); empty is `None`.
pub(crate) fn parse_flag(text: &str) -> Result<Option<bool>, String> {
    match text.trim() {
        "" => Ok(None),
        "0" | "0.0" => Ok(Some(false)),
        "1" | "1.0" => Ok(Some(true)),
        other => Err(format!("expected 0, 1 or empty, got \"{other}\"")),
    }
}

#[cfg(test)]
mod tests;
