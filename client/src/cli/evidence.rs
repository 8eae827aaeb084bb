//! `spoofwatch evidence`: the causal evidence of recorded data, row by row, as CSV.
//! Owns the CSV column layout only; the evidence itself is computed by `spoofwatch_core::evidence`.

use std::io::Write;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::builder::{PossibleValuesParser, TypedValueParser};
use spoofwatch_core::evidence::drift::DriftEvidence;
use spoofwatch_core::evidence::fit_evidence;
use spoofwatch_core::evidence::offset::OffsetEvidence;
use spoofwatch_core::evidence::{Evidence, EvidenceParams, FeatureSchema, build_track};
use spoofwatch_core::model::artifact::ModelArtifact;

use crate::cli::flags::ProjectionArg;
use crate::input::load_tracks;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Recorded data (AV-GPS or telemetry CSV).
    #[arg(long, required = true, num_args = 1..)]
    data: Vec<PathBuf>,
    /// Evidence statistics: a model artifact or an `EvidenceParams` JSON. Without it, Σ̂ and μ_e are
    /// fitted on the data's own normal (label 0) rows.
    #[arg(long)]
    stats: Option<PathBuf>,
    /// Where to write the CSV (default: standard output).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Local frame for GNSS displacements (ignored with --stats, which carries its own).
    #[arg(long, value_enum, default_value_t)]
    projection: ProjectionArg,
    /// Evidence channels fitted without --stats: `v2` adds the drift channels to the paper's, `v3`
    /// the offset channels to those.
    #[arg(
        long,
        default_value = FeatureSchema::V2.name(),
        value_parser = PossibleValuesParser::new(FeatureSchema::NAMED.map(|(name, _)| name))
            .map(|name| FeatureSchema::from_name(&name).unwrap_or_default()),
    )]
    schema: FeatureSchema,
}

/// The columns before the evidence values: who, where in the input, which trajectory.
const KEY_COLUMNS: [&str; 3] = ["vehicle_id", "line", "trajectory"];

/// Reads one column's value from a row's evidence.
type ColumnValue = fn(&Evidence) -> f64;

/// The evidence columns, each name with how to read it, so header and values cannot drift.
const EVIDENCE_COLUMNS: [(&str, ColumnValue); 14] = [
    ("delta_t", |e| e.delta_t),
    ("nu", |e| f64::from(u8::from(e.valid))),
    ("r_e", |e| e.residual[0]),
    ("r_n", |e| e.residual[1]),
    ("eta_e", |e| e.eta[0]),
    ("eta_n", |e| e.eta[1]),
    ("eta_dot_e", |e| e.eta_dot[0]),
    ("eta_dot_n", |e| e.eta_dot[1]),
    ("eta_ddot_e", |e| e.eta_ddot[0]),
    ("eta_ddot_n", |e| e.eta_ddot[1]),
    ("energy", |e| e.energy),
    ("q", |e| e.q),
    ("a", |e| e.accum),
    ("a_log", |e| e.accum_log),
];

/// Reads one drift column's value from a row's drift channels.
type DriftValue = fn(&DriftEvidence) -> f64;

/// Evidence v2's columns, written when the parameters carry drift parameters.
const DRIFT_COLUMNS: [(&str, DriftValue); 21] = [
    ("r_clip_e", |d| d.clipped_residual[0]),
    ("r_clip_n", |d| d.clipped_residual[1]),
    ("r_clean_e", |d| d.cleaned_residual[0]),
    ("r_clean_n", |d| d.cleaned_residual[1]),
    ("speed_scale_error", |d| d.calibration[0]),
    ("heading_bias_deg", |d| d.calibration[1]),
    ("timing_offset_s", |d| d.calibration[2]),
    ("warm_up", |d| d.warm_up),
    ("raw_chi2_10s", |d| d.raw_chi2()[0]),
    ("raw_chi2_30s", |d| d.raw_chi2()[1]),
    ("raw_chi2_60s", |d| d.raw_chi2()[2]),
    ("raw_chi2_120s", |d| d.raw_chi2()[3]),
    ("calibrated_chi2_10s", |d| d.calibrated_chi2()[0]),
    ("calibrated_chi2_30s", |d| d.calibrated_chi2()[1]),
    ("calibrated_chi2_60s", |d| d.calibrated_chi2()[2]),
    ("calibrated_chi2_120s", |d| d.calibrated_chi2()[3]),
    ("drift_statistic", |d| d.statistic),
    ("stale_fix_s", |d| d.stale_fix_s),
    ("residual_log", |d| d.residual_log),
    ("drift_rate_east_mps", |d| d.rate_mps[0]),
    ("drift_rate_north_mps", |d| d.rate_mps[1]),
];

/// Reads one offset column's value from a row's offset channels.
type OffsetValue = fn(&OffsetEvidence) -> f64;

/// Evidence v3's columns, written when the parameters carry offset parameters.
const OFFSET_COLUMNS: [(&str, OffsetValue); 6] = [
    ("offset_east_m", |o| o.offset_m[0]),
    ("offset_north_m", |o| o.offset_m[1]),
    ("offset_sigma_m", |o| o.sigma_m),
    ("offset_nis_fast", |o| o.nis[0]),
    ("offset_nis_slow", |o| o.nis[1]),
    ("offset_held_s", |o| o.held_s),
];

pub fn run(args: Args) -> Result<()> {
    let tracks = load_tracks(&args.data)?;
    let params = match &args.stats {
        Some(path) => load_params(path)?,
        None => {
            let fit = fit_evidence(&tracks, args.projection.into(), 0.0, 0.98, args.schema)
                .context(
                    "fitting the evidence statistics on the data's normal rows (pass --stats for \
                     unlabelled data)",
                )?;
            eprintln!(
                "evidence statistics fitted on {} normal valid rows of the input (mu_e = {:.4})",
                fit.normal_rows, fit.params.mu_e
            );
            fit.params
        }
    };
    let sink: Box<dyn Write> = match &args.out {
        Some(path) => Box::new(
            std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?,
        ),
        None => Box::new(std::io::stdout().lock()),
    };
    let mut out = csv::Writer::from_writer(std::io::BufWriter::new(sink));
    let has_drift = params.drift.is_some();
    let drift_names: &[&str] = if has_drift {
        &DRIFT_COLUMNS.map(|(name, _)| name)
    } else {
        &[]
    };
    let offset_names: &[&str] = if params.offset.is_some() {
        &OFFSET_COLUMNS.map(|(name, _)| name)
    } else {
        &[]
    };
    let value_names = EVIDENCE_COLUMNS.map(|(name, _)| name);
    out.write_record(
        KEY_COLUMNS
            .iter()
            .chain(&value_names)
            .chain(drift_names)
            .chain(offset_names),
    )?;
    for track in &tracks {
        for (e, r) in build_track(&params, &track.records)
            .iter()
            .zip(&track.records)
        {
            let mut row = vec![
                track.vehicle_id.clone(),
                r.line.to_string(),
                e.trajectory.to_string(),
            ];
            row.extend(
                EVIDENCE_COLUMNS
                    .iter()
                    .map(|(_, value)| value(e).to_string()),
            );
            if let Some(drift) = &e.drift {
                row.extend(
                    DRIFT_COLUMNS
                        .iter()
                        .map(|(_, value)| value(drift).to_string()),
                );
            }
            if let Some(offset) = &e.offset {
                row.extend(
                    OFFSET_COLUMNS
                        .iter()
                        .map(|(_, value)| value(offset).to_string()),
                );
            }
            out.write_record(&row)?;
        }
    }
    out.flush()?;
    Ok(())
}

/// Reads evidence parameters from a model artifact or a bare `EvidenceParams` document.
fn load_params(path: &PathBuf) -> Result<EvidenceParams> {
    let text = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let value: serde_json::Value =
        serde_json::from_slice(&text).with_context(|| format!("{} is not JSON", path.display()))?;
    if value.get("schema_version").is_some() {
        let artifact = ModelArtifact::from_slice(&text)
            .with_context(|| format!("loading model artifact {}", path.display()))?;
        return Ok(artifact.evidence);
    }
    match serde_json::from_value::<EvidenceParams>(value) {
        Ok(params) => Ok(params),
        Err(err) => bail!(
            "{} is neither a model artifact nor evidence parameters: {err}",
            path.display()
        ),
    }
}
