//! The streaming, per-vehicle evidence builder (SPEC §3–4).
//!
//! Owns the streaming per-vehicle evidence builder. Must not fit statistics or scale features.

use serde::{Deserialize, Serialize};

use super::drift::{DriftEvidence, DriftInput, DriftTracker, SCALE_COUNT};
use super::linalg::{
    Mat2, floor_at_identity, inverse, inverse_sqrt_positive_definite, inverse_sqrt_symmetric, mul,
    mul_vec,
};
use super::offset::{AnchorPoint, MAX_CARRY_GAP_S, OffsetEvidence, OffsetStep, OffsetTracker};
use super::params::{EvidenceParams, SIGMA_EPSILON};
use super::{DRIFT_FEATURES_START, FEATURE_CAPACITY, Features, NU_INDEX, OFFSET_FEATURES_START};
use crate::geo::{LatLon, Projection};
use crate::sample::{MAX_SPEED_MPS, Record, Sample};

/// A gap longer than this (s) starts a new trajectory (SPEC §3).
pub const MAX_GAP_S: f64 = 5.0;
/// Time going backwards by more than this (s) starts a new trajectory (SPEC §3).
pub const MAX_BACKWARD_S: f64 = 0.5;

/// The causal evidence of one sample (unscaled). Fields that are undefined are NaN (`delta_t` at a
/// trajectory start, `residual` when ν = 0); the ξ components are 0 when they cannot be computed.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Evidence {
    /// 0-based index of the trajectory within this builder's stream.
    pub trajectory: u32,
    /// This sample starts a trajectory (all sequential state was reset here).
    pub trajectory_start: bool,
    /// δ_t = t_t − t_{t−1} (s); NaN at a trajectory start.
    pub delta_t: f64,
    /// ν_t: the residual is usable.
    pub valid: bool,
    /// Σ_t came from the samples' own uncertainties (paper's first branch) rather than Σ̂.
    pub sigma_per_step: bool,
    /// r_t = Δp^g − Δp^u, east/north metres; NaN when ν = 0.
    pub residual: [f64; 2],
    /// η_t = Σ_t^{-1/2} r_t; 0 when ν = 0.
    pub eta: [f64; 2],
    /// η̇_t = (η_t − η_{t−1})/δ_t when ν_t = ν_{t−1} = 1, else 0.
    pub eta_dot: [f64; 2],
    /// η̈_t = (η̇_t − η̇_{t−1})/((δ_t + δ_{t−1})/2) when both η̇ were computed, else 0.
    pub eta_ddot: [f64; 2],
    /// e_t = ‖η_t‖²; 0 when ν = 0.
    pub energy: f64,
    /// q_t = e_t − μ_e − κ; 0 when ν = 0.
    pub q: f64,
    /// a_t = max(0, ρ a_{t−1} + q_t) when ν = 1, else ρ a_{t−1}.
    pub accum: f64,
    /// ã_t = ln(1 + a_t).
    pub accum_log: f64,
    /// Evidence v2's drift channels (`None` with the paper's parameters).
    pub drift: Option<DriftEvidence>,
    /// Evidence v3's offset channels (`None` without offset parameters).
    #[serde(default)]
    pub offset: Option<OffsetEvidence>,
}

impl Evidence {
    /// A sample's evidence before its residual is known (ν = 0, no offset channels): the drift
    /// channels as they hold.
    pub fn invalid(
        trajectory: u32,
        trajectory_start: bool,
        delta_t: f64,
        drift: Option<DriftEvidence>,
    ) -> Self {
        Self {
            trajectory,
            trajectory_start,
            delta_t,
            valid: false,
            sigma_per_step: false,
            residual: [f64::NAN; 2],
            eta: [0.0; 2],
            eta_dot: [0.0; 2],
            eta_ddot: [0.0; 2],
            energy: 0.0,
            q: 0.0,
            accum: 0.0,
            accum_log: 0.0,
            drift,
            offset: None,
        }
    }

    /// Unscaled ξ_t in the order of `FEATURE_NAMES`: the paper's 9 channels (ν as 0/1), then the drift
    /// channels ln(1 + χ²_k) per scale (uncalibrated, calibrated), ln(1 + drift statistic), ω_t and
    /// ln(1 + stale-fix seconds) and ln(1 + ‖r‖/c); then the offset channels ln(1 + NIS) of the fast
    /// and the slow anchor, ln(1 + held seconds) and the shares of the last 10 s and 60 s beyond the
    /// follow gate. A schema reads its prefix; channels the parameters lack are 0.
    pub fn raw_features(&self) -> Features {
        let mut features: Features = [0.0; FEATURE_CAPACITY];
        features[..DRIFT_FEATURES_START].copy_from_slice(&[
            self.eta[0],
            self.eta[1],
            self.eta_dot[0],
            self.eta_dot[1],
            self.eta_ddot[0],
            self.eta_ddot[1],
            self.q,
            self.accum_log,
            if self.valid { 1.0 } else { 0.0 },
        ]);
        debug_assert_eq!(NU_INDEX, DRIFT_FEATURES_START - 1);
        let Some(drift) = &self.drift else {
            return features;
        };
        let raw = drift.raw_chi2();
        let calibrated = drift.calibrated_chi2();
        let channels = &mut features[DRIFT_FEATURES_START..];
        for k in 0..SCALE_COUNT {
            channels[k] = raw[k].ln_1p();
            channels[SCALE_COUNT + k] = calibrated[k].ln_1p();
        }
        channels[2 * SCALE_COUNT] = drift.statistic.ln_1p();
        channels[2 * SCALE_COUNT + 1] = drift.warm_up;
        channels[2 * SCALE_COUNT + 2] = drift.stale_fix_s.ln_1p();
        channels[2 * SCALE_COUNT + 3] = drift.residual_log;
        if let Some(offset) = &self.offset {
            features[OFFSET_FEATURES_START..].copy_from_slice(&[
                offset.nis[0].ln_1p(),
                offset.nis[1].ln_1p(),
                offset.held_s.ln_1p(),
                offset.share[0],
                offset.share[1],
            ]);
        }
        features
    }
}

/// What the builder remembers about the previous sample of the current trajectory.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
struct Previous {
    #[serde(with = "measurements_only")]
    sample: Sample,
    fix: LatLon,
    velocity: [f64; 2],
    usable: bool,
    valid: bool,
    eta: [f64; 2],
    eta_dot: [f64; 2],
    eta_dot_computed: bool,
    delta_t: f64,
}

/// The previous sample as a saved builder stores it: its measurements and uncertainties, the
/// encoding session snapshots have always had. No evidence reads the receiver's status fields, so a
/// restored builder continues exactly without them.
mod measurements_only {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    use crate::sample::Sample;

    #[derive(Serialize, Deserialize)]
    struct Measurements {
        timestamp_s: f64,
        latitude_deg: f64,
        longitude_deg: f64,
        speed_mps: f64,
        heading_deg: f64,
        position_std_m: Option<f64>,
        speed_std_mps: Option<f64>,
        heading_std_deg: Option<f64>,
    }

    pub fn serialize<S: Serializer>(sample: &Sample, serializer: S) -> Result<S::Ok, S::Error> {
        Measurements {
            timestamp_s: sample.timestamp_s,
            latitude_deg: sample.latitude_deg,
            longitude_deg: sample.longitude_deg,
            speed_mps: sample.speed_mps,
            heading_deg: sample.heading_deg,
            position_std_m: sample.position_std_m,
            speed_std_mps: sample.speed_std_mps,
            heading_std_deg: sample.heading_std_deg,
        }
        .serialize(serializer)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Sample, D::Error> {
        let m = Measurements::deserialize(deserializer)?;
        Ok(Sample {
            position_std_m: m.position_std_m,
            speed_std_mps: m.speed_std_mps,
            heading_std_deg: m.heading_std_deg,
            ..Sample::new(
                m.timestamp_s,
                m.latitude_deg,
                m.longitude_deg,
                m.speed_mps,
                m.heading_deg,
            )
        })
    }
}

/// Why [`EvidenceBuilder::restore`] refuses a saved builder: it was made with (or without) the drift
/// channels and the parameters differ.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DriftChannelsDiffer {
    /// Whether the saved builder has the drift channels.
    pub in_snapshot: bool,
}

/// Streaming per-vehicle builder of ξ_t. `push` never allocates; the same builder serves a live
/// stream and a recorded track ([`build_track`]).
///
/// Serialised (a session snapshot) it holds only the stream's state: what comes from the
/// parameters is skipped and filled in again by [`EvidenceBuilder::restore`].
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvidenceBuilder {
    /// What `push` uses of the [`EvidenceParams`] (not a copy of them: a server holds one builder
    /// per vehicle, and the drift parameters alone are larger than the builder's state).
    #[serde(skip)]
    projection: Projection,
    #[serde(skip)]
    mu_e: f64,
    #[serde(skip)]
    kappa: f64,
    #[serde(skip)]
    rho: f64,
    /// (Σ̂ + εI)^{-1/2} and (Σ̂ + εI)^{1/2}, computed once.
    #[serde(skip)]
    sigma_hat_inv_sqrt: Mat2,
    #[serde(skip)]
    sigma_hat_sqrt: Mat2,
    previous: Option<Previous>,
    /// First valid fix of the current trajectory (the equirectangular origin).
    reference: Option<LatLon>,
    accum: f64,
    trajectory: u32,
    /// Evidence v2's drift tracker (when the parameters carry drift parameters).
    drift: Option<DriftTracker>,
    /// Evidence v3's anchors (when the parameters carry offset parameters), boxed: a server holds
    /// one builder per vehicle, and sessions of older schemas should not pay for the anchors.
    #[serde(default)]
    offset: Option<Box<OffsetTracker>>,
}

impl EvidenceBuilder {
    /// A builder at the start of a stream.
    pub fn new(params: EvidenceParams) -> Self {
        let sigma_hat_inv_sqrt = inverse_sqrt_symmetric(&params.regularised_sigma());
        Self {
            projection: params.projection,
            mu_e: params.mu_e,
            kappa: params.kappa,
            rho: params.rho,
            sigma_hat_inv_sqrt,
            sigma_hat_sqrt: inverse(&sigma_hat_inv_sqrt),
            previous: None,
            reference: None,
            accum: 0.0,
            trajectory: 0,
            drift: params.drift.as_ref().map(DriftTracker::new),
            offset: params
                .offset
                .as_ref()
                .map(|p| Box::new(OffsetTracker::new(p))),
        }
    }

    /// The per-step Σ_t, but never tighter than the training Σ̂ in any direction: with
    /// W = Σ̂^{-1/2}, the eigenvalues of W·Σ_t·W are raised to at least 1. Reported uncertainty can
    /// so only widen the noise model (a degraded fix alarms less), never narrow it below what the
    /// model was trained on: a zero, tiny or lying std cannot blow up η. Σ_t itself when no
    /// eigenvalue needs raising; exactly Σ̂ when both do.
    fn floored_at_training(&self, sigma: &Mat2) -> Mat2 {
        let w = &self.sigma_hat_inv_sqrt;
        match floor_at_identity(&mul(w, &mul(sigma, w))) {
            None => *sigma,
            Some(floored) => {
                let root = &self.sigma_hat_sqrt;
                mul(root, &mul(&floored, root))
            }
        }
    }

    /// A builder of `params` continuing the stream `saved` holds (a deserialised builder, whose
    /// parameter-derived fields are empty). Fails when `saved` was made with or without the drift
    /// channels and `params` disagree.
    pub fn restore(
        params: EvidenceParams,
        saved: EvidenceBuilder,
    ) -> Result<Self, DriftChannelsDiffer> {
        let fresh = Self::new(params);
        let drift = match (&fresh.drift, saved.drift) {
            (Some(fresh), Some(saved)) => Some(DriftTracker::restore(fresh, saved)),
            (None, None) => None,
            (Some(_), None) => return Err(DriftChannelsDiffer { in_snapshot: false }),
            (None, Some(_)) => return Err(DriftChannelsDiffer { in_snapshot: true }),
        };
        let offset = match (&params.offset, saved.offset) {
            (Some(params), Some(saved)) => Some(Box::new(OffsetTracker::restore(params, *saved))),
            (None, None) => None,
            (Some(_), None) => return Err(DriftChannelsDiffer { in_snapshot: false }),
            (None, Some(_)) => return Err(DriftChannelsDiffer { in_snapshot: true }),
        };
        Ok(Self {
            previous: saved.previous,
            reference: saved.reference,
            accum: saved.accum,
            trajectory: saved.trajectory,
            drift,
            offset,
            ..fresh
        })
    }

    /// Forgets the stream: the next sample starts trajectory 0, as in a new builder.
    pub fn reset(&mut self) {
        self.previous = None;
        self.reference = None;
        self.accum = 0.0;
        self.trajectory = 0;
        if let Some(drift) = &mut self.drift {
            drift.reset();
        }
        if let Some(offset) = &mut self.offset {
            offset.reset();
        }
    }

    /// Evidence for the next sample. `trajectory_break` is the source's own "new trajectory here" flag;
    /// the builder also starts one at the first sample, after a gap > 5 s and when time goes
    /// backwards by more than 0.5 s.
    pub fn push(&mut self, sample: &Sample, trajectory_break: bool) -> Evidence {
        let delta_t = match &self.previous {
            Some(previous) => sample.timestamp_s - previous.sample.timestamp_s,
            None => f64::NAN,
        };
        // Two separate comparisons, so that a NaN δ (non-finite timestamps) is neither a gap nor
        // time going backwards: it never starts a trajectory by itself, as in the reference.
        let gap = delta_t > MAX_GAP_S;
        let backwards = delta_t < -MAX_BACKWARD_S;
        let start = self.previous.is_none() || trajectory_break || gap || backwards;
        if start {
            if self.previous.is_some() {
                self.trajectory = self.trajectory.saturating_add(1);
            }
            self.previous = None;
            self.reference = None;
            self.accum = 0.0;
            if let Some(drift) = &mut self.drift {
                drift.start_trajectory();
            }
        }

        let fix = LatLon::new(sample.latitude_deg, sample.longitude_deg);
        if self.reference.is_none() && fix.is_valid() {
            self.reference = Some(fix);
        }
        let velocity = velocity_vector(sample);
        let usable = is_usable(sample, fix);

        let mut evidence = Evidence::invalid(
            self.trajectory,
            start,
            if start { f64::NAN } else { delta_t },
            self.drift.as_ref().map(DriftTracker::hold),
        );

        // ν needs both samples usable and 0 < δ ≤ 5 s (never true at a start: no previous sample).
        if let (Some(previous), Some(reference)) = (self.previous, self.reference)
            && usable
            && previous.usable
            && delta_t > 0.0
            && delta_t <= MAX_GAP_S
        {
            self.fill_valid(&mut evidence, &previous, reference, sample, fix, velocity);
        }
        self.fill_accumulator(&mut evidence);
        evidence.offset = self.move_anchors(sample, fix, velocity, usable, trajectory_break);

        self.previous = Some(Previous {
            sample: *sample,
            fix,
            velocity,
            usable,
            valid: evidence.valid,
            eta: evidence.eta,
            eta_dot: evidence.eta_dot,
            eta_dot_computed: evidence.valid && self.previous_valid(),
            delta_t,
        });
        evidence
    }

    /// The offset channels: the anchors move from the last usable sample to this one, across
    /// trajectory breaks of the stream (a gap up to [`MAX_CARRY_GAP_S`] carries them, with the motion
    /// it may hide as extra uncertainty). The source's own break, time going backwards and a longer
    /// gap re-anchor at this sample.
    fn move_anchors(
        &mut self,
        sample: &Sample,
        fix: LatLon,
        velocity: [f64; 2],
        usable: bool,
        source_break: bool,
    ) -> Option<OffsetEvidence> {
        let projection = self.projection;
        let drift = self.drift.as_ref();
        let offset = self.offset.as_mut()?;
        if source_break {
            offset.re_anchor();
        }
        if !usable {
            return Some(offset.hold());
        }
        let mut here = AnchorPoint {
            fix,
            velocity,
            time_s: sample.timestamp_s,
            repeated: false,
        };
        let Some(from) = offset.point() else {
            offset.set_point(here);
            return Some(offset.hold());
        };
        let delta_t = here.time_s - from.time_s;
        if !(-MAX_BACKWARD_S..=MAX_CARRY_GAP_S).contains(&delta_t) {
            offset.re_anchor();
            offset.set_point(here);
            return Some(offset.hold());
        }
        // Not later than the last usable sample: nothing to move.
        if delta_t <= 0.0 {
            return Some(offset.hold());
        }
        let gnss = projection.displacement(from.fix, from.fix, fix);
        let motion = [
            0.5 * (velocity[0] + from.velocity[0]) * delta_t,
            0.5 * (velocity[1] + from.velocity[1]) * delta_t,
        ];
        let mut residual = [gnss[0] - motion[0], gnss[1] - motion[1]];
        let velocity_change = [
            velocity[0] - from.velocity[0],
            velocity[1] - from.velocity[1],
        ];
        let in_use = drift.and_then(|d| d.calibration_in_use(motion, velocity_change));
        if let Some((correction, _)) = in_use {
            residual = [residual[0] + correction[0], residual[1] + correction[1]];
        }
        if !(residual[0].is_finite() && residual[1].is_finite()) {
            return Some(offset.hold());
        }
        here.repeated = fix == from.fix;
        offset.set_point(here);
        Some(offset.push(&OffsetStep {
            residual,
            motion,
            delta_t,
            calibrated: in_use.is_some(),
            calibration_error: in_use.map_or([0.0; 3], |(_, error)| error),
            reports_placements: drift.is_some_and(DriftTracker::trusts_information),
            leaves_held_fix: from.repeated,
            repeats_fix: here.repeated,
            velocity_change,
            theta_in_use: if in_use.is_some() {
                drift.map_or([0.0; 3], DriftTracker::theta_in_use)
            } else {
                [0.0; 3]
            },
        }))
    }

    /// ν_{t−1} (before `previous` is overwritten).
    fn previous_valid(&self) -> bool {
        self.previous.is_some_and(|p| p.valid)
    }

    /// Residual, η and its finite differences for a sample whose ν_t is 1 unless r is not finite.
    fn fill_valid(
        &mut self,
        evidence: &mut Evidence,
        previous: &Previous,
        reference: LatLon,
        sample: &Sample,
        fix: LatLon,
        velocity: [f64; 2],
    ) {
        let delta_t = evidence.delta_t;
        let gnss = self.projection.displacement(reference, previous.fix, fix);
        // Causal trapezoid on the velocity vector.
        let motion = [
            0.5 * (velocity[0] + previous.velocity[0]) * delta_t,
            0.5 * (velocity[1] + previous.velocity[1]) * delta_t,
        ];
        let residual = [gnss[0] - motion[0], gnss[1] - motion[1]];
        if !(residual[0].is_finite() && residual[1].is_finite()) {
            return;
        }
        let per_step = per_step_sigma(&previous.sample, sample, delta_t);
        let inv_sqrt = match &per_step {
            Some(sigma) => inverse_sqrt_positive_definite(&self.floored_at_training(sigma)),
            None => self.sigma_hat_inv_sqrt,
        };
        let eta = mul_vec(&inv_sqrt, residual);
        let energy = eta[0] * eta[0] + eta[1] * eta[1];

        evidence.valid = true;
        evidence.sigma_per_step = per_step.is_some();
        evidence.residual = residual;
        evidence.eta = eta;
        evidence.energy = energy;
        evidence.q = energy - self.mu_e - self.kappa;
        // While an anchor is frozen the rows may be an attack's: the calibration and levels wait.
        let learn = self.offset.as_ref().is_none_or(|o| !o.frozen());
        if let Some(drift) = &mut self.drift {
            evidence.drift = Some(drift.push(&DriftInput {
                residual,
                motion,
                velocity_change: [
                    velocity[0] - previous.velocity[0],
                    velocity[1] - previous.velocity[1],
                ],
                delta_t,
                fix_repeated: fix == previous.fix,
                learn,
            }));
        }

        if previous.valid {
            evidence.eta_dot = [
                (eta[0] - previous.eta[0]) / delta_t,
                (eta[1] - previous.eta[1]) / delta_t,
            ];
            if previous.eta_dot_computed && previous.delta_t > 0.0 && previous.delta_t <= MAX_GAP_S
            {
                let mean_delta = 0.5 * (delta_t + previous.delta_t);
                evidence.eta_ddot = [
                    (evidence.eta_dot[0] - previous.eta_dot[0]) / mean_delta,
                    (evidence.eta_dot[1] - previous.eta_dot[1]) / mean_delta,
                ];
            }
        }
    }

    /// a_t and ã_t; a_{t−1} was reset to 0 at a trajectory start.
    fn fill_accumulator(&mut self, evidence: &mut Evidence) {
        let decayed = self.rho * self.accum;
        let accum = if evidence.valid {
            (decayed + evidence.q).max(0.0)
        } else {
            decayed
        };
        // The reference maps a non-finite accumulator to 0.
        self.accum = if accum.is_finite() { accum } else { 0.0 };
        evidence.accum = self.accum;
        evidence.accum_log = self.accum.max(0.0).ln_1p();
    }
}

/// Runs one fresh builder over a recorded track, honouring each record's `trajectory_break`.
pub fn build_track(params: &EvidenceParams, records: &[Record]) -> Vec<Evidence> {
    let mut builder = EvidenceBuilder::new(*params);
    records
        .iter()
        .map(|record| builder.push(&record.sample, record.trajectory_break))
        .collect()
}

/// v = speed·(sin ψ, cos ψ), ψ clockwise from north.
fn velocity_vector(sample: &Sample) -> [f64; 2] {
    let (sin, cos) = sample.heading_deg.to_radians().sin_cos();
    [sample.speed_mps * sin, sample.speed_mps * cos]
}

/// Every field the residual needs is finite and in range (SPEC §2, §4); present uncertainties too.
fn is_usable(sample: &Sample, fix: LatLon) -> bool {
    let speed_ok = sample.speed_mps.is_finite() && sample.speed_mps.abs() <= MAX_SPEED_MPS;
    let heading_ok = sample.heading_deg.is_finite() && sample.heading_deg.abs() <= 360.0;
    fix.is_valid() && speed_ok && heading_ok && sample.uncertainties_in_range()
}

/// Σ_t = Σ^Δg + Σ^Δu + εI when BOTH samples carry position, speed and heading std, else `None`.
///
/// Derivation (errors independent between samples and between fields):
/// - Δp^g = p_t − p_{t−1} with isotropic per-axis std σ_p at each fix → Σ^Δg = (σ_{p,t}² + σ_{p,t−1}²)·I
///   (= 2σ_p²I for equal stds).
/// - v = s·u(ψ) with u = (sin ψ, cos ψ); first order: ∂v/∂s = u, ∂v/∂ψ = s·w with w = (cos ψ, −sin ψ)
///   (ψ in radians), so Cov(v) = σ_s²·uuᵀ + s²σ_ψ²·wwᵀ.
/// - Δp^u = (δ/2)(v_t + v_{t−1}) → Σ^Δu = (δ/2)²·(Cov(v_t) + Cov(v_{t−1})).
fn per_step_sigma(previous: &Sample, current: &Sample, delta_t: f64) -> Option<Mat2> {
    let (prev_pos, prev_vel) = (previous.position_std_m?, velocity_covariance(previous)?);
    let (cur_pos, cur_vel) = (current.position_std_m?, velocity_covariance(current)?);
    let gnss = prev_pos * prev_pos + cur_pos * cur_pos;
    let k = 0.25 * delta_t * delta_t;
    let mut sigma = [[0.0; 2]; 2];
    for (i, row) in sigma.iter_mut().enumerate() {
        for (j, cell) in row.iter_mut().enumerate() {
            *cell = k * (prev_vel[i][j] + cur_vel[i][j]);
        }
    }
    sigma[0][0] += gnss + SIGMA_EPSILON;
    sigma[1][1] += gnss + SIGMA_EPSILON;
    Some(sigma)
}

/// Cov(v) = σ_s²·uuᵀ + s²σ_ψ²·wwᵀ (see [`per_step_sigma`]); `None` without speed and heading std.
fn velocity_covariance(sample: &Sample) -> Option<Mat2> {
    let speed_var = sample.speed_std_mps?.powi(2);
    let heading_std = sample.heading_std_deg?.to_radians();
    let cross_var = (sample.speed_mps * heading_std).powi(2);
    let (sin, cos) = sample.heading_deg.to_radians().sin_cos();
    let u = [sin, cos];
    let w = [cos, -sin];
    let mut cov = [[0.0; 2]; 2];
    for (i, row) in cov.iter_mut().enumerate() {
        for (j, cell) in row.iter_mut().enumerate() {
            *cell = speed_var * u[i] * u[j] + cross_var * w[i] * w[j];
        }
    }
    Some(cov)
}
