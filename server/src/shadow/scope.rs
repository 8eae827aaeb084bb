//! Which vehicles a shadow scores: every vehicle, a share of them chosen by a stable hash of the
//! vehicle id, or a list; its checks (field-level reasons) and its stored form.
//!
//! Pure: no locks, no I/O. The hash is 64-bit FNV-1a over the id's bytes, so the same vehicles are
//! in on every replica, every restart and every build.

use std::collections::BTreeSet;

use serde::{Deserialize, Serialize};
use spoofwatch_proto::wire::VehicleId;

/// Most vehicles a list may name.
pub const MAX_VEHICLES: usize = 10_000;

/// The shares are resolved in millionths: a vehicle is in when its hash modulo a million is below
/// the share times a million.
const SHARE_RESOLUTION: u64 = 1_000_000;

/// Which vehicles a shadow scores.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum ShadowScope {
    All,
    Share { share: f64 },
    Vehicles { vehicle_ids: BTreeSet<String> },
}

/// A scope that cannot be used: the request's field and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ScopeError {
    pub field: String,
    pub reason: String,
}

fn refuse(field: impl Into<String>, reason: impl Into<String>) -> ScopeError {
    ScopeError {
        field: field.into(),
        reason: reason.into(),
    }
}

impl ShadowScope {
    /// A share of the vehicles: finite, above 0 and at most 1.
    pub fn share(share: f64) -> Result<Self, ScopeError> {
        if !share.is_finite() || share <= 0.0 || share > 1.0 {
            return Err(refuse(
                "share",
                format!("must be above 0 and at most 1 (a fraction of the vehicles), got {share}"),
            ));
        }
        Ok(Self::Share { share })
    }

    /// A list of 1 to [`MAX_VEHICLES`] valid vehicle ids (repeats count once).
    pub fn vehicles(ids: &[String]) -> Result<Self, ScopeError> {
        if ids.is_empty() {
            return Err(refuse(
                "vehicles.vehicle_ids",
                "name at least one vehicle (or use all_vehicles or share)",
            ));
        }
        if ids.len() > MAX_VEHICLES {
            return Err(refuse(
                "vehicles.vehicle_ids",
                format!("at most {MAX_VEHICLES} vehicles, got {}", ids.len()),
            ));
        }
        let mut vehicle_ids = BTreeSet::new();
        for (i, id) in ids.iter().enumerate() {
            let id = VehicleId::parse(id)
                .map_err(|e| refuse(format!("vehicles.vehicle_ids[{i}]"), e.to_string()))?;
            vehicle_ids.insert(id.into_string());
        }
        Ok(Self::Vehicles { vehicle_ids })
    }

    /// Whether the shadow scores `vehicle_id`.
    pub fn includes(&self, vehicle_id: &str) -> bool {
        match self {
            Self::All => true,
            Self::Share { share } => {
                // Exact for every share given in millionths; 1.0 includes every vehicle.
                let threshold = (share * SHARE_RESOLUTION as f64).round() as u64;
                stable_hash(vehicle_id) % SHARE_RESOLUTION < threshold
            }
            Self::Vehicles { vehicle_ids } => vehicle_ids.contains(vehicle_id),
        }
    }

    /// How it reads to an operator: `all vehicles`, `share 0.25`, `vehicles a, b`.
    pub fn describe(&self) -> String {
        match self {
            Self::All => "all vehicles".to_string(),
            Self::Share { share } => format!("share {share}"),
            Self::Vehicles { vehicle_ids } => {
                let ids: Vec<&str> = vehicle_ids.iter().map(String::as_str).collect();
                format!("vehicles {}", ids.join(", "))
            }
        }
    }
}

/// 64-bit FNV-1a of the id's bytes: the same on every platform and in every release.
pub fn stable_hash(vehicle_id: &str) -> u64 {
    vehicle_id
        .bytes()
        .fold(0xcbf2_9ce4_8422_2325_u64, |hash, byte| {
            (hash ^ u64::from(byte)).wrapping_mul(0x0000_0100_0000_01b3)
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_hash_is_fnv1a() {
        // Published FNV-1a 64 test vectors: the hash may not change between releases.
        assert_eq!(stable_hash(""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(stable_hash("a"), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(stable_hash("foobar"), 0x8594_4171_f739_67e8);
    }

    #[test]
    fn a_share_takes_about_that_share_and_grows_by_adding_vehicles() {
        let ids: Vec<String> = (0..10_000).map(|i| format!("veh-{i}")).collect();
        let quarter = ShadowScope::share(0.25).unwrap();
        let half = ShadowScope::share(0.5).unwrap();
        let in_quarter = ids.iter().filter(|id| quarter.includes(id)).count();
        assert!((2_300..2_700).contains(&in_quarter), "{in_quarter}");
        // Every vehicle in a smaller share is in a larger one.
        assert!(
            ids.iter()
                .all(|id| !quarter.includes(id) || half.includes(id))
        );
        let all = ShadowScope::share(1.0).unwrap();
        assert!(ids.iter().all(|id| all.includes(id)));
    }

    #[test]
    fn bad_scopes_name_their_field() {
        for share in [0.0, -0.1, 1.5, f64::NAN, f64::INFINITY] {
            assert_eq!(ShadowScope::share(share).unwrap_err().field, "share");
        }
        assert_eq!(
            ShadowScope::vehicles(&[]).unwrap_err().field,
            "vehicles.vehicle_ids"
        );
        let error = ShadowScope::vehicles(&["ok".into(), "not ok".into()]).unwrap_err();
        assert_eq!(error.field, "vehicles.vehicle_ids[1]");
    }

    #[test]
    fn a_scope_round_trips_through_its_stored_form() {
        for scope in [
            ShadowScope::All,
            ShadowScope::share(0.3).unwrap(),
            ShadowScope::vehicles(&["b".into(), "a".into(), "a".into()]).unwrap(),
        ] {
            let json = serde_json::to_value(&scope).unwrap();
            assert_eq!(serde_json::from_value::<ShadowScope>(json).unwrap(), scope);
        }
        assert_eq!(
            ShadowScope::vehicles(&["b".into(), "a".into()])
                .unwrap()
                .describe(),
            "vehicles a, b"
        );
    }
}
