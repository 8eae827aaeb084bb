//! SVG figures of the experiments and of `spoofwatch-lab evaluate --plot`: line charts of stacked panels
//! that share their x axis ([`line_chart_svg`]) and the per-recording detector trace built on them
//! ([`trace_of`], [`trace_svg`]). The trace's panels: p̂ with θ, the confirmed alarm and the truth; why
//! the detector says so (a band per dominant evidence kind of the detections' explanations); the
//! recording's own detector against the truth, when it has one; the evidence channels (with evidence
//! v3 the offset channels among them); with v3, the slow anchor's offset ‖o‖ against its 5σ gate.
//!
//! Pure drawing: plain data in, SVG text out; the caller writes the file. Text is left to the SVG
//! viewer's fonts (plotters without a font feature only estimates text widths), which keeps the
//! build free of font and bitmap crates.

use anyhow::{Context, Result, bail, ensure};
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use spoofwatch_core::evaluation::RowResult;
use spoofwatch_core::evidence::Evidence;
use spoofwatch_core::evidence::offset::DECISIVE_GATE;
use spoofwatch_core::explain::EvidenceKind;
use spoofwatch_core::sample::Record;

/// How a series is stroked.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stroke {
    /// A plain line.
    Line,
    /// A dashed line, for thresholds and other reference levels.
    Dashed,
    /// A thick line, for on/off intervals drawn as a strip at a fixed level.
    Band,
}

/// One named line of a chart.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    /// The legend text.
    pub name: String,
    /// (x, y) in drawing order. A point with a non-finite coordinate is a gap: the line stops
    /// there and starts again at the next finite point.
    pub points: Vec<(f64, f64)>,
    pub stroke: Stroke,
}

impl Series {
    pub fn line(name: impl Into<String>, points: Vec<(f64, f64)>) -> Self {
        Self {
            name: name.into(),
            points,
            stroke: Stroke::Line,
        }
    }

    pub fn dashed(name: impl Into<String>, points: Vec<(f64, f64)>) -> Self {
        Self {
            stroke: Stroke::Dashed,
            ..Self::line(name, points)
        }
    }

    /// The rows where `on` holds as a strip at height `level` (a gap wherever it does not), so
    /// several on/off signals can share a panel without hiding each other.
    pub fn band(name: impl Into<String>, x: &[f64], on: &[bool], level: f64) -> Self {
        let points = x
            .iter()
            .zip(on)
            .map(|(&x, &on)| (x, if on { level } else { f64::NAN }))
            .collect();
        Self {
            stroke: Stroke::Band,
            ..Self::line(name, points)
        }
    }
}

/// One labelled panel of a line chart.
#[derive(Clone, Debug, PartialEq)]
pub struct Panel {
    /// Drawn above the panel.
    pub title: String,
    pub y_label: String,
    /// Coloured in order from one palette (the first series black), so a chart that lists the
    /// same quantity first in every panel draws it alike everywhere.
    pub series: Vec<Series>,
    /// Fixed y range; points outside it are drawn at its edge (plotters does not clip). `None`:
    /// the finite values' range, padded.
    pub y_range: Option<(f64, f64)>,
}

/// Okabe–Ito colours (told apart with the common colour-vision deficiencies), black first.
const PALETTE: [RGBColor; 8] = [
    RGBColor(0, 0, 0),
    RGBColor(213, 94, 0),
    RGBColor(0, 114, 178),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
    RGBColor(240, 228, 66),
];

/// Series a panel can tell apart by colour alone.
pub const DISTINCT_COLOURS: usize = PALETTE.len();

const WIDTH: u32 = 1100;
const TITLE_HEIGHT: u32 = 40;
const PANEL_HEIGHT: u32 = 260;
/// The legend has its own column right of the plots, so it never covers data.
const LEGEND_WIDTH: u32 = 240;
const FONT: &str = "sans-serif";

fn style_of(series_index: usize, stroke: Stroke) -> ShapeStyle {
    let color = PALETTE[series_index % PALETTE.len()];
    color.stroke_width(match stroke {
        Stroke::Line | Stroke::Dashed => 2,
        Stroke::Band => 7,
    })
}

/// A chart of `panels` stacked top to bottom over one x range, with `x_label` under the last.
/// Each panel has its title, y axis and a legend entry per series.
///
/// # Errors
/// When there are no panels or no finite point at all.
pub fn line_chart_svg(title: &str, x_label: &str, panels: &[Panel]) -> Result<String> {
    ensure!(!panels.is_empty(), "a chart needs at least one panel");
    let all_points = || {
        panels
            .iter()
            .flat_map(|p| &p.series)
            .flat_map(|s| &s.points)
    };
    let x_range = finite_range(all_points().filter(|p| p.1.is_finite()).map(|p| p.0))
        .context("a chart needs at least one finite point")?;
    // No margin, except that a single x gets a width.
    let x_range = pad(x_range, 0.0);
    let panel_count = u32::try_from(panels.len()).context("too many panels")?;
    let mut svg = String::new();
    {
        let size = (WIDTH, TITLE_HEIGHT + PANEL_HEIGHT * panel_count);
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE)?;
        let below_title = root.titled(title, (FONT, 22))?;
        let areas = below_title.split_evenly((panels.len(), 1));
        for (index, (panel, area)) in panels.iter().zip(&areas).enumerate() {
            let is_last = index + 1 == panels.len();
            draw_panel(area, panel, x_range, is_last.then_some(x_label))?;
        }
        root.present()?;
    }
    Ok(svg)
}

fn draw_panel(
    area: &DrawingArea<SVGBackend<'_>, Shift>,
    panel: &Panel,
    x_range: (f64, f64),
    x_label: Option<&str>,
) -> Result<()> {
    let y_range = match panel.y_range {
        // plotters asserts on a NaN range: an error here instead.
        Some((lo, hi)) if lo.is_finite() && hi.is_finite() && lo < hi => (lo, hi),
        Some(range) => bail!(
            "panel {:?}: y range {range:?} is not increasing",
            panel.title
        ),
        None => {
            let ys = panel.series.iter().flat_map(|s| &s.points);
            let ys = ys.filter(|p| p.0.is_finite()).map(|p| p.1);
            finite_range(ys).map_or((0.0, 1.0), |range| pad(range, 0.05))
        }
    };
    let (plot_area, legend_area) = area.split_horizontally(WIDTH - LEGEND_WIDTH);
    let mut chart = ChartBuilder::on(&plot_area)
        .caption(&panel.title, (FONT, 16))
        .margin(8)
        .x_label_area_size(if x_label.is_some() { 45 } else { 28 })
        .y_label_area_size(70)
        .build_cartesian_2d(x_range.0..x_range.1, y_range.0..y_range.1)?;
    chart
        .configure_mesh()
        .x_desc(x_label.unwrap_or(""))
        .y_desc(panel.y_label.as_str())
        .x_label_formatter(&tick_label)
        .y_label_formatter(&tick_label)
        .label_style((FONT, 13))
        .axis_desc_style((FONT, 14))
        .max_light_lines(2)
        .draw()?;
    for (index, series) in panel.series.iter().enumerate() {
        let style = style_of(index, series.stroke);
        for run in finite_runs(&series.points, y_range) {
            match (series.stroke, run.as_slice()) {
                // A lone point would be an invisible one-point line.
                (_, [point]) => {
                    let radius = if series.stroke == Stroke::Band { 4 } else { 2 };
                    chart.draw_series([Circle::new(*point, radius, style.filled())])?;
                }
                (Stroke::Dashed, _) => {
                    chart.draw_series(DashedLineSeries::new(run, 8, 5, style))?;
                }
                (Stroke::Line | Stroke::Band, _) => {
                    chart.draw_series(LineSeries::new(run, style))?;
                }
            }
        }
    }
    draw_legend(&legend_area, &panel.series)
}

/// One entry per series: a sample of its stroke, then its name.
fn draw_legend(area: &DrawingArea<SVGBackend<'_>, Shift>, series: &[Series]) -> Result<()> {
    const TOP: i32 = 40;
    const ROW: i32 = 20;
    let text = TextStyle::from((FONT, 14).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    for (index, series) in series.iter().enumerate() {
        let y = TOP + ROW * i32::try_from(index).context("too many series")?;
        let style = style_of(index, series.stroke);
        let sample = vec![(6, y), (40, y)];
        if series.stroke == Stroke::Dashed {
            area.draw(&DashedPathElement::new(sample, 8, 5, style))?;
        } else {
            area.draw(&PathElement::new(sample, style))?;
        }
        area.draw(&Text::new(series.name.as_str(), (48, y), text.clone()))?;
    }
    Ok(())
}

/// A tick value in few characters (plotters' default writes 100000.0), so labels stay clear of the
/// axis description.
fn tick_label(value: &f64) -> String {
    if value.abs() >= 1e5 {
        format!("{value:.1e}")
    } else {
        // Rounded to 3 decimals so that 0.30000000000000004 reads 0.3; + 0.0 turns -0 into 0.
        format!("{}", (value * 1000.0).round() / 1000.0 + 0.0)
    }
}

/// The maximal runs of consecutive finite points, y limited to `y_range`.
fn finite_runs(points: &[(f64, f64)], y_range: (f64, f64)) -> Vec<Vec<(f64, f64)>> {
    let mut runs = Vec::new();
    let mut run = Vec::new();
    for &(x, y) in points {
        if x.is_finite() && y.is_finite() {
            run.push((x, y.clamp(y_range.0, y_range.1)));
        } else if !run.is_empty() {
            runs.push(std::mem::take(&mut run));
        }
    }
    if !run.is_empty() {
        runs.push(run);
    }
    runs
}

/// (min, max) of the finite values; `None` when there is none.
fn finite_range(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    values
        .filter(|v| v.is_finite())
        .fold(None, |range, v| match range {
            None => Some((v, v)),
            Some((lo, hi)) => Some((f64::min(lo, v), f64::max(hi, v))),
        })
}

/// `range` widened by `fraction` of its width on each side; a single value gets a width of 1, so
/// the axis is never empty.
fn pad((lo, hi): (f64, f64), fraction: f64) -> (f64, f64) {
    if hi > lo {
        let margin = (hi - lo) * fraction;
        (lo - margin, hi + margin)
    } else {
        (lo - 0.5, hi + 0.5)
    }
}

/// The detector's view of one recording, row for row: what [`trace_svg`] draws.
#[derive(Clone, Debug, PartialEq)]
pub struct Trace {
    pub title: String,
    /// Row times (s); the figure's x axis is the time since the first finite one.
    pub time_s: Vec<f64>,
    /// p̂_t.
    pub probability: Vec<f64>,
    /// The operating point's threshold θ.
    pub theta: f64,
    /// The confirmed alarm c̄_t.
    pub alarm: Vec<bool>,
    /// Ground truth; `None` for unlabelled rows.
    pub truth: Vec<Option<bool>>,
    /// Another detector's verdict from the recording (AV-GPS `EKF Detector`) and its name; rows
    /// without one are `None`.
    pub comparator: Option<(String, Vec<Option<bool>>)>,
    /// Evidence channels over the same times as `time_s` (absolute, not yet shifted).
    pub channels: Vec<Series>,
    /// The slow anchor's offset ‖o‖ (m) and its 5σ gate over the same times (absolute); empty
    /// without offset evidence.
    pub offset: Vec<Series>,
    /// Why: per dominant evidence kind that occurs (never [`EvidenceKind::None`]), in the order of
    /// [`EvidenceKind::ALL`], the rows whose detection names it.
    pub why: Vec<(EvidenceKind, Vec<bool>)>,
}

/// The trace of one vehicle's evaluated rows (`Evaluation::rows` of that track, in order) and its
/// records (for the recording's own comparator verdict), at threshold `theta`.
///
/// The evidence panel shows the whitened residual ‖η_t‖ (a gap where ν = 0), ã_t = ln(1 + a_t),
/// with evidence v2 the drift statistic and the stale-fix time, and with v3 the fast and slow
/// anchors' NIS and the seconds the offset has been held beyond the decisive gate. All are drawn as
/// ln(1 + x), as ã and the model's drift and offset inputs are: AV-GPS's spoofed jumps reach
/// ‖η‖ ≈ 10⁵, which on a linear axis flattens every other channel to a line at 0.
///
/// Why is each row's own explanation ([`Decision::explanation`], what the service sends as a
/// detection's `why`), so the figure and the service never disagree on a row.
///
/// [`Decision::explanation`]: spoofwatch_core::detector::Decision::explanation
///
/// # Errors
/// When rows and records are not the same rows.
pub fn trace_of(
    title: impl Into<String>,
    rows: &[RowResult],
    records: &[Record],
    theta: f64,
) -> Result<Trace> {
    ensure!(
        rows.len() == records.len(),
        "{} evaluated rows for {} records",
        rows.len(),
        records.len()
    );
    if let Some((row, record)) = rows.iter().zip(records).find(|(r, rec)| r.line != rec.line) {
        bail!(
            "evaluated row of line {} paired with the record of line {}",
            row.line,
            record.line
        );
    }
    let per_row = |value: fn(&Evidence) -> f64| -> Vec<(f64, f64)> {
        let points = rows.iter().map(|r| (r.time_s, value(&r.decision.evidence)));
        points.collect()
    };
    let channel = |name: &str, value: fn(&Evidence) -> f64| Series::line(name, per_row(value));
    let mut channels = vec![
        channel("ln(1 + ‖η‖) (whitened residual)", |e| {
            if e.valid {
                e.energy.sqrt().ln_1p()
            } else {
                f64::NAN
            }
        }),
        channel("ã = ln(1 + a)", |e| e.accum_log),
    ];
    if rows.iter().any(|r| r.decision.evidence.drift.is_some()) {
        channels.push(channel("ln(1 + drift statistic)", |e| {
            e.drift.map_or(f64::NAN, |d| d.statistic.ln_1p())
        }));
        channels.push(channel("ln(1 + stale fix s)", |e| {
            e.drift.map_or(f64::NAN, |d| d.stale_fix_s.ln_1p())
        }));
    }
    let mut offset = Vec::new();
    if rows.iter().any(|r| r.decision.evidence.offset.is_some()) {
        // The anchors are (fast, slow); destructuring keeps that pairing checked by the compiler.
        channels.push(channel("ln(1 + NIS fast)", |e| {
            e.offset.map_or(f64::NAN, |o| {
                let [fast, _] = o.nis;
                fast.ln_1p()
            })
        }));
        channels.push(channel("ln(1 + NIS slow)", |e| {
            e.offset.map_or(f64::NAN, |o| {
                let [_, slow] = o.nis;
                slow.ln_1p()
            })
        }));
        channels.push(channel("ln(1 + held s)", |e| {
            e.offset.map_or(f64::NAN, |o| o.held_s.ln_1p())
        }));
        // In metres, not ln(1 + x): the reader compares the displacement with the gate directly.
        // The gate is the decisive NIS gate on ‖o‖ alone (√25 = 5σ); while an anchor is frozen the
        // slow NIS can cross it earlier, as it also tests the change since the last trusted fix.
        offset.push(Series::line(
            "‖o‖ slow anchor (m)",
            per_row(|e| {
                e.offset
                    .map_or(f64::NAN, |o| o.offset_m[0].hypot(o.offset_m[1]))
            }),
        ));
        offset.push(Series::dashed(
            "5σ gate (m)",
            per_row(|e| {
                e.offset
                    .map_or(f64::NAN, |o| DECISIVE_GATE.sqrt() * o.sigma_m)
            }),
        ));
    }
    // The kinds in a fixed order, each kept only where some row names it, so the legend lists what
    // the trace shows and nothing else.
    let why = EvidenceKind::ALL
        .into_iter()
        .filter(|&kind| kind != EvidenceKind::None)
        .map(|kind| {
            let on: Vec<bool> = rows
                .iter()
                .map(|r| r.decision.explanation.dominant == kind)
                .collect();
            (kind, on)
        })
        .filter(|(_, on)| on.contains(&true))
        .collect();
    let comparator = records
        .iter()
        .any(|r| r.comparator_alarm.is_some())
        .then(|| {
            let verdicts = records.iter().map(|r| r.comparator_alarm).collect();
            ("EKF Detector".to_string(), verdicts)
        });
    Ok(Trace {
        title: title.into(),
        time_s: rows.iter().map(|r| r.time_s).collect(),
        probability: rows.iter().map(|r| r.decision.probability).collect(),
        theta,
        alarm: rows.iter().map(|r| r.decision.alarm).collect(),
        truth: rows.iter().map(|r| r.label).collect(),
        comparator,
        channels,
        offset,
        why,
    })
}

/// The legend name of a why band: the kind's name in words.
fn why_label(kind: EvidenceKind) -> String {
    kind.name().replace('_', " ")
}

/// The trace figure: p̂ with θ, the confirmed alarm and the truth; why (a band per dominant evidence
/// kind, right under the alarm it explains); the comparator against the truth (when the recording
/// has one); the evidence channels; the slow anchor's offset against its 5σ gate (with offset
/// evidence).
///
/// # Errors
/// When the per-row vectors differ in length or there is no finite time.
pub fn trace_svg(trace: &Trace) -> Result<String> {
    let rows = trace.time_s.len();
    ensure!(rows > 0, "a trace needs at least one row");
    ensure!(
        [
            trace.probability.len(),
            trace.alarm.len(),
            trace.truth.len()
        ] == [rows; 3],
        "the trace's probability, alarm and truth must have one value per row ({rows})"
    );
    if let Some((name, verdicts)) = &trace.comparator {
        ensure!(
            verdicts.len() == rows,
            "{name} must have one value per row ({rows})"
        );
    }
    for (kind, on) in &trace.why {
        ensure!(
            on.len() == rows,
            "why {:?} must have one value per row ({rows})",
            kind.name()
        );
    }
    let origin = trace.time_s.iter().copied().find(|t| t.is_finite());
    let origin = origin.context("the trace has no finite time")?;
    let t: Vec<f64> = trace.time_s.iter().map(|t| t - origin).collect();
    let spoofed: Vec<bool> = trace.truth.iter().map(|l| *l == Some(true)).collect();
    let (first, last) = finite_range(t.iter().copied()).context("the trace has no finite time")?;

    // Truth and alarm as strips above p̂ ∈ [0, 1], so neither hides p̂ or the other.
    let probability = t.iter().copied().zip(trace.probability.iter().copied());
    let top = vec![
        Series::band("ground truth: spoofed", &t, &spoofed, 1.24),
        Series::band("confirmed alarm", &t, &trace.alarm, 1.12),
        Series::line("p̂ (spoofing probability)", probability.collect()),
        Series::dashed(
            format!("θ = {:.2}", trace.theta),
            vec![(first, trace.theta), (last, trace.theta)],
        ),
    ];
    let mut panels = vec![Panel {
        title: "spoofing probability and confirmed alarm".into(),
        y_label: "p̂".into(),
        series: top,
        y_range: Some((0.0, 1.32)),
    }];
    panels.push(why_panel(&t, &trace.why));
    if let Some((name, verdicts)) = &trace.comparator {
        let comparator_on: Vec<bool> = verdicts.iter().map(|v| *v == Some(true)).collect();
        panels.push(Panel {
            title: format!("{name} (from the recording) against the truth"),
            y_label: "on".into(),
            series: vec![
                Series::band("ground truth: spoofed", &t, &spoofed, 0.75),
                Series::band("confirmed alarm", &t, &trace.alarm, 0.5),
                Series::band(name.as_str(), &t, &comparator_on, 0.25),
            ],
            y_range: Some((0.0, 1.0)),
        });
    }
    let shifted = |series: &[Series]| -> Vec<Series> {
        let shift = |s: &Series| Series {
            points: s.points.iter().map(|&(x, y)| (x - origin, y)).collect(),
            ..s.clone()
        };
        series.iter().map(shift).collect()
    };
    if !trace.channels.is_empty() {
        panels.push(Panel {
            title: "evidence channels".into(),
            y_label: "value".into(),
            series: shifted(&trace.channels),
            y_range: None,
        });
    }
    if !trace.offset.is_empty() {
        panels.push(Panel {
            title: "GNSS offset from the slow anchor against its 5σ gate".into(),
            y_label: "m".into(),
            series: shifted(&trace.offset),
            y_range: None,
        });
    }
    line_chart_svg(&trace.title, "time since the first row (s)", &panels)
}

/// The why panel over times `t`: a band per kind at a level of its own, fixed per kind (the order
/// of [`EvidenceKind::ALL`] from the top), so a kind sits at the same height in every trace.
fn why_panel(t: &[f64], why: &[(EvidenceKind, Vec<bool>)]) -> Panel {
    let kinds = EvidenceKind::ALL.len() as f64;
    let series = why.iter().map(|(kind, on)| {
        let rank = EvidenceKind::ALL
            .iter()
            .position(|k| k == kind)
            .unwrap_or(0) as f64;
        Series::band(why_label(*kind), t, on, 1.0 - rank / kinds)
    });
    let title = if why.is_empty() {
        "why: no evidence stands out on any row"
    } else {
        "why: the dominant evidence of each detection"
    };
    Panel {
        title: title.into(),
        y_label: "on".into(),
        series: series.collect(),
        y_range: Some((0.0, 1.0)),
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use spoofwatch_core::evaluation::evaluate_tracks;
    use spoofwatch_core::evidence::drift::DriftEvidence;
    use spoofwatch_core::evidence::offset::OffsetEvidence;
    use spoofwatch_core::explain::Explanation;
    use spoofwatch_core::metrics::EventRules;
    use spoofwatch_core::model::artifact::ModelArtifact;
    use spoofwatch_core::scenario::{DriveSpec, simulate_drive};

    use super::*;

    /// What a test reads back from an SVG.
    struct Drawn {
        /// Every `<text>`'s content, trimmed (plotters ends each with a newline).
        texts: Vec<String>,
        /// The stroke colour of every series `<polyline>`, in document order: plotters draws each
        /// line of a series, and each legend sample, as one. It draws the axes and their ticks as
        /// polylines too, but 1 px wide, and the grid as `<line>`s; series are at least 2 px wide.
        polylines: Vec<String>,
    }

    impl Drawn {
        fn count_text(&self, text: &str) -> usize {
            self.texts.iter().filter(|t| *t == text).count()
        }
    }

    fn parse(svg: &str) -> Drawn {
        let doc = roxmltree::Document::parse(svg).expect("the SVG is well-formed XML");
        assert_eq!(doc.root_element().tag_name().name(), "svg");
        let elements = |name: &'static str| {
            doc.descendants()
                .filter(move |n| n.is_element() && n.tag_name().name() == name)
        };
        Drawn {
            texts: elements("text")
                .map(|n| n.text().unwrap_or_default().trim().to_string())
                .collect(),
            polylines: elements("polyline")
                .filter(|n| n.attribute("stroke-width") != Some("1"))
                .map(|n| n.attribute("stroke").unwrap_or_default().to_string())
                .collect(),
        }
    }

    /// The stroke plotters writes for palette colour `index`.
    fn stroke(index: usize) -> String {
        let RGBColor(r, g, b) = PALETTE[index];
        format!("#{r:02X}{g:02X}{b:02X}")
    }

    fn ramp(scale: f64) -> Vec<(f64, f64)> {
        (0..50)
            .map(|i| (f64::from(i), scale * f64::from(i)))
            .collect()
    }

    fn panel(title: &str, series: Vec<Series>) -> Panel {
        Panel {
            title: title.into(),
            y_label: "y".into(),
            series,
            y_range: None,
        }
    }

    #[test]
    fn every_series_has_its_line_and_its_legend_entry() {
        let panels = [
            panel(
                "first panel",
                vec![
                    Series::line("alpha", ramp(1.0)),
                    Series::line("beta", ramp(2.0)),
                    Series::line("gamma", ramp(-1.0)),
                ],
            ),
            panel(
                "second panel",
                vec![
                    Series::line("delta", ramp(0.5)),
                    Series::line("epsilon", ramp(3.0)),
                ],
            ),
        ];
        let svg = line_chart_svg("A & B <chart>", "x (s)", &panels).expect("drawn");
        let drawn = parse(&svg);
        for text in ["A & B <chart>", "first panel", "second panel", "x (s)"] {
            assert_eq!(drawn.count_text(text), 1, "{text}: {:?}", drawn.texts);
        }
        for name in ["alpha", "beta", "gamma", "delta", "epsilon"] {
            assert_eq!(drawn.count_text(name), 1, "{name}: {:?}", drawn.texts);
        }
        // Per panel: one line per series, then the legend's sample of each, in the same colours.
        let first: Vec<String> = (0..3).map(stroke).collect();
        let second: Vec<String> = (0..2).map(stroke).collect();
        let expected = [&first[..], &first[..], &second[..], &second[..]].concat();
        assert_eq!(drawn.polylines, expected);
    }

    #[test]
    fn non_finite_points_are_gaps_and_the_svg_stays_valid() {
        let mut broken = ramp(1.0);
        broken[10].1 = f64::NAN;
        broken[20].0 = f64::NAN;
        broken[30].1 = f64::INFINITY;
        // A lone finite point between gaps is a dot, not an invisible line.
        broken[40].1 = f64::NAN;
        broken[42].1 = f64::NAN;
        let panels = [panel(
            "gaps",
            vec![
                Series::line("broken", broken),
                Series::dashed("nothing finite", vec![(0.0, f64::NAN), (1.0, f64::NAN)]),
            ],
        )];
        let svg = line_chart_svg("gaps", "x", &panels).expect("drawn");
        let drawn = parse(&svg);
        assert!(!svg.contains("NaN") && !svg.contains("inf"), "{svg}");
        assert_eq!(drawn.count_text("broken"), 1);
        assert_eq!(drawn.count_text("nothing finite"), 1);
        // Runs 0–9, 11–19, 21–29, 31–39, 43–49 (and the dot at 41), then the legend sample.
        let broken_lines = drawn.polylines.iter().filter(|s| **s == stroke(0)).count();
        assert_eq!(broken_lines, 5 + 1);
        assert!(svg.contains("<circle"), "the lone point is drawn");
        // The series without a finite point has no line, only its (dashed) legend sample.
        assert!(drawn.polylines.iter().any(|s| *s == stroke(1)));
    }

    #[test]
    fn nothing_to_draw_is_an_error() {
        assert!(line_chart_svg("t", "x", &[]).is_err());
        let empty = [panel("p", vec![Series::line("s", Vec::new())])];
        assert!(line_chart_svg("t", "x", &empty).is_err());
        let all_nan = [panel("p", vec![Series::line("s", vec![(f64::NAN, 1.0)])])];
        assert!(line_chart_svg("t", "x", &all_nan).is_err());
        for y_range in [(f64::NAN, 1.0), (1.0, 1.0), (2.0, 1.0)] {
            let fixed = [Panel {
                y_range: Some(y_range),
                ..panel("p", vec![Series::line("s", ramp(1.0))])
            }];
            assert!(line_chart_svg("t", "x", &fixed).is_err(), "{y_range:?}");
        }

        let mut trace = small_trace();
        trace.time_s.clear();
        assert!(trace_svg(&trace).is_err(), "no rows");
        let mut trace = small_trace();
        trace.alarm.pop();
        assert!(trace_svg(&trace).is_err(), "a short column");
        let mut trace = small_trace();
        trace.time_s = vec![f64::NAN; 4];
        assert!(trace_svg(&trace).is_err(), "no finite time");
        let mut trace = small_trace();
        trace.why[0].1.pop();
        assert!(trace_svg(&trace).is_err(), "a short why band");
    }

    fn small_trace() -> Trace {
        Trace {
            title: "vehicle 7".into(),
            time_s: vec![100.0, 101.0, 102.0, 103.0],
            probability: vec![0.1, f64::NAN, 0.9, 0.95],
            theta: 0.6,
            alarm: vec![false, false, true, true],
            truth: vec![Some(false), None, Some(true), Some(true)],
            comparator: Some((
                "EKF Detector".into(),
                vec![None, Some(false), Some(true), Some(false)],
            )),
            channels: vec![Series::line(
                "‖η‖",
                vec![(100.0, f64::NAN), (101.0, 1.0), (102.0, 5.0), (103.0, 7.0)],
            )],
            offset: Vec::new(),
            why: vec![(EvidenceKind::Energy, vec![false, false, true, true])],
        }
    }

    #[test]
    fn the_trace_draws_probability_threshold_alarm_truth_comparator_and_channels() {
        let svg = trace_svg(&small_trace()).expect("drawn");
        let drawn = parse(&svg);
        assert_eq!(drawn.count_text("vehicle 7"), 1);
        for (name, panels) in [
            ("ground truth: spoofed", 2),
            ("confirmed alarm", 2),
            ("p̂ (spoofing probability)", 1),
            ("θ = 0.60", 1),
            ("EKF Detector", 1),
            ("‖η‖", 1),
            ("why: the dominant evidence of each detection", 1),
            ("energy", 1),
        ] {
            assert_eq!(drawn.count_text(name), panels, "{name}: {:?}", drawn.texts);
        }
        // Top panel 4 series, why 1, comparator panel 3, evidence 1: a legend sample and at least
        // one line each (the dashed θ is many short ones; the comparator's one `on` row is a dot).
        assert!(
            drawn.polylines.len() >= 2 * 9 - 1,
            "{}",
            drawn.polylines.len()
        );

        let mut without = small_trace();
        without.comparator = None;
        let drawn = parse(&trace_svg(&without).expect("drawn"));
        assert_eq!(drawn.count_text("EKF Detector"), 0);
        assert_eq!(drawn.count_text("ground truth: spoofed"), 1);
    }

    /// A simulated drive of `duration_s` evaluated by the bundled (v3) model: its rows and records.
    fn evaluated_drive(duration_s: f64, comparator_from: usize) -> (Vec<RowResult>, Vec<Record>) {
        let model = concat!(env!("CARGO_MANIFEST_DIR"), "/../models/default.json");
        let bytes = std::fs::read(model).expect("the bundled model");
        let artifact = Arc::new(ModelArtifact::from_slice(&bytes).expect("valid"));
        let spec = DriveSpec {
            duration_s,
            ..DriveSpec::default()
        };
        let mut track = simulate_drive(&spec, "sim").expect("simulated");
        for record in track.records.iter_mut().skip(comparator_from) {
            record.comparator_alarm = Some(true);
        }
        let evaluation = evaluate_tracks(&artifact, &[track.clone()], EventRules::default());
        (evaluation.rows, track.records)
    }

    /// The first rows of a real drive with their evidence and verdict set by hand, each row's
    /// explanation made as the detector makes it: `([NIS fast, NIS slow], arrived by step, held s,
    /// p̂ ≥ θ)` per row, or no offset evidence at all with `offset: false` (a v2 model's rows); the
    /// drift evidence cycles through `drift`.
    fn hand_rows(
        hand: &[([f64; 2], bool, f64, bool)],
        offset: bool,
        drift: &[DriftEvidence],
    ) -> (Vec<RowResult>, Vec<Record>) {
        let (mut rows, mut records) = evaluated_drive(20.0, usize::MAX);
        rows.truncate(hand.len());
        records.truncate(hand.len());
        assert_eq!(rows.len(), hand.len(), "the drive has enough rows");
        for (i, (row, &(nis, arrived_by_step, held_s, positive))) in
            rows.iter_mut().zip(hand).enumerate()
        {
            let decision = &mut row.decision;
            decision.evidence.drift = Some(drift[i % drift.len()]);
            // ‖o‖ = 5i m (a 3-4-5 triangle) against 5σ = 10 m.
            let i = i as f64;
            decision.evidence.offset = offset.then_some(OffsetEvidence {
                offset_m: [3.0 * i, 4.0 * i],
                sigma_m: 2.0,
                nis,
                held_s,
                arrived_by_step,
                ..OffsetEvidence::EMPTY
            });
            decision.positive = positive;
            decision.explanation = Explanation::of(&decision.evidence, positive);
        }
        (rows, records)
    }

    /// None, jump, jump, held offset (at the follow gate), held offset (beyond the decisive gate
    /// without a step), energy (the model's verdict alone); the drift is quiet throughout.
    const OFFSET_ROWS: [([f64; 2], bool, f64, bool); 6] = [
        ([1.0, 2.0], false, 0.0, false),
        ([40.0, 30.0], true, 0.0, false),
        ([50.0, 36.0], true, 1.0, true),
        ([20.0, 5.0], false, 0.0, false),
        ([30.0, 30.0], false, 3.0, true),
        ([0.0, 0.0], false, 0.0, true),
    ];

    fn values(series: &[Series], name: &str) -> Vec<f64> {
        let found = series.iter().find(|s| s.name == name);
        let found = found.unwrap_or_else(|| panic!("no series {name} in {series:?}"));
        found.points.iter().map(|p| p.1).collect()
    }

    fn on(rows: &[usize], of: usize) -> Vec<bool> {
        (0..of).map(|row| rows.contains(&row)).collect()
    }

    #[test]
    fn trace_of_offset_evidence_has_the_offset_channels_and_a_why_band_per_kind_that_occurs() {
        let (rows, records) = hand_rows(&OFFSET_ROWS, true, &[DriftEvidence::EMPTY]);
        let trace = trace_of("hand", &rows, &records, 0.5).expect("same rows");

        let ln_1p = |v: [f64; 6]| v.map(f64::ln_1p).to_vec();
        let channels = &trace.channels;
        assert_eq!(
            values(channels, "ln(1 + NIS fast)"),
            ln_1p([1.0, 40.0, 50.0, 20.0, 30.0, 0.0])
        );
        assert_eq!(
            values(channels, "ln(1 + NIS slow)"),
            ln_1p([2.0, 30.0, 36.0, 5.0, 30.0, 0.0])
        );
        assert_eq!(
            values(channels, "ln(1 + held s)"),
            ln_1p([0.0, 0.0, 1.0, 0.0, 3.0, 0.0])
        );
        assert_eq!(
            values(&trace.offset, "‖o‖ slow anchor (m)"),
            [0.0, 5.0, 10.0, 15.0, 20.0, 25.0]
        );
        assert_eq!(values(&trace.offset, "5σ gate (m)"), [10.0; 6]);
        assert_eq!(trace.offset[1].stroke, Stroke::Dashed);

        // Exactly the rows the explanation names, in the order of `EvidenceKind::ALL`; no band for
        // drift or a frozen fix, which no row names, nor for rows where nothing stands out.
        assert_eq!(
            trace.why,
            [
                (EvidenceKind::Jump, on(&[1, 2], 6)),
                (EvidenceKind::HeldOffset, on(&[3, 4], 6)),
                (EvidenceKind::Energy, on(&[5], 6)),
            ]
        );
        for (kind, on) in &trace.why {
            for (row, on) in rows.iter().zip(on) {
                let why = Explanation::of(&row.decision.evidence, row.decision.positive);
                assert_eq!(*on, why.dominant == *kind, "{kind:?} at line {}", row.line);
            }
        }
    }

    #[test]
    fn trace_of_rows_without_offset_evidence_has_the_why_the_explanation_gives() {
        let frozen = DriftEvidence {
            stale_fix_s: 3.0,
            ..DriftEvidence::EMPTY
        };
        let drifting = DriftEvidence {
            statistic: 2.0,
            ..DriftEvidence::EMPTY
        };
        let quiet = DriftEvidence::EMPTY;
        // Rows 0–5 under drift frozen, drifting, quiet, frozen, drifting, quiet; the quiet rows 2
        // and 5 are p̂ ≥ θ, which leaves the model's own reading.
        let (rows, records) = hand_rows(&OFFSET_ROWS, false, &[frozen, drifting, quiet]);
        let trace = trace_of("v2", &rows, &records, 0.5).expect("same rows");

        let names: Vec<&str> = trace.channels.iter().map(|s| s.name.as_str()).collect();
        assert!(!names.iter().any(|n| n.contains("NIS")), "{names:?}");
        assert!(trace.offset.is_empty());
        assert_eq!(
            trace.why,
            [
                (EvidenceKind::Drift, on(&[1, 4], 6)),
                (EvidenceKind::FrozenFix, on(&[0, 3], 6)),
                (EvidenceKind::Energy, on(&[2, 5], 6)),
            ]
        );
    }

    #[test]
    fn the_trace_names_the_why_bands_present_and_the_offset_panel() {
        let (rows, records) = hand_rows(&OFFSET_ROWS, true, &[DriftEvidence::EMPTY]);
        let trace = trace_of("hand", &rows, &records, 0.5).expect("same rows");
        let drawn = parse(&trace_svg(&trace).expect("drawn"));
        for text in [
            "why: the dominant evidence of each detection",
            "jump",
            "held offset",
            "energy",
            "ln(1 + NIS fast)",
            "ln(1 + NIS slow)",
            "ln(1 + held s)",
            "GNSS offset from the slow anchor against its 5σ gate",
            "‖o‖ slow anchor (m)",
            "5σ gate (m)",
        ] {
            assert_eq!(drawn.count_text(text), 1, "{text}: {:?}", drawn.texts);
        }
        for absent in ["drift", "frozen fix", "none"] {
            assert_eq!(drawn.count_text(absent), 0, "{absent}: {:?}", drawn.texts);
        }

        let (rows, records) = hand_rows(&OFFSET_ROWS[..3], false, &[DriftEvidence::EMPTY]);
        let quiet = trace_of("quiet", &rows, &records, 0.5).expect("same rows");
        let drawn = parse(&trace_svg(&quiet).expect("drawn"));
        // Only row 2 is p̂ ≥ θ: its energy is the one reason left; nothing about offsets.
        assert_eq!(drawn.count_text("energy"), 1, "{:?}", drawn.texts);
        for absent in [
            "jump",
            "held offset",
            "ln(1 + NIS slow)",
            "GNSS offset from the slow anchor against its 5σ gate",
        ] {
            assert_eq!(drawn.count_text(absent), 0, "{absent}: {:?}", drawn.texts);
        }

        let mut calm = quiet;
        calm.why.clear();
        let drawn = parse(&trace_svg(&calm).expect("drawn"));
        assert_eq!(
            drawn.count_text("why: no evidence stands out on any row"),
            1
        );
        assert_eq!(drawn.count_text("energy"), 0);
    }

    #[test]
    fn trace_of_an_evaluated_drive_has_the_evidence_channels_and_the_comparator() {
        let (rows, records) = evaluated_drive(60.0, 30);
        let trace = trace_of("sim", &rows, &records, 0.5).expect("same rows");
        assert_eq!(trace.time_s.len(), records.len());
        let names: Vec<&str> = trace.channels.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "ln(1 + ‖η‖) (whitened residual)",
                "ã = ln(1 + a)",
                "ln(1 + drift statistic)",
                "ln(1 + stale fix s)",
                "ln(1 + NIS fast)",
                "ln(1 + NIS slow)",
                "ln(1 + held s)",
            ]
        );
        assert_eq!(trace.offset.len(), 2);
        // Every row is either in the band of its detection's kind or explained by nothing.
        for (index, row) in rows.iter().enumerate() {
            let dominant = row.decision.explanation.dominant;
            let bands: Vec<EvidenceKind> = trace
                .why
                .iter()
                .filter(|(_, on)| on[index])
                .map(|(kind, _)| *kind)
                .collect();
            let expected: &[EvidenceKind] = if dominant == EvidenceKind::None {
                &[]
            } else {
                &[dominant]
            };
            assert_eq!(bands, expected, "line {}", row.line);
        }
        // ν = 0 at the trajectory start: no residual to draw there.
        assert!(trace.channels[0].points[0].1.is_nan());
        let (name, verdicts) = trace
            .comparator
            .as_ref()
            .expect("the records have verdicts");
        assert_eq!(name, "EKF Detector");
        assert_eq!(verdicts[29..31], [None, Some(true)]);
        parse(&trace_svg(&trace).expect("drawn"));

        assert!(trace_of("sim", &rows, &records[1..], 0.5).is_err());
    }
}
