#!/usr/bin/env bash
# Installs Debian packages for the CI and the fleet scripts: apt-install.sh package...
#
# A machine whose earlier install was cut off (a killed job, a restarted VM) has dpkg marked as
# interrupted, and every apt-get install then refuses until `dpkg --configure -a` has run; another
# apt-get still running holds dpkg's lock. Both are repaired or waited out here rather than failing
# a test run for a reason that has nothing to do with the sources.
set -euo pipefail
[ $# -gt 0 ] || { echo "usage: $0 package..." >&2; exit 2; }
sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
lock_wait=(-o DPkg::Lock::Timeout=300)
export DEBIAN_FRONTEND=noninteractive

# An interrupted dpkg leaves its journal in /var/lib/dpkg/updates; `--audit` also lists half-configured
# packages. Finishing that work is what apt-get itself asks for.
if [ -n "$(ls -A /var/lib/dpkg/updates 2>/dev/null)" ] || [ -n "$($sudo dpkg --audit 2>/dev/null)" ]; then
  echo "dpkg was interrupted earlier: finishing its configuration first (dpkg --configure -a)" >&2
  $sudo env DEBIAN_FRONTEND=noninteractive dpkg --force-confdef --force-confold --configure -a >/dev/null
fi
$sudo apt-get "${lock_wait[@]}" update -qq
$sudo env DEBIAN_FRONTEND=noninteractive apt-get "${lock_wait[@]}" install -y -qq --no-install-recommends "$@" >/dev/null
