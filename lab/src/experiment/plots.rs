//! The experiments' figures, drawn with [`crate::figures`] and written beside report.md.

use std::path::Path;

use anyhow::{Context, Result};
use spoofwatch_baselines::Epoch;

use crate::figures::{DISTINCT_COLOURS, Panel, Series, Stroke, line_chart_svg};

/// `series` with the lines past the palette's colours dashed, so no two series look alike.
pub fn distinct(mut series: Vec<Series>) -> Vec<Series> {
    for s in series.iter_mut().skip(DISTINCT_COLOURS) {
        if s.stroke == Stroke::Line {
            s.stroke = Stroke::Dashed;
        }
    }
    series
}

/// Writes `svg` to `out/file`.
pub fn write_svg(out: &Path, file: &str, svg: &str) -> Result<()> {
    let path = out.join(file);
    std::fs::write(&path, svg).with_context(|| format!("writing {}", path.display()))
}

/// Training loss, validation loss and validation AUROC per epoch (or per tree), one series per
/// model.
pub fn training_curves_svg(
    title: &str,
    x_label: &str,
    curves: &[(String, &[Epoch])],
) -> Result<String> {
    let series = |value: fn(&Epoch) -> Option<f64>| -> Vec<Series> {
        let all = curves
            .iter()
            .map(|(name, epochs)| {
                let points = epochs
                    .iter()
                    .map(|e| (e.epoch as f64, value(e).unwrap_or(f64::NAN)))
                    .collect();
                Series::line(name.clone(), points)
            })
            .filter(|s| s.points.iter().any(|p| p.1.is_finite()))
            .collect();
        distinct(all)
    };
    let mut panels = vec![
        Panel {
            title: "training loss (weighted BCE)".into(),
            y_label: "loss".into(),
            series: series(|e| Some(e.train_loss)),
            y_range: None,
        },
        Panel {
            title: "validation loss (weighted BCE, whole trajectories)".into(),
            y_label: "loss".into(),
            series: series(|e| Some(e.val_loss)),
            y_range: None,
        },
    ];
    let auroc = series(|e| e.val_auroc);
    if !auroc.is_empty() {
        panels.push(Panel {
            title: "validation AUROC (ν = 1 rows)".into(),
            y_label: "AUROC".into(),
            series: auroc,
            y_range: Some((0.0, 1.0)),
        });
    }
    line_chart_svg(title, x_label, &panels)
}

/// File of the nets' and HO-LLN's training curves (per epoch).
pub const CURVES_SVG: &str = "training-curves.svg";
/// File of the tree ensembles' curves (per tree).
pub const TREE_CURVES_SVG: &str = "training-curves-trees.svg";

/// Writes the training curves of `curves` (in legend order): the tree ensembles (named "… trees
/// …") to [`TREE_CURVES_SVG`], every other model to [`CURVES_SVG`].
pub fn write_training_curves(out: &Path, title: &str, curves: &[(String, &[Epoch])]) -> Result<()> {
    let (trees, epochs): (Vec<_>, Vec<_>) = curves
        .iter()
        .cloned()
        .partition(|(name, _)| name.contains("trees"));
    write_svg(
        out,
        CURVES_SVG,
        &training_curves_svg(title, "epoch", &epochs)?,
    )?;
    if !trees.is_empty() {
        write_svg(
            out,
            TREE_CURVES_SVG,
            &training_curves_svg(title, "trees", &trees)?,
        )?;
    }
    Ok(())
}
