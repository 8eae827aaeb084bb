#!/usr/bin/env bash
# Soak test with faults (docs/reliability.md "Soak test"): PostgreSQL + two server replicas behind the
# shipped HAProxy configuration, on loopback. Simulated vehicles (one in eight attacked: jumps, a frozen
# fix, a drift, a hopping position, onsets spread over the run) stream at 1 Hz, one sample per message,
# while, at fixed fractions of the run:
#   20 %  replica 1 is killed with SIGKILL and restarted 5 % of the run later (30 s of 10 minutes);
#   40 %  PostgreSQL is stopped for 10 % of the run (60 s of 10 minutes);
#   60 %  a new model is activated (a roll-out: open streams keep their model until they end);
#   80 %  HAProxy is restarted, which cuts every stream at once (a reconnect storm).
# Checked against one uninterrupted server (SQLite) fed the same drives: every detection made by the model
# the reference ran equals the reference's bit for bit, and each vehicle changes model at most once, at the
# roll-out; every alarm onset the client was shown is stored exactly once with its end, and no other;
# every failover resumed the vehicle's session (from its snapshot when it moved) or went on under the new
# model; no replica's memory grows by more than 5 % while the sessions it holds stay the same.
# Reports per tenth of the run: delivered share and latency (from when each sample was due), CPU and RSS
# per replica, alarm outbox backlog and snapshot lag (scripts/soak_report.py).
#
# Usage: scripts/soak-test.sh [--bin DIR] [--seconds N] [--vehicles N] [--report FILE]
#   defaults: target/release, 600 s, 20,000 vehicles (docs/soak-report.md is this run's report).
#   .ci/run runs the short version: --bin target/debug --seconds 60 --vehicles 200.
# Needs PostgreSQL (Debian's postgresql package) and HAProxy (Debian's haproxy); installs them when missing.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
bin=target/release seconds=600 vehicles=20000 report=""
while [ $# -gt 0 ]; do
  case "$1" in
    --bin) bin=$2; shift 2 ;;
    --seconds) seconds=$2; shift 2 ;;
    --vehicles) vehicles=$2; shift 2 ;;
    --report) report=$2; shift 2 ;;
    *) echo "unknown argument $1 (see the usage at the top of $0)" >&2; exit 2 ;;
  esac
done
[ "$seconds" -ge 60 ] || { echo "--seconds must be at least 60" >&2; exit 2; }
[ "$vehicles" -ge 40 ] || { echo "--vehicles must be at least 40" >&2; exit 2; }
bin=$(cd "$bin" && pwd)
source scripts/lib/fleet.sh
fleet_setup spoofwatch-soak
load_before=$(cut -d' ' -f1-3 /proc/loadavg)

at() { echo $((seconds * $1 / 100)); } # a percentage of the run, in seconds
interval=$((seconds / 10))

step "inputs: $vehicles simulated drives of $seconds s at 1 Hz"
# Five attacked groups, each a fortieth of the fleet, with onsets spread over the run.
group=$((vehicles / 40))
attack_s=$(at 12)
simulate() { # out count seed [attack flags...]
  local out=$1 count=$2 seed=$3
  shift 3
  "$bin/spoofwatch" scenario simulate --out "$work/$out.csv" --vehicles "$count" --duration "$seconds" \
    --seed "$seed" "$@" >/dev/null
  inputs+=("$work/$out.csv")
}
inputs=()
# Vehicle i of a group drives with seed + i: the groups' seeds are a million apart, so that no two
# vehicles share a drive.
simulate normal $((vehicles - 5 * group)) 1
simulate jump $group 1000001 --attack jump --magnitude 50 --onset "$(at 10)" --attack-duration "$attack_s"
simulate frozen $group 2000001 --attack frozen --onset "$(at 25)" --attack-duration "$attack_s"
simulate ramp $group 3000001 --attack ramp --magnitude 1.5 --onset "$(at 45)" --attack-duration "$attack_s"
simulate hop $group 4000001 --attack hop --magnitude 200 --onset "$(at 65)" --attack-duration "$attack_s"
simulate far-jump $group 5000001 --attack jump --magnitude 300 --onset "$(at 85)" --attack-duration "$attack_s"

# Replicas as shipped, but a snapshot every tenth of the run (every 60 s, the default, in 10 minutes), so
# that a short run hands sessions over from a snapshot as the full one does.
server_flags=(--snapshot-every-secs "$interval")

step "reference: one uninterrupted server (SQLite), the drives sent as fast as it answers"
start_server reference "$reference_port" "$work/reference.db" "${server_flags[@]}"
"$bin/spoofwatch" detect --server "127.0.0.1:$reference_port" --data "${inputs[@]}" --batch 50 --quiet \
  --out "$work/reference.csv" >"$work/reference-detect.log" 2>&1 \
  || { tail -20 "$work/reference-detect.log" >&2; fail "the reference run failed"; }
"$bin/spoofwatch" alarms list --server "127.0.0.1:$reference_port" --json --limit 10000000 >"$work/reference-alarms.json"
# The roll-out's model: the bundled one, imported again under a new name.
"$bin/spoofwatch" models export --server "127.0.0.1:$reference_port" --out "$work/rollout-model.json" \
  models/default >/dev/null
stop reference

step "PostgreSQL, two replicas, HAProxy"
start_postgres
url=$(new_database soak)
replica_flags() { # replica
  echo --instance-id "replica-$1" --metrics-listen "127.0.0.1:${metrics_port[$1]}" "${server_flags[@]}"
}
start_replica() { # replica
  # shellcheck disable=SC2046 # the flags are words without spaces
  start_server "replica-$1" "${port[$1]}" "$url" $(replica_flags "$1")
}
start_replica 1
start_replica 2
start_balancer

# Per-replica CPU, RSS and metrics, sampled until the run ends.
python3 scripts/soak_report.py sample --work "$work" --every "$(((seconds + 119) / 120))" \
  --replica "replica-1=127.0.0.1:${metrics_port[1]}" --replica "replica-2=127.0.0.1:${metrics_port[2]}" &
sampler=$!

faults() {
  local start=$SECONDS
  until_s() { local wait=$(($1 - (SECONDS - start))); [ "$wait" -le 0 ] || sleep "$wait"; }
  log() { echo "$((SECONDS - start)) $*" >>"$work/faults.txt"; step "$*"; }
  until_s "$(at 20)"; log "kill -9 replica 1"; stop replica-1 KILL
  until_s "$(at 25)"; start_replica 1; log "replica 1 restarted"
  until_s "$(at 40)"; log "PostgreSQL stopped"; scripts/postgres-ephemeral.sh stop "$work/pg" >/dev/null
  until_s "$(at 50)"; scripts/postgres-ephemeral.sh start "$work/pg" "$pg_port" >/dev/null; log "PostgreSQL back"
  until_s "$(at 60)"
  "$bin/spoofwatch" models import --server "127.0.0.1:$lb_port" --file "$work/rollout-model.json" \
    --name rollout --activate >"$work/rollout.txt"
  log "a new model activated"
  until_s "$(at 80)"; log "HAProxy restarted"; stop balancer KILL; start_balancer
}

step "soak: $vehicles vehicles at 1 Hz for $seconds s through HAProxy"
"$bin/spoofwatch" detect --server "127.0.0.1:$lb_port" --data "${inputs[@]}" --rate 1 --batch 1 --quiet \
  --failover-secs "$seconds" --timeline "$work/timeline.csv" --timeline-every "$interval" \
  --out "$work/run.csv" --summary "$work/run-summary.json" >"$work/run-detect.log" 2>&1 &
client=$!
# The run's clock starts when the client starts replaying (after reading the drives).
until grep -q '^replaying' "$work/run-detect.log" 2>/dev/null; do
  kill -0 "$client" 2>/dev/null || { tail -20 "$work/run-detect.log" >&2; fail "the client exited before replaying"; }
  sleep 0.2
done
date +%s.%N >"$work/client-started.txt"
faults
wait "$client" || { tail -20 "$work/run-detect.log" >&2; fail "the client gave up"; }
step "client done; waiting for both replicas to store what they queued"
python3 scripts/soak_report.py drained --replica "127.0.0.1:${metrics_port[1]}" --replica "127.0.0.1:${metrics_port[2]}"
kill "$sampler"; wait "$sampler" 2>/dev/null || true
"$bin/spoofwatch" alarms list --server "127.0.0.1:$lb_port" --json --limit 10000000 >"$work/run-alarms.json"

step "checks and report"
python3 scripts/soak_report.py report --work "$work" --seconds "$seconds" --vehicles "$vehicles" \
  --rollout-model "$(grep -o 'models/[A-Za-z0-9._-]*' "$work/rollout.txt" | head -1)" \
  --load-before "$load_before" --load-after "$(cut -d' ' -f1-3 /proc/loadavg)" ${report:+--out "$report"}
step "soak test passed"
