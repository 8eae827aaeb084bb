#!/usr/bin/env bash
# A throw-away PostgreSQL cluster for tests and local fleets, on 127.0.0.1 only, trust auth.
#
#   scripts/postgres-ephemeral.sh start <dir> <port>   # initdb (once) + start; prints the URL
#   scripts/postgres-ephemeral.sh stop <dir>           # fast shutdown (no error if not running)
#   scripts/postgres-ephemeral.sh url <dir> <port>     # the URL, without starting anything
#
# <dir> holds the data directory, the unix socket and the server log (<dir>/postgres.log). Start is
# idempotent: a cluster already running from <dir> on <port> is reused; a stale postmaster.pid
# (killed server) is cleared by PostgreSQL itself. A port taken by anything else is an error.
# PostgreSQL refuses to run as root, so as root the cluster runs as the `postgres` OS user (created
# by Debian's postgresql package). The binaries are found in PG_BIN, else on PATH, else in the
# newest /usr/lib/postgresql/<version>/bin. Durability is traded for speed (fsync=off): the data of
# this cluster is disposable by design.
set -euo pipefail

die() { echo "postgres-ephemeral: $*" >&2; exit 1; }

pg_bin() {
  if [ -n "${PG_BIN:-}" ]; then echo "$PG_BIN"; return; fi
  if command -v pg_ctl >/dev/null 2>&1; then dirname "$(command -v pg_ctl)"; return; fi
  local newest
  newest=$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -1 || true)
  [ -n "$newest" ] || die "PostgreSQL binaries not found (apt-get install postgresql, or set PG_BIN)"
  echo "$newest"
}

# Runs a command as the cluster's owner: `postgres` when we are root, else ourselves.
as_owner() {
  if [ "$(id -u)" -eq 0 ]; then
    id postgres >/dev/null 2>&1 || die "running as root needs the 'postgres' OS user (Debian's postgresql package creates it)"
    runuser -u postgres -- "$@"
  else
    "$@"
  fi
}

url_of() { echo "postgres://postgres@127.0.0.1:$1/postgres"; }

# Whether something accepts TCP connections on 127.0.0.1:<port>.
port_in_use() { (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; }

# The port the cluster of <data> was started on (line 4 of postmaster.pid), if it runs.
running_port() {
  local data=$1
  as_owner "$BIN/pg_ctl" status -D "$data" >/dev/null 2>&1 || return 1
  sed -n 4p "$data/postmaster.pid"
}

cmd=${1:-}
case "$cmd" in
  start)
    [ $# -eq 3 ] || die "usage: $0 start <dir> <port>"
    dir=$(realpath -m "$2"); port=$3
    [[ "$port" =~ ^[0-9]+$ ]] && [ "$port" -ge 1024 ] && [ "$port" -le 65535 ] || die "port must be 1024-65535, got '$port'"
    BIN=$(pg_bin)
    data=$dir/data; socket=$dir/socket; log=$dir/postgres.log
    mkdir -p "$data" "$socket"
    [ "$(id -u)" -eq 0 ] && chown -R postgres: "$dir"
    chmod 700 "$data"
    if current=$(running_port "$data"); then
      [ "$current" = "$port" ] || die "the cluster in $dir already runs on port $current, not $port"
      url_of "$port"
      exit 0
    fi
    port_in_use "$port" && die "port $port on 127.0.0.1 is in use by another process"
    if [ ! -s "$data/PG_VERSION" ]; then
      as_owner "$BIN/initdb" -D "$data" -U postgres --auth=trust --encoding=UTF8 --locale=C.UTF-8 \
        --no-instructions >"$dir/initdb.log" 2>&1 || { cat "$dir/initdb.log" >&2; die "initdb failed"; }
    fi
    options="-c listen_addresses=127.0.0.1 -c port=$port -c unix_socket_directories=$socket"
    options+=" -c max_connections=300 -c fsync=off -c synchronous_commit=off -c full_page_writes=off"
    if ! as_owner "$BIN/pg_ctl" start -D "$data" -l "$log" -w -t 60 -o "$options" >/dev/null; then
      tail -n 20 "$log" >&2 || true
      die "PostgreSQL did not start (log: $log)"
    fi
    url_of "$port"
    ;;
  stop)
    [ $# -eq 2 ] || die "usage: $0 stop <dir>"
    dir=$(realpath -m "$2"); data=$dir/data
    [ -d "$data" ] || exit 0
    BIN=$(pg_bin)
    if as_owner "$BIN/pg_ctl" status -D "$data" >/dev/null 2>&1; then
      as_owner "$BIN/pg_ctl" stop -D "$data" -m fast -w -t 60 >/dev/null
    fi
    ;;
  url)
    [ $# -eq 3 ] || die "usage: $0 url <dir> <port>"
    url_of "$3"
    ;;
  *)
    die "usage: $0 start <dir> <port> | stop <dir> | url <dir> <port>"
    ;;
esac
