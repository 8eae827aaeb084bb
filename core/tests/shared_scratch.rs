//! Detectors share one step scratch per thread: detectors of different models stepped alternately
//! on one thread give exactly what each gives alone.

use std::sync::Arc;

use spoofwatch_core::detector::Detector;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::scenario::{DriveSpec, simulate_drive};

fn model(bytes: &[u8]) -> Arc<ModelArtifact> {
    Arc::new(ModelArtifact::from_slice(bytes).expect("a bundled model loads"))
}

#[test]
fn interleaved_detectors_of_different_models_match_their_solo_runs() {
    // v2 (14 persistence inputs) and paper (2): the shared buffers change shape at every step.
    let models = [
        model(include_bytes!("../../models/default.json")),
        model(include_bytes!("../../models/paper.json")),
    ];
    let spec = DriveSpec {
        duration_s: 300.0,
        ..DriveSpec::default()
    };
    let track = simulate_drive(&spec, "vehicle").expect("a drive");
    let bits = |detector: &mut Detector, sample| detector.step(sample, false).probability.to_bits();
    let solo: Vec<Vec<u64>> = models
        .iter()
        .map(|m| {
            let mut detector = Detector::new(Arc::clone(m));
            track
                .records
                .iter()
                .map(|r| bits(&mut detector, &r.sample))
                .collect()
        })
        .collect();
    let mut detectors: Vec<Detector> = models
        .iter()
        .map(|m| Detector::new(Arc::clone(m)))
        .collect();
    let mut interleaved = vec![Vec::new(); models.len()];
    for record in &track.records {
        for (k, detector) in detectors.iter_mut().enumerate() {
            interleaved[k].push(bits(detector, &record.sample));
        }
    }
    assert_eq!(interleaved, solo);
}
