//! Row-by-row parity with the reference preprocessing (fixtures computed with proxy statistics).
//! Needs SPOOFWATCH_AVGPS_DIR and SPOOFWATCH_REFERENCE_DIR (skipped when either is unset).
//!
//! Segment starts and ν must match exactly; δ_t, r, η, η̇, η̈, e, q, a, ã within 1 % relative or
//! 1e-6 absolute. The fixtures round to 10 significant digits.

use std::collections::HashMap;
use std::path::Path;

use spoofwatch_core::data::read_path;
use spoofwatch_core::evidence::{
    Evidence, EvidenceParams, SIGMA_EPSILON, build_track, fit_normal_stats,
};
use spoofwatch_core::geo::Projection;
use spoofwatch_core::testdata::{AVGPS_DIR_VAR, REFERENCE_DIR_VAR, data_file};

const REL_TOL: f64 = 0.01;
const ABS_TOL: f64 = 1e-6;

/// One fixture row, by column name.
struct FixtureRow(HashMap<String, String>);

impl FixtureRow {
    fn text(&self, column: &str) -> &str {
        self.0
            .get(column)
            .unwrap_or_else(|| panic!("fixture has no column {column}"))
    }

    /// Empty cells are NaN.
    fn number(&self, column: &str) -> f64 {
        let text = self.text(column);
        if text.is_empty() {
            f64::NAN
        } else {
            text.parse()
                .unwrap_or_else(|_| panic!("{column}: not a number: {text}"))
        }
    }
}

fn read_fixture(path: &Path) -> Vec<FixtureRow> {
    let mut reader = csv::Reader::from_path(path).expect("fixture opens");
    let header = reader.headers().expect("fixture header").clone();
    reader
        .records()
        .map(|record| {
            let record = record.expect("fixture row");
            FixtureRow(
                header
                    .iter()
                    .zip(record.iter())
                    .map(|(h, v)| (h.to_string(), v.to_string()))
                    .collect(),
            )
        })
        .collect()
}

/// Σ̂ and μ_e of `proxy_stats.json`. `cov_regularized` already includes ε; the builder adds ε itself,
/// so ε is taken off here to invert exactly the reference's matrix.
fn proxy_params(reference_dir: &Path) -> EvidenceParams {
    let text = std::fs::read_to_string(reference_dir.join("proxy_stats.json")).expect("stats");
    let json: serde_json::Value = serde_json::from_str(&text).expect("stats json");
    let cov = &json["cov_regularized"];
    let at = |i: usize, j: usize| cov[i][j].as_f64().expect("cov entry");
    let sigma_hat = [
        [at(0, 0) - SIGMA_EPSILON, at(0, 1)],
        [at(1, 0), at(1, 1) - SIGMA_EPSILON],
    ];
    let mu_e = json["train_normal_energy_median_mu_e"]
        .as_f64()
        .expect("mu_e");
    EvidenceParams::new(sigma_hat, mu_e, Projection::Equirectangular).expect("valid proxy stats")
}

/// Largest deviations seen per quantity, for the report.
#[derive(Default)]
struct Deviations {
    worst: Vec<(&'static str, f64, f64)>, // (name, max abs, max rel)
    failures: Vec<String>,
}

impl Deviations {
    fn check(&mut self, name: &'static str, row: usize, ours: f64, theirs: f64) {
        let abs = (ours - theirs).abs();
        let rel = if theirs == 0.0 {
            0.0
        } else {
            abs / theirs.abs()
        };
        let ok = abs <= ABS_TOL || rel <= REL_TOL;
        if !ok && self.failures.len() < 20 {
            self.failures
                .push(format!("row {row}: {name} ours {ours} reference {theirs}"));
        }
        match self.worst.iter_mut().find(|w| w.0 == name) {
            Some(w) => {
                w.1 = w.1.max(abs);
                if abs > ABS_TOL {
                    w.2 = w.2.max(rel);
                }
            }
            None => self
                .worst
                .push((name, abs, if abs > ABS_TOL { rel } else { 0.0 })),
        }
    }
}

/// Compares every row; returns the fixture's ν per row.
fn compare(dataset: &str, fixture_name: &str) -> Option<Vec<bool>> {
    let data = data_file(AVGPS_DIR_VAR, dataset)?;
    let fixture = data_file(REFERENCE_DIR_VAR, fixture_name)?;
    let reference_dir = fixture.parent().expect("fixture directory");
    let params = proxy_params(reference_dir);
    let track = read_path(&data).expect("dataset reads").tracks.remove(0);
    let evidence: Vec<Evidence> = build_track(&params, &track.records);
    let rows = read_fixture(&fixture);
    assert_eq!(rows.len(), evidence.len(), "{fixture_name}: row count");

    let mut dev = Deviations::default();
    let mut exact_failures = Vec::new();
    for (i, (row, e)) in rows.iter().zip(&evidence).enumerate() {
        assert_eq!(row.number("raw_row_index") as usize, i, "fixture order");
        let start = row.text("within_segment_index") == "0";
        let segment: u32 = row
            .text("segment_id")
            .rsplit('_')
            .next()
            .and_then(|n| n.parse().ok())
            .expect("segment number");
        let valid = row.text("nu") == "1";
        if start != e.trajectory_start || segment != e.trajectory || valid != e.valid {
            exact_failures.push(format!(
                "row {i}: start/segment/ν ours {}/{}/{} reference {start}/{segment}/{valid}",
                e.trajectory_start, e.trajectory, e.valid
            ));
        }
        let delta = row.number("delta_t_seconds");
        if start {
            assert!(e.delta_t.is_nan(), "row {i}: δ is NaN at a start");
        } else if delta.is_nan() {
            // The reference leaves δ undefined where neither clock nor Run Time advanced; our
            // cumulative timestamps then give δ = 0 (also ν = 0).
            assert!(e.delta_t == 0.0 && !e.valid, "row {i}: δ {}", e.delta_t);
        } else {
            dev.check("delta_t", i, e.delta_t, delta);
        }
        if valid {
            dev.check("r_east", i, e.residual[0], row.number("residual_east_m"));
            dev.check("r_north", i, e.residual[1], row.number("residual_north_m"));
        }
        let pairs = [
            ("eta_east", e.eta[0], "xi_eta_east"),
            ("eta_north", e.eta[1], "xi_eta_north"),
            ("eta_dot_east", e.eta_dot[0], "xi_eta_dot_east"),
            ("eta_dot_north", e.eta_dot[1], "xi_eta_dot_north"),
            ("eta_ddot_east", e.eta_ddot[0], "xi_eta_ddot_east"),
            ("eta_ddot_north", e.eta_ddot[1], "xi_eta_ddot_north"),
            ("energy", e.energy, "xi_residual_energy"),
            ("q", e.q, "xi_q"),
            ("accum", e.accum, "xi_accum_raw"),
            ("accum_log", e.accum_log, "xi_accum_log"),
        ];
        for (name, ours, column) in pairs {
            dev.check(name, i, ours, row.number(column));
        }
        assert_eq!(row.number("xi_nu"), e.raw_features()[8], "row {i}: ξ_ν");
    }
    eprintln!("{fixture_name}: max deviations (abs, rel where abs > 1e-6):");
    for (name, abs, rel) in &dev.worst {
        eprintln!("  {name:>15}: {abs:.3e} {rel:.3e}");
    }
    assert!(exact_failures.is_empty(), "{exact_failures:#?}");
    assert!(dev.failures.is_empty(), "{:#?}", dev.failures);
    Some(rows.iter().map(|r| r.text("nu") == "1").collect())
}

#[test]
fn dataset2_matches_the_reference_rows() {
    compare("AV-GPS-Dataset-2.csv", "dataset2_legacy_xi_proxystats.csv");
}

#[test]
fn dataset3_matches_the_corrected_reference_rows() {
    compare(
        "AV-GPS-Dataset-3.csv",
        "dataset3_corrected_xi_proxystats.csv",
    );
}

#[test]
fn dataset3_legacy_differs_only_by_the_label_leak_at_row_323() {
    let Some(corrected) = compare(
        "AV-GPS-Dataset-3.csv",
        "dataset3_corrected_xi_proxystats.csv",
    ) else {
        return;
    };
    let Some(legacy_path) = data_file(REFERENCE_DIR_VAR, "dataset3_legacy_xi_proxystats.csv")
    else {
        return;
    };
    let legacy: Vec<bool> = read_fixture(&legacy_path)
        .iter()
        .map(|r| r.text("nu") == "1")
        .collect();
    let differing: Vec<usize> = (0..legacy.len())
        .filter(|&i| legacy[i] != corrected[i])
        .collect();
    assert_eq!(differing, [323], "we implement label-free ν (SPEC §1)");
}

#[test]
fn proxy_inverse_square_root_matches_the_reference() {
    let Some(dir) = spoofwatch_core::testdata::data_dir(REFERENCE_DIR_VAR) else {
        return;
    };
    let params = proxy_params(&dir);
    let ours =
        spoofwatch_core::evidence::linalg::inverse_sqrt_symmetric(&params.regularised_sigma());
    let text = std::fs::read_to_string(dir.join("proxy_stats.json")).expect("stats");
    let json: serde_json::Value = serde_json::from_str(&text).expect("stats json");
    for i in 0..2 {
        for j in 0..2 {
            let theirs = json["residual_inverse_sqrt_covariance"][i][j]
                .as_f64()
                .expect("entry");
            assert!((ours[i][j] - theirs).abs() < 1e-9, "{ours:?} vs {theirs}");
        }
    }
}

#[test]
fn dataset2_normal_rows_reproduce_the_proxy_statistics() {
    // proxy_stats.json was estimated from Dataset-2's normal ν = 1 residuals (equirectangular).
    let Some(data) = data_file(AVGPS_DIR_VAR, "AV-GPS-Dataset-2.csv") else {
        return;
    };
    let Some(dir) = spoofwatch_core::testdata::data_dir(REFERENCE_DIR_VAR) else {
        return;
    };
    let proxy = proxy_params(&dir);
    let tracks = read_path(&data).expect("dataset reads").tracks;
    let stats = fit_normal_stats(&tracks, Projection::Equirectangular).expect("enough rows");
    assert_eq!(stats.rows, 5180);
    for i in 0..2 {
        for j in 0..2 {
            let (ours, theirs) = (stats.sigma_hat[i][j], proxy.sigma_hat[i][j]);
            assert!(
                (ours - theirs).abs() < 1e-8 * theirs.abs(),
                "Σ̂ {ours} vs {theirs}"
            );
        }
    }
    assert!(
        (stats.mu_e - proxy.mu_e).abs() < 1e-9,
        "μ_e {} vs {}",
        stats.mu_e,
        proxy.mu_e
    );
    let wgs84 = fit_normal_stats(&tracks, Projection::Wgs84Local).expect("enough rows");
    eprintln!("D2 normal stats, equirectangular: {stats:?}");
    eprintln!("D2 normal stats, WGS-84 local:    {wgs84:?}");
}
