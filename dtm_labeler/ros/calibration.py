"""Subject calibration from the live stream (``~/calibrate``): the window of confirmed labels.

A call to ``~/calibrate`` opens a :class:`CalibrationWindow` of ``calibration_s`` seconds of
the node's own time base. Every frame labelled in it adds the positions of the labels
confirmed with at least ``min_confidence`` (the labeler's ``confirmation``,
:func:`~dtm_labeler.training.calibrate.confirmation_of` and
:func:`~dtm_labeler.training.calibrate.confirmed_positions`, as the offline self-calibration); when the window is full, :meth:`CalibrationWindow.add` hands back a
labelled clip of them (NaN where a label was not confirmed) at the window's own frame rate (the
velocities the calibrated model's fit reference needs). The node's loader thread then computes
the calibrated model (:func:`~dtm_labeler.training.calibrate.calibrate`: medians over the window,
the placement shift of each triangle's means and the fit reference -- 0.3-0.4 s at 41 markers
and 600 frames; the calibrated model's terms are built there too, 0.8 s, before the swap)
and the worker swaps it in between two frames, keeping tracks and votes, like a new
``noise_mm``. Nothing here runs a search: collecting costs one (M, 3) copy per frame.

The node's ``auto_calibrate`` opens a window with ``keep_clouds`` after each model load: it
also keeps each frame's points (an (n, 3) copy), on which the loader has
:func:`~dtm_labeler.training.calibrate.auto_calibrate` self-calibrate the model in a process
of its own and keep the result only when it holds up, as ``dtm-label`` does by default.

Pure numpy, no ROS: tested without a node.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from ..labeling.confidence import CONFIRMED
from ..motion.clip import MotionClip
from ..training.calibrate import confirmed_positions

__all__ = ["CalibrationWindow", "MIN_CONFIDENCE"]

#: confidence a published label needs to count as confirmed (as the offline self-calibration)
MIN_CONFIDENCE = CONFIRMED


class CalibrationWindow:
    """Confirmed labels of ``seconds`` of stream (module doc); ``status`` says where it is."""

    def __init__(self, seconds: float, labels: Sequence[str], min_confidence: float = MIN_CONFIDENCE,
                 keep_clouds: bool = False):
        if seconds <= 0 or len(labels) < 1:
            raise ValueError("a calibration window needs a positive length and at least one label")
        self.seconds, self.labels, self.min_confidence = float(seconds), tuple(labels), float(min_confidence)
        self.n_labels = len(self.labels)
        self.keep_clouds = bool(keep_clouds)     # the auto calibration: the frames' points too
        self.clouds: list[np.ndarray] = []
        self._frames: list[np.ndarray] = []
        self._t0: Optional[float] = None
        self._last = 0.0

    @property
    def frames(self) -> int:
        return len(self._frames)

    @property
    def status(self) -> str:
        done = 0.0 if self._t0 is None else self._last - self._t0
        return f"collecting ({min(done, self.seconds):.1f} of {self.seconds:g} s, {self.frames} frames)"

    def add(self, stamp: float, labels: np.ndarray, confidence: np.ndarray, xyz: np.ndarray
            ) -> Optional[MotionClip]:
        """Add one labelled frame; once ``seconds`` are covered, the window's confirmed positions
        as a clip (F frames of the labels, at F - 1 frames over the window's span), else None."""
        if self._t0 is None:
            self._t0 = stamp
        if stamp < self._t0:                     # the time base went back (a reset): start again
            self._frames, self.clouds, self._t0 = [], [], stamp
        self._last = stamp
        self._frames.append(confirmed_positions(labels, confidence, xyz, self.n_labels, self.min_confidence))
        if self.keep_clouds:
            self.clouds.append(np.array(xyz, dtype=np.float64))
        if stamp - self._t0 >= self.seconds:
            rate = (len(self._frames) - 1) / (stamp - self._t0)
            return MotionClip(np.stack(self._frames), rate, self.labels, source="live stream (~/calibrate)")
        return None
