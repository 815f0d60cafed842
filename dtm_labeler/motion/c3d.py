"""C3D marker files (via ezc3d) -> MotionClip (metres, Z up, NaN = missing).

* Labels: ``POINT:LABELS`` (+ ``LABELS2``, ``LABELS3`` ... for > 255 points); the subject
  prefix up to the last ``':'`` is stripped (``Male:LFHD -> LFHD``). If stripping makes two
  labels equal, those keep their full label.
* Labels starting with ``'*'`` (or empty) are unlabelled/auxiliary points (HDM05 ``*0``).
  They are excluded from the clip by default but always kept in
  ``meta['unlabelled']`` (frames x K x 3, metres, Z up, NaN = missing) and
  ``meta['unlabelled_names']``; ``include_unlabelled=True`` appends them as points.
  ``meta['unlabelled_duplicates']`` maps unlabelled names that are exact copies of a
  labelled point in every frame to that label (true for HDM05 ``*0 *1 *2`` =
  ``LFWT CLAV LFHD``: they are not independent clutter).
* Missing samples: NaN from ezc3d, negative residual, and exact ``(0, 0, 0)``.
* Units from ``POINT:UNITS`` ('mm', 'cm', 'm'); ``unit_scale`` overrides (metres per unit).
* ``up_axis``: the file's vertical axis, 'Z' (default; all shared files) or 'Y'
  (converted with ``(x, y, z) -> (x, -z, y)``).
* Analog channels are ignored.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .bvh import y_up_to_z_up
from .clip import MotionClip

_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "dm": 0.1}


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


def strip_prefix(label: str) -> str:
    """``'Male:LFHD' -> 'LFHD'`` (everything up to the last ':' removed)."""
    return label.rsplit(":", 1)[-1].strip()


def load_c3d(path: str | Path, up_axis: str = "Z", include_unlabelled: bool = False,
             unit_scale: float | None = None) -> MotionClip:
    """Read the 3-D points of a C3D file as a MotionClip (see module doc for rules).

    ``meta``: ``format``, ``unit_scale``, ``raw_labels`` (labelled points, unstripped),
    ``unlabelled``, ``unlabelled_names``, ``unlabelled_duplicates``, ``first_frame``
    (C3D header frame number).
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
    if unit_scale is None:
        units = _param(params, "POINT", "UNITS")
        u = (str(units[0]) if units else "mm").strip().lower()
        if u not in _UNITS:
            raise ValueError(f"{path}: POINT:UNITS {u!r} not understood; pass unit_scale (metres per unit)")
        unit_scale = _UNITS[u]
    xyz *= unit_scale
    up = up_axis.upper()
    if up == "Y":
        xyz = y_up_to_z_up(xyz)
    elif up != "Z":
        raise ValueError(f"{path}: up_axis must be 'Z' or 'Y', got {up_axis!r}")
    rate = _param(params, "POINT", "RATE")
    rate = float(rate[0]) if rate is not None and len(rate) else float(c["header"]["points"]["frame_rate"])
    if not rate > 0:
        raise ValueError(f"{path}: POINT:RATE is {rate}")

    raw = _labels(params, n)
    unl = [i for i, s in enumerate(raw) if not s or s.startswith("*")]
    lab = [i for i in range(n) if i not in set(unl)]
    short = [strip_prefix(raw[i]) for i in lab]
    names = [s if short.count(s) == 1 else raw[i] for s, i in zip(short, lab)]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: duplicate point labels {sorted({s for s in names if names.count(s) > 1})}")
    unl_names = [raw[i] or f"*{i}" for i in unl]
    dup = {}  # unlabelled points that are bit-identical copies of a labelled one (HDM05 *0-*2)
    for k in unl:
        for i, nm in zip(lab, names):
            if np.array_equal(xyz[:, k], xyz[:, i], equal_nan=True):
                dup[raw[k] or f"*{k}"] = nm
                break
    meta = dict(format="c3d", unit_scale=unit_scale, raw_labels=tuple(raw[i] for i in lab),
                unlabelled=xyz[:, unl].copy(), unlabelled_names=tuple(unl_names), unlabelled_duplicates=dup,
                first_frame=int(c["header"]["points"].get("first_frame", 0)))
    if include_unlabelled:
        idx, all_names = lab + unl, names + unl_names
    else:
        idx, all_names = lab, names
    return MotionClip(positions=xyz[:, idx], rate=rate, names=tuple(all_names), source=path, meta=meta)
