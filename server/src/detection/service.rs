//! The DetectionService RPCs: the edge between the wire and the [`SessionManager`]. Validates
//! vehicle ids ([`VehicleId`]) and paging, converts wire samples to core samples and decisions back to wire
//! detections, and maps [`super::SessionError`] once (through `crate::error`); it must not hold
//! session state. Per-vehicle calls may carry the `x-vehicle-id` routing header
//! ([`crate::edge::routed_vehicle_ids`]); it must name the message's vehicle. Every vehicle a call
//! names must be one its caller may stream for ([`Caller::check_vehicle`]), and an open stream
//! ends as soon as a change of the identity files no longer admits its caller
//! ([`Caller::until_revoked`]: UNAUTHENTICATED or PERMISSION_DENIED). Each StreamDetect and
//! StreamDetectFleet call runs in its own task that reads the inbound stream and writes replies into
//! a buffer bounded in replies and bytes (`crate::replies`): a slow client fills only its own
//! buffer, which pauses only its own task. Each batch, scored or refused, is counted here for the
//! metrics (`crate::telemetry`), once per batch.

use std::pin::Pin;
use std::sync::Arc;
use std::time::Instant;

use spoofwatch_core::sample::Sample;
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::detection_service_server::DetectionService;
use spoofwatch_proto::v1::stream_detect_request::Kind as RequestKind;
use spoofwatch_proto::v1::stream_detect_response::Kind as ResponseKind;
use spoofwatch_proto::wire::ModelName;
use spoofwatch_proto::wire::VehicleId;
use spoofwatch_proto::wire::convert::{detection_to_proto, sample_from_proto, timestamp_from_ms};
use spoofwatch_proto::wire::limits::{DEFAULT_SESSION_PAGE_SIZE, MAX_SESSION_PAGE_SIZE};
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status, Streaming};

use super::error::SessionError;
use super::persistence::SNAPSHOT_WAIT;
use super::sessions::{
    Accepted, Attachment, Decisions, ForVehicle, SessionManager, SessionSummary,
};
use crate::access::Caller;
use crate::edge::{
    check_routed_vehicle, model_name, optional_model_name, optional_vehicle_id, routed_vehicle_ids,
    vehicle_id,
};
use crate::idle::{IdleClock, StreamIdle};
use crate::models::service::ModelDeletion;
use crate::replies::{self, ReplySender, ReplyStream};
use crate::status::{invalid_field, shutting_down, to_rpc_status};
use crate::telemetry::{self, Rpc};

type Reply = Result<v1::StreamDetectResponse, Status>;

/// The DetectionService implementation.
#[derive(Debug, Clone)]
pub struct DetectionApi {
    pub sessions: Arc<SessionManager>,
    /// Cancelled when the server starts draining.
    pub shutdown: CancellationToken,
    /// How long a stream may send nothing.
    pub stream_idle: StreamIdle,
}

fn reply(kind: ResponseKind) -> Reply {
    Ok(v1::StreamDetectResponse { kind: Some(kind) })
}

/// Wire samples as core samples (their values are validated later, against the session). A
/// receiver state number this build does not know refuses the batch, every such field named
/// under `field` (e.g. `batch.samples[3].spoofing_state`).
fn samples_from_proto(samples: &[v1::Sample], field: &str) -> Result<Vec<Sample>, SessionError> {
    let mut violations = Vec::new();
    let converted = samples
        .iter()
        .enumerate()
        .filter_map(|(i, s)| match sample_from_proto(s) {
            Ok(sample) => Some(sample),
            Err(unknown) => {
                violations.extend(
                    unknown
                        .into_iter()
                        .map(|v| (format!("{field}[{i}].{}", v.field), v.description)),
                );
                None
            }
        })
        .collect();
    if violations.is_empty() {
        Ok(converted)
    } else {
        Err(SessionError::InvalidBatch(violations))
    }
}

/// A processed batch on the wire: each decision paired with its sample's time.
fn detections_to_proto(samples: &[Sample], batch: &Decisions) -> Vec<v1::Detection> {
    let model = batch.model.to_string();
    samples
        .iter()
        .zip(&batch.decisions)
        .map(|(s, d)| detection_to_proto(s.timestamp_s, d, &model))
        .collect()
}

fn session_to_proto(s: SessionSummary) -> v1::Session {
    v1::Session {
        vehicle_id: s.vehicle_id.into_string(),
        model: s.model.to_string(),
        connected: s.connected,
        samples: s.samples,
        trajectories: s.trajectories,
        alarm_active: s.alarm_active,
        alarms_raised: s.alarms_raised,
        last_seq: s.last_seq,
        last_timestamp_s: s.last_timestamp_s.unwrap_or(0.0),
        last_activity: Some(timestamp_from_ms(s.last_activity_ms)),
    }
}

/// How many decisions have the alarm on (counted per batch, for metrics).
fn alarming(batch: &Decisions) -> usize {
    batch.decisions.iter().filter(|d| d.alarm).count()
}

/// A StreamDetect message that is not a batch after the start: refused without a seq.
fn stream_misuse(status: Status) -> Reply {
    telemetry::batch_rejected(Rpc::StreamDetect, &status, 0);
    item_error(0, &status)
}

fn item_error(seq: u64, status: &Status) -> Reply {
    reply(ResponseKind::ItemError(v1::ItemError {
        seq,
        status: Some(to_rpc_status(status)),
    }))
}

/// What a stream is told when its session is attached.
fn accepted_to_proto(accepted: &Accepted) -> v1::SessionAccepted {
    v1::SessionAccepted {
        vehicle_id: accepted.vehicle_id.to_string(),
        model: accepted.model.to_string(),
        resumed: accepted.resumed,
        samples_seen: accepted.samples_seen,
        last_seq: accepted.last_seq,
        replaced_model: accepted
            .replaced_model
            .as_ref()
            .map(ToString::to_string)
            .unwrap_or_default(),
        from_snapshot: accepted.from_snapshot,
        snapshot_refused: accepted
            .snapshot_refused
            .as_ref()
            .map(ToString::to_string)
            .unwrap_or_default(),
    }
}

/// Reads a StreamDetect call's first message and attaches the session it starts, for a vehicle
/// `caller` may stream for; `routed` are the call's `x-vehicle-id` header values. `Ok(None)`: the client closed the stream without
/// starting. A refusal is counted here and becomes the call's status.
async fn start_stream(
    sessions: &SessionManager,
    shutdown: &CancellationToken,
    inbound: &mut Streaming<v1::StreamDetectRequest>,
    idle: &StreamIdle,
    routed: &[String],
    caller: &mut Caller,
) -> Result<Option<Attachment>, Status> {
    let first = tokio::select! {
        _ = shutdown.cancelled() => Err(shutting_down()),
        message = idle.next(inbound) => message,
    };
    let start = match first {
        Ok(Some(v1::StreamDetectRequest {
            kind: Some(RequestKind::Start(start)),
        })) => start,
        Ok(Some(_)) => {
            let status = invalid_field(
                "start",
                "the first message of a stream must be a SessionStart",
            );
            telemetry::batch_rejected(Rpc::StreamDetect, &status, 0);
            return Err(status);
        }
        Ok(None) => return Ok(None),
        Err(status) => {
            telemetry::stream_failed(Rpc::StreamDetect, &status);
            return Err(status);
        }
    };
    let attached = async {
        let vehicle = vehicle_id("start.vehicle_id", &start.vehicle_id)?;
        // The identities may have changed while the stream waited for its start.
        caller.check_standing(Some(vehicle.as_str()))?;
        caller.check_vehicle("start.vehicle_id", vehicle.as_str())?;
        check_routed_vehicle(routed, "start.vehicle_id", vehicle.as_str())?;
        let model = optional_model_name("start.model", &start.model)?;
        Ok::<_, Status>(
            sessions
                .attach(&vehicle, &caller.grant.name, model.as_ref(), start.reset)
                .await?,
        )
    };
    attached.await.map(Some).inspect_err(|status| {
        telemetry::batch_rejected(Rpc::StreamDetect, status, 0);
    })
}

/// Why an attached stream must end before its client closes it: the server drains, a newer stream
/// took the session over, or the session's model was deleted. Made once per stream and polled
/// beside every read (with its caller's standing, [`next_request`]).
async fn forced_end(shutdown: &CancellationToken, attachment: &Attachment) -> Status {
    tokio::select! {
        biased;
        _ = shutdown.cancelled() => shutting_down(),
        _ = attachment.evicted.cancelled() => Status::aborted(
            "another stream for this vehicle took the session over",
        ),
        _ = attachment.slot.model_deleted.cancelled() => {
            SessionError::ModelDeleted(attachment.accepted.model.clone()).into()
        }
    }
}

/// The next message of an attached stream for `vehicle`. `Ok(None)`: the client closed its side
/// (the call ends with OK). `Err`: the call ends with that status ([`forced_end`] first, then a
/// change of the identity files that no longer admits `caller` for the vehicle, or the inbound
/// stream failed). A change that still admits it is judged before the message is read: the
/// message is then scored under the caller's new grant and credential.
async fn next_request(
    forced: Pin<&mut impl Future<Output = Status>>,
    (caller, vehicle): (&mut Caller, &str),
    clock: &mut IdleClock,
    inbound: &mut Streaming<v1::StreamDetectRequest>,
) -> Result<Option<v1::StreamDetectRequest>, Status> {
    tokio::select! {
        biased;
        status = forced => Err(status),
        status = caller.until_revoked(Some(vehicle)) => Err(status),
        // e.g. an oversized message or the idle timeout: the call's status.
        message = clock.next(inbound) => message.inspect_err(|status| {
            telemetry::stream_failed(Rpc::StreamDetect, status);
        }),
    }
}

/// One batch of an attached stream, run on its session: its detections or its item error.
async fn batch_reply(
    sessions: &SessionManager,
    (attachment, caller): (&Attachment, &Caller),
    batch: v1::SampleBatch,
) -> Reply {
    let started = Instant::now();
    let outcome = match samples_from_proto(&batch.samples, "batch.samples") {
        Ok(samples) => sessions
            .process(
                attachment,
                &caller.credential,
                batch.seq,
                &samples,
                "batch.samples",
            )
            .await
            .map(|decisions| (samples, decisions)),
        Err(refused) => Err(refused),
    };
    match outcome {
        Ok((_, decisions)) if decisions.duplicate => {
            telemetry::batch_duplicate(Rpc::StreamDetect);
            reply(ResponseKind::Detections(v1::DetectionBatch {
                seq: batch.seq,
                detections: Vec::new(),
                duplicate: true,
            }))
        }
        Ok((samples, decisions)) => {
            let detections = detections_to_proto(&samples, &decisions);
            telemetry::batch_scored(
                Rpc::StreamDetect,
                samples.len(),
                alarming(&decisions),
                started,
            );
            reply(ResponseKind::Detections(v1::DetectionBatch {
                seq: batch.seq,
                detections,
                duplicate: false,
            }))
        }
        Err(error) => {
            let status = error.into();
            telemetry::batch_rejected(Rpc::StreamDetect, &status, batch.samples.len());
            item_error(batch.seq, &status)
        }
    }
}

/// Drives one StreamDetect call of `caller` to its end; `routed` are the call's `x-vehicle-id`
/// header values.
async fn run_stream(
    sessions: Arc<SessionManager>,
    shutdown: CancellationToken,
    mut inbound: Streaming<v1::StreamDetectRequest>,
    tx: ReplySender<Reply>,
    idle: StreamIdle,
    (routed, mut caller): (Vec<String>, Caller),
) {
    let started = start_stream(
        &sessions,
        &shutdown,
        &mut inbound,
        &idle,
        &routed,
        &mut caller,
    );
    let attachment = match started.await {
        Ok(Some(attachment)) => attachment,
        Ok(None) => return,
        Err(status) => {
            idle.send(&tx, Err(status)).await;
            return;
        }
    };
    let vehicle = &attachment.accepted.vehicle_id;
    let accepted = accepted_to_proto(&attachment.accepted);
    tracing::debug!(vehicle = %vehicle, resumed = accepted.resumed, "stream attached");
    // The call's final status (None: OK), sent only after the session's snapshot is stored, so a
    // client that reconnects elsewhere at once finds it.
    let mut end = None;
    let forced = forced_end(&shutdown, &attachment);
    tokio::pin!(forced);
    let mut clock = idle.clock();
    if idle
        .send(&tx, reply(ResponseKind::Accepted(accepted)))
        .await
    {
        loop {
            let standing = (&mut caller, vehicle.as_str());
            let kind = match next_request(forced.as_mut(), standing, &mut clock, &mut inbound).await
            {
                Ok(Some(message)) => message.kind,
                Ok(None) => break,
                Err(status) => {
                    end = Some(status);
                    break;
                }
            };
            let outcome = match kind {
                Some(RequestKind::Batch(batch)) => {
                    batch_reply(&sessions, (&attachment, &caller), batch).await
                }
                Some(RequestKind::Start(_)) => stream_misuse(invalid_field(
                    "start",
                    "the session has already started on this stream",
                )),
                None => stream_misuse(invalid_field("kind", "empty message: send a batch")),
            };
            if !idle.send(&tx, outcome).await {
                break; // the client went away or stopped reading
            }
        }
    }
    if let Some(stored) = sessions.detach(&attachment).await
        && tokio::time::timeout(SNAPSHOT_WAIT, stored).await.is_err()
    {
        tracing::warn!(vehicle = %vehicle, "the session's snapshot is not stored yet; ending the stream anyway (it stays queued)");
    }
    if let Some(status) = end {
        idle.send(&tx, Err(status)).await;
    }
    tracing::debug!(vehicle = %vehicle, "stream detached");
}

type FleetReply = Result<v1::FleetDetections, Status>;

/// INVALID_ARGUMENT for a fleet message beyond the per-message bounds, or `None`.
fn fleet_batch_violation(batch: &v1::FleetBatch, max_samples: usize) -> Option<Status> {
    let samples: usize = batch.vehicles.iter().map(|v| v.samples.len()).sum();
    if batch.vehicles.is_empty() {
        Some(invalid_field(
            "vehicles",
            "empty: send at least one vehicle",
        ))
    } else if batch.vehicles.len() > max_samples {
        Some(invalid_field(
            "vehicles",
            format!(
                "{} vehicles in one message; at most {max_samples}",
                batch.vehicles.len()
            ),
        ))
    } else if samples > max_samples {
        Some(invalid_field(
            "vehicles",
            format!("{samples} samples in one message; at most {max_samples} in total"),
        ))
    } else {
        None
    }
}

/// Samples scored in a fleet message so far, and how many of them alarm (for metrics).
#[derive(Default)]
struct Scored {
    samples: usize,
    alarming: usize,
}

/// One vehicle of a fleet message, run on its session; a refusal (a vehicle outside `caller`'s
/// scope included) becomes the vehicle's status.
async fn detect_vehicle(
    sessions: &SessionManager,
    caller: &Caller,
    seq: u64,
    index: usize,
    vehicle: v1::VehicleSamples,
    scored: &mut Scored,
) -> v1::VehicleDetections {
    // Field paths are built only for errors: this runs once per vehicle and message.
    let at = |field: &str| format!("vehicles[{index}].{field}");
    let sample_count = vehicle.samples.len();
    let outcome = async {
        let vehicle_id = VehicleId::parse(&vehicle.vehicle_id)
            .map_err(|problem| invalid_field(at("vehicle_id"), problem.to_string()))?;
        caller.check_vehicle(&at("vehicle_id"), vehicle_id.as_str())?;
        let model = match vehicle.model.as_str() {
            "" => None,
            name => Some(model_name(&at("model"), name)?),
        };
        let samples =
            samples_from_proto(&vehicle.samples, "samples").map_err(|error| match error {
                SessionError::InvalidBatch(violations) => SessionError::InvalidBatch(
                    violations.into_iter().map(|(f, p)| (at(&f), p)).collect(),
                ),
                other => other,
            })?;
        let decisions = sessions
            .detect_unattached(
                ForVehicle {
                    vehicle_id: &vehicle_id,
                    identity: &caller.grant.name,
                    credential: &caller.credential,
                },
                model.as_ref(),
                vehicle.reset,
                Some(seq),
                &samples,
                "samples",
            )
            .await
            .map_err(|error| match error {
                SessionError::InvalidBatch(violations) => SessionError::InvalidBatch(
                    violations.into_iter().map(|(f, p)| (at(&f), p)).collect(),
                ),
                other => other,
            })?;
        let detections = samples
            .iter()
            .zip(&decisions.decisions)
            .map(|(s, d)| detection_to_proto(s.timestamp_s, d, ""))
            .collect();
        Ok::<_, Status>((decisions, detections))
    };
    match outcome.await {
        Ok((decisions, detections)) => {
            if decisions.duplicate {
                telemetry::batch_duplicate(Rpc::StreamDetectFleet);
            } else {
                scored.samples += sample_count;
                scored.alarming += alarming(&decisions);
            }
            v1::VehicleDetections {
                vehicle_id: vehicle.vehicle_id,
                model: decisions.model.to_string(),
                detections,
                error: None,
                duplicate: decisions.duplicate,
            }
        }
        Err(status) => {
            telemetry::batch_rejected(Rpc::StreamDetectFleet, &status, sample_count);
            v1::VehicleDetections {
                vehicle_id: vehicle.vehicle_id,
                model: String::new(),
                detections: Vec::new(),
                error: Some(to_rpc_status(&status)),
                duplicate: false,
            }
        }
    }
}

/// Drives one StreamDetectFleet call of `caller` to its end: one reply per message, in order,
/// each vehicle checked against the caller's grant as the identities in force give it.
async fn run_fleet_stream(
    sessions: Arc<SessionManager>,
    shutdown: CancellationToken,
    mut inbound: Streaming<v1::FleetBatch>,
    tx: ReplySender<FleetReply>,
    idle: StreamIdle,
    mut caller: Caller,
) {
    let max_samples = sessions.limits().max_batch_samples;
    loop {
        let message = tokio::select! {
            biased;
            _ = shutdown.cancelled() => {
                idle.send(&tx, Err(shutting_down())).await;
                break;
            }
            status = caller.until_revoked(None) => {
                idle.send(&tx, Err(status)).await;
                break;
            }
            message = idle.next(&mut inbound) => message,
        };
        let batch = match message {
            Ok(Some(batch)) => batch,
            Ok(None) => break,
            Err(status) => {
                telemetry::stream_failed(Rpc::StreamDetectFleet, &status);
                idle.send(&tx, Err(status)).await;
                break;
            }
        };
        let started = Instant::now();
        let reply = match fleet_batch_violation(&batch, max_samples) {
            Some(status) => {
                let samples = batch.vehicles.iter().map(|v| v.samples.len()).sum();
                telemetry::batch_rejected(Rpc::StreamDetectFleet, &status, samples);
                v1::FleetDetections {
                    seq: batch.seq,
                    vehicles: Vec::new(),
                    error: Some(to_rpc_status(&status)),
                }
            }
            None => {
                let mut scored = Scored::default();
                let mut vehicles = Vec::with_capacity(batch.vehicles.len());
                for (index, vehicle) in batch.vehicles.into_iter().enumerate() {
                    vehicles.push(
                        detect_vehicle(&sessions, &caller, batch.seq, index, vehicle, &mut scored)
                            .await,
                    );
                }
                telemetry::batch_scored(
                    Rpc::StreamDetectFleet,
                    scored.samples,
                    scored.alarming,
                    started,
                );
                v1::FleetDetections {
                    seq: batch.seq,
                    vehicles,
                    error: None,
                }
            }
        };
        if !idle.send(&tx, Ok(reply)).await {
            break; // the client went away or stopped reading
        }
    }
}

impl DetectionApi {
    /// Starts a streaming call: `run` reads `inbound` in its own task, with `context`, and writes
    /// the replies into a small bounded channel, which is the call's response stream.
    fn spawn_call<In, Out, Context, Fut>(
        &self,
        inbound: Streaming<In>,
        context: Context,
        run: impl FnOnce(
            Arc<SessionManager>,
            CancellationToken,
            Streaming<In>,
            ReplySender<Result<Out, Status>>,
            StreamIdle,
            Context,
        ) -> Fut,
    ) -> Result<Response<ReplyStream<Result<Out, Status>>>, Status>
    where
        Fut: Future<Output = ()> + Send + 'static,
    {
        if self.shutdown.is_cancelled() {
            return Err(shutting_down());
        }
        let (tx, rx) = replies::channel();
        tokio::spawn(run(
            Arc::clone(&self.sessions),
            self.shutdown.clone(),
            inbound,
            tx,
            self.stream_idle,
            context,
        ));
        Ok(Response::new(rx))
    }

    /// One Detect call: the request's samples and their decisions, or its refusal.
    async fn detect_once(
        &self,
        request: Request<v1::DetectRequest>,
    ) -> Result<(Vec<Sample>, Decisions), Status> {
        if self.shutdown.is_cancelled() {
            return Err(shutting_down());
        }
        let routed = routed_vehicle_ids(request.metadata())?;
        let caller = Caller::of(&request)?;
        let r = request.into_inner();
        let vehicle = optional_vehicle_id("vehicle_id", &r.vehicle_id)?;
        // A stateless call (no vehicle id) touches no session: every caller of Detect may make it.
        if let Some(vehicle) = &vehicle {
            caller.check_vehicle("vehicle_id", vehicle.as_str())?;
        }
        // A stateless call (no vehicle id) routed as a vehicle's is a mismatch too.
        check_routed_vehicle(
            &routed,
            "vehicle_id",
            vehicle.as_ref().map_or("", VehicleId::as_str),
        )?;
        let model = optional_model_name("model", &r.model)?;
        let samples = samples_from_proto(&r.samples, "samples")?;
        let decisions = match &vehicle {
            Some(vehicle) => {
                self.sessions
                    .detect_unattached(
                        ForVehicle {
                            vehicle_id: vehicle,
                            identity: &caller.grant.name,
                            credential: &caller.credential,
                        },
                        model.as_ref(),
                        false,
                        None,
                        &samples,
                        "samples",
                    )
                    .await?
            }
            None => {
                self.sessions
                    .detect_stateless(model.as_ref(), &samples, "samples")
                    .await?
            }
        };
        Ok((samples, decisions))
    }
}

#[tonic::async_trait]
impl DetectionService for DetectionApi {
    type StreamDetectStream = ReplyStream<Reply>;
    type StreamDetectFleetStream = ReplyStream<FleetReply>;

    async fn stream_detect_fleet(
        &self,
        request: Request<Streaming<v1::FleetBatch>>,
    ) -> Result<Response<Self::StreamDetectFleetStream>, Status> {
        let caller = Caller::of(&request)?;
        self.spawn_call(request.into_inner(), caller, run_fleet_stream)
    }

    async fn stream_detect(
        &self,
        request: Request<Streaming<v1::StreamDetectRequest>>,
    ) -> Result<Response<Self::StreamDetectStream>, Status> {
        let routed = routed_vehicle_ids(request.metadata())?;
        let caller = Caller::of(&request)?;
        self.spawn_call(request.into_inner(), (routed, caller), run_stream)
    }

    async fn detect(
        &self,
        request: Request<v1::DetectRequest>,
    ) -> Result<Response<v1::DetectResponse>, Status> {
        let started = Instant::now();
        let sample_count = request.get_ref().samples.len();
        let detected = self.detect_once(request).await;
        match &detected {
            Ok((samples, decisions)) => {
                telemetry::batch_scored(Rpc::Detect, samples.len(), alarming(decisions), started)
            }
            Err(status) => telemetry::batch_rejected(Rpc::Detect, status, sample_count),
        }
        let (samples, decisions) = detected?;
        Ok(Response::new(v1::DetectResponse {
            detections: detections_to_proto(&samples, &decisions),
            model: decisions.model.to_string(),
        }))
    }

    async fn list_sessions(
        &self,
        request: Request<v1::ListSessionsRequest>,
    ) -> Result<Response<v1::ListSessionsResponse>, Status> {
        let r = request.into_inner();
        let size = match usize::try_from(r.page_size) {
            Err(_) => return Err(invalid_field("page_size", "must not be negative")),
            Ok(0) => DEFAULT_SESSION_PAGE_SIZE,
            Ok(n) => n.min(MAX_SESSION_PAGE_SIZE),
        };
        let (sessions, next_page_token) = self.sessions.list(size, &r.page_token).await;
        Ok(Response::new(v1::ListSessionsResponse {
            sessions: sessions.into_iter().map(session_to_proto).collect(),
            next_page_token,
        }))
    }

    async fn get_session(
        &self,
        request: Request<v1::GetSessionRequest>,
    ) -> Result<Response<v1::Session>, Status> {
        let routed = routed_vehicle_ids(request.metadata())?;
        let vehicle = vehicle_id("vehicle_id", &request.get_ref().vehicle_id)?;
        check_routed_vehicle(&routed, "vehicle_id", vehicle.as_str())?;
        let session = self.sessions.get(&vehicle).await?;
        Ok(Response::new(session_to_proto(session)))
    }

    async fn reset_session(
        &self,
        request: Request<v1::ResetSessionRequest>,
    ) -> Result<Response<v1::Session>, Status> {
        let routed = routed_vehicle_ids(request.metadata())?;
        let vehicle = vehicle_id("vehicle_id", &request.get_ref().vehicle_id)?;
        check_routed_vehicle(&routed, "vehicle_id", vehicle.as_str())?;
        let session = self.sessions.reset(&vehicle).await?;
        Ok(Response::new(session_to_proto(session)))
    }
}

/// DeleteModel ends a deleted model's sessions through the session manager.
#[tonic::async_trait]
impl ModelDeletion for SessionManager {
    async fn delete_and_end_sessions(&self, name: &ModelName) -> Result<usize, Status> {
        Ok(self.delete_model(name).await?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_receiver_state_numbers_are_refused_by_field() {
        let good = v1::Sample {
            spoofing_state: v1::SpoofingState::Indicated as i32,
            satellites_used: Some(9),
            ..v1::Sample::default()
        };
        let bad = v1::Sample {
            jamming_state: 7,
            ..v1::Sample::default()
        };
        let samples = samples_from_proto(std::slice::from_ref(&good), "batch.samples")
            .expect("known numbers");
        assert_eq!(
            samples[0].spoofing_state,
            spoofwatch_core::sample::SpoofingState::Indicated
        );
        match samples_from_proto(&[good, bad], "batch.samples") {
            Err(SessionError::InvalidBatch(violations)) => assert_eq!(
                violations,
                [(
                    "batch.samples[1].jamming_state".to_string(),
                    "must be a state number in [0, 3], got 7".to_string()
                )]
            ),
            other => panic!("expected a field violation, got {other:?}"),
        }
    }
}
