#!/usr/bin/env bash
# The README's load rows with the server plaintext, with metrics on, and with TLS on (issue #10): one
# release build, the three configurations alternating within each of 3 rounds, server on core 0 and
# load generator on core 1, `uptime` load noted before each run.
# Usage: scripts/bench_operating_modes.sh target/release > bench.log
set -euo pipefail
bin=${1:?directory of spoofwatch-server and spoofwatch}
port=50073 metrics=9473
work=$(mktemp -d)
trap 'pkill -f "spoofwatch-server --listen 127.0.0.1:$port" || true; rm -rf "$work"' EXIT
# A CA and a server certificate for 127.0.0.1.
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 2 -subj "/CN=bench CA" \
  -keyout "$work/ca-key.pem" -out "$work/ca.pem" 2>/dev/null
openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=bench" \
  -keyout "$work/server-key.pem" -out "$work/server.csr" 2>/dev/null
openssl x509 -req -in "$work/server.csr" -CA "$work/ca.pem" -CAkey "$work/ca-key.pem" -CAcreateserial \
  -days 2 -out "$work/server.pem" -extfile <(printf "subjectAltName=IP:127.0.0.1") 2>/dev/null

run() { # $1 = plain|metrics|tls, then the bench arguments
  local mode=$1; shift
  pkill -f "spoofwatch-server --listen 127.0.0.1:$port" || true; sleep 1; rm -f "$work"/bench.db*
  local extra=() url="http://127.0.0.1:$port" client=()
  case $mode in
    metrics) extra=(--metrics-listen "127.0.0.1:$metrics") ;;
    tls) extra=(--tls-cert "$work/server.pem" --tls-key "$work/server-key.pem")
         url="https://127.0.0.1:$port"; client=(--ca-cert "$work/ca.pem") ;;
  esac
  taskset -c 0 "$bin/spoofwatch-server" --listen "127.0.0.1:$port" --database "$work/bench.db" \
    "${extra[@]}" > "$work/server.log" 2>&1 &
  sleep 2
  local pid; pid=$(pgrep -f "spoofwatch-server --listen 127.0.0.1:$port")
  echo "## $(date +%T) load: $(cut -d' ' -f1-3 /proc/loadavg) :: $mode bench $*"
  taskset -c 1 "$bin/spoofwatch" bench --server "$url" "${client[@]}" --server-pid "$pid" --sessions 0 "$@" \
    2>&1 | grep -E "^\| [0-9]|refused|failed|error" || true
  if [ "$mode" = metrics ]; then
    curl -s "127.0.0.1:$metrics/metrics" | grep -E '^spoofwatch_detection_samples_total' || true
  fi
}
for round in 1 2 3; do
  for mode in plain metrics tls; do
    run "$mode" --streams 100 --rate 60000 --seconds 10
    run "$mode" --streams 10000 --batch 1 --rate 10000 --seconds 30
    run "$mode" --streams 1000 --batch 1 --vehicles-per-message 100 --seconds 10
  done
done
