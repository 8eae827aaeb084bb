#!/usr/bin/env bash
# Fleet fault test (docs/fleet.md, "Running a fleet"): PostgreSQL + two server replicas + HAProxy on loopback.
# ~100 vehicles (a real AV-GPS recording and simulated drives, half of them attacked) stream through the
# balancer while
#   1. one replica is killed with SIGKILL mid-stream (its vehicles fail over to the other, which continues
#      their sessions from the stored snapshots, and the clients resend from SessionAccepted.last_seq);
#   2. both replicas are restarted one after the other (SIGTERM, rolling restart).
# Each time every vehicle's detections must equal those of one uninterrupted single server (SQLite), bit for
# bit, and the stored alarms (ListAlarms through the balancer) must equal that server's: none lost, none
# duplicated, none left open. Models and jobs read the same through both replicas.
#
# Usage: scripts/fleet-fault-test.sh [BIN_DIR]   (default target/debug: spoofwatch and spoofwatch-server)
# Needs PostgreSQL (Debian's postgresql package) and HAProxy (Debian's haproxy); installs them when missing.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
bin=$(cd "${1:-target/debug}" && pwd)
source scripts/lib/fleet.sh
fleet_setup spoofwatch-fault

step "inputs: a real recording and simulated drives (half of them attacked)"
[ -f "$data/AV-GPS-Dataset-3.csv" ] || fail "AV-GPS Dataset-3 not found under $data (set SPOOFWATCH_AVGPS_DIR)"
"$bin/spoofwatch" scenario simulate --out "$work/normal.csv" --vehicles 50 --duration 240 --seed 100
"$bin/spoofwatch" scenario simulate --out "$work/attacked.csv" --vehicles 49 --duration 240 --seed 200 \
  --attack frozen --onset 90 --attack-duration 80
inputs=("$data/AV-GPS-Dataset-3.csv" "$work/normal.csv" "$work/attacked.csv")
# Paced (10 samples/s per vehicle, batches of 5) so that a run lasts ~25 s and the faults land mid-stream.
detect_flags=(--batch 5 --quiet --failover-secs 60)

# Snapshots every 20 samples, so that a failover resends little and resumes mid-drive.
server_flags=(--snapshot-every-samples 20 --shutdown-grace-secs 5)

step "reference: one uninterrupted server (SQLite)"
start_server reference "$reference_port" "$work/reference.db" "${server_flags[@]}"
"$bin/spoofwatch" detect --server "127.0.0.1:$reference_port" --data "${inputs[@]}" --batch 5 --quiet \
  --out "$work/reference.csv" >"$work/reference-detect.log" 2>&1
stored_alarms "127.0.0.1:$reference_port" >"$work/reference-alarms.txt"
stop reference
rows=$(($(wc -l <"$work/reference.csv") - 1))
alarms=$(wc -l <"$work/reference-alarms.txt")
[ "$alarms" -gt 0 ] || fail "the reference run raised no alarm: the comparison would show nothing"
echo "reference: $rows detections, $alarms alarms"

step "PostgreSQL"
start_postgres

compare() { # run
  local run=$1
  cmp -s "$work/reference.csv" "$work/$run.csv" || {
    diff "$work/reference.csv" "$work/$run.csv" | sed -n 1,20p >&2
    fail "$run: the detections differ from the uninterrupted run's"
  }
  stored_alarms "127.0.0.1:$lb_port" >"$work/$run-alarms.txt"
  cmp -s "$work/reference-alarms.txt" "$work/$run-alarms.txt" || {
    diff "$work/reference-alarms.txt" "$work/$run-alarms.txt" | sed -n 1,20p >&2
    fail "$run: the stored alarms differ from the uninterrupted run's (lost, duplicated or left open)"
  }
  for what in models jobs; do
    "$bin/spoofwatch" "$what" list --server "127.0.0.1:${port[1]}" >"$work/$run-$what-1.txt"
    "$bin/spoofwatch" "$what" list --server "127.0.0.1:${port[2]}" >"$work/$run-$what-2.txt"
    cmp -s "$work/$run-$what-1.txt" "$work/$run-$what-2.txt" || fail "$run: the replicas list different $what"
  done
  echo "$run: $rows detections and $alarms alarms equal the uninterrupted run's"
}

run_with() { # run fault
  local run=$1 fault=$2
  url=$(new_database "$run")
  start_server replica-1 "${port[1]}" "$url" --instance-id replica-1 "${server_flags[@]}"
  start_server replica-2 "${port[2]}" "$url" --instance-id replica-2 "${server_flags[@]}"
  start_balancer
  "$bin/spoofwatch" detect --server "127.0.0.1:$lb_port" --data "${inputs[@]}" "${detect_flags[@]}" \
    --rate 10 --out "$work/$run.csv" --summary "$work/$run-summary.json" >"$work/$run-detect.log" 2>&1 &
  local client=$!
  "$fault"
  wait "$client" || { tail -20 "$work/$run-detect.log" >&2; fail "$run: the client gave up"; }
  # Every failover must have continued the session (from its snapshot: the replica that took the
  # vehicle over never held it), not started it afresh and resent the whole drive.
  check_failovers_resumed "$work/$run-summary.json" "$run"
  compare "$run"
  stop balancer; stop replica-1; stop replica-2
}

kill_one_replica() {
  sleep 8
  step "kill -9 replica 1 mid-stream"
  stop replica-1 KILL
  sleep 5
  step "replica 1 back"
  start_server replica-1 "${port[1]}" "$url" --instance-id replica-1 "${server_flags[@]}"
}

rolling_restart() {
  for replica in 1 2; do
    sleep 5
    step "rolling restart: replica $replica"
    stop "replica-$replica" TERM
    start_server "replica-$replica" "${port[$replica]}" "$url" --instance-id "replica-$replica" \
      "${server_flags[@]}"
  done
}

step "run 1: kill -9 one replica mid-stream"
run_with killed kill_one_replica
step "run 2: rolling restart of both replicas"
run_with rolling rolling_restart
step "fleet fault test passed"
