//! All geodesy of the crate: local east/north displacements between GNSS fixes (SPEC §4) and the
//! inverse, moving a fix by metres (used by the scenarios).
//!
//! Two projections: the default WGS-84 local form (meridian and prime-vertical radii at the previous
//! fix) and the reference code's spherical equirectangular form (one Earth radius for both axes,
//! [`EQUIRECTANGULAR_RADIUS_M`]), which the parity tests use. Must not know about samples, evidence or
//! tracks.

use serde::{Deserialize, Serialize};

/// WGS-84 semi-major axis (m).
pub const WGS84_A_M: f64 = 6_378_137.0;
/// WGS-84 flattening.
pub const WGS84_F: f64 = 1.0 / 298.257_223_563;
/// Sphere radius of the reference's equirectangular projection (m).
pub const EQUIRECTANGULAR_RADIUS_M: f64 = 6_378_137.0;

/// A GNSS fix in degrees.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LatLon {
    /// Latitude, degrees north.
    pub lat_deg: f64,
    /// Longitude, degrees east.
    pub lon_deg: f64,
}

impl LatLon {
    /// A fix from latitude and longitude in degrees.
    pub fn new(lat_deg: f64, lon_deg: f64) -> Self {
        Self { lat_deg, lon_deg }
    }

    /// Finite and inside |lat| ≤ 90, |lon| ≤ 180 (the reference's "valid lat/lon").
    pub fn is_valid(&self) -> bool {
        self.lat_deg.is_finite()
            && self.lon_deg.is_finite()
            && self.lat_deg.abs() <= 90.0
            && self.lon_deg.abs() <= 180.0
    }
}

/// How GNSS fixes become local east/north metres.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Projection {
    /// East/north from the WGS-84 meridian and prime-vertical radii at the previous fix (SPEC default).
    #[default]
    Wgs84Local,
    /// The reference's sphere (R = 6,378,137 m) around the trajectory's first valid fix.
    Equirectangular,
}

impl Projection {
    /// East/north displacement (m) from `previous` to `current`. `reference` is the trajectory's
    /// first valid fix; only the equirectangular form uses it.
    pub fn displacement(self, reference: LatLon, previous: LatLon, current: LatLon) -> [f64; 2] {
        match self {
            Projection::Wgs84Local => wgs84_local_displacement(previous, current),
            Projection::Equirectangular => {
                // Difference of two projected positions, as the reference computes it.
                let p = equirectangular_position(reference, previous);
                let c = equirectangular_position(reference, current);
                [c[0] - p[0], c[1] - p[1]]
            }
        }
    }
}

/// East/north metres of `point` on the reference sphere around `reference`:
/// east = R·cos(lat_ref)·(lon − lon_ref), north = R·(lat − lat_ref), angles in radians.
pub fn equirectangular_position(reference: LatLon, point: LatLon) -> [f64; 2] {
    let lat_ref = reference.lat_deg.to_radians();
    let east = EQUIRECTANGULAR_RADIUS_M
        * lat_ref.cos()
        * (point.lon_deg.to_radians() - reference.lon_deg.to_radians());
    let north =
        EQUIRECTANGULAR_RADIUS_M * (point.lat_deg.to_radians() - reference.lat_deg.to_radians());
    [east, north]
}

/// East/north metres from `from` to `to` with the WGS-84 radii of curvature at `from`:
/// east = N·cos(lat)·Δlon, north = M·Δlat (Δlon wrapped to (−π, π]).
pub fn wgs84_local_displacement(from: LatLon, to: LatLon) -> [f64; 2] {
    let (meridian, prime_vertical) = wgs84_radii(from.lat_deg);
    let lat = from.lat_deg.to_radians();
    let d_lat = (to.lat_deg - from.lat_deg).to_radians();
    let d_lon = wrap_degrees(to.lon_deg - from.lon_deg).to_radians();
    [prime_vertical * lat.cos() * d_lon, meridian * d_lat]
}

/// (meridian radius M, prime-vertical radius N) in metres at a geodetic latitude in degrees.
pub fn wgs84_radii(lat_deg: f64) -> (f64, f64) {
    let e2 = WGS84_F * (2.0 - WGS84_F);
    let sin_lat = lat_deg.to_radians().sin();
    let w2 = 1.0 - e2 * sin_lat * sin_lat;
    let w = w2.sqrt();
    let prime_vertical = WGS84_A_M / w;
    let meridian = WGS84_A_M * (1.0 - e2) / (w2 * w);
    (meridian, prime_vertical)
}

/// Moves a fix by `east_m`/`north_m` using the WGS-84 radii at the fix (the inverse of
/// [`wgs84_local_displacement`] to rounding); returns (lat, lon) in degrees, longitude wrapped into
/// [-180, 180). The latitude is NOT clamped: callers check it. Against a true geodesic the error grows
/// with the offset squared (a few cm at 1 km, far below GNSS noise).
pub fn displace_fix(
    latitude_deg: f64,
    longitude_deg: f64,
    east_m: f64,
    north_m: f64,
) -> (f64, f64) {
    let (meridian, prime_vertical) = wgs84_radii(latitude_deg);
    let d_lat = (north_m / meridian).to_degrees();
    let d_lon = (east_m / (prime_vertical * latitude_deg.to_radians().cos())).to_degrees();
    (
        latitude_deg + d_lat,
        wrap_longitude_deg(longitude_deg + d_lon),
    )
}

/// Wraps a longitude into [-180, 180); values already inside are returned bit-identical.
fn wrap_longitude_deg(longitude_deg: f64) -> f64 {
    if (-180.0..180.0).contains(&longitude_deg) {
        longitude_deg
    } else {
        (longitude_deg + 180.0).rem_euclid(360.0) - 180.0
    }
}

/// An angle difference in degrees, wrapped into (−180, 180] so the antimeridian is not a jump.
fn wrap_degrees(d: f64) -> f64 {
    if (-180.0..=180.0).contains(&d) {
        d
    } else {
        let wrapped = (d + 180.0).rem_euclid(360.0) - 180.0;
        if wrapped == -180.0 { 180.0 } else { wrapped }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    #[test]
    fn wgs84_radii_at_equator_and_pole() {
        // M(0) = a(1−e²), N(0) = a; at the pole M = N = a/√(1−e²).
        let e2 = WGS84_F * (2.0 - WGS84_F);
        let (m0, n0) = wgs84_radii(0.0);
        assert!(close(m0, 6_335_439.327, 1e-3), "{m0}");
        assert!(close(n0, WGS84_A_M, 1e-9));
        assert!(close(m0, WGS84_A_M * (1.0 - e2), 1e-6));
        let (m90, n90) = wgs84_radii(90.0);
        assert!(close(m90, 6_399_593.626, 1e-3), "{m90}");
        assert!(close(n90, m90, 1e-6));
    }

    #[test]
    fn wgs84_local_displacement_at_45_degrees() {
        // At 45°: e² sin² = 0.0033469..., N = a/√(1−e²/2) = 6,388,838.290 m,
        // M = a(1−e²)/(1−e²/2)^1.5 = 6,367,381.816 m.
        let from = LatLon::new(45.0, 10.0);
        let to = LatLon::new(45.001, 10.001);
        let d = wgs84_local_displacement(from, to);
        let d_rad = 0.001_f64.to_radians();
        let east = 6_388_838.290 * 45.0_f64.to_radians().cos() * d_rad;
        let north = 6_367_381.816 * d_rad;
        assert!(close(d[0], east, 1e-4), "{} vs {east}", d[0]);
        assert!(close(d[1], north, 1e-4), "{} vs {north}", d[1]);
        // ≈ 78.847 m east, 111.132 m north.
        assert!(
            close(d[0], 78.8468, 1e-3) && close(d[1], 111.1318, 1e-3),
            "{d:?}"
        );
    }

    #[test]
    fn wgs84_local_displacement_wraps_the_antimeridian() {
        let d = wgs84_local_displacement(LatLon::new(0.0, 179.9999), LatLon::new(0.0, -179.9999));
        // 0.0002° of longitude at the equator = a·0.0002·π/180 = 22.2639 m eastwards.
        assert!(close(d[0], 22.2639, 1e-3), "{d:?}");
        assert!(close(d[1], 0.0, 1e-12));
    }

    #[test]
    fn equirectangular_uses_the_reference_latitude() {
        // lat_ref = 60° → cos = 0.5; 0.001° = 1.745329e-5 rad; R·rad = 111.3195 m.
        let reference = LatLon::new(60.0, 20.0);
        let p = equirectangular_position(reference, LatLon::new(60.001, 20.002));
        assert!(close(p[0], 111.3195, 1e-3), "{p:?}");
        assert!(close(p[1], 111.3195, 1e-3), "{p:?}");
        // The displacement is a difference of positions around the SAME reference, even when
        // the previous fix is elsewhere.
        let d = Projection::Equirectangular.displacement(
            reference,
            LatLon::new(61.0, 21.0),
            LatLon::new(61.001, 21.002),
        );
        assert!(close(d[0], 111.3195, 1e-3), "{d:?}");
        assert!(close(d[1], 111.3195, 1e-3), "{d:?}");
    }

    #[test]
    fn fix_validity() {
        assert!(LatLon::new(-90.0, 180.0).is_valid());
        assert!(!LatLon::new(90.1, 0.0).is_valid());
        assert!(!LatLon::new(0.0, -180.5).is_valid());
        assert!(!LatLon::new(f64::NAN, 0.0).is_valid());
    }

    #[test]
    fn projection_default_and_serde_names() {
        assert_eq!(Projection::default(), Projection::Wgs84Local);
        let json = serde_json::to_string(&Projection::Equirectangular).expect("serialise");
        assert_eq!(json, "\"equirectangular\"");
        let back: Projection = serde_json::from_str("\"wgs84_local\"").expect("deserialise");
        assert_eq!(back, Projection::Wgs84Local);
    }

    #[test]
    fn radii_at_the_equator_and_pole_match_the_closed_forms() {
        // Equator: M = a(1-e²), N = a. Pole: M = N = a/sqrt(1-e²).
        let (m, n) = wgs84_radii(0.0);
        assert!((m - 6_335_439.327_083).abs() < 1e-3, "{m}");
        assert!((n - 6_378_137.0).abs() < 1e-6, "{n}");
        let (m, n) = wgs84_radii(90.0);
        assert!((m - 6_399_593.625_864).abs() < 1e-3, "{m}");
        assert!((n - 6_399_593.625_864).abs() < 1e-3, "{n}");
    }

    #[test]
    fn displacing_at_the_equator_moves_by_the_hand_computed_angles() {
        let (lat, lon) = displace_fix(0.0, 10.0, 100.0, 200.0);
        assert!((lat - (200.0 / 6_335_439.327_083_f64).to_degrees()).abs() < 1e-12);
        assert!((lon - 10.0 - (100.0 / 6_378_137.0_f64).to_degrees()).abs() < 1e-12);
    }

    #[test]
    fn longitude_wraps_across_the_antimeridian() {
        let (_, lon) = displace_fix(0.0, 179.9999, 50.0, 0.0);
        assert!(lon < -179.999, "{lon}");
        assert_eq!(wrap_longitude_deg(-110.91), -110.91);
        assert!((wrap_longitude_deg(190.0) + 170.0).abs() < 1e-12);
    }
}
