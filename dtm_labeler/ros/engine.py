"""The node's one contact with the labeling core: load, prepare, label.

Everything the node asks of :mod:`dtm_labeler.labeling` goes through this module, so a change of
the labeler's API is a change here only.

* :func:`load` (slow, loader thread): the model or bank a :class:`Source` names, after
  :func:`~.model_check.check_model_file` has vetted the file.
* :func:`prepare` (slow, loader thread): what a labeler needs before its first frame -- the model
  widened by the declared measurement noise, densities built and the kernel compiled.
* :class:`Engine` (fast to build, worker thread only): a labeler over a prepared model, with the
  calls the node makes per frame (:meth:`Engine.process`, :meth:`Engine.predicted_position`) and
  between frames (:meth:`Engine.reset`, :meth:`Engine.update_settings`).

The labeler gets ``noise_mm = 0`` because the model it is given is already widened: so a new
``noise_mm`` never makes the worker rebuild anything (a new prepared engine is swapped in),
and the labeler's own gap check is off (``max_gap_s`` huge): the node judges gaps on the stamps it
receives (:mod:`.stamps`), including frames it skipped.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Optional, Sequence, Tuple

import numpy as np

from ..labeling.bank_labeler import BankLabeler
from ..labeling.stream import LabelerSettings, StreamLabeler
from ..model.bank import ModelBank, load_bank
from ..model.io import load_model
from .model_check import check_model_file
from .params import settings_equal

__all__ = ["Source", "Prepared", "Engine", "load", "prepare", "NO_GAP"]

#: max_gap_s given to the labeler: gaps are the node's business (see module doc)
NO_GAP = 1e12


@dataclass(frozen=True)
class Source:
    """What to label with: a model file, a bank (file or directory), or nothing."""

    path: str = ""
    bank: bool = False
    expected_labels: Tuple[str, ...] = ()

    @property
    def empty(self) -> bool:
        return not self.path

    def describe(self) -> str:
        return f"{'bank' if self.bank else 'model'} {self.path}" if self.path else "no model"


@dataclass(frozen=True)
class Prepared:
    """A loaded model or bank, widened by ``noise_mm`` and warmed up: ready for :class:`Engine`."""

    source: Source
    base: Any                  # the model / bank as loaded (kept for re-widening)
    noise_mm: float
    engine_model: Any          # the widened model, or the bank
    labels: Tuple[str, ...]
    edges: Tuple[Tuple[int, int], ...]


def load(source: Source) -> Any:
    """The model or bank of ``source`` (ValueError with the reason when it cannot be used)."""
    check_model_file(source.path, source.expected_labels, bank=source.bank)
    if source.bank:
        return load_bank(source.path)
    return load_model(source.path)


def prepare(source: Source, base: Any, noise_mm: float) -> Prepared:
    """Widen and warm up (see module doc); pure: touches no labeler."""
    if isinstance(base, ModelBank):
        first = base[base.actions[0]]
        for action in base.actions:
            base[action].warm_up()
        engine_model, labels = base, tuple(first.labels)
        edges = tuple(sorted(first.structure.edges()))
    else:
        engine_model = base.with_noise(noise_mm * 1e-3).warm_up()
        labels, edges = tuple(base.labels), tuple(sorted(base.structure.edges()))
    return Prepared(source, base, float(noise_mm), engine_model, labels, edges)


def _labeler_settings(settings: LabelerSettings) -> LabelerSettings:
    return replace(settings, noise_mm=0.0, max_gap_s=NO_GAP)


class Engine:
    """A labeler over a :class:`Prepared` model; used by one thread (the node's worker)."""

    def __init__(self, prepared: Prepared, settings: LabelerSettings):
        self.prepared = prepared
        self.settings = settings
        s = _labeler_settings(settings)
        if isinstance(prepared.engine_model, ModelBank):
            self._lab = BankLabeler(prepared.engine_model, s)
        else:
            self._lab = StreamLabeler(prepared.engine_model, s)

    @property
    def labels(self) -> Tuple[str, ...]:
        return self.prepared.labels

    @property
    def edges(self) -> Sequence[Tuple[int, int]]:
        return self.prepared.edges

    @property
    def active_model(self) -> str:
        return str(getattr(self._lab, "active_action", "") or "")

    @property
    def actions(self) -> Tuple[str, ...]:
        return tuple(getattr(self._lab, "actions", ()) or ())

    def process(self, xyz: np.ndarray, stamp: float, ids: Optional[np.ndarray] = None):
        """Label one frame: the labeler's FrameResult (labels, confidence, track_ids, ...)."""
        return self._lab.process(xyz, stamp, ids)

    def predicted_position(self, track_id: int, stamp: float) -> np.ndarray:
        return self._lab.predicted_position(track_id, stamp)

    def reset(self) -> None:
        self._lab.reset()

    def update_settings(self, settings: LabelerSettings) -> bool:
        """Apply settings that need no new model (``noise_mm`` is the loader's: it needs a new
        :class:`Prepared`); returns False when they equal the current ones."""
        if settings_equal(settings, self.settings):
            return False
        self.settings = settings
        self._lab.update_settings(_labeler_settings(settings))
        return True
