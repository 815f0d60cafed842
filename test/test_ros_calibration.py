"""The live calibration window (ros/calibration.py), without a node: confirmed labels only,
closed after its seconds of stream, restarted when the time base goes back."""
import numpy as np
import pytest

from dtm_labeler.ros.calibration import CalibrationWindow


def test_window_keeps_confirmed_labels_and_closes_after_its_seconds():
    w = CalibrationWindow(0.1, labels=("a", "b", "c"))
    xyz = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    labels = np.array([2, -1, 0, 1])
    conf = np.array([0.9, 0.9, 0.4, 0.5])              # label 0 not confirmed (0.4 < 0.5)
    out = None
    for k in range(20):                                # 120 Hz: 0.1 s after 12 or 13 frames (rounding)
        out = w.add(10.0 + k / 120, labels, conf, xyz)
        if out is not None:
            break
    assert out is not None and k in (12, 13) and out.positions.shape == (k + 1, 3, 3)
    assert out.names == ("a", "b", "c") and out.rate == pytest.approx(120.0)   # the window's own frame rate
    P = out.positions
    assert np.isnan(P[:, 0]).all()                     # unconfirmed label: not seen
    assert np.allclose(P[:, 1], [3, 0, 0]) and np.allclose(P[:, 2], [0, 0, 0])
    assert f"{k + 1} frames" in w.status


def test_window_restarts_when_time_goes_back():
    w = CalibrationWindow(1.0, labels=("a", "b"))
    one = (np.array([0, 1]), np.ones(2), np.zeros((2, 3)))
    assert w.add(5.0, *one) is None and w.add(5.9, *one) is None
    assert w.add(1.0, *one) is None and w.frames == 1            # a reset of the time base
    assert w.add(2.0, *one).positions.shape == (2, 2, 3)
    with pytest.raises(ValueError):
        CalibrationWindow(0.0, ("a", "b"))
