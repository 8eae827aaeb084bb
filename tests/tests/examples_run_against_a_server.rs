//! The integrators' examples (`examples/`) against a live server: the fleet backend streams a
//! drive whose fix freezes and prints every detection with the alarm's onset, and the alarm
//! watcher, from cursor 0, replays that onset and says it caught up.

use std::time::Duration;

use spoofwatch_core::scenario::AttackKind;
use spoofwatch_examples::{alarm_watcher, fleet_backend};
use spoofwatch_tests::{attacked_drive, start_server, track_samples};

#[tokio::test]
async fn the_fleet_backend_prints_detections_and_the_watcher_follows_the_alarm() {
    let (_dir, server, _clients) = start_server(|_| {}).await;
    let url = server.url();
    let track = attacked_drive(
        "example-car",
        240.0,
        21,
        AttackKind::FrozenPosition,
        100.0,
        60.0,
    );
    let samples = track_samples(&track);

    let mut printed = Vec::new();
    let detections = fleet_backend::run(&url, "example-car", samples.clone(), &mut printed)
        .await
        .expect("the fleet backend streams the drive");
    let printed = String::from_utf8(printed).expect("UTF-8");
    assert_eq!(detections.len(), samples.len());
    assert!(
        printed.starts_with("example-car streams to models/"),
        "{printed}"
    );
    assert_eq!(printed.lines().count(), samples.len() + 1, "{printed}");
    assert!(
        printed.contains("ALARM ON"),
        "the frozen fix alarms: {printed}"
    );

    // The onset is stored by the outbox shortly after it was decided: replay until it is there.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let mut printed = Vec::new();
        let cursor = alarm_watcher::run(&url, Some(0), true, &mut printed)
            .await
            .expect("the watcher replays the stored events");
        let printed = String::from_utf8(printed).expect("UTF-8");
        assert!(
            printed.ends_with(&format!("caught up at cursor {cursor}\n")),
            "{printed}"
        );
        if printed.contains("Onset alarm") && printed.contains("of example-car") {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the onset is replayed within 30 s: {printed}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    server.stop().await;
}
