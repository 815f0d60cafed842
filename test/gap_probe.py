"""What the fast path offers, frame by frame, around a gap: a stream of ``clip`` with two points
hidden in the frames ``HIDDEN``, and a probe of the labeler after each frame (the young checks'
centres, the releasable labels)."""
from __future__ import annotations

from typing import Callable

import numpy as np

from dtm_labeler.labeling.stream import StreamLabeler

HIDDEN = (80, 100)                                          # frames in which the points are hidden


def probe_per_frame(model, clip, hidden, settings, frames: int,
                    probe: Callable[[StreamLabeler, object, np.ndarray], set]) -> list[set]:
    """``probe(labeler, problem, assignment)`` after each of the first ``frames`` frames of
    ``clip`` with the points ``hidden`` gone in ``HIDDEN``."""
    seen = []
    with StreamLabeler(model, settings) as lab:
        for k in range(frames):
            xyz = clip.positions[k].copy()
            if HIDDEN[0] <= k < HIDDEN[1]:
                xyz[hidden] = np.nan
            lab.process(xyz, k / clip.rate)
            problems, _, found = lab.last_frame
            seen.append(probe(lab, problems[found.best_model], found.best.assignment))
    return seen
