"""No compiled kernel is compiled or loaded on a frame: building a labeler warms up every
kernel a frame calls (``Engine.prepare``), with the very signatures the frames use. A kernel
loaded on a stream's first frames costs 20-50 ms (from numba's disk cache; seconds to compile),
several frame budgets. Checked in a fresh process that only loads a model file -- as the node
does -- for the 14 body points and for a marker set (body factors, rigid clusters), inline and
with the background worker, on streams with gaps, ghosts and noise."""
import subprocess
import sys

import numpy as np

from dtm_labeler.model.io import save_model
from dtm_labeler.motion.load import load_clip
from dtm_labeler.motion.synthetic import synthesize
from dtm_labeler.training.calibrate import calibrate_on_takes
from dtm_labeler.training.train import TrainConfig, train_model

HDM = "markers_c3d/hdm05_bd_05-01_01_120.c3d"
ARM = ["LFHD", "RFHD", "C7", "CLAV", "STRN", "LSHO", "RSHO", "LELB", "LFRM", "LWRA", "LWRB", "LFIN",
       "LFWT", "RFWT"]

STREAM = """
import sys, time
import numpy as np
from numba.core.registry import CPUDispatcher
from dtm_labeler.evaluation.corruption import corrupt_clip
from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler
from dtm_labeler.model.io import load_model

def loaded():
    return {f"{name}.{attr}": len(obj.signatures) for name, mod in list(sys.modules.items())
            if name.startswith("dtm_labeler") for attr, obj in list(vars(mod).items())
            if isinstance(obj, CPUDispatcher)}

model = load_model(sys.argv[1])
test = np.load(sys.argv[2])
from dtm_labeler.motion.clip import MotionClip
clip = MotionClip(positions=test, rate=120.0, names=tuple(model.labels))
for recovery in ("inline", "background"):
    lab = StreamLabeler(model, LabelerSettings(recovery=recovery))
    while recovery == "background" and not lab.recovery.ready:
        lab.recovery.poll()
        time.sleep(0.05)
    before, frames = loaded(), 0
    for fr in corrupt_clip(clip, seed=1, occlude=3, clutter=2, noise_mm=1.0, gap_frames=12):
        lab.process(fr.xyz, fr.stamp)
        frames += 1
    lab.close()
    late = {k: (before.get(k, 0), n) for k, n in loaded().items() if n != before.get(k, 0)}
    assert frames > 50 and not late, (recovery, late)
print("ok")
"""


def _run(tmp_path, model, positions) -> None:
    path = save_model(model, tmp_path / "model.npz")
    np.save(tmp_path / "stream.npy", positions)
    out = subprocess.run([sys.executable, "-c", STREAM, str(path), str(tmp_path / "stream.npy")],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-3000:]


def test_no_kernel_is_loaded_on_a_frame_body_points(tmp_path):
    clips = [synthesize(duration=3.0, seed=s, heading=h, noise_mm=2) for s, h in [(0, 0.0), (1, 1.0), (2, 2.5)]]
    model, _ = train_model(clips, TrainConfig(mixture="fixed", k_fixed=2, structure="given"))
    _run(tmp_path, model, synthesize(duration=1.0, seed=7, heading=-2.0, noise_mm=2, start_xy=(1.0, 2.0)).positions)


def test_no_kernel_is_loaded_on_a_frame_marker_set(tmp_path, data_dir):
    clip = load_clip(data_dir / HDM).select(ARM)
    model, _ = train_model([clip.slice(0, 400)], TrainConfig(structure="greedy", seed=0))
    model = calibrate_on_takes(model, [clip.slice(0, 400)])          # body factors and clusters applied
    assert model.body is not None and model.body.calibration
    _run(tmp_path, model, clip.slice(400, 520).positions)


def test_the_check_sees_a_kernel_a_warm_up_left_out(tmp_path):
    """The check itself: with the votes' warm-up left out, the votes' kernels are loaded on the
    first frame and the check names them."""
    clips = [synthesize(duration=2.0, seed=s, heading=h, noise_mm=2) for s, h in [(0, 0.0), (1, 1.0)]]
    model, _ = train_model(clips, TrainConfig(mixture="fixed", k_fixed=2, structure="given"))
    path = save_model(model, tmp_path / "model.npz")
    np.save(tmp_path / "stream.npy", synthesize(duration=1.0, seed=7, noise_mm=2).positions)
    code = "import dtm_labeler.labeling.voting as v; v.warm_up = lambda: None\n" + STREAM
    out = subprocess.run([sys.executable, "-c", code, str(path), str(tmp_path / "stream.npy")],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode != 0 and "voting._window_counts" in out.stderr, out.stderr[-3000:]
