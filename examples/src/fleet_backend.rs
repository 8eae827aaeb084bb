//! A fleet backend: opens a detection stream for one vehicle, sends its samples in batches, and
//! prints each detection as it comes back.

use std::io::Write;

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::detection_service_client::DetectionServiceClient;
use spoofwatch_proto::v1::stream_detect_request::Kind as Request;
use spoofwatch_proto::v1::stream_detect_response::Kind as Reply;

use crate::Error;

/// Samples per batch: a backend that relays a vehicle's telemetry as it arrives would send one.
const BATCH: usize = 10;

/// Streams `samples` of `vehicle_id` to the server at `url` (e.g. `http://127.0.0.1:50051`),
/// writes one line per detection to `out`, and returns the detections.
pub async fn run(
    url: &str,
    vehicle_id: &str,
    samples: Vec<v1::Sample>,
    out: &mut impl Write,
) -> Result<Vec<v1::Detection>, Error> {
    let mut client = DetectionServiceClient::connect(url.to_string()).await?;
    // The first message names the vehicle (and, left empty, takes the active model); each batch
    // after it carries an increasing seq, so that a resent batch is never scored twice.
    let start = v1::StreamDetectRequest {
        kind: Some(Request::Start(v1::SessionStart {
            vehicle_id: vehicle_id.to_string(),
            ..Default::default()
        })),
    };
    let batches = samples
        .chunks(BATCH)
        .zip(1..)
        .map(|(chunk, seq)| v1::StreamDetectRequest {
            kind: Some(Request::Batch(v1::SampleBatch {
                seq,
                samples: chunk.to_vec(),
            })),
        });
    let requests: Vec<_> = std::iter::once(start).chain(batches).collect();
    let mut replies = client
        .stream_detect(tokio_stream::iter(requests))
        .await?
        .into_inner();
    let mut detections = Vec::with_capacity(samples.len());
    while detections.len() < samples.len() {
        let Some(reply) = replies.message().await? else {
            return Err("the server ended the stream early".into());
        };
        match reply.kind {
            Some(Reply::Accepted(accepted)) => {
                writeln!(out, "{} streams to {}", accepted.vehicle_id, accepted.model)?;
            }
            Some(Reply::Detections(batch)) => {
                for d in batch.detections {
                    let alarm = if d.alarm_onset {
                        "  ALARM ON"
                    } else if d.alarm_end {
                        "  alarm off"
                    } else {
                        ""
                    };
                    writeln!(
                        out,
                        "t={:.1} s  p={:.3}{alarm}",
                        d.timestamp_s, d.probability
                    )?;
                    detections.push(d);
                }
            }
            Some(Reply::ItemError(error)) => {
                return Err(format!("batch {} refused: {:?}", error.seq, error.status).into());
            }
            None => {}
        }
    }
    Ok(detections)
}

/// `seconds` samples at 1 Hz of a vehicle driving north at 10 m/s from (`lat_deg`, `lon_deg`):
/// telemetry for trying the example without a vehicle.
pub fn straight_drive(lat_deg: f64, lon_deg: f64, seconds: u32) -> Vec<v1::Sample> {
    const METRES_PER_DEGREE: f64 = 111_320.0;
    (0..seconds)
        .map(|t| v1::Sample {
            timestamp_s: f64::from(t),
            latitude_deg: lat_deg + 10.0 * f64::from(t) / METRES_PER_DEGREE,
            longitude_deg: lon_deg,
            speed_mps: 10.0,
            heading_deg: 0.0,
            ..Default::default()
        })
        .collect()
}
