#!/usr/bin/env bash
# Fresh machine -> installed suite -> the built-in demo, with no Bluetooth radio and no camera.
#   bash scripts/demo.sh [--out DIR]   (extra arguments go to `annotator demo`)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[all]'
exec .venv/bin/annotator demo "$@"
