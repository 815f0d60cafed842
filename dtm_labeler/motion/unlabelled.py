"""What a labeler gets from a take: the model's points, and every other point as unlabelled input.

A real capture holds more than the model's points: unlabelled trajectories (C3D ``*``
channels, unnamed CSV columns: ghosts, reflections, stray markers) and named markers the
model does not know. An optical system streams all of them, so a fair offline run feeds
all of them to the labeler as points that must stay unlabelled. :func:`model_input` splits
a take accordingly:

* the take names every model label: the model's points carry the truth; the unlabelled
  channels and, in marker captures (C3D, marker CSV), the other named markers are extra
  (unlabelled) points -- the other joints of a skeleton (BVH, ASF/AMC) are not points any
  optical system streams, so they are left out;
* a model over the 14 body points on a marker take: the joints derived from the markers are
  the input (the raw markers are not what a joint stream carries): no extra points;
* the take has no named points (only ``*`` channels / unnamed columns), or ``ignore_names``:
  every point is an extra point and nothing can be scored (``named`` is False);
* otherwise (model labels missing): ValueError naming them.

Copies of another channel (HDM05 ``*0 *1 *2``, see :mod:`.naming`) are never fed twice; runs of
an unlabelled channel that continue a named marker across its gap were joined to it by the loader
(:mod:`.fragments`) and are that marker here.
``keep_unlabelled=False`` gives the model's points only (``--drop-unlabelled``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .clip import MotionClip
from .naming import is_unnamed
from .pointsets import BODY14, model_points

MARKER_FORMATS = ("c3d", "markers_csv", "trc", "qtm_tsv", "motive_csv")     # takes from optical systems: every point is a measured marker


@dataclass
class ModelInput:
    """A take split for a model (see the module doc)."""

    clip: MotionClip              # the model's labels, model order (all NaN when the take has no names)
    extra: np.ndarray             # (F, K, 3) unlabelled points, metres, Z up, NaN = absent
    extra_names: tuple[str, ...]  # where each came from (a channel name)
    named: bool                   # the take names the model's points: the labels can be scored
    note: str = ""

    @property
    def n_extra(self) -> int:
        return self.extra.shape[1]


def unlabelled_channels(clip: MotionClip) -> tuple[np.ndarray, tuple[str, ...]]:
    """``(points (F, K, 3), names)``: the take's unlabelled channels without copies, and without
    channels left with no sample (every run a named marker's fragment, :mod:`.fragments`)."""
    pts = clip.meta.get("unlabelled")
    if not isinstance(pts, np.ndarray) or pts.ndim != 3 or pts.shape[0] != clip.n_frames or not pts.shape[1]:
        return np.zeros((clip.n_frames, 0, 3)), ()
    names = tuple(clip.meta.get("unlabelled_names", ()))
    dup = clip.meta.get("unlabelled_duplicates", {}) or {}
    emptied = {fr["channel"] for fr in clip.meta.get("unlabelled_fragments", ())}
    keep = [k for k, nm in enumerate(names) if nm not in dup
            and not (nm in emptied and not np.isfinite(pts[:, k]).any())]
    return pts[:, keep], tuple(names[k] for k in keep)


def model_input(clip: MotionClip, labels: Sequence[str], keep_unlabelled: bool = True,
                ignore_names: bool = False) -> ModelInput:
    """Split ``clip`` for a model over ``labels`` (module doc). A model's anonymous points
    (``*`` names, :mod:`dtm_labeler.training.anonymous`) are never named by a take: their
    columns are unseen (all NaN) and the take's unlabelled channels are extra points as ever."""
    labels = tuple(labels)
    anon = [k for k, n in enumerate(labels) if is_unnamed(n)]
    if anon:
        mi = model_input(clip, [n for n in labels if not is_unnamed(n)], keep_unlabelled, ignore_names)
        named = mi.clip
        pos = np.full((named.n_frames, len(labels), 3), np.nan)
        pos[:, [k for k in range(len(labels)) if k not in set(anon)]] = named.positions
        return ModelInput(named._replace(positions=pos, names=labels), mi.extra, mi.extra_names, mi.named, mi.note)
    F = clip.n_frames
    none = np.zeros((F, 0, 3))
    unl, unl_names = unlabelled_channels(clip) if keep_unlabelled else (none, ())
    have = set(clip.names)
    if set(labels) <= have and not ignore_names:
        marker_take = clip.meta.get("format") in MARKER_FORMATS
        others = [n for n in clip.names if n not in set(labels)] if keep_unlabelled and marker_take else []
        extra = np.concatenate([clip.select(others).positions, unl], axis=1) if others else unl
        return ModelInput(clip.select(labels), extra, tuple(others) + unl_names, True)
    if set(labels) <= set(BODY14) and clip.n_points and not ignore_names:
        return ModelInput(model_points(clip, labels), none, (), True)
    if not clip.n_points or ignore_names:
        empty = clip._replace(positions=np.full((F, len(labels), 3), np.nan), names=labels)
        empty.meta["unnamed"] = True
        extra = np.concatenate([clip.positions, unl], axis=1) if clip.n_points else unl
        if not extra.shape[1]:
            raise ValueError(f"{clip.source}: no points to label")
        return ModelInput(empty, extra, tuple(clip.names) + unl_names, False)
    try:
        return ModelInput(model_points(clip, labels), none, (), True)
    except ValueError as e:                 # names the missing labels
        raise ValueError(f"{e}; to label its points as unnamed ones (no score), ignore its names "
                         "(--ignore-names)") from None
