//! The shipped HAProxy configuration (`deploy/haproxy/spoofwatch.cfg`, unchanged: addresses come
//! from its environment variables) in front of two real replicas: its gRPC health check passes
//! (L7OK), every vehicle's streams land on exactly one replica and always the same one (consistent
//! hashing on the `x-vehicle-id` header the client sends), and when one replica stops, HAProxy takes
//! it out and its vehicles are served by the other through the balancer.
//!
//! Needs a real HAProxy (`spoofwatch_tests::balancer`); skipped without one unless
//! `SPOOFWATCH_REQUIRE_HAPROXY=1`.

use spoofwatch_proto::v1;
use spoofwatch_tests::balancer::{Balancer, REPLICAS, haproxy};
use spoofwatch_tests::{
    Connection, normal_drive, sessions_on, start_server, stream_samples, track_samples,
};

/// Vehicles streamed through the balancer.
const VEHICLES: usize = 12;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn haproxy_pins_each_vehicle_to_one_replica_and_fails_over_when_it_stops() {
    let Some(haproxy) = haproxy() else {
        return;
    };
    let (_dir_1, server_1, clients_1) = start_server(|_| {}).await;
    let (_dir_2, server_2, clients_2) = start_server(|_| {}).await;
    let lb_dir = tempfile::tempdir().expect("temp dir");
    let balancer = Balancer::start(&haproxy, lb_dir.path(), [server_1.addr, server_2.addr]);
    for replica in REPLICAS {
        // L7OK: the gRPC health check saw SERVING.
        balancer.wait_for(replica, "UP", Some("L7OK")).await;
    }
    let lb_url = format!("http://{}", balancer.addr);
    let through_lb = Connection::connect(lb_url.clone(), None)
        .await
        .expect("connect to the balancer");

    let vehicles: Vec<(String, Vec<v1::Sample>)> = (0..VEHICLES)
        .map(|k| {
            let id = format!("car-{k:02}");
            let samples = track_samples(&normal_drive(&id, 39.0, 40 + k as u64));
            (id, samples)
        })
        .collect();
    for (id, samples) in &vehicles {
        stream_samples(&through_lb, id, true, 1, &samples[..20]).await;
    }
    let on_1 = sessions_on(&clients_1).await;
    let on_2 = sessions_on(&clients_2).await;
    for (id, _) in &vehicles {
        assert!(
            on_1.contains(id) ^ on_2.contains(id),
            "{id} is on exactly one replica: {on_1:?} / {on_2:?}"
        );
    }
    assert!(
        !on_1.is_empty() && !on_2.is_empty(),
        "the vehicles are spread over both replicas: {on_1:?} / {on_2:?}"
    );

    // Again, in the reverse order and over a new connection to the balancer: every vehicle finds
    // its session (resumed with its 20 samples), so it landed on the same replica.
    let again = Connection::connect(lb_url.clone(), None)
        .await
        .expect("connect to the balancer");
    for (id, samples) in vehicles.iter().rev() {
        let accepted = stream_samples(&again, id, false, 5, &samples[20..30]).await;
        assert!(
            accepted.resumed && accepted.samples_seen == 20,
            "{id}: {accepted:?}"
        );
    }
    assert_eq!(sessions_on(&clients_1).await, on_1);
    assert_eq!(sessions_on(&clients_2).await, on_2);

    // The replica holding car-00 stops; HAProxy takes it out and its vehicles move to the other.
    let lost_index = if on_1.contains(&vehicles[0].0) { 0 } else { 1 };
    let mut servers = [Some(server_1), Some(server_2)];
    let mut clients = [Some(clients_1), Some(clients_2)];
    let placement = [on_1, on_2];
    let (lost, kept) = (&placement[lost_index], &placement[1 - lost_index]);
    clients[lost_index] = None;
    let stopped = servers[lost_index].take().expect("the replica to stop");
    stopped.stop().await;
    balancer.wait_for(REPLICAS[lost_index], "DOWN", None).await;
    for (id, samples) in &vehicles {
        let accepted = stream_samples(&again, id, false, 7, &samples[30..]).await;
        if kept.contains(id) {
            assert!(
                accepted.resumed && accepted.samples_seen == 30,
                "{id} stays on its replica: {accepted:?}"
            );
        }
    }
    let survivor_clients = clients[1 - lost_index]
        .take()
        .expect("the remaining replica");
    let now_on_survivor = sessions_on(&survivor_clients).await;
    for id in lost.iter().chain(kept) {
        assert!(
            now_on_survivor.contains(id),
            "{id} is served by the remaining replica: {now_on_survivor:?}"
        );
    }
    drop((through_lb, again, survivor_clients));
    drop(balancer);
    let survivor = servers[1 - lost_index]
        .take()
        .expect("the remaining replica");
    survivor.stop().await;
}
