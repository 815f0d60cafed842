"""``bench_stream_latency``'s 14-point case on a smaller budget, for the tests of the fast path's
checks: the model of the first halves of walk 07_01, run 09_11 and dance 55_01, and 360 frames
of the dance's second half with 3 markers in gaps of ~24 frames, 2 ghosts and 1 mm noise."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dtm_labeler.evaluation.corruption import corrupt_clip
from dtm_labeler.evaluation.metrics import MetricsAccumulator
from dtm_labeler.labeling.config import LabelerSettings
from dtm_labeler.labeling.stream import StreamLabeler
from dtm_labeler.motion import load_clip, to_point_set
from dtm_labeler.training.train import TrainConfig, train_model

BVH = ["cmu_07_01_walk_s07.bvh", "cmu_09_11_run_s09.bvh", "cmu_55_01_dance-whirl_s55.bvh"]
SEEDS = (1, 2, 3, 4)


def dance_case(data_dir: Path, trained=lambda name, build: build()):
    """(model, the 360 test frames of the dance); ``trained(name, build)``: the model
    ``build()`` trains (conftest's ``trained_once`` shares it between a run's workers)."""
    clips = [to_point_set(load_clip(data_dir / "cmu_skeletal/bvh_from_fbx" / f), "body14") for f in BVH]
    model = trained("dance_case", lambda: train_model([c.slice(0, c.n_frames // 2) for c in clips],
                                                      TrainConfig(seed=0))[0])
    dance = clips[2]
    return model, dance.slice(dance.n_frames // 2, dance.n_frames // 2 + 360)


def pooled(model, test, **settings) -> tuple[float, int]:
    """Accuracy and search errors over the four corruption seeds' streams, inline searches."""
    correct = points = errors = 0
    for seed in SEEDS:
        stream = corrupt_clip(test, occlude=3, clutter=2, noise_mm=1.0, gap_frames=24, seed=seed)
        acc = MetricsAccumulator(model.labels, test.rate)
        with StreamLabeler(model, LabelerSettings(recovery="inline", **settings)) as lab:
            for fr in stream:
                r = lab.process(fr.xyz, fr.stamp, truth=fr.label_to_index)
                acc.add_result(fr.truth, r, valid=np.isfinite(fr.xyz).all(1))
        m = acc.metrics()
        correct, points, errors = correct + m.correct, points + m.points, errors + m.search_errors
    return correct / points, errors
