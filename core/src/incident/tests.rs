use super::*;

/// A point `east_m`/`north_m` from a city centre.
fn at(east_m: f64, north_m: f64) -> LatLon {
    let (lat, lon) = displace_fix(32.2, -110.9, east_m, north_m);
    LatLon::new(lat, lon)
}

/// An onset of a vehicle whose true position is `anchor` and whose fix is displaced by `offset_m`.
fn onset(vehicle: &str, time_s: f64, anchor: LatLon, offset_m: [f64; 2]) -> AlarmOnset {
    let (lat, lon) = displace_fix(anchor.lat_deg, anchor.lon_deg, offset_m[0], offset_m[1]);
    AlarmOnset {
        vehicle_id: vehicle.to_string(),
        alarm_id: time_s as i64,
        time_s,
        fix: LatLon::new(lat, lon),
        offset_m,
        drift_mps: [0.0, 0.0],
        credential: None,
        source: String::new(),
    }
}

fn drifting(vehicle: &str, time_s: f64, anchor: LatLon, drift_mps: [f64; 2]) -> AlarmOnset {
    AlarmOnset {
        drift_mps,
        ..onset(vehicle, time_s, anchor, [5.0, -3.0])
    }
}

fn correlator() -> AreaCorrelator {
    AreaCorrelator::new(AreaConfig::default())
}

fn feed(correlator: &mut AreaCorrelator, onsets: Vec<AlarmOnset>) -> Vec<IncidentChange> {
    onsets
        .into_iter()
        .flat_map(|o| correlator.onset(o))
        .collect()
}

fn close(a: f64, b: f64, tolerance: f64) -> bool {
    (a - b).abs() <= tolerance
}

#[test]
fn three_vehicles_displaced_alike_open_a_translation_incident() {
    let mut c = correlator();
    let changes = feed(
        &mut c,
        vec![
            onset("a", 100.0, at(0.0, 0.0), [100.0, 0.0]),
            onset("b", 160.0, at(3_000.0, 0.0), [104.0, 3.0]),
            onset("c", 220.0, at(0.0, 3_000.0), [97.0, -2.0]),
        ],
    );
    assert_eq!(changes.len(), 1);
    let IncidentChange { kind, incident } = &changes[0];
    assert_eq!(*kind, ChangeKind::Opened);
    assert_eq!(incident.id, 1);
    // The component-wise median of (100, 0), (104, 3), (97, -2).
    assert_eq!(
        incident.spoofing,
        Spoofing::Translation {
            offset_m: [100.0, 0.0]
        }
    );
    // Centre: the mean of the true positions (1000, 1000); radius: the farthest (√(2000² + 1000²)
    // = 2236.07 m) plus the 1 km margin.
    let centre = wgs84_local_displacement(at(0.0, 0.0), incident.centre);
    assert!(close(centre[0], 1_000.0, 1.0) && close(centre[1], 1_000.0, 1.0));
    assert!(
        close(incident.radius_m, 3_236.07, 2.0),
        "{}",
        incident.radius_m
    );
    assert_eq!((incident.onset_s, incident.confirmed_s), (100.0, 220.0));
    assert_eq!(incident.vehicles.len(), 3);
    assert!(incident.contains(at(1_000.0, 1_000.0)) && !incident.contains(at(9_000.0, 0.0)));
    assert!(
        c.state().pending.is_empty(),
        "members leave the pending onsets"
    );
}

#[test]
fn receivers_reporting_one_position_open_a_false_position_incident() {
    let target = at(500.0, 500.0);
    let displaced_to_target = |vehicle: &str, time_s: f64, east: f64, north: f64| {
        let offset = wgs84_local_displacement(at(east, north), target);
        onset(vehicle, time_s, at(east, north), offset)
    };
    let mut c = correlator();
    let changes = feed(
        &mut c,
        vec![
            displaced_to_target("a", 0.0, -2_000.0, 0.0),
            displaced_to_target("b", 10.0, 2_000.0, 1_000.0),
            displaced_to_target("c", 20.0, 0.0, -2_500.0),
        ],
    );
    let incident = &changes[0].incident;
    let Spoofing::FalsePosition { position } = incident.spoofing else {
        panic!("{:?}", incident.spoofing);
    };
    assert!(distance_m(position, target) < 0.5);
}

#[test]
fn vehicles_pulled_the_same_way_open_a_drift_incident() {
    let mut c = correlator();
    let changes = feed(
        &mut c,
        vec![
            drifting("a", 0.0, at(0.0, 0.0), [1.0, 0.5]),
            drifting("b", 30.0, at(1_000.0, 0.0), [1.2, 0.45]),
            drifting("c", 60.0, at(0.0, 1_000.0), [0.9, 0.55]),
        ],
    );
    assert_eq!(
        changes[0].incident.spoofing,
        Spoofing::Drift {
            drift_mps: [1.0, 0.5]
        }
    );
}

#[test]
fn too_few_too_far_too_late_or_disagreeing_onsets_open_nothing() {
    let cases: [(&str, Vec<AlarmOnset>); 5] = [
        (
            "two vehicles",
            vec![
                onset("a", 0.0, at(0.0, 0.0), [100.0, 0.0]),
                onset("b", 10.0, at(500.0, 0.0), [100.0, 0.0]),
            ],
        ),
        (
            "one beyond the radius",
            vec![
                onset("a", 0.0, at(0.0, 0.0), [100.0, 0.0]),
                onset("b", 10.0, at(500.0, 0.0), [100.0, 0.0]),
                onset("c", 20.0, at(10_500.0, 0.0), [100.0, 0.0]),
            ],
        ),
        (
            "one beyond the window",
            vec![
                onset("a", 0.0, at(0.0, 0.0), [100.0, 0.0]),
                onset("b", 10.0, at(500.0, 0.0), [100.0, 0.0]),
                onset("c", 320.0, at(0.0, 500.0), [100.0, 0.0]),
            ],
        ),
        (
            "offsets in three directions",
            vec![
                onset("a", 0.0, at(0.0, 0.0), [100.0, 0.0]),
                onset("b", 10.0, at(500.0, 0.0), [0.0, 100.0]),
                onset("c", 20.0, at(0.0, 500.0), [-70.0, -70.0]),
            ],
        ),
        (
            "offsets too small to mean anything",
            vec![
                onset("a", 0.0, at(0.0, 0.0), [20.0, 0.0]),
                onset("b", 10.0, at(500.0, 0.0), [21.0, 0.0]),
                onset("c", 20.0, at(0.0, 500.0), [19.0, 0.0]),
            ],
        ),
    ];
    for (case, onsets) in cases {
        let mut c = correlator();
        assert!(feed(&mut c, onsets).is_empty(), "{case}");
    }
}

#[test]
fn one_vehicle_alarming_again_is_one_vehicle() {
    let mut c = correlator();
    let changes = feed(
        &mut c,
        vec![
            onset("a", 0.0, at(0.0, 0.0), [100.0, 0.0]),
            onset("a", 50.0, at(100.0, 0.0), [100.0, 0.0]),
            onset("b", 60.0, at(500.0, 0.0), [100.0, 0.0]),
        ],
    );
    assert!(changes.is_empty());
    assert_eq!(c.state().pending.len(), 2, "the latest onset per vehicle");
}

#[test]
fn agreeing_vehicles_join_and_the_incident_ends_after_the_quiet_time() {
    let mut c = correlator();
    feed(
        &mut c,
        vec![
            onset("a", 0.0, at(0.0, 0.0), [100.0, 0.0]),
            onset("b", 10.0, at(500.0, 0.0), [100.0, 0.0]),
            onset("c", 20.0, at(0.0, 500.0), [100.0, 0.0]),
        ],
    );
    // Long after the window: a vehicle that agrees joins, one that does not waits.
    let joined = c.onset(onset("d", 1_000.0, at(4_000.0, 0.0), [110.0, 5.0]));
    assert_eq!(joined[0].kind, ChangeKind::Joined);
    assert_eq!(joined[0].incident.vehicles.len(), 4);
    assert!(
        c.onset(onset("e", 1_010.0, at(0.0, 0.0), [0.0, 100.0]))
            .is_empty()
    );
    assert_eq!(c.state().pending.len(), 1);

    for (vehicle, alarm_id, time_s) in [("a", 0, 100.0), ("b", 10, 200.0), ("c", 20, 300.0)] {
        let end = AlarmEnd {
            vehicle_id: vehicle.into(),
            alarm_id,
            time_s,
        };
        assert_eq!(c.end(&end)[0].kind, ChangeKind::Evidence);
    }
    assert!(c.advance(5_000.0).is_empty(), "d's alarm is still open");
    let end = AlarmEnd {
        vehicle_id: "d".into(),
        alarm_id: 1_000,
        time_s: 5_100.0,
    };
    c.end(&end);
    assert!(c.advance(5_699.0).is_empty(), "quiet for 599 s");
    let ended = c.advance(5_700.0);
    assert_eq!(ended[0].kind, ChangeKind::Ended);
    assert_eq!(ended[0].incident.ended_s, Some(5_700.0));
    assert!(c.open_incidents().is_empty());
    assert!(
        c.state().pending.is_empty(),
        "e's onset is older than the window"
    );
}

#[test]
fn a_stored_state_continues_exactly() {
    let onsets = vec![
        onset("a", 0.0, at(0.0, 0.0), [100.0, 0.0]),
        onset("b", 10.0, at(500.0, 0.0), [101.0, 2.0]),
        onset("c", 20.0, at(0.0, 500.0), [99.0, 0.0]),
        onset("d", 30.0, at(900.0, 0.0), [103.0, -1.0]),
    ];
    let mut whole = correlator();
    let expected = feed(&mut whole, onsets.clone());
    let mut changes = Vec::new();
    let mut state = AreaCorrelator::new(AreaConfig::default()).state().clone();
    for o in onsets {
        let json = serde_json::to_string(&state).unwrap();
        let mut resumed =
            AreaCorrelator::resume(AreaConfig::default(), serde_json::from_str(&json).unwrap());
        changes.extend(resumed.onset(o));
        state = resumed.state().clone();
    }
    assert_eq!(changes, expected);
    assert_eq!(&state, whole.state());
}

#[test]
fn confidence_grows_with_agreeing_vehicles() {
    assert_eq!(confidence(3, 0.0), 0.75);
    assert_eq!(confidence(10, 0.0), 1.0 - 0.5f64.powi(9));
    assert_eq!(confidence(3, 0.5), 0.5);
    assert_eq!(confidence(5, 1.0), 0.0);
}

#[test]
fn a_bad_configuration_names_its_field() {
    let bad = [
        (
            AreaConfig {
                radius_m: f64::NAN,
                ..AreaConfig::default()
            },
            "radius_m",
        ),
        (
            AreaConfig {
                window_s: 0.0,
                ..AreaConfig::default()
            },
            "window_s",
        ),
        (
            AreaConfig {
                min_vehicles: 1,
                ..AreaConfig::default()
            },
            "min_vehicles",
        ),
        (
            AreaConfig {
                quiet_s: -1.0,
                ..AreaConfig::default()
            },
            "quiet_s",
        ),
    ];
    for (config, field) in bad {
        assert_eq!(config.validate().unwrap_err().0, field);
    }
    assert!(AreaConfig::default().validate().is_ok());
}

#[test]
fn drifts_agree_by_direction_whatever_their_measured_speed() {
    let mut c = correlator();
    // A 1.5 m/s drift to the north-west, read at 0.4–1.3 m/s depending on how long ago each vehicle
    // was captured.
    let changes = feed(
        &mut c,
        vec![
            drifting("a", 0.0, at(0.0, 0.0), [-0.3, 0.45]),
            drifting("b", 30.0, at(1_000.0, 0.0), [-0.8, 1.0]),
            drifting("c", 60.0, at(0.0, 1_000.0), [-0.75, 1.05]),
        ],
    );
    assert!(matches!(
        changes[0].incident.spoofing,
        Spoofing::Drift { .. }
    ));
    // A drift a quarter turn away is another story.
    assert!(
        c.onset(drifting("d", 90.0, at(500.0, 500.0), [0.8, 0.6]))
            .is_empty()
    );
    // Alarmed seconds into the drift, a vehicle reads 0.2 m/s: it joins the open incident it lies
    // in, without moving the estimate; 0.1 m/s says nothing, and 0.2 m/s could not open one.
    let estimate = changes[0].incident.spoofing;
    assert!(
        c.onset(drifting("e", 100.0, at(300.0, 300.0), [-0.05, 0.09]))
            .is_empty()
    );
    let joined = c.onset(drifting("f", 110.0, at(300.0, 300.0), [-0.12, 0.16]));
    assert_eq!(joined.len(), 1);
    assert_eq!(joined[0].kind, ChangeKind::Joined);
    assert_eq!(joined[0].incident.vehicles.len(), 4);
    assert_eq!(joined[0].incident.spoofing, estimate);
}

#[test]
fn a_member_let_go_by_the_spoofer_stays_in_its_incident() {
    let mut c = correlator();
    let members = ["a", "b", "c"];
    feed(
        &mut c,
        members
            .iter()
            .zip([0.0, 500.0, 1_000.0])
            .map(|(v, east)| onset(v, 0.0, at(east, 0.0), [100.0, 0.0]))
            .collect(),
    );
    // The spoofer stops: each fix steps back, the alarms read the opposite translation.
    let exits: Vec<_> = members
        .iter()
        .zip([0.0, 500.0, 1_000.0])
        .map(|(v, east)| onset(v, 600.0, at(east, 0.0), [-100.0, 0.0]))
        .collect();
    let changes = feed(&mut c, exits);
    assert!(
        changes
            .iter()
            .all(|x| x.kind == ChangeKind::Evidence && x.incident.id == 1)
    );
    assert_eq!(c.open_incidents().len(), 1);
    assert_eq!(
        c.open_incidents()[0].spoofing,
        Spoofing::Translation {
            offset_m: [100.0, 0.0]
        },
        "the estimate keeps the evidence the members joined with"
    );
}

/// `onset` sent under the credential `credential`, all of whose vehicles are one source.
fn sent_by(credential: &str, onset: AlarmOnset) -> AlarmOnset {
    AlarmOnset {
        credential: Some(credential.to_string()),
        source: credential.to_string(),
        ..onset
    }
}

/// One credential inventing three vehicle ids, each displaced alike (a gateway's vehicles, or
/// three made-up ids of one token), opens nothing: they are one source. The same onsets from two
/// credentials open the incident, which lists both.
#[test]
fn an_incident_needs_alarms_from_independent_sources() {
    let onsets = || {
        vec![
            onset("a", 100.0, at(0.0, 0.0), [200.0, 0.0]),
            onset("b", 101.0, at(9_900.0, 0.0), [200.0, 0.0]),
            onset("c", 102.0, at(4_950.0, 8_570.0), [200.0, 0.0]),
        ]
    };
    let mut one = correlator();
    let alone: Vec<_> = onsets()
        .into_iter()
        .map(|o| sent_by("token gw sha256:aa", o))
        .collect();
    assert_eq!(
        feed(&mut one, alone),
        [],
        "one source is one piece of evidence"
    );
    assert_eq!(one.state().pending.len(), 3, "they wait for another source");

    let mut two = correlator();
    let credentials = [
        "token gw sha256:aa",
        "token gw sha256:aa",
        "certificate c sha256:bb",
    ];
    let mixed: Vec<_> = onsets()
        .into_iter()
        .zip(credentials)
        .map(|(o, credential)| sent_by(credential, o))
        .collect();
    let changes = feed(&mut two, mixed);
    assert_eq!(changes.len(), 1);
    let incident = &changes[0].incident;
    assert_eq!(changes[0].kind, ChangeKind::Opened);
    assert_eq!(
        incident.credentials(),
        ["certificate c sha256:bb", "token gw sha256:aa"]
    );
    assert_eq!(incident.source_count(), 2);

    // A setting may ask for more sources than two.
    let mut strict = AreaCorrelator::new(AreaConfig {
        min_sources: 3,
        ..AreaConfig::default()
    });
    let mixed: Vec<_> = onsets()
        .into_iter()
        .zip(credentials)
        .map(|(o, credential)| sent_by(credential, o))
        .collect();
    assert_eq!(feed(&mut strict, mixed), []);
}

/// Ten made-up vehicles, each placed 9.5 km east of where the incident's centre is by then (as an
/// attacker who sees the incident would), cannot walk it across the region: it keeps the centre of
/// the vehicles that opened it, so its area stays within the radius (plus the margin) of that
/// centre; a vehicle beyond the radius of it does not join.
#[test]
fn joins_cannot_move_an_incident_beyond_its_radius() {
    let config = AreaConfig::default();
    let mut c = AreaCorrelator::new(config);
    let opened = feed(
        &mut c,
        vec![
            sent_by("a", onset("v0", 0.0, at(0.0, 0.0), [200.0, 0.0])),
            sent_by("b", onset("v1", 1.0, at(0.0, 2_000.0), [200.0, 0.0])),
            sent_by("c", onset("v2", 2.0, at(0.0, -2_000.0), [200.0, 0.0])),
        ],
    );
    assert_eq!(opened.len(), 1);
    let centre = opened[0].incident.centre;
    for k in 1..=10 {
        let now = wgs84_local_displacement(at(0.0, 0.0), c.open_incidents()[0].centre);
        let vehicle = format!("made-up-{k}");
        let time_s = 10.0 + f64::from(k);
        let placed = onset(&vehicle, time_s, at(now[0] + 9_500.0, now[1]), [200.0, 0.0]);
        let changes = feed(
            &mut c,
            vec![sent_by(&format!("made-up-source-{k}"), placed)],
        );
        assert_eq!(changes.len(), 1, "made-up-{k} joins within the radius");
    }
    let first = &c.open_incidents()[0];
    assert_eq!(first.centre, centre, "the centre stays where it opened");
    assert!(
        first.radius_m <= config.radius_m + config.margin_m,
        "{} m",
        first.radius_m
    );
    // Beyond the radius of the fixed centre, a vehicle does not join.
    let beyond = onset("far", 30.0, at(10_500.0, 0.0), [200.0, 0.0]);
    assert_eq!(feed(&mut c, vec![sent_by("far", beyond)]), []);
    assert_eq!(c.open_incidents()[0].vehicles.len(), 13);
}

/// A source that takes part in its bound of open incidents joins and opens no other: its onsets
/// wait, and an incident elsewhere opens, and grows, on the other sources' vehicles alone.
#[test]
fn a_source_takes_part_in_a_bounded_number_of_incidents() {
    let mut c = AreaCorrelator::new(AreaConfig {
        max_incidents_per_source: 1,
        ..AreaConfig::default()
    });
    let here = |east: f64| at(east, 0.0);
    let there = |east: f64| at(east, 50_000.0);
    let first = feed(
        &mut c,
        vec![
            sent_by("gw", onset("gw-1", 0.0, here(0.0), [200.0, 0.0])),
            sent_by("gw", onset("gw-2", 1.0, here(2_000.0), [200.0, 0.0])),
            sent_by("b", onset("b-1", 2.0, here(4_000.0), [200.0, 0.0])),
        ],
    );
    assert_eq!(first.len(), 1, "the gateway's first incident");
    let elsewhere = feed(
        &mut c,
        vec![
            sent_by("gw", onset("gw-3", 3.0, there(0.0), [200.0, 0.0])),
            sent_by("c", onset("c-1", 4.0, there(2_000.0), [200.0, 0.0])),
            sent_by("d", onset("d-1", 5.0, there(4_000.0), [200.0, 0.0])),
        ],
    );
    assert_eq!(
        elsewhere,
        [],
        "without the gateway's onset two vehicles are too few"
    );
    let opened = feed(
        &mut c,
        vec![sent_by(
            "e",
            onset("e-1", 6.0, there(3_000.0), [200.0, 0.0]),
        )],
    );
    assert_eq!(opened.len(), 1);
    let members: Vec<&str> = opened[0]
        .incident
        .vehicles
        .iter()
        .map(|v| v.vehicle_id.as_str())
        .collect();
    assert_eq!(
        members,
        ["e-1", "c-1", "d-1"],
        "the gateway's onset takes no part"
    );
    let joined = feed(
        &mut c,
        vec![sent_by(
            "gw",
            onset("gw-4", 7.0, there(1_000.0), [200.0, 0.0]),
        )],
    );
    assert_eq!(joined, [], "nor does its next one join it");
    // Within its incident, the gateway's vehicles still join.
    let within = feed(
        &mut c,
        vec![sent_by(
            "gw",
            onset("gw-5", 8.0, here(1_000.0), [200.0, 0.0]),
        )],
    );
    assert_eq!(within.len(), 1);
    assert_eq!(within[0].kind, ChangeKind::Joined);
}

/// An incident ended by hand leaves the correlator's state: its members' alarms still open are
/// spent (their ends change nothing, and they form no new incident), and the source bound is free
/// again; the same vehicles' new alarms are new evidence and open a new incident.
#[test]
fn an_incident_ended_by_hand_is_forgotten_and_only_new_alarms_reopen_one() {
    let config = AreaConfig {
        max_incidents_per_source: 1,
        ..AreaConfig::default()
    };
    let mut c = AreaCorrelator::new(config);
    let members = |time_s: f64| {
        vec![
            sent_by("x", onset("a", time_s, at(0.0, 0.0), [150.0, 0.0])),
            sent_by("y", onset("b", time_s + 1.0, at(500.0, 0.0), [150.0, 0.0])),
            sent_by("x", onset("c", time_s + 2.0, at(0.0, 500.0), [150.0, 0.0])),
        ]
    };
    let opened = feed(&mut c, members(100.0));
    assert_eq!(opened.len(), 1);
    let mut ended = opened[0].incident.clone();
    ended.end_by_hand(50.0);
    assert_eq!(
        ended.ended_s,
        Some(102.0),
        "never before its latest evidence"
    );

    assert_eq!(c.forget(&[7]), [], "not an open incident");
    let forgotten = c.forget(&[1]);
    assert_eq!(forgotten.len(), 1);
    assert!(c.open_incidents().is_empty());
    assert!(
        c.state().pending.is_empty(),
        "the members' onsets are spent"
    );
    let end = AlarmEnd {
        vehicle_id: "a".into(),
        alarm_id: 100,
        time_s: 130.0,
    };
    assert!(c.end(&end).is_empty(), "no incident holds that alarm");
    assert!(c.advance(5_000.0).is_empty());

    // New alarms of the same vehicles (new evidence): a new incident, the bound free again.
    let reopened = feed(&mut c, members(5_100.0));
    assert_eq!(reopened.len(), 1);
    assert_eq!(reopened[0].kind, ChangeKind::Opened);
    assert_eq!(reopened[0].incident.id, 2);
}
