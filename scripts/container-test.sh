#!/usr/bin/env bash
# Container test: builds the shipped image (Dockerfile) from the binaries built here and a local Debian
# base, and runs it in real containers with podman:
#   1. compose: compose.yaml as written: the server, its health check gating the smoke client, and the
#      smoke client's attacked drive alarmed;
#   2. security: the server runs as uid 10001 on a read-only root file system with only its data volume
#      writable, and the image adds no package (no compiler, no package manager) to the base;
#   3. persistence: an alarm, an imported model and a vehicle's session snapshot outlive the container
#      (stopped, removed, a new one started on the same volume; the vehicle resumes its session);
#   4. drain: SIGTERM with 2,000 open streams: health turns NOT_SERVING, every stream ends UNAVAILABLE,
#      and the container exits 0 within compose.yaml's stop_grace_period;
#   5. TLS: configured by environment only, certificates and roles file mounted read-only, a client on
#      the host connects over mutual TLS (and one without a certificate is refused);
#   6. replicas: two containers on a PostgreSQL behind the shipped HAProxy configuration; one is killed
#      (SIGKILL) mid-stream and its vehicles continue on the other from their session snapshots, their
#      detections and alarms equal to one uninterrupted container's.
# --break MODE builds a deliberately broken image on top of the real one, to show that the checks catch
# it: `entrypoint` (the CLI instead of the server), `model` (the model files missing), `volume` (the data
# directory not writable by the server's user). The test must then fail.
#
# Needs root or sudo (podman, and apt-get for what is missing: podman, runc, debootstrap, catatonit,
# python3-yaml, openssl, curl, PostgreSQL, HAProxy). The Debian base image (localhost/debian-bookworm)
# is made once with debootstrap from the mirror apt uses and kept in podman's storage, outside the
# clone; it is rebuilt when missing.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
started_at=$SECONDS

usage() {
  sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'
  cat <<'EOF'
Usage: scripts/container-test.sh [--checks 1,2,...] [--break entrypoint|model|volume] [--keep]
                                 [--image NAME --bin DIR] [--base-image NAME]
  --checks LIST   run only these checks (default: all, 1 to 6)
  --break MODE    test a deliberately broken image (the test must fail)
  --keep          keep the containers, pods, volumes and work directory for inspection
  --image NAME    test this image instead of building one (e.g. one built from the Dockerfile's default,
                  multi-stage way); its Debian base for check 2 is --base-image
  --bin DIR       the host's spoofwatch and spoofwatch-server (the clients run on the host) instead of
                  building them with `cargo build --profile image` into target/image
  --base-image N  the Debian 12 base (default localhost/debian-bookworm, made with debootstrap if missing)
  -h, --help      this text
Environment: SPOOFWATCH_GRPCURL (grpcurl for the drain check; installed from PyPI when unset).
EOF
}

checks="1,2,3,4,5,6"; break_mode=""; keep=0; base_image=localhost/debian-bookworm; given_image=""; bin=""
while [ $# -gt 0 ]; do
  case $1 in
    --checks) checks=$2; shift 2 ;;
    --break) break_mode=$2; shift 2 ;;
    --keep) keep=1; shift ;;
    --base-image) base_image=$2; shift 2 ;;
    --image) given_image=$2; shift 2 ;;
    --bin) bin=$(cd "$2" && pwd); shift 2 ;;
    -h|--help) usage; exit 0 ;;
    *) echo "unknown argument: $1 (see --help)" >&2; exit 2 ;;
  esac
done
case $break_mode in ""|entrypoint|model|volume) ;; *) echo "--break: entrypoint, model or volume" >&2; exit 2 ;; esac

sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
step() { echo "== $(date +%T) $*"; }
apt_install() { scripts/apt-install.sh "$@"; } # package...

step "tools: podman, runc, debootstrap (Debian packages)"
missing=()
# catatonit: the pods' pause process (check 1).
for tool in podman:podman runc:runc debootstrap:debootstrap catatonit:catatonit openssl:openssl curl:curl; do
  command -v "${tool#*:}" >/dev/null || missing+=("${tool%%:*}")
done
/usr/bin/python3 -c 'import yaml' 2>/dev/null || missing+=(python3-yaml)
[ ${#missing[@]} -eq 0 ] || apt_install "${missing[@]}"
podman --version

# crun fails on some hosts (cgroups, setrlimit); runc without default ulimits runs everywhere.
conf_dir=$(mktemp -d /tmp/spoofwatch-containers-conf.XXXXXX)
printf '[containers]\ndefault_ulimits = []\n' >"$conf_dir/containers.conf"
export CONTAINERS_CONF="$conf_dir/containers.conf"
pm() { $sudo env CONTAINERS_CONF="$CONTAINERS_CONF" podman --runtime runc "$@"; }

if [ -z "$bin" ]; then
  step "the binaries (cargo build --profile image, the profile the Dockerfile builds with)"
  build_started=$SECONDS
  cargo build --profile image --locked --bin spoofwatch-server --bin spoofwatch
  echo "cargo build --profile image: $((SECONDS - build_started)) s"
  bin=$root/target/image
elif [ -z "$given_image" ]; then
  echo "--bin needs --image: the image is built from target/image (see Dockerfile)" >&2; exit 2
fi

source scripts/lib/fleet.sh
fleet_setup spoofwatch-containers
label="spoofwatch-container-test=$$"
image=localhost/spoofwatch:test

container_cleanup() {
  if [ "$keep" = 1 ]; then
    echo "kept: containers, pods and volumes labelled $label; podman ps -a --filter label=$label"
    KEEP_WORK=1
  else
    local ids
    ids=$(pm ps -a -q --filter "label=$label" 2>/dev/null || true)
    [ -z "$ids" ] || pm rm -f -t 0 $ids >/dev/null 2>&1 || true
    for pod in $(pm pod ls -q --filter "label=$label" 2>/dev/null || true); do pm pod rm -f "$pod" >/dev/null 2>&1 || true; done
    for volume in $(pm volume ls -q --filter "label=$label" 2>/dev/null || true); do pm volume rm -f "$volume" >/dev/null 2>&1 || true; done
    # The images this run built (the host stage's too): a CI machine must not fill up with them.
    ids=$(pm images -q --filter "label=$label" 2>/dev/null | sort -u || true)
    [ -z "$ids" ] || pm rmi -f $ids >/dev/null 2>&1 || true
  fi
  rm -rf "$conf_dir"
  fleet_cleanup
  echo "container test: $((SECONDS - started_at)) s in all"
}
trap container_cleanup EXIT

# The Debian mirror apt already uses (deb822 .sources or the one-line format), for debootstrap.
apt_mirror() {
  local uri
  uri=$(cat /etc/apt/sources.list.d/*.sources 2>/dev/null | awk -v RS= '/(^|\n)Suites:[^\n]*bookworm( |\n|$)/ {
          if (match($0, /URIs: *[^ \n]+/)) { split(substr($0, RSTART, RLENGTH), f, " "); print f[2]; exit } }')
  [ -n "$uri" ] || uri=$(awk '$1 == "deb" && $3 == "bookworm" { print $2; exit }' /etc/apt/sources.list 2>/dev/null || true)
  echo "${uri:-http://deb.debian.org/debian}"
}

step "base image $base_image"
if pm image exists "$base_image"; then
  echo "reusing $base_image ($(pm image inspect --format '{{.Created}}' "$base_image"))"
elif [ "$base_image" != localhost/debian-bookworm ]; then
  fail "$base_image does not exist (only localhost/debian-bookworm is made here)"
else
  mirror=$(apt_mirror)
  rootfs=$(mktemp -d /var/tmp/spoofwatch-debian-bookworm.XXXXXX)
  echo "debootstrap --variant=minbase bookworm from $mirror"
  $sudo debootstrap --variant=minbase bookworm "$rootfs" "$mirror" >"$work/debootstrap.log" 2>&1 ||
    { tail -20 "$work/debootstrap.log" >&2; fail "debootstrap failed"; }
  $sudo tar -C "$rootfs" -c . | pm import - "$base_image" >"$work/import.log" 2>&1 ||
    { tail -5 "$work/import.log" >&2; fail "podman import of the base failed"; }
  $sudo rm -rf "$rootfs"
fi

if [ -n "$given_image" ]; then
  image=$given_image
  step "image $image (given)"
else
  step "image $image (Dockerfile, --target host, BASE_IMAGE=$base_image)"
  pm build --isolation chroot --build-arg BASE_IMAGE="$base_image" --target host \
    --label "$label" -t "$image" . >"$work/build.log" 2>&1 || { tail -30 "$work/build.log" >&2; fail "podman build failed"; }
  grep -E '^\[[0-9]/[0-9]\] (STEP|COMMIT)' "$work/build.log" | cut -c1-160 || true
fi
pm image inspect --format 'size {{.Size}} bytes, user {{.Config.User}}, entrypoint {{.Config.Entrypoint}}' "$image"

if [ -n "$break_mode" ]; then
  step "BROKEN image on purpose (--break $break_mode): the checks below must fail"
  broken=localhost/spoofwatch:broken-$$
  mkdir -p "$work/broken"
  case $break_mode in
    entrypoint) layer='ENTRYPOINT ["/usr/local/bin/spoofwatch"]' ;;
    model) layer=$'USER root\nRUN rm /usr/share/spoofwatch/models/paper.json /usr/share/spoofwatch/models/default.json\nUSER spoofwatch' ;;
    volume) layer=$'USER root\nRUN chown root:root /var/lib/spoofwatch && chmod 755 /var/lib/spoofwatch\nUSER spoofwatch' ;;
  esac
  printf 'FROM %s\n%s\n' "$image" "$layer" | tee "$work/broken/Dockerfile"
  pm build --isolation chroot --label "$label" -t "$broken" "$work/broken" >"$work/broken/build.log" 2>&1 ||
    { tail -20 "$work/broken/build.log" >&2; fail "building the broken image failed"; }
  image=$broken
fi

source scripts/lib/container-checks.sh

want() { [[ ",$checks," == *",$1,"* ]]; }
for check in 1 2 3 4 5 6; do
  want "$check" || continue
  check_started=$SECONDS
  "check_$check"
  echo "check $check passed in $((SECONDS - check_started)) s"
done
step "container test passed (checks $checks)"
