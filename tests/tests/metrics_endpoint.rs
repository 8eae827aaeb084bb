//! Prometheus metrics after real traffic: a server with a metrics listener replays an attacked
//! drive on StreamDetect (it alarms), a Detect call and a fleet message, has batches refused for
//! several reasons, and is then scraped over HTTP. The scrape is parsed with a real exposition
//! parser (`prometheus-parse`) and every count is checked against what was sent; `promtool check
//! metrics` lints it when installed (CI sets SPOOFWATCH_REQUIRE_PROMTOOL so it must be).
//!
//! One server and one test in this file on purpose: the metrics recorder is per process, so a
//! second server here would add its traffic to the counts.

use std::io::Write;
use std::net::SocketAddr;
use std::process::{Command, Stdio};
use std::time::Duration;

use http_body_util::{BodyExt, Empty};
use hyper::body::Bytes;
use hyper_util::client::legacy::Client;
use hyper_util::rt::TokioExecutor;
use prometheus_parse::{Scrape, Value};
use spoofwatch_client::FleetDetectStream;
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    REPLY_TIMEOUT, artifact_with_critical_level, attacked_drive, expect_item_error, import_model,
    normal_drive, start_server, start_stream, track_samples,
};
use tonic::Code;

/// The alarm transitions detections show, by severity (index 0 warning, 1 critical): onsets by the
/// severity they opened with, escalations of open warnings, ends by the severity they ended with.
#[derive(Debug, Default)]
struct Transitions {
    onsets: [usize; 2],
    escalations: usize,
    ends: [usize; 2],
    /// The open alarm's severity index (after its onset or escalation).
    open: usize,
}

impl Transitions {
    fn add(&mut self, detections: &[v1::Detection]) {
        let critical = v1::AlarmSeverity::Critical as i32;
        for d in detections {
            if d.alarm_end {
                self.ends[self.open] += 1;
            }
            let index = usize::from(d.severity == critical);
            if d.alarm_onset {
                self.onsets[index] += 1;
            } else if d.alarm_escalated {
                self.escalations += 1;
            }
            if d.alarm {
                self.open = index;
            }
        }
    }

    /// Events emitted: onsets, escalations and ends.
    fn events(&self) -> usize {
        self.onsets.iter().chain(&self.ends).sum::<usize>() + self.escalations
    }
}

/// GETs `/metrics` and returns the exposition text (checking the status and the content type).
async fn scrape_text(addr: SocketAddr) -> String {
    let client = Client::builder(TokioExecutor::new()).build_http::<Empty<Bytes>>();
    let uri: hyper::Uri = format!("http://{addr}/metrics")
        .parse()
        .expect("a valid URI");
    let response = tokio::time::timeout(REPLY_TIMEOUT, client.get(uri))
        .await
        .expect("the metrics endpoint answers in time")
        .expect("the metrics endpoint answers");
    assert_eq!(response.status(), hyper::StatusCode::OK);
    assert_eq!(
        response.headers()[hyper::header::CONTENT_TYPE],
        "text/plain; version=0.0.4; charset=utf-8"
    );
    let body = response
        .into_body()
        .collect()
        .await
        .expect("the whole body arrives")
        .to_bytes();
    String::from_utf8(body.to_vec()).expect("the exposition is UTF-8")
}

fn parse(text: &str) -> Scrape {
    Scrape::parse(text.lines().map(|line| Ok(line.to_string()))).expect("a valid exposition")
}

/// The one sample of `name` with exactly `labels`.
fn sample<'a>(
    scrape: &'a Scrape,
    name: &str,
    labels: &[(&str, &str)],
) -> &'a prometheus_parse::Sample {
    let matching: Vec<_> = scrape
        .samples
        .iter()
        .filter(|s| {
            s.metric == name
                && labels.iter().all(|(k, v)| s.labels.get(k) == Some(*v))
                // `le` belongs to a histogram's buckets, not to its labels.
                && s.labels.keys().filter(|k| *k != "le").count() == labels.len()
        })
        .collect();
    assert_eq!(matching.len(), 1, "one sample of {name}{labels:?}");
    matching[0]
}

/// The value of a counter or gauge.
fn value(scrape: &Scrape, name: &str, labels: &[(&str, &str)]) -> f64 {
    match sample(scrape, name, labels).value {
        Value::Counter(v) | Value::Gauge(v) | Value::Untyped(v) => v,
        ref other => panic!("{name}{labels:?} is not a single value: {other:?}"),
    }
}

/// The number of observations of a histogram: its +Inf bucket, which must equal its `_count`.
fn histogram_count(scrape: &Scrape, name: &str, labels: &[(&str, &str)]) -> f64 {
    let Value::Histogram(buckets) = &sample(scrape, name, labels).value else {
        panic!("{name} is not a histogram");
    };
    let last = buckets.last().expect("a histogram has buckets");
    assert!(last.less_than.is_infinite(), "the last bucket is +Inf");
    assert!(
        buckets.windows(2).all(|w| w[0].count <= w[1].count),
        "buckets are cumulative"
    );
    assert_eq!(value(scrape, &format!("{name}_count"), labels), last.count);
    last.count
}

/// Lints the exposition with `promtool check metrics`; skipped (with a message) when promtool is not
/// installed, unless SPOOFWATCH_REQUIRE_PROMTOOL is set (CI).
fn promtool_check(text: &str) {
    let child = Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn();
    let mut child = match child {
        Ok(child) => child,
        Err(error) if std::env::var_os("SPOOFWATCH_REQUIRE_PROMTOOL").is_none() => {
            eprintln!(
                "SKIPPED promtool check metrics: promtool is not runnable ({error}); install the \
                 Debian package `prometheus` to lint the exposition"
            );
            return;
        }
        Err(error) => panic!("SPOOFWATCH_REQUIRE_PROMTOOL is set but promtool cannot run: {error}"),
    };
    child
        .stdin
        .take()
        .expect("stdin is piped")
        .write_all(text.as_bytes())
        .expect("promtool reads the exposition");
    let output = child.wait_with_output().expect("promtool finishes");
    let report = format!(
        "{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(
        output.status.success() && report.trim().is_empty(),
        "promtool check metrics found problems:\n{report}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scrape_after_a_replay_counts_what_was_sent() {
    let (_dir, server, mut clients) = start_server(|config| {
        config.metrics_listen = Some(SocketAddr::from(([127, 0, 0, 1], 0)));
    })
    .await;
    let metrics = server.metrics_addr().expect("a metrics listener");

    // StreamDetect: a drive whose fix freezes for 60 s alarms; 20 samples per batch.
    let frozen = attacked_drive(
        "m-frozen",
        240.0,
        21,
        AttackKind::FrozenPosition,
        100.0,
        60.0,
    );
    let samples = track_samples(&frozen);
    let (mut stream, _) = start_stream(&clients, "m-frozen", "").await;
    let (mut batches, mut alarming, mut transitions) = (0, 0, Transitions::default());
    for (seq, batch) in samples.chunks(20).enumerate() {
        let detections = stream
            .detect(seq as u64 + 1, batch.to_vec())
            .await
            .expect("one detection per sample, for this batch");
        batches += 1;
        alarming += detections.iter().filter(|d| d.alarm).count();
        transitions.add(&detections);
    }
    // The bundled model pages a fix frozen on a moving vehicle at once: the alarm may open critical.
    assert!(
        transitions.onsets.iter().sum::<usize>() >= 1,
        "the frozen fix raises an alarm"
    );
    let mut streamed = samples.len();

    // Refused on the same stream: a NaN latitude (5 samples), then an empty batch.
    let mut bad = samples[samples.len() - 5..].to_vec();
    bad[1].latitude_deg = f64::NAN;
    let next = batches as u64 + 1;
    let refused = expect_item_error(&mut stream, next, bad).await;
    assert_eq!(refused.code, Code::InvalidArgument as i32);
    let refused = expect_item_error(&mut stream, next + 1, Vec::new()).await;
    assert_eq!(refused.code, Code::InvalidArgument as i32);

    // While the stream is open its session counts as connected.
    let live = parse(&scrape_text(metrics).await);
    assert_eq!(value(&live, "spoofwatch_sessions_open", &[]), 1.0);
    assert_eq!(value(&live, "spoofwatch_sessions_connected", &[]), 1.0);
    stream.finish().await.expect("the stream ends with OK");

    // StreamDetect on a model with a critical level: a 500 m jump pages, and a 2 m/s drift opens
    // as a warning and escalates.
    let paging = import_model(&mut clients, artifact_with_critical_level(), "paging").await;
    let attacks = [
        AttackKind::Jump { offset_m: 500.0 },
        AttackKind::RampDrift { velocity_mps: 2.0 },
    ];
    for (k, attack) in attacks.into_iter().enumerate() {
        let vehicle = format!("m-paging-{k}");
        let track = attacked_drive(&vehicle, 300.0, 41, attack, 100.0, 120.0);
        let samples = track_samples(&track);
        let (mut stream, _) = start_stream(&clients, &vehicle, &paging.name).await;
        for (seq, batch) in samples.chunks(50).enumerate() {
            let detections = stream
                .detect(seq as u64 + 1, batch.to_vec())
                .await
                .expect("one detection per sample, for this batch");
            batches += 1;
            alarming += detections.iter().filter(|d| d.alarm).count();
            transitions.add(&detections);
        }
        streamed += samples.len();
        stream.finish().await.expect("the stream ends with OK");
    }
    assert!(
        transitions.onsets[1] >= 1 && transitions.escalations >= 1,
        "{transitions:?}"
    );

    // Detect: one stateless call, one for a model that does not exist.
    let normal = track_samples(&normal_drive("m-detect", 29.0, 5));
    let detected = clients
        .detection
        .detect(v1::DetectRequest {
            samples: normal.clone(),
            ..v1::DetectRequest::default()
        })
        .await
        .expect("Detect works")
        .into_inner();
    assert_eq!(detected.detections.len(), normal.len());
    let missing = clients
        .detection
        .detect(v1::DetectRequest {
            samples: normal[..7].to_vec(),
            model: "models/no-such-model".into(),
            ..v1::DetectRequest::default()
        })
        .await
        .expect_err("an unknown model is refused");
    assert_eq!(missing.code(), Code::NotFound);

    // StreamDetectFleet: one message, one vehicle scored and one refused for its id.
    let entry = |vehicle_id: &str, samples: Vec<v1::Sample>| v1::VehicleSamples {
        vehicle_id: vehicle_id.into(),
        model: String::new(),
        samples,
        reset: false,
    };
    let mut gateway = FleetDetectStream::open(&clients.connection)
        .await
        .expect("the call is accepted");
    let vehicles = gateway
        .detect(
            1,
            vec![
                entry("m-fleet", normal[..10].to_vec()),
                entry("not a valid id", normal[..4].to_vec()),
            ],
        )
        .await
        .expect("the message is answered");
    assert!(vehicles[0].error.is_none() && vehicles[1].error.is_some());
    gateway
        .finish()
        .await
        .expect("the fleet stream ends with OK");

    // The alarm events reach the database in the background: wait (bounded) until they are stored.
    let events = transitions.events() as f64;
    let mut scrape = parse(&scrape_text(metrics).await);
    for _ in 0..300 {
        if value(&scrape, "spoofwatch_alarm_outbox_stored_writes_total", &[]) >= events {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
        scrape = parse(&scrape_text(metrics).await);
    }
    let text = scrape_text(metrics).await;
    let scrape = parse(&text);
    let v = |name: &str, labels: &[(&str, &str)]| value(&scrape, name, labels);

    let stream_rpc = [("rpc", "StreamDetect")];
    assert_eq!(
        v("spoofwatch_detection_samples_total", &stream_rpc),
        streamed as f64
    );
    assert_eq!(
        v("spoofwatch_detection_batches_total", &stream_rpc),
        batches as f64
    );
    assert_eq!(
        v("spoofwatch_detection_alarming_samples_total", &stream_rpc),
        alarming as f64
    );
    assert_eq!(
        histogram_count(
            &scrape,
            "spoofwatch_detection_batch_duration_seconds",
            &stream_rpc
        ),
        batches as f64,
        "one latency observation per scored batch"
    );
    let refused = |rpc: &str, reason: &str| {
        (
            v(
                "spoofwatch_detection_rejected_batches_total",
                &[("rpc", rpc), ("reason", reason)],
            ),
            v(
                "spoofwatch_detection_rejected_samples_total",
                &[("rpc", rpc), ("reason", reason)],
            ),
        )
    };
    assert_eq!(refused("StreamDetect", "invalid_sample"), (1.0, 5.0));
    assert_eq!(refused("StreamDetect", "batch_size"), (1.0, 0.0));
    assert_eq!(refused("StreamDetect", "invalid_request"), (0.0, 0.0));

    let detect_rpc = [("rpc", "Detect")];
    assert_eq!(v("spoofwatch_detection_batches_total", &detect_rpc), 1.0);
    assert_eq!(
        v("spoofwatch_detection_samples_total", &detect_rpc),
        normal.len() as f64
    );
    assert_eq!(refused("Detect", "model_not_found"), (1.0, 7.0));
    assert_eq!(
        histogram_count(
            &scrape,
            "spoofwatch_detection_batch_duration_seconds",
            &detect_rpc
        ),
        1.0
    );

    let fleet_rpc = [("rpc", "StreamDetectFleet")];
    assert_eq!(v("spoofwatch_detection_batches_total", &fleet_rpc), 1.0);
    assert_eq!(v("spoofwatch_detection_samples_total", &fleet_rpc), 10.0);
    assert_eq!(refused("StreamDetectFleet", "invalid_request"), (1.0, 4.0));

    let t = &transitions;
    for (index, severity) in ["warning", "critical"].into_iter().enumerate() {
        let labels = [("severity", severity)];
        assert_eq!(
            v("spoofwatch_alarm_onsets_total", &labels),
            t.onsets[index] as f64
        );
        assert_eq!(
            v("spoofwatch_alarm_ends_total", &labels),
            t.ends[index] as f64
        );
    }
    let critical = [("severity", "critical")];
    assert_eq!(
        v("spoofwatch_alarm_escalations_total", &critical),
        t.escalations as f64
    );
    // An escalation moves an open alarm from the warnings to the critical ones.
    let open_warnings = t.onsets[0] - t.escalations - t.ends[0];
    let open_critical = t.onsets[1] + t.escalations - t.ends[1];
    assert_eq!(
        v("spoofwatch_alarms_open", &[("severity", "warning")]),
        open_warnings as f64
    );
    assert_eq!(v("spoofwatch_alarms_open", &critical), open_critical as f64);
    assert_eq!(
        v("spoofwatch_alarm_outbox_stored_writes_total", &[]),
        events
    );
    assert_eq!(v("spoofwatch_alarm_outbox_backlog", &[]), 0.0);
    assert_eq!(v("spoofwatch_alarm_outbox_failed_batches_total", &[]), 0.0);
    assert_eq!(v("spoofwatch_alarm_outbox_dropped_onsets_total", &[]), 0.0);
    assert!(
        histogram_count(
            &scrape,
            "spoofwatch_db_operation_duration_seconds",
            &[("op", "alarm_batch_write")]
        ) >= 1.0,
        "the outbox's writes are timed"
    );

    // Sessions: the three streamed vehicles and the fleet's scored one (a stateless Detect keeps
    // none).
    assert_eq!(v("spoofwatch_sessions_open", &[]), 4.0);
    assert_eq!(v("spoofwatch_sessions_connected", &[]), 0.0);
    assert_eq!(v("spoofwatch_sessions_refused_total", &[]), 0.0);
    assert_eq!(v("spoofwatch_jobs", &[("state", "queued")]), 0.0);
    assert_eq!(v("spoofwatch_jobs", &[("state", "running")]), 0.0);
    assert_eq!(v("spoofwatch_store_faults_total", &[("kind", "full")]), 0.0);
    assert_eq!(
        v(
            "spoofwatch_build_info",
            &[("version", env!("CARGO_PKG_VERSION"))]
        ),
        1.0
    );
    assert_eq!(
        v(
            "spoofwatch_active_model_info",
            &[("model", "models/default")]
        ),
        1.0
    );

    // Every family has its HELP text.
    for s in scrape
        .samples
        .iter()
        .filter(|s| s.metric.starts_with("spoofwatch_"))
    {
        let family = s
            .metric
            .strip_suffix("_count")
            .or_else(|| s.metric.strip_suffix("_sum"))
            .filter(|base| scrape.docs.contains_key(*base))
            .unwrap_or(&s.metric);
        assert!(
            scrape.docs.get(family).is_some_and(|help| !help.is_empty()),
            "{} has no HELP text",
            s.metric
        );
    }
    promtool_check(&text);

    drop(clients);
    server.stop().await;
}
