"""Young checks (``TrackedLabeler._young_centres``, setting ``young_checks``): the regions of
labels on points whose track began less than half a second ago are relabelled exactly, one label
per frame in turn, for joint centres (not marker sets: ``TriangulatedModel.marker_set``); on a
real dance with gaps and ghosts the published labeling falls below the truth in fewer frames."""
import dataclasses

import numpy as np

from dtm_labeler.labeling.config import LabelerSettings
from dtm_labeler.labeling.fast_path import YOUNG_S
from dtm_labeler.motion.synthetic import synthesize
from dtm_labeler.training.train import TrainConfig, train_model
from gap_probe import HIDDEN, probe_per_frame


def young_centres_per_frame(model, clip, hidden, settings, frames):
    """The labels :meth:`_young_centres` names after each frame, drawn twice per frame (the
    labels come up in turn)."""
    return probe_per_frame(model, clip, hidden, settings, frames,
                           lambda lab, p, a: set(lab._young_centres(p, a)) | set(lab._young_centres(p, a)))


def test_labels_on_new_tracks_are_checked_while_the_tracks_are_young():
    """A knee and a wrist hidden for 20 frames come back on new tracks: their labels come up in
    turn while the tracks are younger than ``YOUNG_S``, then not; none of the tracks the stream
    began with (every track is new there), and nothing with the setting at 0."""
    walker = train_model([synthesize(duration=2.0, seed=s, heading=h) for s, h in [(0, 0.0), (1, 1.5)]],
                         TrainConfig(mixture="fixed", k_fixed=2, structure="given"))[0]
    assert not walker.marker_set
    labels = list(walker.labels)
    hidden = [labels.index("lknee"), labels.index("rwrist")]
    clip = synthesize(duration=2.0, seed=5, heading=0.3)
    frames = HIDDEN[1] + int(1.5 * YOUNG_S * clip.rate)
    on = young_centres_per_frame(walker, clip, hidden, LabelerSettings(young_checks=1, recovery="inline"), frames)
    assert not set().union(*on[:HIDDEN[1]])
    assert all(s == set(hidden) for s in on[HIDDEN[1] + 1:HIDDEN[1] + int(0.9 * YOUNG_S * clip.rate)])
    assert not set().union(*on[HIDDEN[1] + int(1.1 * YOUNG_S * clip.rate):])
    off = young_centres_per_frame(walker, clip, hidden, LabelerSettings(young_checks=0, recovery="inline"), frames)
    assert not set().union(*off)


def test_no_young_checks_on_a_marker_set(hdm05_markers):
    """HDM05's 41 markers (a body with handedness quadruples): a thigh and a knee marker back
    from a gap are not checked; they are once the body loses its quadruples."""
    model, clip = hdm05_markers                  # a model of the take's first 600 frames
    assert model.marker_set
    test = clip.slice(600, 800)
    labels = list(model.labels)
    hidden = [list(test.names).index(n) for n in ("LTHI", "RKNE")]
    assert [labels[i] for i in hidden] == ["LTHI", "RKNE"]
    settings = LabelerSettings(young_checks=1, recovery="inline")
    assert not set().union(*young_centres_per_frame(model, test, hidden, settings, HIDDEN[1] + 30))
    unsided = model.replace(body=dataclasses.replace(model.body, quads=np.zeros((0, 4), dtype=np.int64),
                                                     quad_sign=np.zeros(0)))
    assert not unsided.marker_set                            # the same body without its clusters' handedness
    assert set().union(*young_centres_per_frame(unsided, test, hidden, settings, HIDDEN[1] + 30)) == set(hidden)


def test_fewer_search_errors_on_a_real_dance_with_gaps_and_ghosts(dance_pooled):
    """``bench_stream_latency``'s 14-point case: the model of the first halves of walk 07_01, run
    09_11 and dance 55_01 labels 360 frames of the dance's second half, 3 markers in gaps of ~24
    frames, 2 ghosts, 1 mm noise, four corruption seeds pooled: search errors 54 -> 20 and
    accuracy 98.52 -> 98.66 % with young checks (measured 2026-12-06; when they landed 42 -> 16,
    98.81 -> 98.90 %; without release moves then 89 -> 39, 98.74 -> 98.88 %)."""
    pooled_by = {v: dance_pooled(young_checks=v) for v in (0, 1)}
    print(pooled_by)
    assert pooled_by[1][1] <= 0.8 * pooled_by[0][1]
    assert pooled_by[1][0] >= pooled_by[0][0] - 0.001
