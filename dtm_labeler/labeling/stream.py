"""The stream labeler: points in, labelled points out, one frame at a time, with one model.

The whole per-frame pipeline -- sanitise, tracker, frame problem, fast path / warm GA / full
GA with restarts, fitness level, votes (eq. 32) -- is :class:`~.tracked.TrackedLabeler`'s;
with one model every search is a GA on one island (:class:`~dtm_labeler.search.label_search.GASearch`)
or the deterministic search of ``method``. The library side of the ROS node and of
``dtm-label``; no ROS imports.
"""
from __future__ import annotations

from ..model.dtm import TriangulatedModel
from .config import METHODS, MODES, LabelerSettings
from .tracked import Engine, FrameResult, TrackedLabeler


class StreamLabeler(TrackedLabeler):
    """Labels a stream of unlabeled point clouds with one trained :class:`TriangulatedModel`."""

    def __init__(self, model: TriangulatedModel | Engine, settings: LabelerSettings | None = None):
        noise = (settings or LabelerSettings()).noise_mm
        self._init_engine(model if isinstance(model, Engine) else Engine.prepare(model, noise), settings)

    @property
    def model(self) -> TriangulatedModel:
        """The model the labeler scores with (widened by ``noise_mm``)."""
        return self.models[0]

    @property
    def base_model(self) -> TriangulatedModel:
        """The model as given."""
        return self.engine.base[0]

    def set_model(self, model: TriangulatedModel) -> None:
        """Swap the model (hot reload); window and tracks restart."""
        self.set_engine(Engine.prepare(model, self.settings.noise_mm))


__all__ = ["StreamLabeler", "LabelerSettings", "FrameResult", "METHODS", "MODES"]
