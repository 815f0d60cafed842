#!/usr/bin/env bash
# One-time (idempotent) set-up: venv with pinned requirements, this package (editable),
# and the interface packages (dtm_labeler_msgs, mocap4r2_msgs' markers) built into the venv (rosidl).
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
# interface packages built into the venv with rosidl (~10-20 s each, once): our messages, and the
# marker interfaces of mocap4r2_msgs (not on the package index; a ROS install uses its own)
build_msgs() {  # <package dir> <python module>
  local dir=$1 mod=$2 stamp=".venv/.msgs.$(basename "$1").built"
  [ -f "$dir/package.xml" ] || return 0
  if ! python -c "import $mod.msg" 2>/dev/null || [ ! -f "$stamp" ] \
     || [ -n "$(find "$dir" -newer "$stamp" 2>/dev/null | head -1)" ]; then
    echo "[setup] building $dir ($mod) into the venv"
    bash scripts/build_msgs.sh "$dir" "$here/.venv/build_$(basename "$dir")"
    touch "$stamp"
  fi
}
build_msgs msg_defs dtm_labeler_msgs
build_msgs vendor/mocap4r2_msgs mocap4r2_msgs
# compile the numba kernels once (cached on disk next to the sources): otherwise the first
# labeler of a fresh checkout -- a node loading its first model -- pays ~10-20 s of compiling
echo "[setup] compiling the labeler's kernels (cached; seconds when up to date)"
python - <<'PY'
from dtm_labeler.evaluation.corruption import corrupt_clip
from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler
from dtm_labeler.motion import synthesize
from dtm_labeler.training.train import TrainConfig, train_model
clip = synthesize(duration=1.0, seed=1)
model, _ = train_model([clip], TrainConfig(mixture="fixed", k_fixed=2, structure="greedy"))
with StreamLabeler(model, LabelerSettings(recovery="inline")) as lab:
    for fr in corrupt_clip(clip.slice(0, 40), occlude=2, clutter=2, gap_frames=1, seed=1):
        lab.process(fr.xyz, fr.stamp)
PY
echo "[setup] ready: source .venv/bin/activate"
