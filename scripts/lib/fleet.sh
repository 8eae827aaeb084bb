# Shared by the fleet scripts (scripts/fleet-fault-test.sh, scripts/soak-test.sh): PostgreSQL, server
# replicas and HAProxy on loopback, started and stopped from one work directory. Sourced, not run.
#
# The sourcing script sets `bin` (the directory of spoofwatch and spoofwatch-server) and `root` (the
# repository), then calls fleet_setup; every process it starts is killed when the script exits.

fail() { echo "FAIL: $*" >&2; exit 1; }
step() { echo "== $(date +%T) $*"; }

# Checks the binaries, installs PostgreSQL and HAProxy when missing (Debian packages), makes the
# work directory and picks the ports.
fleet_setup() { # name-of-work-directory
  for program in spoofwatch spoofwatch-server; do
    [ -x "$bin/$program" ] || { echo "no $bin/$program: build it first (cargo build, or cargo test --workspace)" >&2; exit 1; }
  done
  data="${SPOOFWATCH_AVGPS_DIR:-$root/../shared/data/av-gps}"
  for package in postgresql:pg_ctl haproxy:haproxy; do
    if ! command -v "${package#*:}" >/dev/null && ! ls /usr/lib/postgresql/*/bin/"${package#*:}" /usr/sbin/"${package#*:}" >/dev/null 2>&1; then
      "$root/scripts/apt-install.sh" "${package%%:*}"
    fi
  done
  haproxy=$(command -v haproxy || echo /usr/sbin/haproxy)
  work=$(mktemp -d "/tmp/$1.XXXXXX")
  chmod 755 "$work"
  declare -gA pid=()
  trap fleet_cleanup EXIT
  # A block of ports per run, so that no leftover process of an earlier run answers; below the
  # kernel's range of ephemeral ports (32768 and up), so that no outgoing connection holds one.
  local base=$((20000 + RANDOM % 12000))
  pg_port=$base; reference_port=$((base + 1)); lb_port=$((base + 2))
  declare -gA port=([1]=$((base + 3)) [2]=$((base + 4)))
  declare -gA metrics_port=([1]=$((base + 5)) [2]=$((base + 6)))
}

fleet_cleanup() {
  # Killed and reaped quietly (the shell would report each as killed).
  for p in "${pid[@]}"; do { kill -9 "$p" && wait "$p"; } 2>/dev/null || true; done
  scripts/postgres-ephemeral.sh stop "$work/pg" >/dev/null 2>&1 || true
  if [ "${KEEP_WORK:-0}" = 1 ]; then echo "work directory kept: $work"; else rm -rf "$work"; fi
}

# Waits until `spoofwatch health` answers on host:port; fails at once, with the end of its log,
# when the named process has exited.
wait_serving() { # host:port name
  for _ in $(seq 1 300); do
    "$bin/spoofwatch" health --server "$1" >/dev/null 2>&1 && return 0
    if ! kill -0 "${pid[$2]}" 2>/dev/null; then
      tail -20 "$work/$2.log" >&2
      fail "$2 exited before serving on $1"
    fi
    sleep 0.1
  done
  tail -20 "$work/$2.log" >&2
  fail "nothing serves on $1 ($2)"
}

# Starts a server replica (logs in $work/<name>.log, its pid in $work/<name>.pid), without the area
# prior: with it a vehicle's detections depend on which incidents were open when, which differs
# between a reference run and a faulted one; what the fleet scripts compare is the sessions.
start_server() { # name port database [flags...]
  local name=$1 listen=$2 database=$3
  shift 3
  "$bin/spoofwatch-server" --listen "127.0.0.1:$listen" --database "$database" \
    --incident-prior false "$@" >>"$work/$name.log" 2>&1 &
  pid[$name]=$!
  echo "${pid[$name]}" >"$work/$name.pid"
  wait_serving "127.0.0.1:$listen" "$name"
}

stop() { # name [signal]
  kill "-${2:-TERM}" "${pid[$1]}" 2>/dev/null || true
  wait "${pid[$1]}" 2>/dev/null || true
  unset "pid[$1]"
}

# The shipped HAProxy configuration in front of the two replicas, on $lb_port.
start_balancer() {
  SPOOFWATCH_LB_LISTEN="127.0.0.1:$lb_port" SPOOFWATCH_REPLICA_1="127.0.0.1:${port[1]}" \
    SPOOFWATCH_REPLICA_2="127.0.0.1:${port[2]}" SPOOFWATCH_LB_ADMIN_SOCKET="$work/lb.sock" \
    "$haproxy" -db -f deploy/haproxy/spoofwatch.cfg >>"$work/balancer.log" 2>&1 &
  pid[balancer]=$!
  wait_serving "127.0.0.1:$lb_port" balancer
}

start_postgres() {
  pg_url=$(scripts/postgres-ephemeral.sh start "$work/pg" "$pg_port")
  psql=$(command -v psql || ls -d /usr/lib/postgresql/*/bin/psql | sort -V | tail -1)
}

new_database() { # name → URL of a new, empty database
  "$psql" "$pg_url" -qc "CREATE DATABASE $1" >/dev/null
  echo "${pg_url%/*}/$1"
}

# The stored alarms (ListAlarms on host:port), one line per alarm: vehicle onset end peak samples
# open, sorted.
stored_alarms() { # host:port
  "$bin/spoofwatch" alarms list --server "$1" --json --limit 1000000 | python3 -c '
import json, sys
rows = []
for line in sys.stdin:
    if line.strip():
        a = json.loads(line)
        rows.append((a["vehicle_id"], repr(a["onset_timestamp_s"]), repr(a.get("end_timestamp_s")),
                     repr(a["peak_probability"]), str(a["samples"]), str(a.get("open", False))))
for row in sorted(rows):
    print(" ".join(row))'
}

# Fails unless the replay's summary (spoofwatch detect --summary) shows failovers, each of which
# continued its vehicle's session (from its snapshot) rather than starting it afresh.
check_failovers_resumed() { # summary.json what
  python3 - "$1" <<'PY' || fail "$2: a failover did not continue its session"
import json, sys
summary = json.load(open(sys.argv[1]))
failovers, resumed = summary["failovers"], summary["resumed_reconnects"]
print(f"failovers: {failovers}, of which continued from the session snapshot: {resumed}")
sys.exit(0 if failovers > 0 and resumed == failovers else 1)
PY
}
