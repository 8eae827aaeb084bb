//! Plain-text/markdown tables of metrics.

use spoofwatch_core::metrics::Metrics;

fn opt(x: Option<f64>, digits: usize) -> String {
    x.map_or_else(|| "-".to_string(), |v| format!("{v:.digits$}"))
}

/// The columns of a metrics table, from offline (`core`) or wire (`v1`) metrics.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TableRow {
    pub auroc: Option<f64>,
    pub auprc: Option<f64>,
    pub f1: f64,
    pub precision: f64,
    pub recall: f64,
    pub fpr: f64,
    pub adr: f64,
    pub mean_delay_s: Option<f64>,
    pub false_alarm_rows: u64,
    pub false_alarm_events: u64,
}

impl From<&Metrics> for TableRow {
    fn from(m: &Metrics) -> Self {
        Self {
            auroc: m.auroc,
            auprc: m.auprc,
            f1: m.f1,
            precision: m.precision,
            recall: m.recall,
            fpr: m.fpr,
            adr: m.adr,
            mean_delay_s: m.mean_delay_s,
            false_alarm_rows: m.false_alarm_rows,
            false_alarm_events: m.false_alarm_events,
        }
    }
}

impl From<&spoofwatch_proto::v1::Metrics> for TableRow {
    fn from(m: &spoofwatch_proto::v1::Metrics) -> Self {
        Self {
            auroc: m.auroc,
            auprc: m.auprc,
            f1: m.f1,
            precision: m.precision,
            recall: m.recall,
            fpr: m.fpr,
            adr: m.adr,
            mean_delay_s: m.mean_delay_s,
            false_alarm_rows: m.false_alarm_rows,
            false_alarm_events: m.false_alarm_events,
        }
    }
}

/// A markdown table, one row per named metrics set (SPEC §8 columns).
pub fn metrics_table<N: AsRef<str>, M: Copy + Into<TableRow>>(rows: &[(N, M)]) -> String {
    let mut out = String::from(
        "| data | AUROC | AUPRC | F1 | Prec. | Recall | FPR | ADR | delay (s) | FA rows | FA events |\n\
         |---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for (name, m) in rows {
        let m: TableRow = (*m).into();
        out.push_str(&format!(
            "| {} | {} | {} | {:.4} | {:.4} | {:.4} | {:.4} | {:.2} | {} | {} | {} |\n",
            name.as_ref(),
            opt(m.auroc, 4),
            opt(m.auprc, 4),
            m.f1,
            m.precision,
            m.recall,
            m.fpr,
            m.adr,
            opt(m.mean_delay_s, 1),
            m.false_alarm_rows,
            m.false_alarm_events,
        ));
    }
    out
}

/// Per-event delays as `22.0, 29.0` (`miss` for undetected events).
pub fn delays(m: &Metrics) -> String {
    if m.delays_s.is_empty() {
        return "no events".into();
    }
    m.delays_s
        .iter()
        .map(|d| opt(*d, 1).replace('-', "miss"))
        .collect::<Vec<_>>()
        .join(", ")
}
