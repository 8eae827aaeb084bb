//! The plain telemetry CSV: `vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg[,label]`.

use std::io::Write;

use crate::sample::Track;

/// Required columns, in the order the writer emits them.
pub const REQUIRED_COLUMNS: [&str; 6] = [
    "vehicle_id",
    "timestamp",
    "latitude",
    "longitude",
    "speed_mps",
    "heading_deg",
];

/// Writes tracks in the telemetry format (with a `label` column when any record is labelled).
/// Vehicles are written one after another; floats use Rust's shortest round-trip form.
pub fn write_tracks<W: Write>(writer: W, tracks: &[Track]) -> csv::Result<()> {
    let labelled = tracks
        .iter()
        .any(|t| t.records.iter().any(|r| r.label.is_some()));
    let mut out = csv::Writer::from_writer(writer);
    let mut header: Vec<&str> = REQUIRED_COLUMNS.to_vec();
    if labelled {
        header.push("label");
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
            out.write_record(&row)?;
        }
    }
    out.flush()?;
    Ok(())
}
