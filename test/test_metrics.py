"""labeling.metrics on hand-made frames: every metric can fail."""
import numpy as np
import pytest

from dtm_labeler.evaluation.metrics import (MetricsAccumulator, accuracy, ghost_rejection, is_search_error,
                                          percentile_summary)

LABELS = ["a", "b", "c"]


def test_accuracy_counts_only_visible_true_markers():
    truth = np.array([0, 1, 2, -1])
    assert accuracy(truth, np.array([0, 1, 2, 1])) == 1.0          # ghost labelled: not an accuracy error
    assert accuracy(truth, np.array([0, 2, 1, -1])) == pytest.approx(1 / 3)
    assert accuracy(truth, np.array([0, 1, -1, -1])) == pytest.approx(2 / 3)   # unlabelled = wrong
    assert accuracy(np.array([-1, -1]), np.array([0, 1])) is None


def test_ghost_rejection():
    truth = np.array([0, -1, -1, -1, 1])
    assert ghost_rejection(truth, np.array([0, -1, -1, -1, 1])) == 1.0
    assert ghost_rejection(truth, np.array([0, 2, -1, -1, 1])) == pytest.approx(2 / 3)
    assert ghost_rejection(np.array([0, 1]), np.array([0, 1])) is None


def test_search_error_rule():
    assert is_search_error(10.0, 9.0)
    assert not is_search_error(10.0, 10.0)
    assert not is_search_error(10.0 + 5e-7, 10.0)       # within tolerance
    assert not is_search_error(9.0, 10.0)
    assert not is_search_error(float("nan"), 10.0)


def test_percentiles():
    s = percentile_summary(np.arange(1, 101, dtype=float))
    assert s["p50"] == pytest.approx(50.5)
    assert s["p99"] == pytest.approx(99.01)
    assert s["max"] == 100.0
    assert percentile_summary([])["p50"] is None


def test_accumulator_accuracy_confusion_per_label():
    acc = MetricsAccumulator(LABELS, rate=10.0)
    acc.add([0, 1, 2], [0, 1, 2])
    acc.add([2, 0, 1, -1], [2, 1, -1, 0])          # a->b, b unlabelled, ghost -> a
    m = acc.metrics()
    assert m.frames == 2 and m.points == 6 and m.correct == 4
    assert m.accuracy == pytest.approx(4 / 6)
    assert m.frame_accuracy == pytest.approx(0.5)
    assert m.per_label == {"a": 0.5, "b": 0.5, "c": 1.0}
    assert m.ghosts == 1 and m.ghost_rejection == 0.0
    c = m.confusion
    assert c.shape == (4, 4)
    assert c[0, 0] == 1 and c[0, 1] == 1 and c[1, 3] == 1 and c[3, 0] == 1 and c[2, 2] == 2
    assert c.sum() == 7
    assert ("a", "b", 1) in m.confused_pairs()


def test_valid_mask_excludes_points():
    acc = MetricsAccumulator(LABELS, rate=10.0)
    acc.add([0, 1, 2], [0, -1, 2], valid=[True, False, True])
    m = acc.metrics()
    assert m.points == 2 and m.accuracy == 1.0


def test_swaps_definition():
    acc = MetricsAccumulator(LABELS, rate=60.0)
    acc.add([0, 1], [0, 1])
    acc.add([1, 0], [0, 1])             # order shuffled, labels swapped: 2 swaps
    acc.add([0, 1], [-1, 1])            # a unlabelled: no swap (empty label); b: a -> b: swap
    acc.add([0, 1], [2, 1])             # a: -1 -> c, no swap (previous label empty)
    acc.add([1], [1])                   # a not visible
    acc.add([0, 1], [0, 1])             # a: c (its last visible frame) -> a: swap
    m = acc.metrics()
    assert m.swaps == 4
    assert m.duration_s == pytest.approx(6 / 60)
    assert m.swaps_per_min == pytest.approx(4 / 6 * 60 * 60)


def test_no_swaps_when_labels_stable_under_shuffling():
    rng = np.random.default_rng(0)
    acc = MetricsAccumulator(LABELS, rate=100.0)
    for _ in range(20):
        t = rng.permutation(3)
        acc.add(t, t)
    assert acc.metrics().swaps == 0
    assert acc.metrics().accuracy == 1.0


def test_search_errors_latency_fps():
    acc = MetricsAccumulator(LABELS, rate=10.0)
    acc.add([0], [0], latency_ms=10.0, log_likelihood=5.0, truth_fitness=5.0, full_search=True)
    acc.add([0], [0], latency_ms=30.0, log_likelihood=5.0, truth_fitness=7.0, full_search=False)
    acc.add([0], [0], latency_ms=20.0, log_likelihood=5.0)           # no truth: not checked
    m = acc.metrics()
    assert m.search_errors == 1 and m.search_checked == 2 and m.search_error_rate == 0.5
    assert m.latency_ms["p50"] == 20.0 and m.latency_ms["max"] == 30.0
    assert m.fps == pytest.approx(3 / 0.060)
    assert m.full_search_rate == 0.5


def test_search_errors_the_priors_held():
    """Of the frames whose truth fits better, those whose truth the fast path's priors charge more
    than it gains are held, not missed; merged accumulators add them up."""
    parts = []
    for prior in (1.0, 3.0):
        acc = MetricsAccumulator(LABELS, rate=10.0)
        acc.add([0], [0], log_likelihood=5.0, truth_fitness=7.0, truth_prior=prior)      # gains 2, pays prior
        acc.add([0], [0], log_likelihood=5.0, truth_fitness=4.0, truth_prior=-9.0)       # no search error
        parts.append(acc)
    assert [(p.metrics().search_errors, p.metrics().search_errors_held) for p in parts] == [(1, 0), (1, 1)]
    merged = MetricsAccumulator.merge(parts).metrics()
    assert merged.search_errors == 2 and merged.as_dict()["search_errors_held"] == 1


def test_search_errors_by_kind():
    """A search-error frame counts under each kind of wrong label its search labeling shows (a
    label on a clutter point, a visible marker left out, one under another label); frames that
    are no search error, and search errors without the search's labels, count under none."""
    acc = MetricsAccumulator(LABELS, rate=10.0)
    err = dict(log_likelihood=5.0, truth_fitness=7.0)
    acc.add([0, -1], [0, -1], search_labels=[-1, 0], **err)          # marker 0 left out, a ghost holds 0
    acc.add([0, 1], [0, 1], search_labels=[1, 0], **err)             # swapped
    acc.add([0, 1], [0, 1], search_labels=[1, 0], log_likelihood=5.0, truth_fitness=4.0)    # not an error
    acc.add([0, -1], [0, -1], **err)                                 # an error, no search labels
    acc.add([0, -1, 1], [0, -1, 1], search_labels=[0, 1, -1], valid=[True, False, True], **err)  # only left out
    m = acc.metrics()
    assert m.search_errors == 4
    assert m.search_error_kinds == {"ghost": 1, "left_out": 2, "relabelled": 1}
    merged = MetricsAccumulator.merge([acc, acc]).metrics()
    assert merged.as_dict()["search_error_kinds"] == {"ghost": 2, "left_out": 4, "relabelled": 2}


def test_search_accuracy_uses_search_labels():
    acc = MetricsAccumulator(LABELS, rate=10.0)
    acc.add([0, 1], [0, 1], search_labels=[1, 0])
    m = acc.metrics()
    assert m.accuracy == 1.0 and m.search_accuracy == 0.0


def test_merge_adds_up_and_does_not_swap_across_clips():
    a = MetricsAccumulator(LABELS, rate=10.0)
    a.add([0, 1], [0, 1], latency_ms=1.0)
    b = MetricsAccumulator(LABELS, rate=20.0)
    b.add([0, 1], [1, 0], latency_ms=3.0)
    m = MetricsAccumulator.merge([a, b]).metrics()
    assert m.frames == 2 and m.swaps == 0 and m.points == 4 and m.correct == 2
    assert m.duration_s == pytest.approx(0.1 + 0.05)
    assert m.latency_ms["max"] == 3.0
    with pytest.raises(ValueError):
        MetricsAccumulator.merge([a, MetricsAccumulator(["x"], 10.0)])


def test_bad_input_rejected():
    acc = MetricsAccumulator(LABELS, rate=10.0)
    with pytest.raises(ValueError):
        acc.add([0, 1], [0])
    with pytest.raises(ValueError):
        acc.add([0, 0], [0, 0])          # one true label on two points
    with pytest.raises(ValueError):
        acc.add([3], [0])
    with pytest.raises(ValueError):
        MetricsAccumulator(LABELS, rate=0.0)


def test_empty_accumulator():
    m = MetricsAccumulator(LABELS, rate=10.0).metrics()
    assert m.accuracy is None and m.ghost_rejection is None and m.swaps_per_min is None
    assert m.fps is None and m.search_error_rate is None
    d = m.as_dict()
    assert d["labels"] == 3 and d["latency_ms"]["p50"] is None
