//! The open area incidents' areas as this server sees them, for the detector's prior (§11 of the
//! detector specification): a sample inside one is scored as if its receiver had flagged spoofing.
//! Every server refreshes them from the store once a second (the correlator's tick), whichever server
//! holds the correlator's lease, and every session step reads them. The areas are held in the core's
//! grid index ([`AreaIndex`]), built once per refresh that changes them, so a sample's lookup costs
//! the same with ten thousand open incidents as with one.
//!
//! It owns the shared index and its refresh. It must not decide what an incident is (the core's
//! correlator), how the point-in-area test is answered (the core's index) nor how the prior acts on
//! a detection (the core's detector).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};

use spoofwatch_core::geo::LatLon;
use spoofwatch_core::incident::Incident;
use spoofwatch_core::incident::areas::{Area, AreaIndex};

/// The open incidents' areas, shared by the correlator loop (writer) and the sessions (readers).
/// Disabled (`--incident-prior false`), it is always empty.
#[derive(Debug, Default)]
pub struct IncidentAreas {
    enabled: bool,
    /// Whether `index` is non-empty: the common case (no open incident) costs one atomic load.
    any: AtomicBool,
    index: RwLock<Arc<AreaIndex>>,
}

impl IncidentAreas {
    pub fn new(enabled: bool) -> Self {
        Self {
            enabled,
            any: AtomicBool::new(false),
            index: RwLock::new(Arc::new(AreaIndex::default())),
        }
    }

    /// Whether the point (degrees) lies inside an open incident's area.
    pub fn contains(&self, latitude_deg: f64, longitude_deg: f64) -> bool {
        if !self.any.load(Ordering::Acquire) {
            return false;
        }
        let point = LatLon {
            lat_deg: latitude_deg,
            lon_deg: longitude_deg,
        };
        self.current().contains(point)
    }

    /// Replaces the areas with those of `open` (the store's open incidents). The index is rebuilt
    /// only when they changed, and outside the lock: readers wait for a pointer swap at most.
    pub fn replace<'a>(&self, open: impl IntoIterator<Item = &'a Incident>) {
        if !self.enabled {
            return;
        }
        let areas: Vec<Area> = open
            .into_iter()
            .filter(|incident| incident.is_open())
            .map(|incident| Area {
                centre: incident.centre,
                radius_m: incident.radius_m,
            })
            .collect();
        if self.current().areas() == areas.as_slice() {
            return;
        }
        let any = !areas.is_empty();
        let index = Arc::new(AreaIndex::new(areas));
        *self.index.write().unwrap_or_else(|p| p.into_inner()) = index;
        self.any.store(any, Ordering::Release);
    }

    fn current(&self) -> Arc<AreaIndex> {
        Arc::clone(&self.index.read().unwrap_or_else(|p| p.into_inner()))
    }

    #[cfg(test)]
    fn len(&self) -> usize {
        self.current().len()
    }
}

#[cfg(test)]
mod tests {
    use spoofwatch_core::incident::{Incident, Spoofing};

    use super::*;

    fn incident(lat_deg: f64, radius_m: f64, ended: bool) -> Incident {
        Incident {
            id: 1,
            spoofing: Spoofing::Translation {
                offset_m: [100.0, 0.0],
            },
            centre: LatLon {
                lat_deg,
                lon_deg: 10.0,
            },
            radius_m,
            onset_s: 0.0,
            confirmed_s: 0.0,
            last_evidence_s: 0.0,
            ended_s: ended.then_some(10.0),
            confidence: 0.5,
            vehicles: Vec::new(),
        }
    }

    #[test]
    fn a_point_is_inside_an_open_incidents_circle_only() {
        let areas = IncidentAreas::new(true);
        assert!(!areas.contains(50.0, 10.0), "no incident yet");
        // 0.01° of latitude is about 1,112 m.
        areas.replace(&[incident(50.0, 1_200.0, false), incident(51.0, 1e6, true)]);
        assert_eq!(areas.len(), 1, "the ended incident has no area");
        assert!(areas.contains(50.0, 10.0));
        assert!(areas.contains(50.01, 10.0));
        assert!(!areas.contains(50.02, 10.0));
        assert!(!areas.contains(51.0, 10.0));
        areas.replace(&[]);
        assert!(!areas.contains(50.0, 10.0), "the incident ended");
    }

    #[test]
    fn a_disabled_prior_has_no_area() {
        let areas = IncidentAreas::new(false);
        areas.replace(&[incident(50.0, 1_200.0, false)]);
        assert!(!areas.contains(50.0, 10.0));
    }
}
