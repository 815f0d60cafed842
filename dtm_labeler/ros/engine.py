"""The node's one contact with the labeling core: load, prepare, label.

Everything the node asks of :mod:`dtm_labeler.labeling` goes through this module, so a change of
the labeler's API is a change here only.

* :func:`load` (slow, loader thread): the model or bank a :class:`Source` names, after
  :func:`~.model_check.check_model_file` has vetted the file.
* :func:`prepare` (slow, loader thread): the labeler's prepared models
  (:meth:`dtm_labeler.labeling.tracked.Engine.prepare`, :meth:`BankLabeler.prepare`) -- widened by
  the declared measurement noise, densities built, the kernel compiled; touches no labeler. The
  background recovery worker builds its labeler over the same models meanwhile
  (:func:`~dtm_labeler.labeling.recovery.build_spare`), and a load is done when both are: the
  first searches of a stream that starts right after it do not wait for that build.
* :class:`NodeLabeler` (fast to build, worker thread only): a labeler over them, with the calls
  the node makes per frame (:meth:`NodeLabeler.process`, :meth:`NodeLabeler.predicted_position`)
  and between frames (:meth:`NodeLabeler.reset`, :meth:`NodeLabeler.update_settings`,
  :meth:`NodeLabeler.swap_models`: a new noise keeps the tracks), and :meth:`NodeLabeler.close`
  (the labeler's background recovery worker, if any).

The labeler's own gap check is off (``max_gap_s`` at its maximum): the node judges gaps on the
stamps it receives (:mod:`.stamps`), including frames it skipped.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Optional, Sequence, Tuple

import numpy as np

from ..labeling.bank_labeler import BankLabeler, BankSettings
from ..labeling.config import SPECS, LabelerSettings, settings_equal
from ..labeling.recovery import build_spare
from ..labeling.stream import StreamLabeler
from ..labeling.tracked import Engine
from ..model.bank import ModelBank, load_bank
from ..model.io import load_model
from .model_check import check_model_file

__all__ = ["Source", "Prepared", "NodeSettings", "NodeLabeler", "load", "prepare", "NO_GAP"]

#: max_gap_s given to the labeler (the largest the table allows): gaps are the node's business
NO_GAP = float(SPECS["max_gap_s"].range[1])


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
class NodeSettings:
    """The labeler's settings and, for a bank, the bank's."""

    labeler: LabelerSettings
    bank: BankSettings

    def __eq__(self, other) -> bool:
        return (isinstance(other, NodeSettings) and settings_equal(self.labeler, other.labeler)
                and settings_equal(self.bank, other.bank))


@dataclass(frozen=True)
class Prepared:
    """A loaded model or bank and the labeler's engine for it at ``noise_mm``."""

    source: Source
    base: Any                  # the model / bank as loaded (kept for re-widening)
    noise_mm: float
    engine: Engine
    bank_settings: Optional[BankSettings]
    labels: Tuple[str, ...]
    edges: Tuple[Tuple[int, int], ...]


def load(source: Source) -> Any:
    """The model or bank of ``source`` (ValueError with the reason when it cannot be used)."""
    check_model_file(source.path, source.expected_labels, bank=source.bank)
    if source.bank:
        return load_bank(source.path)
    return load_model(source.path)


def prepare(source: Source, base: Any, noise_mm: float, bank_settings: BankSettings, spare: bool = True
            ) -> Prepared:
    """The labeler's engine for ``base`` at ``noise_mm``, warmed up (slow, see the module doc).
    ``spare``: the spare recovery worker builds the same labeler beside it (for a labeler that
    will be new; models swapped into a running labeler -- a calibration -- go to its own worker)."""
    settings = LabelerSettings(noise_mm=float(noise_mm))
    if isinstance(base, ModelBank):
        acts = BankLabeler.engine_actions(base, bank_settings)
        wait = build_spare([base[a] for a in acts], acts, "BankLabeler", settings, bank_settings) if spare else None
        engine = BankLabeler.prepare(base, bank_settings, noise_mm)
        first = base[base.actions[0]]
    else:
        wait = build_spare([base], [""], "StreamLabeler", settings) if spare else None
        engine, first, bank_settings = Engine.prepare(base, noise_mm), base, None
    prepared = Prepared(source, base, float(noise_mm), engine, bank_settings, tuple(first.labels),
                        tuple(sorted(first.structure.edges())))
    _warm_up(prepared)
    if wait is not None:                 # the background searches' worker builds the same, beside this
        wait(SPARE_BUILD_WAIT_S)
    return prepared


#: how long :func:`prepare` waits for the recovery worker's own build (then the first searches wait for it)
SPARE_BUILD_WAIT_S = 20.0


#: the throw-away labeler of :func:`_warm_up`: every stage runs, with small searches
_WARM_UP = LabelerSettings(recovery="inline", restarts=0,
                           full=replace(LabelerSettings().full, population=16, max_generations=3),
                           warm=replace(LabelerSettings().warm, population=8, max_generations=2))


_warmed: set = set()      # the kinds of engine warmed up in this process (:func:`_engine_kind`)


def _engine_kind(prepared: Prepared) -> tuple:
    """What decides which compiled code a frame runs: a bank or not, and per model whether its
    body is calibrated (segment, off-edge and handedness factors, the broad component) or
    generic (reach limits) or absent."""
    return (prepared.bank_settings is not None,
            tuple(None if m.body is None else bool(m.body.calibration) for m in prepared.engine.base))


def _warm_up(prepared: Prepared) -> None:
    """Once per process and kind of engine (:func:`_engine_kind`), label a few made-up frames
    with a throw-away labeler on the prepared engine, off the labeling thread: the first frames
    of a stream otherwise pay the first calls of the tracker, the fast path, the region checks
    and the confidences (compiled kernels loaded from disk, first allocations) -- 20-30 ms
    offline, 50-70 ms in a node sharing its cores, which dropped the 3-7 frames behind them as
    stale. A model calibrated live (``~/calibrate``, ``auto_calibrate``) runs the calibrated
    body's factors for the first time: unwarmed, its first frame took 235 ms (measured in the
    node, 14 points, 120 Hz). What is per model (its densities, batched terms, bounds)
    :meth:`Engine.prepare` has built already."""
    kind = _engine_kind(prepared)
    if kind in _warmed:
        return
    _warmed.add(kind)
    rng = np.random.default_rng(0)
    xyz = rng.normal(scale=0.4, size=(len(prepared.labels), 3))
    if prepared.bank_settings is not None:
        lab = BankLabeler(prepared.base, _WARM_UP, prepared.bank_settings, engine=prepared.engine)
    else:
        lab = StreamLabeler(prepared.engine, _WARM_UP)
    for k in range(4):
        lab.process(xyz + 0.003 * k, 1.0 + k / 120.0)
    lab.close()


def _labeler_settings(settings: LabelerSettings, prepared: Prepared) -> LabelerSettings:
    """What the labeler gets: the noise its prepared models are widened for (a new noise comes
    as new prepared models, never as a rebuild on the worker), gaps judged by the node, and
    recovery searches in the background unless the parameter asks for inline (``auto``: a live
    stream must not wait for a search)."""
    recovery = "background" if settings.recovery == "auto" else settings.recovery
    return replace(settings, max_gap_s=NO_GAP, noise_mm=prepared.noise_mm, recovery=recovery)


class NodeLabeler:
    """A labeler over a :class:`Prepared` engine; used by one thread (the node's worker)."""

    def __init__(self, prepared: Prepared, settings: NodeSettings):
        self.prepared = prepared
        self.settings = settings
        s = _labeler_settings(settings.labeler, prepared)
        if prepared.bank_settings is not None:
            self._lab = BankLabeler(prepared.base, s, prepared.bank_settings, engine=prepared.engine)
        else:
            self._lab = StreamLabeler(prepared.engine, s)

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

    def observe(self, xyz: np.ndarray, stamp: float, ids: Optional[np.ndarray] = None):
        """A frame the worker does not search: the tracks follow it (they survive the skip);
        returns the labels they carry (:class:`~dtm_labeler.labeling.tracked.CarriedFrame`)."""
        return self._lab.observe(xyz, stamp, ids)

    @property
    def recovery_failed(self) -> str:
        """Why the background recovery worker failed ('' when it runs or is not used)."""
        f = self._lab.recovery.failed
        return "" if f == "closed" else f

    @property
    def anonymous_absent(self) -> str:
        """Why the stream looks like a session without the model's anonymous points ('' when it
        shows them, or the model has none; :mod:`~dtm_labeler.labeling.anonymous_presence`)."""
        found = self._lab.anonymous_presence() if hasattr(self._lab, "anonymous_presence") else None
        return found.note(live=True) if found is not None else ""

    def predicted_position(self, track_id: int, stamp: float) -> np.ndarray:
        return self._lab.predicted_position(track_id, stamp)

    def reset(self) -> None:
        self._lab.reset()

    def same_source(self, prepared: Prepared) -> bool:
        """True when ``prepared`` holds the same models at another noise, or the same model
        calibrated to a person (``~/calibrate``, ``auto_calibrate``): the same labels, so tracks
        and votes can stay. (A calibrated model was once taken as another model: a new labeler,
        the tracks dropped, the stream searched from scratch -- 24-30 frames stale at 120 Hz.)"""
        p = self.prepared
        return p.labels == prepared.labels and (p.bank_settings is None) == (prepared.bank_settings is None)

    def swap_models(self, prepared: Prepared) -> None:
        """The same models widened for another noise, or calibrated: fitness levels restart,
        tracks stay."""
        self.prepared = prepared
        self._update(self.settings, prepared.engine)

    def update_settings(self, settings: NodeSettings) -> bool:
        """Apply settings between frames (a new noise needs :meth:`swap_models`); False when
        they equal the current ones."""
        if settings == self.settings:
            return False
        self._update(settings, None)
        return True

    def _update(self, settings: NodeSettings, engine: Optional[Engine]) -> None:
        self.settings = settings
        s = _labeler_settings(settings.labeler, self.prepared)
        if isinstance(self._lab, BankLabeler):      # bank settings come with prepared models
            self._lab.update_settings(s, self.prepared.bank_settings, engine=engine)
        else:
            self._lab.update_settings(s, engine=engine)

    def close(self) -> None:
        """Stop the labeler's background recovery worker, if any."""
        self._lab.close()
