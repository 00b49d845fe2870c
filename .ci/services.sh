#!/usr/bin/env bash
# Local services for the scale-out test (tests/test_distributed.py): Redis and PostgreSQL from Debian's packages.
# Idempotent and fast when they are already installed. It only installs: the packages' own services are kept
# from starting (policy-rc.d), and the tests start private servers on 127.0.0.1 in temp dirs and stop them.
# Never fails the build: without apt (or root) the distributed test skips and says why.
set -uo pipefail

need=()
command -v redis-server >/dev/null 2>&1 || need+=(redis-server)
compgen -G "/usr/lib/postgresql/*/bin/initdb" >/dev/null || need+=(postgresql)
if [ ${#need[@]} -eq 0 ]; then
  echo "services.sh: redis-server and postgresql already installed"
  exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
  echo "services.sh: no apt-get here; tests/test_distributed.py will skip (needs: ${need[*]})"
  exit 0
fi
SUDO=""
if [ "$(id -u)" != 0 ]; then
  if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then SUDO="sudo -n"; else
    echo "services.sh: not root and no sudo; tests/test_distributed.py will skip (needs: ${need[*]})"
    exit 0
  fi
fi
export DEBIAN_FRONTEND=noninteractive
# keep the packages' init scripts from starting system-wide servers during the install
policy=/usr/sbin/policy-rc.d
created_policy=0
if [ ! -e "$policy" ]; then
  printf '#!/bin/sh\nexit 101\n' | $SUDO tee "$policy" >/dev/null && $SUDO chmod 755 "$policy" && created_policy=1
fi
echo "services.sh: installing ${need[*]}"
ok=1
$SUDO apt-get update -qq || ok=0
[ $ok = 1 ] && { $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null || ok=0; }
[ $created_policy = 1 ] && $SUDO rm -f "$policy"
if [ $ok = 0 ]; then
  echo "services.sh: apt-get failed; tests/test_distributed.py will skip"
fi
exit 0
