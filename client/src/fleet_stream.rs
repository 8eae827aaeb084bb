//! One `StreamDetectFleet` call seen from the client (a gateway that feeds many vehicles through one
//! stream): send a message with the next samples of several vehicles, receive its reply in order,
//! then half-close and drain. The protocol rules (one reply per message, in order, one entry per
//! vehicle with the same id, one detection per sample unless the vehicle was refused) are checked
//! here, once, for every caller (`spoofwatch bench`, the black-box tests).

use spoofwatch_proto::v1;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Streaming;

use crate::connection::Connection;
use crate::error::{ClientError, reply, rpc};

/// Messages buffered between the caller and the HTTP/2 stream.
const REQUEST_BUFFER: usize = 16;

/// An open `StreamDetectFleet` call.
#[derive(Debug)]
pub struct FleetDetectStream {
    requests: mpsc::Sender<v1::FleetBatch>,
    replies: Streaming<v1::FleetDetections>,
}

const CONTEXT: &str = "streaming fleet detections";

impl FleetDetectStream {
    /// Opens the call.
    pub async fn open(connection: &Connection) -> Result<Self, ClientError> {
        let (requests, outbound) = mpsc::channel(REQUEST_BUFFER);
        let mut detection = connection.detection();
        let opening = detection.stream_detect_fleet(ReceiverStream::new(outbound));
        let replies = reply(CONTEXT, opening).await?;
        Ok(Self { requests, replies })
    }

    /// Sends any message as it is (its reply comes from [`FleetDetectStream::recv`]).
    pub async fn send(&self, batch: v1::FleetBatch) -> Result<(), ClientError> {
        self.requests
            .send(batch)
            .await
            .map_err(|_| ClientError::Protocol(format!("{CONTEXT}: the stream is closed")))
    }

    /// The next reply as it is: `Ok(None)` when the call ended with OK.
    pub async fn recv(&mut self) -> Result<Option<v1::FleetDetections>, ClientError> {
        self.replies.message().await.map_err(rpc(CONTEXT))
    }

    /// Sends the next samples of `vehicles` as message `seq` and waits for its reply, checked
    /// against the request. Vehicles refused one by one come back with their `error` set; a
    /// message refused whole is an error.
    pub async fn detect(
        &mut self,
        seq: u64,
        vehicles: Vec<v1::VehicleSamples>,
    ) -> Result<Vec<v1::VehicleDetections>, ClientError> {
        let expected: Vec<(String, usize)> = vehicles
            .iter()
            .map(|v| (v.vehicle_id.clone(), v.samples.len()))
            .collect();
        self.send(v1::FleetBatch { seq, vehicles }).await?;
        let Some(reply) = self.recv().await? else {
            return Err(ClientError::Protocol(format!(
                "{CONTEXT}: the stream ended before message {seq} was answered"
            )));
        };
        if let Some(status) = &reply.error {
            return Err(ClientError::Protocol(format!(
                "{CONTEXT}: message {seq} was refused: {}",
                crate::error::describe_rpc_status(status)
            )));
        }
        check_reply(seq, &expected, &reply)?;
        Ok(reply.vehicles)
    }

    /// Half-closes the call and reads it to its end, which must be OK with nothing more.
    pub async fn finish(mut self) -> Result<(), ClientError> {
        drop(std::mem::replace(&mut self.requests, mpsc::channel(1).0));
        match self.recv().await? {
            None => Ok(()),
            Some(reply) => Err(ClientError::Protocol(format!(
                "{CONTEXT}: unexpected reply after the last message: seq {}",
                reply.seq
            ))),
        }
    }
}

/// A reply must answer message `seq` with one entry per vehicle sent (same ids, same order) and one
/// detection per sample for every vehicle that was not refused.
fn check_reply(
    seq: u64,
    expected: &[(String, usize)],
    reply: &v1::FleetDetections,
) -> Result<(), ClientError> {
    let mismatch = |what: String| {
        Err(ClientError::Protocol(format!(
            "{CONTEXT}: reply to message {seq}: {what}"
        )))
    };
    if reply.seq != seq {
        return mismatch(format!("it answers message {}", reply.seq));
    }
    if reply.vehicles.len() != expected.len() {
        return mismatch(format!(
            "{} vehicles for {} sent",
            reply.vehicles.len(),
            expected.len()
        ));
    }
    for (got, (id, samples)) in reply.vehicles.iter().zip(expected) {
        if &got.vehicle_id != id {
            return mismatch(format!(
                "vehicle {:?} where {id:?} was sent",
                got.vehicle_id
            ));
        }
        if got.error.is_none() && got.detections.len() != *samples {
            return mismatch(format!(
                "{} detections for {samples} samples of {id:?}",
                got.detections.len()
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn answer(seq: u64, vehicles: &[(&str, usize)]) -> v1::FleetDetections {
        v1::FleetDetections {
            seq,
            vehicles: vehicles
                .iter()
                .map(|&(id, n)| v1::VehicleDetections {
                    vehicle_id: id.to_string(),
                    detections: vec![v1::Detection::default(); n],
                    ..v1::VehicleDetections::default()
                })
                .collect(),
            error: None,
        }
    }

    #[test]
    fn a_reply_must_answer_the_message_vehicle_by_vehicle() {
        let sent = vec![("a".to_string(), 1), ("b".to_string(), 2)];
        assert!(check_reply(7, &sent, &answer(7, &[("a", 1), ("b", 2)])).is_ok());
        for (case, reply) in [
            ("another message", answer(6, &[("a", 1), ("b", 2)])),
            ("a vehicle missing", answer(7, &[("a", 1)])),
            ("vehicles swapped", answer(7, &[("b", 2), ("a", 1)])),
            ("a detection missing", answer(7, &[("a", 1), ("b", 1)])),
        ] {
            assert!(check_reply(7, &sent, &reply).is_err(), "{case}");
        }
        // A refused vehicle carries its status instead of detections.
        let mut refused = answer(7, &[("a", 1), ("b", 0)]);
        refused.vehicles[1].error = Some(tonic_types::Status::default());
        assert!(check_reply(7, &sent, &refused).is_ok());
    }
}
