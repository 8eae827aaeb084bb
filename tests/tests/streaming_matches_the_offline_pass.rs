//! Streaming AV-GPS Dataset-3 through `StreamDetect` gives, sample by sample, what the offline
//! pass over the same artifact gives.

use std::sync::Arc;

use spoofwatch_core::data::read_path;
use spoofwatch_core::detector::run_records;
use spoofwatch_core::evaluation::evaluate_tracks;
use spoofwatch_core::metrics::EventRules;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::testdata::{AVGPS_DIR_VAR, data_file};
use spoofwatch_tests::{active_model, export_model, start_server, start_stream, track_samples};

/// Samples per streamed batch: deliberately not a divisor of anything in the data.
const BATCH: usize = 7;
/// Largest tolerated difference between streamed and offline probabilities.
const TOLERANCE: f64 = 1e-9;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streaming_dataset_3_matches_the_offline_pass_sample_by_sample() {
    let Some(path) = data_file(AVGPS_DIR_VAR, "AV-GPS-Dataset-3.csv") else {
        return;
    };
    let recording = read_path(&path).expect("Dataset-3 parses");
    assert_eq!(recording.tracks.len(), 1, "an AV-GPS file is one vehicle");
    let track = &recording.tracks[0];
    // The stream cannot carry source trajectory breaks; Dataset-3 has none beyond its first row.
    let breaks = track.records.iter().filter(|r| r.trajectory_break).count();
    assert_eq!(breaks, 1, "Dataset-3 is a single segment");

    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let model = active_model(&mut clients.models).await;
    assert_eq!(
        model.name, "models/default",
        "the bundled model is active on a fresh database"
    );
    let bytes = export_model(&mut clients.models, &model.name).await;
    let artifact = Arc::new(ModelArtifact::from_slice(&bytes).expect("the export is an artifact"));
    let offline = run_records(&artifact, &track.records);
    // evaluate_tracks runs the same pass; its rows must agree with run_records exactly (bitwise:
    // evidence fields are NaN at invalid rows, so Decision's PartialEq cannot be used).
    let evaluation = evaluate_tracks(&artifact, &recording.tracks, EventRules::Spec);
    assert_eq!(evaluation.rows.len(), offline.len());
    assert!(evaluation.rows.iter().zip(&offline).all(|(row, d)| {
        row.decision.probability.to_bits() == d.probability.to_bits()
            && row.decision.alarm == d.alarm
    }));

    let (mut stream, accepted) = start_stream(&clients, "dataset-3", "").await;
    assert_eq!(accepted.model, model.name);
    assert!(!accepted.resumed);
    let samples = track_samples(track);
    let mut streamed = Vec::with_capacity(samples.len());
    for (seq, batch) in samples.chunks(BATCH).enumerate() {
        streamed.extend(
            stream
                .detect(seq as u64 + 1, batch.to_vec())
                .await
                .expect("one detection per sample, for this batch"),
        );
    }
    drop(stream);

    assert_eq!(streamed.len(), offline.len());
    let mut alarms = 0;
    for (i, (online, expected)) in streamed.iter().zip(&offline).enumerate() {
        let line = track.records[i].line;
        assert!(
            (online.probability - expected.probability).abs() <= TOLERANCE,
            "line {line}: streamed p={} offline p={}",
            online.probability,
            expected.probability
        );
        assert_eq!(online.positive, expected.positive, "line {line}: c_t");
        assert_eq!(online.alarm, expected.alarm, "line {line}: confirmed alarm");
        assert_eq!(
            online.alarm_onset, expected.alarm_onset,
            "line {line}: onset"
        );
        assert_eq!(online.alarm_end, expected.alarm_end, "line {line}: end");
        let evidence = online.evidence.as_ref().expect("evidence");
        assert_eq!(evidence.valid, expected.evidence.valid, "line {line}: ν");
        assert_eq!(
            evidence.trajectory, expected.evidence.trajectory,
            "line {line}"
        );
        assert_eq!(online.model, model.name);
        alarms += usize::from(online.alarm);
    }
    eprintln!(
        "Dataset-3: {} samples streamed in batches of {BATCH}; {alarms} alarming samples, identical to the offline pass",
        streamed.len()
    );
    drop(clients);
    server.stop().await;
}
