//! Plain-text/markdown tables of metrics.

use spoofwatch_core::metrics::Metrics;

fn opt(x: Option<f64>, digits: usize) -> String {
    x.map_or_else(|| "-".to_string(), |v| format!("{v:.digits$}"))
}

/// A markdown table, one row per named metrics set (SPEC §8 columns).
pub fn metrics_table(rows: &[(String, &Metrics)]) -> String {
    let mut out = String::from(
        "| data | AUROC | AUPRC | F1 | Prec. | Recall | FPR | ADR | delay (s) | FA rows | FA events |\n\
         |---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for (name, m) in rows {
        out.push_str(&format!(
            "| {name} | {} | {} | {:.4} | {:.4} | {:.4} | {:.4} | {:.2} | {} | {} | {} |\n",
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
