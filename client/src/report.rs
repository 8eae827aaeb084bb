//! Plain-text/markdown tables of metrics, for offline (core) and remote (wire) results alike.
//! Owns only formatting; converting wire metrics is `spoofwatch_proto::wire::convert`'s job.

use std::borrow::Cow;

use spoofwatch_core::metrics::Metrics;
use spoofwatch_proto::wire::convert::metrics_from_proto;

fn opt(x: Option<f64>, digits: usize) -> String {
    x.map_or_else(|| "-".to_string(), |v| format!("{v:.digits$}"))
}

/// Metrics a table can show: the core's own, or wire metrics read through the one wire-to-core
/// conversion (so the table has a single column mapping).
pub trait TableMetrics {
    fn table_metrics(&self) -> Cow<'_, Metrics>;
}

impl TableMetrics for Metrics {
    fn table_metrics(&self) -> Cow<'_, Metrics> {
        Cow::Borrowed(self)
    }
}

impl TableMetrics for spoofwatch_proto::v1::Metrics {
    fn table_metrics(&self) -> Cow<'_, Metrics> {
        Cow::Owned(metrics_from_proto(self))
    }
}

/// A markdown table, one row per named metrics set (SPEC §8 columns).
pub fn metrics_table<N: AsRef<str>, M: TableMetrics>(rows: &[(N, &M)]) -> String {
    let mut out = String::from(
        "| data | AUROC | AUPRC | F1 | Prec. | Recall | FPR | ADR | delay (s) | FA rows | FA events |\n\
         |---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for (name, m) in rows {
        let m = m.table_metrics();
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
