"""A background search's result joins a stream whose markers keep disappearing
(:meth:`~dtm_labeler.labeling.tracked.TrackedLabeler._join`).

HDM05's 41 markers with half of the samples hidden as a capture's occlusions hide them (gaps of
~0.25 s): few of the tracks a search was asked about outlive it. Background recovery is made
deterministic (``DeferredRecovery``: the search's first interim result two frames after the
request, the final one 25 frames after)."""
import pytest

from dtm_labeler.evaluation.corruption import corrupt_clip
from dtm_labeler.evaluation.pipeline import model_clip
from dtm_labeler.labeling.tracked import TrackedLabeler
from background_runs import background_run
from test_gappy_training import _gapped

@pytest.fixture(scope="module")
def stream(hdm05_half_hidden):
    return hdm05_half_hidden


def _run(model, frames) -> tuple[float, list[tuple[int, bool]], list[list[int]]]:
    """Share of the visible markers labelled right, the number of readings each join offered
    (with whether a search had vouched for a frame of the stream by then), and every frame's
    labels."""
    run = background_run(model, frames)
    return run["accuracy"], run["offered"], run["labels"]


def test_a_search_few_of_whose_tracks_outlive_it_joins_on_its_own_labels(hdm05_calibrated, stream,
                                                                       half_hidden_background, monkeypatch):
    """At the start of the stream the carried labeling filling the labels of the search's gone
    tracks made the joined labeling fit worse than the (wrong) carried one, so the search never
    joined; its labels alone, the rest placed by the fast path, do. (No frame of this stream is
    vouched for: a right labeling of half the markers fits below the running level.)"""
    acc, offered = half_hidden_background["accuracy"], half_hidden_background["offered"]   # _run on the stream
    assert max(k for k, _ in offered) == 2           # the bare reading was offered beside the filled one
    assert acc > 0.5
    _filled_only(monkeypatch)
    before, _, _ = _run(hdm05_calibrated, stream)
    assert before < acc - 0.2


def test_after_a_vouched_frame_the_carried_labeling_fills_a_join(hdm05_calibrated, hdm05_take):
    """A quarter of the samples hidden: searches vouch for frames after the first ones. Before
    that, joins offer the search's bare labels too; after it, the carried labeling -- now one a
    search vouched for -- fills the labels of the search's gone tracks, one reading."""
    clip = _gapped(hdm05_take, 0.25, seed=1, gap_s=0.25).slice(2400, 2640)
    frames = list(corrupt_clip(model_clip(hdm05_calibrated, clip), noise_mm=1.0, seed=1))
    acc, offered, _ = _run(hdm05_calibrated, frames)
    assert any(k == 2 for k, v in offered if not v)
    assert sum(v for _, v in offered) >= 5
    assert all(k == 1 for k, v in offered if v)
    assert acc > 0.7


def _filled_only(monkeypatch) -> None:
    """The join as it was before the bare reading: the filled reading only."""
    join = TrackedLabeler._join

    def filled_only(self, inp):
        out = join(self, inp)
        return None if out is None else (out[0][:1], out[1])
    monkeypatch.setattr(TrackedLabeler, "_join", filled_only)


def test_a_join_onto_tracks_that_all_survive_offers_one_reading(hdm05_calibrated, hdm05_take, monkeypatch):
    """A stream without gaps: every track the search labelled is still there, nothing to fill,
    so each join offers one reading and the labels are those of the join before."""
    frames = list(corrupt_clip(model_clip(hdm05_calibrated, hdm05_take.slice(2400, 2480)), noise_mm=1.0, seed=1))
    _, offered, labels = _run(hdm05_calibrated, frames)
    assert offered and {k for k, _ in offered} == {1}
    _filled_only(monkeypatch)
    assert _run(hdm05_calibrated, frames)[2] == labels
