#!/usr/bin/env bash
# One-time (idempotent) set-up: venv with pinned requirements, this package (editable),
# and the dtm_labeler_msgs interface package built into the venv (rosidl, ~10 s).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
cd "$here"
PY=${PYTHON:-python3.11}
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $PY"
  "$PY" -m venv .venv
fi
# shellcheck disable=SC1091
source .venv/bin/activate
if ! cmp -s requirements.txt .venv/.requirements.installed 2>/dev/null; then
  echo "[setup] installing pinned requirements (about a minute the first time)"
  # a pip that builds editable installs through PEP 660 (the stock one falls back to
  # 'setup.py develop', which the ament setup.cfg options break under setuptools 80)
  pip install -q --disable-pip-version-check pip==26.3
  pip install -q --disable-pip-version-check -r requirements.txt
  cp requirements.txt .venv/.requirements.installed
fi
pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e . >/dev/null
if [ -d msg_defs ] && ! python -c "import dtm_labeler_msgs.msg" 2>/dev/null \
   || [ -n "$(find msg_defs -newer .venv/.msgs.built 2>/dev/null | head -1)" ] \
   || [ ! -f .venv/.msgs.built ]; then
  if [ -f msg_defs/package.xml ]; then
    echo "[setup] building msg_defs (dtm_labeler_msgs) into the venv"
    bash scripts/build_msgs.sh msg_defs "$here/.venv/build_msgs"
    touch .venv/.msgs.built
  fi
fi
echo "[setup] ready: source .venv/bin/activate"
