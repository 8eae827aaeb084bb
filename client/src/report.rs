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

/// Mean and sample standard deviation (n − 1) of the values; `None` for no values, std 0 for one.
pub fn mean_std(values: &[f64]) -> Option<(f64, f64)> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    let mean = values.iter().sum::<f64>() / n as f64;
    let variance = if n > 1 {
        values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64
    } else {
        0.0
    };
    Some((mean, variance.sqrt()))
}

/// `mean ± std` of the values with `digits` decimals (just the value for one, `-` for none).
pub fn mean_std_cell(values: &[f64], digits: usize) -> String {
    match mean_std(values) {
        None => "-".into(),
        Some((mean, _)) if values.len() == 1 => format!("{mean:.digits$}"),
        Some((mean, std)) => format!("{mean:.digits$} ± {std:.digits$}"),
    }
}

/// A markdown table of metrics over seeds, one row per named detector: mean ± sample std of each
/// SPEC §8 column (AUROC, AUPRC and the delay over the seeds that have them).
pub fn seeds_table<N: AsRef<str>>(rows: &[(N, Vec<&Metrics>)]) -> String {
    let mut out = String::from(
        "| detector | AUROC | AUPRC | F1 | Prec. | Recall | FPR | ADR | delay (s) | FA events |\n\
         |---|---|---|---|---|---|---|---|---|---|\n",
    );
    for (name, seeds) in rows {
        let column = |f: &dyn Fn(&Metrics) -> Option<f64>| -> Vec<f64> {
            seeds.iter().filter_map(|m| f(m)).collect()
        };
        out.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            name.as_ref(),
            mean_std_cell(&column(&|m| m.auroc), 4),
            mean_std_cell(&column(&|m| m.auprc), 4),
            mean_std_cell(&column(&|m| Some(m.f1)), 4),
            mean_std_cell(&column(&|m| Some(m.precision)), 4),
            mean_std_cell(&column(&|m| Some(m.recall)), 4),
            mean_std_cell(&column(&|m| Some(m.fpr)), 4),
            mean_std_cell(&column(&|m| Some(m.adr)), 2),
            mean_std_cell(&column(&|m| m.mean_delay_s), 1),
            mean_std_cell(&column(&|m| Some(m.false_alarm_events as f64)), 1),
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_and_sample_std_by_hand() {
        assert_eq!(mean_std(&[]), None);
        assert_eq!(mean_std(&[3.0]), Some((3.0, 0.0)));
        // mean 2, squared deviations 1 + 0 + 1 = 2, / (3 − 1) = 1.
        assert_eq!(mean_std(&[1.0, 2.0, 3.0]), Some((2.0, 1.0)));
        assert_eq!(mean_std_cell(&[1.0, 2.0, 3.0], 2), "2.00 ± 1.00");
        assert_eq!(mean_std_cell(&[0.5], 2), "0.50");
    }
}
