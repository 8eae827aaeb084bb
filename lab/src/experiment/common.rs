//! What every experiment starts from: the common flags, the two AV-GPS recordings, the output
//! directory and Dataset-2's chronological split (SPEC §9), the seeds of a multi-seed run and the
//! report files. It owns loading, splitting and writing reports, not training or scoring.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::Serialize;
use spoofwatch_client::cli::json::write_json;
use spoofwatch_client::input::load_file;
use spoofwatch_core::sample::Track;
use spoofwatch_core::train::data::{ChronologicalSplit, split_with_warmup};
use spoofwatch_core::train::spec::{AnchorRebase, SplitFractions};
use spoofwatch_core::train::{DEFAULT_MAX_EPOCHS, DEFAULT_SEED};

/// Arguments every experiment takes.
#[derive(Debug, clap::Args)]
pub struct CommonArgs {
    /// Directory holding AV-GPS-Dataset-2.csv and AV-GPS-Dataset-3.csv.
    #[arg(long, env = "SPOOFWATCH_AVGPS_DIR")]
    pub data_dir: PathBuf,
    /// Output directory (model.json, report.md, report.json).
    #[arg(long)]
    pub out: PathBuf,
    /// Training seed.
    #[arg(long, default_value_t = DEFAULT_SEED)]
    pub seed: u64,
    /// Maximum epochs per model.
    #[arg(long, default_value_t = DEFAULT_MAX_EPOCHS)]
    pub epochs: u32,
    /// Worker threads for independent work (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
}

/// `--anchor-rebase`: [`AnchorRebase`] on the command line.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum AnchorRebaseArg {
    Off,
    Margin,
    Serve,
    TrainAndServe,
}

impl From<AnchorRebaseArg> for AnchorRebase {
    fn from(arg: AnchorRebaseArg) -> Self {
        match arg {
            AnchorRebaseArg::Off => Self::Off,
            AnchorRebaseArg::Margin => Self::Margin,
            AnchorRebaseArg::Serve => Self::Serve,
            AnchorRebaseArg::TrainAndServe => Self::TrainAndServe,
        }
    }
}

/// The two AV-GPS recordings the experiments use.
pub struct AvGpsData {
    pub dataset2: Vec<Track>,
    pub dataset3: Vec<Track>,
}

/// Reads `AV-GPS-Dataset-2.csv` and `AV-GPS-Dataset-3.csv` from `dir`.
pub fn load_avgps(dir: &Path) -> Result<AvGpsData> {
    let file = |name: &str| -> PathBuf { dir.join(name) };
    Ok(AvGpsData {
        dataset2: load_file(&file("AV-GPS-Dataset-2.csv"))
            .context("the AV-GPS data directory must hold AV-GPS-Dataset-2.csv")?,
        dataset3: load_file(&file("AV-GPS-Dataset-3.csv"))
            .context("the AV-GPS data directory must hold AV-GPS-Dataset-3.csv")?,
    })
}

/// Creates the output directory.
fn prepare_out(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))
}

/// What every experiment starts from: both recordings (the output directory created) and Dataset-2
/// split chronologically 70/15/15 (SPEC §9), its validation and test parts after `warmup_s`
/// seconds of warm-up rows ([`split_with_warmup`]).
pub fn prepare(common: &CommonArgs, warmup_s: f64) -> Result<(AvGpsData, ChronologicalSplit)> {
    let data = load_avgps(&common.data_dir)?;
    prepare_out(&common.out)?;
    let split = split_with_warmup(&data.dataset2, SplitFractions::default(), warmup_s);
    Ok((data, split))
}

/// The training seeds of a multi-seed run: `first`, `first` + 1, ..., `count` of them.
pub fn seed_list(first: u64, count: u64) -> Vec<u64> {
    (0..count).map(|k| first.wrapping_add(k)).collect()
}

/// Writes an experiment's report.json and report.md into `out` and prints the markdown.
pub fn write_report(out: &Path, report: &impl Serialize, markdown: &str) -> Result<()> {
    write_json(&out.join("report.json"), report)?;
    std::fs::write(out.join("report.md"), markdown).context("writing report.md")?;
    print!("{markdown}");
    Ok(())
}
