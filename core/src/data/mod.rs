//! Recorded data: AV-GPS CSVs and the plain telemetry CSV, detected by header (SPEC §2–3).

pub mod telemetry;
