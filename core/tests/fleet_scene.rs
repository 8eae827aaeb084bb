//! Fleet scenes: a regional spoofer over many simulated vehicles (SPEC §9). Every check rebuilds what it
//! expects from the ground truth with its own geodesy and the plain drive simulator.

use spoofwatch_core::sample::{Sample, Track};
use spoofwatch_core::scenario::{
    DriveSpec, FleetScene, FleetSpec, FleetTruth, Range, RegionalAttack, ScenarioError, Spoofer,
    TrueState, generate_fleet, simulate_drive_with_truth,
};

// ---- independent geodesy (WGS-84 local radii; the library keeps its own copy) ----

fn wgs84_radii_m(latitude_deg: f64) -> (f64, f64) {
    let a = 6_378_137.0;
    let f = 1.0 / 298.257_223_563;
    let e2 = f * (2.0 - f);
    let s2 = latitude_deg.to_radians().sin().powi(2);
    let w = (1.0 - e2 * s2).sqrt();
    (a * (1.0 - e2) / (w * w * w), a / w)
}

/// Flat-earth (east, north) metres from one position to another, radii at the first.
fn offset_m(from: (f64, f64), to: (f64, f64)) -> (f64, f64) {
    let (meridian, prime_vertical) = wgs84_radii_m(from.0);
    let east = (to.1 - from.1).to_radians() * prime_vertical * from.0.to_radians().cos();
    let north = (to.0 - from.0).to_radians() * meridian;
    (east, north)
}

fn fix(sample: &Sample) -> (f64, f64) {
    (sample.latitude_deg, sample.longitude_deg)
}

fn position(state: &TrueState) -> (f64, f64) {
    (state.latitude_deg, state.longitude_deg)
}

fn distance_m(from: (f64, f64), to: (f64, f64)) -> f64 {
    let (east, north) = offset_m(from, to);
    east.hypot(north)
}

// ---- scenes ----

const CENTRE: (f64, f64) = (32.23, -110.91);

/// 40 vehicles (10 routed through) for 20 minutes at 1 Hz in an 8 km square; an 800 m spoofer at the
/// centre, active from 5 to 15 minutes.
fn small_spec(attack: RegionalAttack) -> FleetSpec {
    FleetSpec {
        vehicles: 40,
        pass_through: 10,
        area_size_m: 8_000.0,
        duration_s: 1_200.0,
        spoofer: Spoofer {
            lat_deg: CENTRE.0,
            lon_deg: CENTRE.1,
            radius_m: 800.0,
            start_s: 300.0,
            duration_s: 600.0,
            attack,
        },
        seed: 7,
        ..FleetSpec::default()
    }
}

const TRANSLATION: RegionalAttack = RegionalAttack::Translation {
    east_m: 300.0,
    north_m: -400.0,
};
const DRIFT: RegionalAttack = RegionalAttack::Drift {
    east_mps: 0.6,
    north_mps: 0.8,
};
const FALSE_POSITION: RegionalAttack = RegionalAttack::Position {
    lat_deg: 32.30,
    lon_deg: -110.80,
};

fn scene(spec: &FleetSpec) -> FleetScene {
    generate_fleet(spec).expect("a valid fleet spec")
}

/// The vehicle's drive as the plain simulator makes it (unspoofed), from its drive seed and its start
/// (the true position of row 0, which no outage drops).
fn unspoofed_drive(spec: &FleetSpec, scene: &FleetScene, vehicle: usize) -> Track {
    let truth = &scene.truth.vehicles[vehicle];
    let start = scene.true_states[vehicle][0];
    let drive_spec = DriveSpec {
        duration_s: spec.duration_s,
        rate_hz: spec.rate_hz,
        start_lat_deg: start.latitude_deg,
        start_lon_deg: start.longitude_deg,
        ..spec.distribution.draw(truth.drive_seed)
    };
    let drive = simulate_drive_with_truth(&drive_spec, &truth.vehicle_id).expect("a drawn spec");
    assert_eq!(
        drive.truth, scene.true_states[vehicle],
        "{}",
        truth.vehicle_id
    );
    drive.track
}

/// Whether the spoofer captures a vehicle at a true state, decided with this file's geodesy; `None` when
/// the true position lies within a micrometre of the circle (either answer is right there).
fn should_capture(spoofer: &Spoofer, state: &TrueState) -> Option<bool> {
    let active = state.timestamp_s >= spoofer.start_s
        && state.timestamp_s < spoofer.start_s + spoofer.duration_s;
    let distance = distance_m((spoofer.lat_deg, spoofer.lon_deg), position(state));
    if active && (distance - spoofer.radius_m).abs() < 1e-6 {
        return None;
    }
    Some(active && distance <= spoofer.radius_m)
}

fn labels(track: &Track) -> Vec<bool> {
    track
        .records
        .iter()
        .map(|r| r.label.expect("every row is labelled"))
        .collect()
}

#[test]
fn the_same_seed_gives_the_same_scene_and_another_seed_differs() {
    let spec = small_spec(DRIFT);
    let first = scene(&spec);
    assert_eq!(first, scene(&spec));
    let other = scene(&FleetSpec { seed: 8, ..spec });
    assert_ne!(first.tracks, other.tracks);
    assert_ne!(first.truth.vehicles, other.truth.vehicles);
}

#[test]
fn captured_rows_are_exactly_those_whose_true_position_is_inside_while_the_spoofer_is_active() {
    let spec = small_spec(TRANSLATION);
    let scene = scene(&spec);
    assert_eq!(scene.tracks.len(), 40);
    let mut spoofed_rows = 0;
    for ((track, states), truth) in scene
        .tracks
        .iter()
        .zip(&scene.true_states)
        .zip(&scene.truth.vehicles)
    {
        assert_eq!(track.vehicle_id, truth.vehicle_id);
        assert_eq!(track.records.len(), states.len());
        let labels = labels(track);
        for ((row, &label), state) in labels.iter().enumerate().zip(states) {
            if let Some(expected) = should_capture(&spec.spoofer, state) {
                assert_eq!(
                    label, expected,
                    "{} row {row} at {} s",
                    track.vehicle_id, state.timestamp_s
                );
            }
        }
        let captured_rows = labels.iter().filter(|&&l| l).count();
        spoofed_rows += captured_rows;
        // Uncaptured vehicles have no spoofed row; the episodes count exactly the labelled rows.
        assert_eq!(truth.captured, captured_rows > 0, "{}", truth.vehicle_id);
        assert_eq!(
            truth.captures.iter().map(|c| c.rows).sum::<usize>(),
            captured_rows
        );
        for episode in &truth.captures {
            let rows: Vec<usize> = (0..states.len())
                .filter(|&i| {
                    let t = states[i].timestamp_s;
                    t >= episode.start.timestamp_s && t <= episode.end.timestamp_s
                })
                .collect();
            assert_eq!(rows.len(), episode.rows, "an episode is one run of rows");
            assert!(rows.iter().all(|&i| labels[i]));
            let first = rows[0];
            assert_eq!(
                (episode.start.true_lat_deg, episode.start.true_lon_deg),
                position(&states[first])
            );
            assert_eq!(
                (
                    episode.start.reported_lat_deg,
                    episode.start.reported_lon_deg
                ),
                fix(&track.records[first].sample)
            );
            let last = rows[rows.len() - 1];
            assert_eq!(
                (episode.end.reported_lat_deg, episode.end.reported_lon_deg),
                fix(&track.records[last].sample)
            );
        }
    }
    assert_eq!(scene.truth.spoofed_rows, spoofed_rows);
    assert_eq!(
        scene.truth.captured_vehicles,
        scene.truth.vehicles.iter().filter(|v| v.captured).count()
    );
}

#[test]
fn the_routed_vehicles_pass_through_and_the_others_keep_clear() {
    let spec = small_spec(DRIFT);
    let scene = scene(&spec);
    let routed: Vec<_> = scene
        .truth
        .vehicles
        .iter()
        .filter(|v| v.routed_through)
        .collect();
    assert_eq!(routed.len(), 10);
    assert!(routed.iter().all(|v| v.captured), "{routed:?}");
    assert_eq!(scene.truth.captured_vehicles, 10);
    // The others start in the square.
    for (states, truth) in scene.true_states.iter().zip(&scene.truth.vehicles) {
        if !truth.routed_through {
            let (east, north) = offset_m(CENTRE, position(&states[0]));
            assert!(east.abs() <= 4_000.0 + 1e-6 && north.abs() <= 4_000.0 + 1e-6);
        }
    }
    // Both kinds of capture occur: inside at switch-on, and driving in later; and vehicles leave the
    // circle while the spoofer is still on.
    let episodes: Vec<_> = scene
        .truth
        .vehicles
        .iter()
        .flat_map(|v| &v.captures)
        .collect();
    assert!(episodes.iter().any(|e| e.start.timestamp_s == 300.0));
    assert!(episodes.iter().any(|e| e.start.timestamp_s > 300.0));
    assert!(episodes.iter().any(|e| e.end.timestamp_s < 899.0));

    // A larger fleet in a larger area: all of the asked-for vehicles, and nobody else.
    let many = FleetSpec {
        vehicles: 120,
        pass_through: 25,
        area_size_m: 20_000.0,
        duration_s: 900.0,
        spoofer: Spoofer {
            radius_m: 1_500.0,
            start_s: 200.0,
            duration_s: 500.0,
            ..spec.spoofer
        },
        seed: 11,
        ..spec
    };
    let truth = scene_truth(&many);
    assert_eq!(truth.captured_vehicles, 25);
    assert!(
        truth
            .vehicles
            .iter()
            .all(|v| v.captured == v.routed_through)
    );
}

fn scene_truth(spec: &FleetSpec) -> FleetTruth {
    scene(spec).truth
}

#[test]
fn uncaptured_rows_are_the_plain_simulator_and_a_translation_moves_every_captured_fix_alike() {
    let spec = small_spec(TRANSLATION);
    let scene = scene(&spec);
    let mut checked = 0;
    for (vehicle, track) in scene.tracks.iter().enumerate() {
        let plain = unspoofed_drive(&spec, &scene, vehicle);
        for (record, original) in track.records.iter().zip(&plain.records) {
            assert_eq!(record.line, original.line);
            // Onboard motion is never touched.
            assert_eq!(record.sample.speed_mps, original.sample.speed_mps);
            assert_eq!(record.sample.heading_deg, original.sample.heading_deg);
            if record.label == Some(true) {
                let (east, north) = offset_m(fix(&original.sample), fix(&record.sample));
                assert!(
                    (east - 300.0).abs() < 1e-6 && (north + 400.0).abs() < 1e-6,
                    "{}: ({east}, {north})",
                    track.vehicle_id
                );
                checked += 1;
            } else {
                assert_eq!(record.sample, original.sample, "{}", track.vehicle_id);
            }
        }
    }
    assert!(checked > 1_000, "{checked} captured rows");
}

#[test]
fn a_drift_grows_at_the_given_velocity_from_each_capture() {
    let spec = small_spec(DRIFT);
    let scene = scene(&spec);
    let mut largest_m: f64 = 0.0;
    for (vehicle, track) in scene.tracks.iter().enumerate() {
        let plain = unspoofed_drive(&spec, &scene, vehicle);
        let episodes = &scene.truth.vehicles[vehicle].captures;
        for (record, original) in track.records.iter().zip(&plain.records) {
            if record.label != Some(true) {
                continue;
            }
            let t = record.sample.timestamp_s;
            let episode = episodes
                .iter()
                .find(|e| e.start.timestamp_s <= t && t <= e.end.timestamp_s)
                .expect("a captured row lies in an episode");
            let since_s = t - episode.start.timestamp_s;
            let (east, north) = offset_m(fix(&original.sample), fix(&record.sample));
            assert!(
                (east - 0.6 * since_s).abs() < 1e-6 && (north - 0.8 * since_s).abs() < 1e-6,
                "{} at {t} s: ({east}, {north}) after {since_s} s",
                track.vehicle_id
            );
            largest_m = largest_m.max(east.hypot(north));
        }
    }
    // Some vehicle stays captured for minutes: its drift reaches hundreds of metres.
    assert!(largest_m > 300.0, "{largest_m}");
}

#[test]
fn a_common_false_position_makes_every_captured_vehicle_report_the_same_place() {
    let mut spec = small_spec(FALSE_POSITION);
    // Without multipath outliers the receivers' errors stay metre-level.
    spec.distribution.multipath_probability = Range { min: 0.0, max: 0.0 };
    let scene = scene(&spec);
    let target = (32.30, -110.80);
    let mut captured_vehicles = 0;
    for (vehicle, track) in scene.tracks.iter().enumerate() {
        let plain = unspoofed_drive(&spec, &scene, vehicle);
        let states = &scene.true_states[vehicle];
        let mut captured = false;
        for ((record, original), state) in track.records.iter().zip(&plain.records).zip(states) {
            if record.label != Some(true) {
                continue;
            }
            captured = true;
            // The receiver's own error from the truth, carried to the false position.
            let own_error = offset_m(position(state), fix(&original.sample));
            let reported = offset_m(target, fix(&record.sample));
            assert!(
                (reported.0 - own_error.0).abs() < 1e-6 && (reported.1 - own_error.1).abs() < 1e-6,
                "{}: {reported:?} vs {own_error:?}",
                track.vehicle_id
            );
            assert!(distance_m(target, fix(&record.sample)) < 15.0);
        }
        captured_vehicles += usize::from(captured);
    }
    assert_eq!(captured_vehicles, 10);
}

#[test]
fn the_ground_truth_round_trips_through_json_and_names_the_attack() {
    let truth = scene_truth(&FleetSpec {
        vehicles: 6,
        pass_through: 2,
        duration_s: 400.0,
        spoofer: Spoofer {
            start_s: 100.0,
            duration_s: 200.0,
            ..Spoofer::default()
        },
        ..FleetSpec::default()
    });
    let json = serde_json::to_string_pretty(&truth).expect("serialises");
    assert!(
        json.contains("\"type\": \"drift\"") && json.contains("\"routed_through\""),
        "{json}"
    );
    let back: FleetTruth = serde_json::from_str(&json).expect("parses");
    assert_eq!(back, truth);
    assert_eq!(truth.captured_vehicles, 2);
}

#[test]
fn bad_specs_are_refused_naming_the_field() {
    let base = small_spec(DRIFT);
    let with_spoofer = |spoofer: Spoofer| FleetSpec {
        spoofer,
        ..base.clone()
    };
    let cases: Vec<(&str, FleetSpec)> = vec![
        (
            "vehicles",
            FleetSpec {
                vehicles: 0,
                pass_through: 0,
                ..base.clone()
            },
        ),
        (
            "pass_through",
            FleetSpec {
                pass_through: 41,
                ..base.clone()
            },
        ),
        (
            "centre_lat_deg",
            FleetSpec {
                centre_lat_deg: 81.0,
                ..base.clone()
            },
        ),
        (
            "centre_lon_deg",
            FleetSpec {
                centre_lon_deg: f64::NAN,
                ..base.clone()
            },
        ),
        (
            "area_size_m",
            FleetSpec {
                area_size_m: 50.0,
                ..base.clone()
            },
        ),
        (
            "duration_s",
            FleetSpec {
                duration_s: -1.0,
                ..base.clone()
            },
        ),
        (
            "rate_hz",
            FleetSpec {
                rate_hz: 0.0,
                ..base.clone()
            },
        ),
        (
            "vehicles * duration_s * rate_hz",
            FleetSpec {
                vehicles: 10_000,
                pass_through: 0,
                duration_s: 3_600.0,
                ..base.clone()
            },
        ),
        (
            "spoofer.lat_deg",
            with_spoofer(Spoofer {
                lat_deg: -95.0,
                ..base.spoofer
            }),
        ),
        (
            "spoofer.radius_m",
            with_spoofer(Spoofer {
                radius_m: 0.0,
                ..base.spoofer
            }),
        ),
        (
            "spoofer.start_s",
            with_spoofer(Spoofer {
                start_s: 1_200.0,
                ..base.spoofer
            }),
        ),
        (
            "spoofer.duration_s",
            with_spoofer(Spoofer {
                duration_s: 901.0,
                ..base.spoofer
            }),
        ),
        (
            "spoofer.attack",
            with_spoofer(Spoofer {
                attack: RegionalAttack::Translation {
                    east_m: 0.0,
                    north_m: 0.0,
                },
                ..base.spoofer
            }),
        ),
        (
            "spoofer.attack.north_mps",
            with_spoofer(Spoofer {
                attack: RegionalAttack::Drift {
                    east_mps: 1.0,
                    north_mps: f64::INFINITY,
                },
                ..base.spoofer
            }),
        ),
        (
            "spoofer.attack",
            with_spoofer(Spoofer {
                attack: RegionalAttack::Drift {
                    east_mps: 60.0,
                    north_mps: 60.0,
                },
                ..base.spoofer
            }),
        ),
        (
            "spoofer.attack.lat_deg",
            with_spoofer(Spoofer {
                attack: RegionalAttack::Position {
                    lat_deg: 89.0,
                    lon_deg: 0.0,
                },
                ..base.spoofer
            }),
        ),
    ];
    for (field, spec) in cases {
        let err = generate_fleet(&spec).expect_err(field);
        assert!(
            matches!(&err, ScenarioError::InvalidFleet { field: named, .. } if *named == field),
            "{field}: {err}"
        );
        assert!(err.to_string().contains(field), "{err}");
    }
    // The drive distribution is checked too.
    let mut bad = base.clone();
    bad.distribution.rates_hz.clear();
    assert!(matches!(
        generate_fleet(&bad),
        Err(ScenarioError::InvalidDistribution {
            field: "rates_hz",
            ..
        })
    ));
    assert_eq!(FleetSpec::default().validate(), Ok(()));
}
