//! The black-box tests, one module per behaviour (`tests/tests/<behaviour>.rs`), linked into one
//! test binary: each binary links the whole server and client, so one link instead of one per
//! file is most of the suite's build time. `metrics_endpoint` is its own binary: it checks exact
//! counts, and the metrics recorder is per process, so servers of other tests would add to them;
//! so is `stream_replies_are_bounded`, which reads the gauge of every stream's queued replies.
//!
//! Run one behaviour with `cargo test -p spoofwatch-tests --test black_box <module>::`.

mod raw_grpc;

mod a_clean_fleet_does_not_alarm;
mod a_gateway_streams_many_vehicles;
mod alarm_consumption;
mod alarm_severities;
mod alarms_say_why;
mod authentication;
mod authorization;
mod bounded_work;
mod clocks_never_decide;
mod dashboard_metrics;
mod error_statuses_are_bounded;
mod evaluation_jobs;
mod examples_run_against_a_server;
mod fleet_fit_jobs;
mod haproxy_routes_vehicles;
mod incidents_across_replicas;
mod incidents_bound_each_source;
mod incidents_end;
mod incidents_need_independent_evidence;
mod invalid_input_is_refused;
mod malformed_protobuf_is_invalid_argument;
mod metrics_connections_are_bounded;
mod migration_failures_are_named;
mod model_rollout;
mod postgres_outage;
mod protobuf_fuzzing;
mod readme_grpcurl;
mod replay_fails_over;
mod replicas_share_one_database;
mod reset_after_eviction;
mod restart_keeps_stored_state;
mod revocation_reaches_open_streams;
mod sequence_numbers;
mod server_lifecycle;
mod session_handoff;
mod session_lifecycle;
mod sessions_under_pressure;
mod shadow_evaluation;
mod storage_faults;
mod streaming_matches_the_offline_pass;
mod training_jobs;
mod transport_security;
mod vehicle_routing_header;
