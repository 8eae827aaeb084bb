//! Every baseline on Dataset-2's chronological split: fitted under HO-LLN's protocol, calibrated on
//! validation, deterministic per seed, and the GPS-IDS row reading the documented raw columns.
//! Skipped (with a line on stderr) when SPOOFWATCH_AVGPS_DIR is unset.

use spoofwatch_baselines::{Baseline, Dataset, GPS_IDS_COLUMNS, Protocol, fit};
use spoofwatch_core::alarm::OperatingPointRule;
use spoofwatch_core::data::{read_numeric_columns, read_path};
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::metrics::EventRules;
use spoofwatch_core::testdata::{AVGPS_DIR_VAR, data_file};
use spoofwatch_core::train::data::split_chronologically;
use spoofwatch_core::train::spec::SplitFractions;

#[test]
fn every_baseline_fits_and_the_same_seed_gives_the_same_scores() {
    let Some(path) = data_file(AVGPS_DIR_VAR, "AV-GPS-Dataset-2.csv") else {
        return;
    };
    let tracks = read_path(&path).expect("Dataset-2 reads").tracks;
    let file = std::fs::File::open(&path).expect("Dataset-2 opens");
    let columns =
        read_numeric_columns(file, "AV-GPS-Dataset-2.csv", &GPS_IDS_COLUMNS).expect("columns");
    let split = split_chronologically(&tracks, SplitFractions::default());
    let data = |tracks| Dataset {
        tracks,
        columns: Some(&columns),
    };
    let protocol = Protocol::new(7, 4, OperatingPointRule::BestValidationF1);
    let mut baselines = Baseline::on_evidence(FeatureSchema::Paper).to_vec();
    baselines.push(Baseline::GPS_IDS);
    for baseline in baselines {
        let started = std::time::Instant::now();
        let fitted = fit(
            baseline,
            data(&split.train),
            data(&split.validation),
            &protocol,
        )
        .unwrap_or_else(|e| panic!("{}: {e}", baseline.name()));
        let test = fitted.score(data(&split.test)).expect("scores");
        let metrics = test.metrics(EventRules::Spec);
        eprintln!(
            "{}: {:.1} s, θ {} N_p {}, kept {}, D2 test AUROC {:?} F1 {:.3}",
            baseline.name(),
            started.elapsed().as_secs_f64(),
            fitted.operating_point.theta,
            fitted.operating_point.n_p,
            fitted.best_epoch,
            metrics.auroc,
            metrics.f1
        );
        assert!(
            !fitted.history.is_empty(),
            "{}: a training curve",
            baseline.name()
        );
        assert_eq!(
            test.rows.len(),
            split.test.iter().map(|t| t.records.len()).sum::<usize>()
        );
        assert!(test.rows.iter().all(|r| (0.0..=1.0).contains(&r.score)));
        let again = fit(
            baseline,
            data(&split.train),
            data(&split.validation),
            &protocol,
        )
        .expect("refits");
        assert_eq!(
            again.score(data(&split.test)).expect("scores"),
            test,
            "{}: same seed, same scores and alarms",
            baseline.name()
        );
    }
}
