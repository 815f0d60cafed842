"""Accuracy floors on real recordings (CMU walk 07_01, run 09_11, dance 55_01; body14).

One model is trained on the first 90 % of each of the three BVH recordings; the test frames
come from the last 10 % (within-sequence, unseen frames). Every case pools three corruption /
search seeds, because a single unlucky start can cost a stream a lot.
Floors sit a few points below what was measured (measured values in comments: engine
0e909b0, 3 seeds pooled). No wall-clock assertions.
"""
import numpy as np
import pytest

from dtm_labeler.evaluation.pipeline import label_clip, label_clip_run, label_clips
from dtm_labeler.evaluation.metrics import MetricsAccumulator
from dtm_labeler.labeling.stream import LabelerSettings
from dtm_labeler.training.train import TrainConfig, train_model
from dtm_labeler.motion import load_clip, to_point_set

BVH = {"walk": "cmu_07_01_walk_s07.bvh", "run": "cmu_09_11_run_s09.bvh", "dance": "cmu_55_01_dance-whirl_s55.bvh"}
SEEDS = (0, 1, 2)
STREAM_FRAMES = 40          # run 09_11 has only 17 test frames
SINGLE_FRAMES = 10


@pytest.fixture(scope="module")
def clips(data_dir):
    return {k: to_point_set(load_clip(data_dir / "cmu_skeletal/bvh_from_fbx" / f), "body14") for k, f in BVH.items()}


def split(clip):
    return int(round(0.9 * clip.n_frames))


@pytest.fixture(scope="module")
def model(clips):
    train = [c.slice(0, split(c)) for c in clips.values()]
    m, _ = train_model(train, TrainConfig(seed=0))
    return m


def pooled(model, clip, mode, frames, **corruption):
    """Metrics pooled over SEEDS (each seed: its own corruption and search seed)."""
    test = clip.slice(split(clip), split(clip) + frames)
    accs = []
    for s in SEEDS:
        m, _ = label_clip(model, test, LabelerSettings(mode=mode, seed=s), seed=s, keep_records=False,
                          **corruption)
        accs.append(m)
    points = sum(m.points for m in accs)
    correct = sum(m.correct for m in accs)
    ghosts = sum(m.ghosts for m in accs)
    rejected = sum(round(m.ghost_rejection * m.ghosts) for m in accs if m.ghosts)
    per_seed = [round(m.accuracy, 3) for m in accs]
    print(f"{mode} {corruption}: accuracy {correct / points:.3f} per seed {per_seed}"
          + (f", ghost rejection {rejected / ghosts:.3f}" if ghosts else ""))
    return correct / points, (rejected / ghosts if ghosts else None)


# (clip, mode, occlude, floor)   measured pooled accuracy in the comment
CASES = [
    ("walk", "stream", 0, 0.95),     # 1.000
    ("run", "stream", 0, 0.95),      # 1.000
    ("dance", "stream", 0, 0.95),    # 1.000
    ("walk", "stream", 3, 0.85),     # 0.924 (1.0, 0.773, 1.0)
    ("run", "stream", 3, 0.90),      # 0.977
    ("dance", "stream", 3, 0.85),    # 0.913 (1.0, 0.739, 1.0)
    ("walk", "single", 0, 0.95),     # 1.000
    ("run", "single", 0, 0.95),      # 0.994
    ("dance", "single", 0, 0.95),    # 1.000
    ("walk", "single", 3, 0.80),     # 0.867 (0.9, 0.764, 0.936)
    ("run", "single", 3, 0.82),      # 0.897
    ("dance", "single", 3, 0.85),    # 0.924
]


@pytest.mark.parametrize("name, mode, occlude, floor", CASES, ids=[f"{c}-{m}-occ{o}" for c, m, o, _ in CASES])
def test_accuracy_floor(model, clips, name, mode, occlude, floor):
    frames = STREAM_FRAMES if mode == "stream" else SINGLE_FRAMES
    acc, _ = pooled(model, clips[name], mode, frames, occlude=occlude)
    assert acc >= floor


def test_ghosts_and_occlusion_walk_stream(model, clips):
    acc, rej = pooled(model, clips["walk"], "stream", STREAM_FRAMES, occlude=2, clutter=2, noise_mm=1.0)
    assert acc >= 0.85              # measured 0.931 (1.0, 0.797, 0.997)
    assert rej >= 0.78              # measured 0.849


def test_label_clips_pools_the_three_recordings(model, clips):
    tests = [c.slice(split(c), split(c) + 15) for c in clips.values()]
    m, runs = label_clips(model, tests, LabelerSettings(mode="stream"), seed=0)
    assert len(runs) == 3
    assert m.frames == sum(r.metrics.frames for r in runs) == 15 + 15 + 15
    assert m.points == sum(r.metrics.points for r in runs)
    pooled_acc = MetricsAccumulator.merge(r.accumulator for r in runs).metrics().accuracy
    assert m.accuracy == pytest.approx(pooled_acc)
    assert m.accuracy >= 0.95


def test_run_only_model_stream_recovers_from_first_frame(clips):
    """Regression: with engine 53fe377 a wrong first full search (no velocities yet) was kept by
    the fast path for the whole stream (accuracy 0.786 for seeds 0 and 1); fixed by 0e909b0."""
    run = clips["run"]
    m, _ = train_model([run.slice(0, split(run))], TrainConfig(seed=0))
    accs = []
    for s in (0, 1):
        met, _ = label_clip(m, run.slice(split(run), None), LabelerSettings(mode="stream", seed=s), seed=s,
                            keep_records=False)
        accs.append(met.accuracy)
    print("run-only model, stream, clean:", np.round(accs, 3))      # measured 1.0, 1.0
    assert min(accs) >= 0.95


def test_published_confidence_is_calibrated(model, clips):
    """Of the labels published with confidence c, about a fraction c is right (labeling/
    confidence.py): walk and dance streams with 3 hidden points and 2 ghosts, 3 seeds, 5070
    labels. Expected calibration error over 10 bins measured 1.2 % (2.1 % before the product
    of the confidence's factors was tempered; 1.1 % with the tempering refitted, 0.6 -> 0.45)."""
    runs = []
    for name in ("walk", "dance"):
        test = clips[name].slice(split(clips[name]), split(clips[name]) + 120)
        for s in SEEDS:
            runs.append(label_clip_run(model, test, LabelerSettings(seed=s), seed=s, occlude=3, clutter=2,
                                       keep_records=False).accumulator)
    m = MetricsAccumulator.merge(runs).metrics()
    assert m.calibration_error < 0.018
    lo, hi, n, conf, right = m.reliability[-1]
    assert lo == 0.9 and n > 0.8 * sum(r[2] for r in m.reliability) and right > 0.99
