#!/usr/bin/env bash
# README "Running a fleet" numbers (issue #12): one replica's throughput on SQLite and on PostgreSQL
# (alternating within each of 3 rounds), the session snapshot write load of 10,000 vehicles at 1 Hz, and
# the hand-off time between two replicas on PostgreSQL (3 rounds).
# One release build; server on core 0, load generator on core 1; `uptime` load noted before each run.
# Usage: scripts/bench_fleet.sh target/release [all|handoff] > bench.log
set -euo pipefail
cd "$(dirname "$0")/.."
bin=$(cd "${1:?directory of spoofwatch-server and spoofwatch}" && pwd)
parts=${2:-all}
port=50083 metrics=9483 pg_port=55483 second_port=50084
work=$(mktemp -d /tmp/spoofwatch-bench.XXXXXX)
chmod 755 "$work"
trap 'pkill -f "spoofwatch-server --listen 127.0.0.1:$port" || true
      pkill -f "spoofwatch-server --listen 127.0.0.1:$second_port" || true
      scripts/postgres-ephemeral.sh stop "$work/pg" >/dev/null 2>&1 || true; rm -rf "$work"' EXIT
pg_url=$(scripts/postgres-ephemeral.sh start "$work/pg" "$pg_port")
psql=$(command -v psql || ls -d /usr/lib/postgresql/*/bin/psql | sort -V | tail -1)
runs=0

# Stops the server listening on 127.0.0.1:<port> and waits until it has drained and exited (its ports
# are free again for the next start).
stop_server() {
  pkill -f "spoofwatch-server --listen 127.0.0.1:$1" || true
  while pgrep -f "spoofwatch-server --listen 127.0.0.1:$1" >/dev/null; do sleep 0.2; done
}

start() { # sqlite|postgres, then server flags
  local backend=$1; shift
  runs=$((runs + 1))
  stop_server "$port"
  if [ "$backend" = postgres ]; then
    "$psql" "$pg_url" -qc "CREATE DATABASE bench$runs"
    database="${pg_url%/*}/bench$runs"
  else
    database="$work/bench$runs.db"
  fi
  taskset -c 0 "$bin/spoofwatch-server" --listen "127.0.0.1:$port" --database "$database" \
    --metrics-listen "127.0.0.1:$metrics" "$@" >"$work/server.log" 2>&1 &
  sleep 2
  pid=$(pgrep -f "spoofwatch-server --listen 127.0.0.1:$port")
}

scrape() { curl -s "127.0.0.1:$metrics/metrics" | grep -E "^spoofwatch_session_snapshots_stored_total|^spoofwatch_db_operation_duration_seconds_(sum|count)\{op=\"alarm_batch_write\"" || true; }

bench() { # backend, then bench flags
  local backend=$1; shift
  start "$backend"
  echo "## $(date +%T) load: $(cut -d' ' -f1-3 /proc/loadavg) :: $backend bench $*"
  taskset -c 1 "$bin/spoofwatch" bench --server "http://127.0.0.1:$port" --server-pid "$pid" --sessions 0 "$@" \
    2>&1 | grep -E "^\| [0-9]|refused|failed|error" || true
  scrape
}

# Hand-off: the bench's vehicles stream to a replica on core 1 (beside the load generator) and end their
# streams; then they start on a second replica (core 0) on the same database, each alone and all at once.
handoff() {
  start postgres
  taskset -c 1 "$bin/spoofwatch-server" --listen "127.0.0.1:$second_port" --database "$database" \
    >"$work/second.log" 2>&1 &
  sleep 2
  for concurrency in 1 1000; do
    echo "## $(date +%T) load: $(cut -d' ' -f1-3 /proc/loadavg) :: postgres hand-off, 1,000 vehicles, $concurrency at a time"
    taskset -c 1 "$bin/spoofwatch" bench --server "http://127.0.0.1:$second_port" \
      --handoff-to "http://127.0.0.1:$port" --handoff "${HANDOFF_VEHICLES:-1000}" --handoff-concurrency "$concurrency" \
      2>&1 | grep -E "^\| (from|fresh)|refused|failed|error" || true
  done
  stop_server "$second_port"
}

if [ "$parts" = handoff ]; then
  for round in 1 2 3; do handoff; done
  exit 0
fi

for round in 1 2 3; do
  for backend in sqlite postgres; do
    bench "$backend" --streams 100 --batch 10 --seconds 10
    bench "$backend" --streams 1000 --batch 1 --vehicles-per-message 100 --seconds 10
  done
done

# Write load: 10,000 vehicles at 1 Hz for 70 s under the default snapshot policy (every 600 samples or
# 60 s): the sessions start together, so their periodic snapshots come as one burst a minute. Scraped
# at 30 s (only the snapshots of the session starts so far) and after the run (stream ends included).
for backend in sqlite postgres; do
  start "$backend"
  echo "## $(date +%T) load: $(cut -d' ' -f1-3 /proc/loadavg) :: $backend write load, 10,000 vehicles at 1 Hz, 70 s"
  taskset -c 1 "$bin/spoofwatch" bench --server "http://127.0.0.1:$port" --server-pid "$pid" --sessions 0 \
    --streams 10000 --batch 1 --rate 10000 --seconds 70 2>&1 | grep -E "^\| [0-9]|refused|failed|error" &
  client=$!
  sleep 35; echo "# at ~30 s"; scrape
  wait "$client" || true
  echo "# after the run"; scrape
done

for round in 1 2 3; do handoff; done
