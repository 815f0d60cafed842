"""LabelTenure: how long each track has carried each label (the fast path's hold prior)."""
from __future__ import annotations

import numpy as np

from dtm_labeler.labeling.label_tenure import LabelTenure


def test_a_pair_keeps_the_time_it_was_first_published():
    t = LabelTenure(n_labels=4)
    t.update([10, 11], [0, 1], [], 0.0)
    t.update([10, 11, 12], [0, 1, 2], [], 0.5)
    held = t.held_for([10, 11, 12], [0, 1, 2], 1.0)
    assert held.tolist() == [1.0, 1.0, 0.5]
    assert t.held_for([10], [1], 1.0).tolist() == [0.0]           # never published together


def test_a_label_that_flickers_to_a_neighbour_and_back_keeps_its_tenure():
    t = LabelTenure(n_labels=3)
    t.update([5, 6], [0, 1], [], 0.0)
    t.update([5, 6], [1, 0], [], 0.3)                              # one frame exchanged
    t.update([5, 6], [0, 1], [], 0.4)
    assert t.held_for([5, 6, 5], [0, 1, 1], 1.0).tolist() == [1.0, 1.0, 0.7]


def test_lost_tracks_are_forgotten_and_unlabelled_points_add_nothing():
    t = LabelTenure(n_labels=3)
    t.update([1, 2, 3], [0, 1, -1], [], 0.0)
    assert len(t) == 2
    t.update([2], [1], [1], 1.0)
    assert len(t) == 1
    assert t.held_for([1, 2], [0, 1], 2.0).tolist() == [0.0, 2.0]


def test_broadcast_lookup():
    t = LabelTenure(n_labels=5)
    t.update([7, 8], [3, 4], [], 0.25)
    held = t.held_for(np.array([[7, 8]]), np.array([[3], [4]]), 1.25)   # (2 labels, 2 tracks)
    assert held.tolist() == [[1.0, 0.0], [0.0, 1.0]]
    t.reset()
    assert len(t) == 0 and t.held_for([7], [3], 2.0).tolist() == [0.0]


def test_clutter_runs_count_unbroken_frames_left_unlabelled():
    t = LabelTenure(n_labels=3)
    t.update([1, 2], [0, -1], [], 0.0)
    t.update([1, 2, 3], [-1, -1, -1], [], 0.5)          # track 1 loses its label, 3 is new
    assert t.clutter_for([1, 2, 3, 9], 1.0).tolist() == [0.5, 1.0, 0.5, 0.0]
    t.update([2, 3], [1, -1], [], 1.0)                  # 2 labelled: its run ends; 1 unseen keeps its run
    assert t.clutter_for([1, 2, 3], 1.5).tolist() == [1.0, 0.0, 1.0]
    t.update([2], [-1], [3], 2.0)                       # 3 lost: forgotten; 2 starts a new run
    assert t.clutter_for([1, 2, 3], 2.5).tolist() == [2.0, 0.5, 0.0]
    assert t.held_for([2], [1], 2.5).tolist() == [1.5]  # the label's tenure is kept beside
    t.reset()
    assert t.clutter_for([1, 2], 3.0).tolist() == [0.0, 0.0]


def test_clutter_runs_start_and_the_labels_last_publication():
    t = LabelTenure(n_labels=3)
    t.update([1, 2], [0, -1], [], 0.0)
    t.update([2], [-1], [1], 0.5)                       # track 1 (label 0) lost
    assert np.isnan(t.clutter_since([1, 7])).all()
    assert t.clutter_since([2]).tolist() == [0.0]
    assert t.last_published.tolist() == [0.0, -np.inf, -np.inf]
