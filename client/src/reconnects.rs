//! When a replayed vehicle's streams reconnect: each vehicle's own random intervals, from the
//! replay's seed and its id, so that a fleet's reconnects do not happen in step.
//!
//! Owns the reconnect times and the vehicle id's hash they (and the send phase) are drawn from.
//! Must not open a stream or send anything (the replay does).

use spoofwatch_core::rng::Rng;

/// Shortest and longest time between reconnects, as fractions of `reconnect_every_s`: wide
/// enough that a fleet's reconnects do not happen in step.
const RECONNECT_JITTER: (f64, f64) = (0.5, 1.5);

/// A vehicle id's FNV-1a hash: what makes a vehicle's reconnect times and send phase its own,
/// whatever else is replayed with it.
pub(crate) fn id_hash(vehicle_id: &str) -> u64 {
    vehicle_id.bytes().fold(0xcbf2_9ce4_8422_2325_u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// The random stream of one vehicle's reconnect times: from the seed and the vehicle id.
pub(crate) fn reconnect_rng(seed: u64, vehicle_id: &str) -> Rng {
    Rng::seed_from_u64(seed ^ id_hash(vehicle_id))
}

/// Indices of the records at which a stream opens: always 0, then, when `every_s` > 0, the first
/// record at least one interval after the current stream's first record, each interval drawn
/// uniformly from [0.5, 1.5] × `every_s` by `rng`. Time is the replayed `timestamps`; records
/// with non-finite timestamps never start a stream.
pub fn stream_starts(timestamps: &[f64], every_s: f64, rng: &mut Rng) -> Vec<usize> {
    let mut starts = vec![0];
    if every_s <= 0.0 {
        return starts;
    }
    let (low, high) = RECONNECT_JITTER;
    let mut interval = rng.uniform_range(low * every_s, high * every_s);
    let mut stream_t = timestamps.first().copied().unwrap_or(f64::NAN);
    for (index, &t) in timestamps.iter().enumerate().skip(1) {
        if !stream_t.is_finite() {
            // The stream's first record had no usable time: its clock starts at the next one.
            stream_t = t;
            continue;
        }
        if t - stream_t >= interval {
            starts.push(index);
            stream_t = t;
            interval = rng.uniform_range(low * every_s, high * every_s);
        }
    }
    starts
}
