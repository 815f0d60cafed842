"""TRC (track row column: Motion Analysis Cortex, OpenSim, many converters) <-> MotionClip.

Layout (tab-separated text): a ``PathFileType`` line; a line of header keys and a line of
their values (``DataRate``, ``NumFrames``, ``NumMarkers``, ``Units``, ``OrigDataStartFrame``,
...); a line ``Frame#  Time  <M1>  <M2> ...`` naming each marker over its three columns; a
line ``X1 Y1 Z1 X2 ...``; then one row per frame. A missing sample is an empty cell, ``NaN``,
a row cut short, or (0, 0, 0). Some writers separate with spaces instead of tabs; such files
are read when no marker name holds a space.

What the file states: the units (``Units``) and the rate (``DataRate``, checked against the
``Time`` column). It does not state the vertical -- OpenSim's files are Y up, Cortex's
often Z up -- so it is found from the body (:mod:`.axes`; ``--up-axis`` forces it), and
where the body cannot tell (a marker set of the upper body), Y, OpenSim's convention. Marker
names follow the rules of every format (:mod:`.naming`): a ``*N`` or empty name, or a
system's word for an unlabelled trajectory, is an unlabelled point.

:func:`write_trc` writes the same layout (``dtm-label --out labelled.trc``): the labels as
markers, unlabelled points as ``*N``, empty cells for gaps, in the input's units and axes.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

import numpy as np

from .axes import from_z_up
from .clip import MotionClip
from .marker_table import UNITS_M, MarkerTable, missing_zeros, numeric_rows, table_clip
from .sanity import check_rate

#: the header keys a TRC file must give
REQUIRED_KEYS = ("DataRate", "NumMarkers")


def _split(line: str, tabs: bool) -> list[str]:
    return line.rstrip("\r\n").split("\t") if tabs else line.split()


def read_trc(path: str | Path) -> MarkerTable:
    """Parse a TRC file into a :class:`~.marker_table.MarkerTable` (file units and axes)."""
    where = str(path)
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        lines = fh.read().splitlines()
    if not lines or not lines[0].startswith("PathFileType"):
        raise ValueError(f"{where}: not a TRC file (the first line does not start with 'PathFileType')")
    if len(lines) < 5:
        raise ValueError(f"{where}: the TRC header needs 5 lines, the file has {len(lines)}")
    tabs = "\t" in lines[1]
    keys, values = _split(lines[1], tabs), _split(lines[2], tabs)
    header = {k.strip(): v.strip() for k, v in zip(keys, values) if k.strip()}
    missing = [k for k in REQUIRED_KEYS if not header.get(k)]
    if missing:
        raise ValueError(f"{where}: the TRC header gives no {', '.join(missing)} (line 2: {', '.join(keys)})")
    try:
        rate, n = float(header["DataRate"]), int(float(header["NumMarkers"]))
    except ValueError:
        raise ValueError(f"{where}: DataRate {header['DataRate']!r} / NumMarkers {header['NumMarkers']!r} "
                         "are not numbers") from None
    if not rate > 0 or n < 1:
        raise ValueError(f"{where}: DataRate {rate:g} and NumMarkers {n} must be positive")
    cells = _split(lines[3], tabs)
    if len(cells) < 2 or not cells[0].strip().lower().startswith("frame"):
        raise ValueError(f"{where}:4: the marker-name line must start with 'Frame#' and 'Time', got {cells[:2]}")
    names = [c.strip() for c in cells[2::3]] if tabs else [c.strip() for c in cells[2:]]
    names = (names + [""] * n)[:n]
    if len(cells) > 2 + 3 * n and any(c.strip() for c in cells[2 + 3 * n:]):
        raise ValueError(f"{where}:4: more marker names than NumMarkers ({n})")
    start = 5
    while start < len(lines) and not lines[start].strip():
        start += 1
    body = [ln for ln in lines[start:] if ln.strip()]
    if not tabs:
        body = ["\t".join(ln.split()) for ln in body]
    a = numeric_rows(body, 2 + 3 * n, where, first_line=start + 1)
    if np.isnan(a[:, 0]).any():
        raise ValueError(f"{where}: a data row has no frame number")
    times = a[:, 1]
    if np.isfinite(times).all():
        check_rate(rate, times, where, "DataRate")
    units = header.get("Units") or None
    meta = dict(trc_header=header)
    return MarkerTable(path=where, format="trc", names=tuple(names), xyz=missing_zeros(a[:, 2:].reshape(len(a), n, 3)),
                       rate=rate, units=units.lower() if units else None, units_source="the TRC header (Units)",
                       frame_numbers=a[:, 0].astype(int), default_up="Y", meta=meta)


def load_trc(path: str | Path, unit_scale: float | None = None, up_axis: str = "auto", join_fragments: bool = True,
             subject: str | None = None) -> MotionClip:
    """TRC -> MotionClip (metres, Z up; the module doc and :func:`.marker_table.table_clip`).
    ``meta`` adds ``trc_header`` (the header's keys and values)."""
    return table_clip(read_trc(path), unit_scale, up_axis, join_fragments, subject)


def write_trc(path: str | Path, positions: np.ndarray, names: Sequence[str], rate: float,
              frame_numbers: np.ndarray | None = None, units: str = "mm", up_axis: str = "Y") -> Path:
    """Write (F, N, 3) ``positions`` (metres, Z up, NaN = missing) named ``names`` as a TRC
    file in ``units`` with ``up_axis`` vertical (the file's own axes); gaps as empty cells.
    Frame numbers from ``frame_numbers`` (default 1..F), times from 0 at ``1 / rate``."""
    if units not in UNITS_M:
        raise ValueError(f"units must be one of {', '.join(UNITS_M)}, got {units!r}")
    if not rate > 0:
        raise ValueError(f"rate must be positive, got {rate}")
    names = [str(n) for n in names]
    if any(re.search(r"[\t\r\n]", n) for n in names):
        raise ValueError("TRC marker names cannot hold tabs or line breaks")
    P = from_z_up(np.asarray(positions, dtype=np.float64), up_axis) / UNITS_M[units]
    if P.ndim != 3 or P.shape[1:] != (len(names), 3):
        raise ValueError(f"positions must be (frames, {len(names)}, 3), got {P.shape}")
    F, N, _ = P.shape
    frames = np.arange(1, F + 1) if frame_numbers is None else np.asarray(frame_numbers, dtype=int)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(f"PathFileType\t4\t(X/Y/Z)\t{path.name}\n")
        fh.write("DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n")
        first = int(frames[0]) if F else 1
        fh.write(f"{rate:g}\t{rate:g}\t{F}\t{N}\t{units}\t{rate:g}\t{first}\t{F}\n")
        fh.write("Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in names) + "\n")
        fh.write("\t\t" + "\t".join(f"X{k}\tY{k}\tZ{k}" for k in range(1, N + 1)) + "\n")
        fh.write("\n")
        flat = P.reshape(F, N * 3)
        for i in range(F):
            cells = ["" if not np.isfinite(v) else f"{v:.6f}" for v in flat[i]]
            fh.write(f"{int(frames[i])}\t{i / rate:.6f}\t" + "\t".join(cells) + "\n")
    return path
