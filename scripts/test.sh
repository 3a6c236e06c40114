#!/usr/bin/env bash
# Installs everything the test suite needs on a fresh Debian machine, then runs it.
#   bash scripts/test.sh            # whole suite
#   bash scripts/test.sh -k wire    # extra arguments go to pytest
set -euo pipefail
cd "$(dirname "$0")/.."

# Debian packages: dbus-daemon + headers to build dbus-python (BlueZ is mocked on a private bus),
# systemd for `systemd-analyze verify` of our units; debootstrap, systemd-container, iproute2 and
# openssh-client for the fleet test bed (tests/deploy/test_testbed.py boots Debian hosts); chromium
# to load the operator console's page in a real headless browser (tests/collector/test_console_web.py).
need_apt=()
for pkg in libdbus-1-dev libglib2.0-dev pkg-config dbus systemd \
           debootstrap systemd-container iproute2 openssh-client chromium; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
if ((${#need_apt[@]})); then
  if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
  echo "installing Debian packages: ${need_apt[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[dev]'
# Lint, formatting and type errors fail the run before any test starts (settings: [tool.ruff], [tool.mypy]).
.venv/bin/python -m ruff check .
.venv/bin/python -m ruff format --check .
.venv/bin/python -m mypy
# One worker per core, at most 4 (pytest-xdist). --dist loadfile keeps each file on one worker, so a
# file's module fixtures (the booted test-bed hosts, a shared render) are built once. `-n 0` after
# the script's name runs the suite in one process (the last -n given wins).
workers=$(nproc 2>/dev/null || echo 1)
((workers > 4)) && workers=4
exec .venv/bin/python -m pytest -n "$workers" --dist loadfile "$@"
