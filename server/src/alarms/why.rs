//! Why an alarm was raised, between its three forms: the core's [`Explanation`] of the onset sample
//! (what the detector says), the alarm row's [`StoredWhy`] (what the store keeps) and the wire's
//! `v1::Explanation` (what ListAlarms and WatchAlarms send).
//!
//! It owns only that mapping: it must not store, queue, log or serve anything.

use spoofwatch_core::explain::{EvidenceKind, Explanation};
use spoofwatch_core::geo::LatLon;
use spoofwatch_proto::v1;
use spoofwatch_proto::wire::convert::explanation_to_proto;

use crate::store::{StoredPlace, StoredWhy};

/// Why and where an alarm started: its onset sample's explanation and fix.
#[derive(Clone, Copy, Debug)]
pub struct OnsetWhy<'a> {
    pub explanation: &'a Explanation,
    pub fix: LatLon,
}

/// The onset's explanation as the alarm row stores it.
pub fn stored(x: &Explanation) -> StoredWhy {
    StoredWhy {
        why_kind: Some(x.dominant.name().to_string()),
        why_offset_east_m: Some(x.offset_m[0]),
        why_offset_north_m: Some(x.offset_m[1]),
        why_drift_east_mps: Some(x.drift_rate_mps[0]),
        why_drift_north_mps: Some(x.drift_rate_mps[1]),
    }
}

/// The onset's fix as the alarm row stores it.
pub fn place(fix: LatLon) -> StoredPlace {
    StoredPlace {
        onset_latitude_deg: Some(fix.lat_deg),
        onset_longitude_deg: Some(fix.lon_deg),
    }
}

/// A stored explanation back as the core's: `None` for a row without one (stored before schema
/// version 6) or with a kind this build does not know; a missing vector component reads as 0.
pub fn explanation(why: &StoredWhy) -> Option<Explanation> {
    let name = why.why_kind.as_deref()?;
    let dominant = EvidenceKind::from_name(name)?;
    let or_zero = |v: Option<f64>| v.unwrap_or(0.0);
    Some(Explanation {
        dominant,
        offset_m: [
            or_zero(why.why_offset_east_m),
            or_zero(why.why_offset_north_m),
        ],
        drift_rate_mps: [
            or_zero(why.why_drift_east_mps),
            or_zero(why.why_drift_north_mps),
        ],
    })
}

/// A stored explanation on the wire (absent when the row has none).
pub fn to_proto(why: &StoredWhy) -> Option<v1::Explanation> {
    explanation(why).as_ref().map(explanation_to_proto)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_survives_the_store() {
        for dominant in EvidenceKind::ALL {
            let x = Explanation {
                dominant,
                offset_m: [-30.0, 40.0],
                drift_rate_mps: [0.5, -0.25],
            };
            assert_eq!(explanation(&stored(&x)), Some(x));
        }
    }

    #[test]
    fn a_stored_jump_reads_as_distance_and_bearing_on_the_wire() {
        let why = stored(&Explanation {
            dominant: EvidenceKind::Jump,
            // 400 m west, 300 m south: 500 m toward 270° − atan(3/4) = 233.13°.
            offset_m: [-400.0, -300.0],
            drift_rate_mps: [0.0, 0.0],
        });
        assert_eq!(why.why_kind.as_deref(), Some("jump"));
        let wire = to_proto(&why).expect("stored");
        assert_eq!(wire.dominant(), v1::EvidenceKind::Jump);
        assert_eq!(wire.offset_m, 500.0);
        assert!((wire.offset_bearing_deg - 233.130_102_354_155_98).abs() < 1e-9);
        assert_eq!((wire.drift_mps, wire.drift_bearing_deg), (0.0, 0.0));
    }

    #[test]
    fn rows_without_an_explanation_have_none_on_the_wire() {
        assert_eq!(to_proto(&StoredWhy::default()), None);
        let unknown = StoredWhy {
            why_kind: Some("telepathy".to_string()),
            ..StoredWhy::default()
        };
        assert_eq!(to_proto(&unknown), None);
    }
}
