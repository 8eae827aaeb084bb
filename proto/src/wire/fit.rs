//! A fleet fit's report (core's `FleetFitReport`) as its wire message, for the server's job result
//! and the CLI's offline fit alike. Plain conversion: it must not compute anything the report does
//! not hold.

use crate::v1;
use spoofwatch_core::fleet_fit::score::{CleanRate, KindScore, ModelScore};
use spoofwatch_core::fleet_fit::{FleetFitReport, PartSummary};
use spoofwatch_core::metrics::Pace;

/// The report on the wire (headings and spreads of the prior in degrees).
pub fn fit_report_to_proto(report: &FleetFitReport) -> v1::FleetFitReport {
    let prior = &report.calibration_prior;
    let degrees = |values: [f64; 3]| vec![values[0], values[1].to_degrees(), values[2]];
    v1::FleetFitReport {
        fit: Some(part(&report.fit)),
        validation: Some(part(&report.validation)),
        test: Some(part(&report.test)),
        rates_hz: report.rates_hz.clone(),
        calibration_prior_mean: degrees(prior.prior.mean),
        calibration_prior_std: degrees(prior.prior.std),
        calibration_known_drives: u32::try_from(prior.known_drives).unwrap_or(u32::MAX),
        calibration_kept_default: prior.kept_default.clone().unwrap_or_default(),
        gnss_sigma_m: report.gnss_sigma_m.to_vec(),
        starting_gnss_sigma_m: report.starting_gnss_sigma_m.to_vec(),
        warning_theta: report.warning_theta,
        critical_choice: report.critical.how.clone(),
        critical_reason: report.critical.reason.clone(),
        fitted: Some(score(&report.fitted)),
        starting: Some(score(&report.starting)),
    }
}

fn part(summary: &PartSummary) -> v1::FitPart {
    v1::FitPart {
        drives: u32::try_from(summary.drives).unwrap_or(u32::MAX),
        vehicles: u32::try_from(summary.vehicles).unwrap_or(u32::MAX),
        hours: summary.hours,
    }
}

fn score(score: &ModelScore) -> v1::FitScore {
    v1::FitScore {
        clean: score.clean.iter().map(clean).collect(),
        detection: score.detection.iter().map(detection).collect(),
    }
}

fn clean(rate: &CleanRate) -> v1::FitCleanRate {
    v1::FitCleanRate {
        rate_hz: rate.rate_hz,
        road: rate.pace.map_or("", Pace::name).to_owned(),
        drives: u32::try_from(rate.drives).unwrap_or(u32::MAX),
        hours: rate.hours,
        warning_onsets: rate.warning_onsets,
        critical_onsets: rate.critical_onsets,
        warning_per_hour: rate.warning_per_hour,
        critical_per_hour: rate.critical_per_hour,
    }
}

fn detection(kind: &KindScore) -> v1::FitDetection {
    v1::FitDetection {
        attack: kind.attack.clone(),
        injected: kind.injected,
        warning_within_s: kind.warning_within_s,
        critical_within_s: kind.critical_within_s,
        warned: kind.warned,
        critical: kind.critical,
        warning_coverage: kind.warning_coverage,
        critical_coverage: kind.critical_coverage,
    }
}
