//! A fleet fit's report as the CLI prints it, offline and from a server's job alike: the split, the
//! fitted priors, the operating points, and the test part's false alarms and detections for the
//! fitted model beside the starting one. Owns the layout only.

use std::fmt::Write as _;

use spoofwatch_proto::v1;

/// The report as text tables.
pub fn render(report: &v1::FleetFitReport) -> String {
    let mut out = String::from("fleet fit:\n");
    for (name, part) in [
        ("fit", &report.fit),
        ("validation", &report.validation),
        ("test", &report.test),
    ] {
        let part = part.unwrap_or_default();
        let _ = writeln!(
            out,
            "  {name:<10} {} drives of {} vehicles, {:.2} h",
            part.drives, part.vehicles, part.hours
        );
    }
    let three =
        |v: &[f64]| -> [f64; 3] { std::array::from_fn(|i| v.get(i).copied().unwrap_or(f64::NAN)) };
    let [ms, mh, ml] = three(&report.calibration_prior_mean);
    let [ss, sh, sl] = three(&report.calibration_prior_std);
    let _ = writeln!(
        out,
        "  calibration prior: speed scale {ms:+.3} ± {ss:.3}, heading {mh:+.2}° ± {sh:.2}°, lag \
         {ml:+.2} ± {sl:.2} s ({} fit drives taught a known calibration){}",
        report.calibration_known_drives,
        if report.calibration_kept_default.is_empty() {
            String::new()
        } else {
            format!(
                "; the default prior was kept: {}",
                report.calibration_kept_default
            )
        }
    );
    let sigma = |v: &[f64]| {
        v.iter()
            .map(|s| format!("{s:.2}"))
            .collect::<Vec<_>>()
            .join(" / ")
    };
    let _ = writeln!(
        out,
        "  GNSS noise per axis: {} m (starting model {} m)\n  warning θ {:.3}; critical test {}: {}",
        sigma(&report.gnss_sigma_m),
        sigma(&report.starting_gnss_sigma_m),
        report.warning_theta,
        report.critical_choice,
        report.critical_reason
    );
    let (fitted, starting) = (
        report.fitted.clone().unwrap_or_default(),
        report.starting.clone().unwrap_or_default(),
    );
    out.push_str(
        "false alarms on the test part (onsets per vehicle-hour):\n  rate      road        hours   \
         warning fitted  warning starting  critical fitted  critical starting\n",
    );
    for (f, s) in fitted.clean.iter().zip(&starting.clean) {
        let road = if f.road.is_empty() { "all" } else { &f.road };
        let _ = writeln!(
            out,
            "  {:>5} Hz {road:<10} {:>6.2}  {:>14.3}  {:>16.3}  {:>15.4}  {:>17.4}",
            f.rate_hz,
            f.hours,
            f.warning_per_hour,
            s.warning_per_hour,
            f.critical_per_hour,
            s.critical_per_hour
        );
    }
    out.push_str(
        "attacks injected into the test part (share alarmed within the deadline, fitted / starting):\n",
    );
    for (f, s) in fitted.detection.iter().zip(&starting.detection) {
        let share = |n: u64| n as f64 / f.injected.max(1) as f64;
        let _ = writeln!(
            out,
            "  {:<18} ×{:<3} warning ≤ {:>2} s {:.2} / {:.2}   critical ≤ {:>2} s {:.2} / {:.2}   \
             coverage {:.2} / {:.2}",
            f.attack,
            f.injected,
            f.warning_within_s,
            share(f.warned),
            share(s.warned),
            f.critical_within_s,
            share(f.critical),
            share(s.critical),
            f.warning_coverage,
            s.warning_coverage
        );
    }
    out
}
