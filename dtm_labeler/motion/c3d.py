"""C3D marker files (via ezc3d) -> MotionClip (metres, Z up, NaN = missing).

* Labels: ``POINT:LABELS`` (+ ``LABELS2``, ``LABELS3`` ... for > 255 points); names follow
  :mod:`.naming` (subject prefix dropped, ``*``/empty/``Subject:*0`` = unlabelled point).
  Unlabelled points are excluded from the clip by default but always kept in
  ``meta['unlabelled']`` (frames x K x 3, metres, Z up, NaN = missing) and
  ``meta['unlabelled_names']``; ``include_unlabelled=True`` appends them as points.
  ``meta['unlabelled_duplicates']`` maps unlabelled names that are exact copies of a
  labelled (or earlier unlabelled) point in every frame to that point (true for HDM05
  ``*0 *1 *2`` = ``LFWT CLAV LFHD``: they are not independent clutter). An unlabelled run
  that continues a named marker across its gap (the system's auto-labelling lost it for a
  while) is that marker: joined to it (:mod:`.fragments`, ``meta['unlabelled_fragments']``).
* Model outputs are not markers: the channels a processing pipeline (Vicon Nexus' Plug-in
  Gait, Visual3D, btk) lists in ``POINT:ANGLES``, ``FORCES``, ``MOMENTS``, ``POWERS`` or
  ``SCALARS`` hold joint angles, forces and powers in the POINT block (as OpenSim's reader,
  these are left out); they are named in ``meta['model_outputs']`` and fed to nothing -- as
  points they would be ghosts at the angles' values, near the lab's origin.
* Missing samples: NaN from ezc3d, negative residual, and exact ``(0, 0, 0)``.
* Units from ``POINT:UNITS`` ('mm', 'cm', 'm'); ``unit_scale`` overrides (metres per unit).
  The body is measured after reading (:func:`.sanity.check_body_units`): a take whose units
  cannot be right for a person is refused with the unit its numbers look like.
* ``up_axis``: ``'auto'`` (default) reads ``POINT:Y_SCREEN`` and checks it against the body,
  or finds the vertical from the body (:mod:`.axes`); ``'X'``/``'Y'``/``'Z'`` force it.
  ``meta['up_axis']``, ``meta['up_axis_source']`` record the decision.
* ``POINT:RATE`` is checked against the header's frame rate.
* Analog channels are ignored.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .clip import MotionClip
from .marker_table import UNITS_M as _UNITS
from .marker_table import MarkerTable, table_clip
from .naming import strip_prefix
from .sanity import check_rate

__all__ = ["load_c3d", "strip_prefix", "c3d_units"]


#: POINT parameters that list channels holding a model's outputs, not marker positions
MODEL_OUTPUT_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS")


def _param(params: dict, group: str, name: str):
    try:
        return params[group][name]["value"]
    except KeyError:
        return None


def _labels(params: dict, n: int) -> list[str]:
    labels = list(_param(params, "POINT", "LABELS") or [])
    k = 2
    while len(labels) < n and _param(params, "POINT", f"LABELS{k}") is not None:
        labels += list(_param(params, "POINT", f"LABELS{k}"))
        k += 1
    labels = [str(s).strip() for s in labels[:n]]
    labels += [f"*{i}" for i in range(len(labels), n)]  # unnamed points count as unlabelled
    return labels


def _model_outputs(params: dict, labels: list[str]) -> list[int]:
    """Indices of the channels whose label a model-output parameter lists (module doc)."""
    listed: set[str] = set()
    for group in MODEL_OUTPUT_GROUPS:
        listed |= {str(v).strip() for v in (_param(params, "POINT", group) or []) if str(v).strip()}
    return [i for i, lab in enumerate(labels) if lab in listed or strip_prefix(lab) in listed]


def c3d_units(unit_scale: float) -> str:
    """The POINT:UNITS text for ``unit_scale`` metres per unit ('mm' when none fits)."""
    return next((u for u, v in _UNITS.items() if abs(v / unit_scale - 1.0) < 1e-9), "mm")


def load_c3d(path: str | Path, up_axis: str = "auto", include_unlabelled: bool = False,
             unit_scale: float | None = None, join_fragments: bool = True, subject: str | None = None) -> MotionClip:
    """Read the 3-D points of a C3D file as a MotionClip (see module doc for rules).

    ``meta``: ``format``, ``unit_scale``, ``units`` (POINT:UNITS text of that scale),
    ``raw_labels`` (labelled points, unstripped), ``unlabelled``, ``unlabelled_names``,
    ``unlabelled_duplicates``, ``first_frame`` (C3D header frame number), ``up_axis``,
    ``up_axis_source`` (+ ``up_axis_note``), ``screen`` (POINT:X_SCREEN, Y_SCREEN or None);
    ``unlabelled_fragments`` and ``fragments_note`` when unlabelled channels continued named
    markers across their gaps and were joined to them (:mod:`.fragments`; ``join_fragments=False``
    keeps them apart). ``subject``: the subject whose markers are the points, in a capture of
    several (:func:`.naming.split_channels`).
    """
    import ezc3d  # local import: only needed for C3D

    path = str(path)
    try:
        c = ezc3d.c3d(path)
    except Exception as exc:  # ezc3d raises RuntimeError/IOError with terse messages
        raise ValueError(f"{path}: cannot read C3D ({exc})") from exc
    params = c["parameters"]
    pts = np.asarray(c["data"]["points"], dtype=np.float64)  # 4 x N x F
    if pts.ndim != 3 or pts.shape[0] < 3:
        raise ValueError(f"{path}: unexpected POINT data shape {pts.shape}")
    n = pts.shape[1]
    xyz = np.transpose(pts[:3], (2, 1, 0)).copy()  # F x N x 3
    try:
        res = np.asarray(c["data"]["meta_points"]["residuals"], dtype=np.float64)  # 1 x N x F
        xyz[res[0].T < 0] = np.nan
    except (KeyError, IndexError, ValueError):
        pass
    xyz[np.all(xyz == 0.0, axis=2)] = np.nan
    units = _param(params, "POINT", "UNITS")
    rate = _param(params, "POINT", "RATE")
    header_rate = float(c["header"]["points"]["frame_rate"])
    rate = float(rate[0]) if rate is not None and len(rate) else header_rate
    if not rate > 0:
        raise ValueError(f"{path}: POINT:RATE is {rate}")
    if header_rate > 0:
        check_rate(rate, np.arange(3) / header_rate, path, "POINT:RATE")

    labels = _labels(params, n)
    extra: dict = dict(first_frame=int(c["header"]["points"].get("first_frame", 0)))
    outputs = _model_outputs(params, labels)
    if outputs:
        skip = set(outputs)
        keep = [i for i in range(n) if i not in skip]
        extra["model_outputs"] = tuple(labels[i] for i in outputs)
        labels, xyz = [labels[i] for i in keep], xyz[:, keep]
    screen = [_param(params, "POINT", k) for k in ("X_SCREEN", "Y_SCREEN")]
    extra["screen"] = screen = (tuple(str(v[0]).strip() for v in screen)
                                if all(v is not None and len(v) for v in screen) else None)
    table = MarkerTable(path=path, format="c3d", names=tuple(labels), xyz=xyz, rate=rate,
                        units=(str(units[0]) if units else "mm").strip().lower(), units_source="POINT:UNITS",
                        stated_up=screen[1] if screen else None, up_source="POINT:Y_SCREEN", meta=extra)
    clip = table_clip(table, unit_scale, up_axis, join_fragments, subject)
    if include_unlabelled:
        m = clip.meta
        clip = clip._replace(positions=np.concatenate([clip.positions, m["unlabelled"]], axis=1),
                             names=clip.names + tuple(m["unlabelled_names"]))
    return clip
