use crate::geo::displace_fix;
use crate::rng::Rng;

use super::*;

fn area(lat_deg: f64, lon_deg: f64, radius_m: f64) -> Area {
    Area {
        centre: LatLon::new(lat_deg, lon_deg),
        radius_m,
    }
}

/// Random areas of the correlator's sizes (up to 200 km + 100 km), centres anywhere (a share of
/// them within a degree of the antimeridian or of a pole), and a few that are not valid at all.
fn random_areas(rng: &mut Rng, count: usize) -> Vec<Area> {
    (0..count)
        .map(|i| {
            let radius_m = match i % 10 {
                0 => rng.uniform_range(0.0, 300_000.0),
                _ => rng.uniform_range(100.0, 11_000.0),
            };
            let (lat, lon) = match i % 7 {
                0 => (
                    rng.uniform_range(-80.0, 80.0),
                    rng.uniform_range(179.0, 180.0),
                ),
                1 => (
                    rng.uniform_range(-80.0, 80.0),
                    rng.uniform_range(-180.0, -179.0),
                ),
                2 => (
                    rng.uniform_range(89.0, 90.0),
                    rng.uniform_range(-180.0, 180.0),
                ),
                3 => (
                    rng.uniform_range(-90.0, -89.0),
                    rng.uniform_range(-180.0, 180.0),
                ),
                _ => (
                    rng.uniform_range(-90.0, 90.0),
                    rng.uniform_range(-180.0, 180.0),
                ),
            };
            area(lat, lon, radius_m)
        })
        .collect()
}

/// A point near an area: on its edge (where rounding decides), just inside or outside it, or
/// anywhere around, wrapped across the antimeridian as a fix would be.
fn point_near(rng: &mut Rng, area: &Area) -> LatLon {
    let bearing = rng.uniform_range(0.0, std::f64::consts::TAU);
    let scale = match rng.below(4) {
        0 => 1.0,
        1 => 1.0 - 1e-12,
        2 => 1.0 + 1e-12,
        _ => rng.uniform_range(0.0, 2.0),
    };
    let distance = area.radius_m * scale;
    let (lat, lon) = displace_fix(
        area.centre.lat_deg,
        area.centre.lon_deg,
        distance * bearing.sin(),
        distance * bearing.cos(),
    );
    LatLon::new(lat.clamp(-90.0, 90.0), lon)
}

#[test]
fn the_index_answers_as_the_linear_scan_for_random_areas_and_points() {
    let mut rng = Rng::seed_from_u64(54);
    for round in 0..40 {
        let count = [0, 1, 3, 10, 100, 1_000][round % 6];
        let areas = random_areas(&mut rng, count);
        let index = AreaIndex::new(areas.clone());
        let mut inside = 0;
        for _ in 0..4_000 {
            let point = if areas.is_empty() || rng.below(3) == 0 {
                LatLon::new(
                    rng.uniform_range(-90.0, 90.0),
                    rng.uniform_range(-180.0, 180.0),
                )
            } else {
                let near = rng.below(areas.len());
                point_near(&mut rng, &areas[near])
            };
            let expected = areas.iter().any(|a| a.contains(point));
            assert_eq!(
                index.contains(point),
                expected,
                "{point:?} among {count} areas (round {round})"
            );
            inside += usize::from(expected);
        }
        if count > 0 {
            assert!(inside > 100, "the points test the inside too ({inside})");
        }
    }
}

#[test]
fn areas_across_the_antimeridian_are_found_from_both_sides() {
    // distance_m wraps the longitude difference: 0.02° apart across ±180 is about 2.2 km at the
    // equator.
    assert!(distance_m(LatLon::new(0.0, 179.99), LatLon::new(0.0, -179.99)) < 2_300.0);
    let index = AreaIndex::new(vec![
        area(0.0, 179.99, 5_000.0),
        area(10.0, -180.0, 5_000.0),
    ]);
    assert_eq!(index.unindexed(), 0);
    for (lat, lon, inside) in [
        (0.0, 179.99, true),
        (0.0, 180.0, true),
        (0.0, -180.0, true),
        (0.0, -179.98, true),
        (0.0, -179.9, false),
        (10.0, 179.99, true),
        (10.0, -179.99, true),
        (10.0, 179.9, false),
    ] {
        let point = LatLon::new(lat, lon);
        assert_eq!(index.contains(point), inside, "{point:?}");
        assert_eq!(index.linear_contains(point), inside, "{point:?}");
    }
}

#[test]
fn areas_at_the_poles_cover_every_longitude_as_the_distance_does() {
    // On the local plane at a centre near the pole a degree of longitude is a few metres, so the
    // area takes in every longitude of its latitude band; the distance does not go across the pole
    // (the far side is as far as the latitude difference says).
    let index = AreaIndex::new(vec![area(89.999, 0.0, 1_000.0), area(-90.0, 0.0, 1_000.0)]);
    assert!(index.contains(LatLon::new(89.999, 180.0)));
    assert!(index.contains(LatLon::new(90.0, -90.0)));
    assert!(index.contains(LatLon::new(-90.0, 123.0)));
    assert!(!index.contains(LatLon::new(89.98, 0.0)));
    assert!(!index.contains(LatLon::new(-89.98, 0.0)));
    assert_eq!(
        index.unindexed(),
        2,
        "every column: beyond the cells an area may take"
    );
}

#[test]
fn odd_areas_and_points_answer_as_the_linear_scan() {
    let areas = vec![
        area(f64::NAN, 0.0, 1_000.0),
        area(0.0, 0.0, f64::NAN),
        area(0.0, 0.0, -1.0),
        area(0.0, 0.0, f64::INFINITY),
        area(95.0, 200.0, 1_000.0),
        area(45.0, 7.0, 1e300),
        area(45.0, 7.0, 0.0),
        area(30.0, 7.0, 1_000.0),
    ];
    let index = AreaIndex::new(areas.clone());
    assert_eq!(index.unindexed(), 6);
    let points = [
        LatLon::new(f64::NAN, 0.0),
        LatLon::new(0.0, f64::INFINITY),
        LatLon::new(f64::NEG_INFINITY, 0.0),
        LatLon::new(45.0, 7.0),
        LatLon::new(30.0, 7.0),
        LatLon::new(95.0, 200.0),
        LatLon::new(90.0000001, 7.0),
        LatLon::new(-20.0, -181.0),
        LatLon::new(1e300, 1e300),
    ];
    for point in points {
        assert_eq!(
            index.contains(point),
            areas.iter().any(|a| a.contains(point)),
            "{point:?}"
        );
    }
}

#[test]
fn cells_follow_the_median_area() {
    let mut areas: Vec<Area> = (0..100)
        .map(|i| area(40.0 + f64::from(i) * 0.1, 10.0, 11_000.0))
        .collect();
    areas.push(area(0.0, 0.0, 300_000.0));
    let index = AreaIndex::new(areas);
    // 22 km across is about 0.2° of latitude; the one large area does not coarsen the grid.
    assert!((0.19..0.21).contains(&index.cell_deg), "{}", index.cell_deg);
    assert_eq!(index.unindexed(), 0);
    // At most 3 × 3 cells for each small area; the large one spans about 28 × 28.
    assert!(
        index.entries.len() <= 100 * 9 + 30 * 30,
        "{}",
        index.entries.len()
    );
    assert!(AreaIndex::new(Vec::new()).is_empty());
    assert!(!AreaIndex::new(Vec::new()).contains(LatLon::new(0.0, 0.0)));
}
