"""Marker CSV (MoCap Toolbox layout, ``markers_csv/*.csv``) <-> MotionClip (metres, Z up).

Layout: ``#`` comment lines, then the header ``frame,time_s,<M>_x,<M>_y,<M>_z,...``; an
empty cell is a missing sample. The comments may say the units, the vertical and the rate
in the shared files' style (``# units mm, Z up, 60 Hz``); without them: mm, the vertical
found from the body (:mod:`.axes`), the rate from the ``time_s`` column. A stated rate is
checked against ``time_s``. Columns without a name (``_x,_y,_z``) or named ``*N`` are
unlabelled points (``meta['unlabelled']``, as for C3D; see :mod:`.naming`); their runs that
continue a named marker across its gap are joined to it (:mod:`.fragments`).
:func:`write_markers_csv` writes the same layout (``dtm-label --out labelled.csv``).

:func:`read_xyz_csv` is the shared low-level parser (also used by
:mod:`dtm_labeler.motion.positions_csv`).
"""
from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .axes import from_z_up
from .clip import MotionClip
from .marker_table import UNITS_M, MarkerTable, table_clip
from .sanity import check_rate

#: the units the CSV comments may state (``# units mm``)
CSV_UNITS = {u: UNITS_M[u] for u in ("mm", "cm", "m")}


@dataclass
class XyzCsv:
    path: str
    comments: list[str]
    names: tuple[str, ...]
    frames: np.ndarray  # (F,) frame numbers from the 'frame' column
    times: np.ndarray  # (F,) seconds
    xyz: np.ndarray  # (F, N, 3) file units/axes, NaN = empty cell

    def stated(self, pattern: str) -> str | None:
        """The first group of ``pattern`` in the comments (case-insensitive), else None."""
        for c in self.comments:
            m = re.search(pattern, c, re.IGNORECASE)
            if m:
                return m.group(1)
        return None

    def stated_rate(self) -> float | None:
        hz = self.stated(r"(\d+(?:\.\d+)?)\s*Hz\b")
        return None if hz is None else float(hz)

    def rate(self) -> float:
        hz = self.stated_rate()
        if hz is not None:
            return hz
        if len(self.times) < 2 or not self.times[-1] > self.times[0]:
            raise ValueError(f"{self.path}: cannot determine the frame rate (no 'Hz' comment, bad time_s)")
        return round((len(self.times) - 1) / (self.times[-1] - self.times[0]), 3)


def read_header(path: str | Path) -> tuple[list[str], list[str]]:
    """(comment lines, header fields) of an xyz CSV without reading the data."""
    comments: list[str] = []
    with open(path, "r", encoding="utf-8", errors="replace", newline="") as fh:
        for line in fh:
            if line.startswith("#"):
                comments.append(line[1:].strip())
            elif line.strip():
                return comments, next(csv.reader([line]))
    raise ValueError(f"{path}: no header line")


def read_xyz_csv(path: str | Path) -> XyzCsv:
    """Parse ``frame,time_s,<P>_x,<P>_y,<P>_z,...`` with '#' comments; empty cell -> NaN."""
    path = str(path)
    comments, header = read_header(path)
    header = [h.strip() for h in header]
    if len(header) < 5 or header[0] != "frame" or header[1] != "time_s" or (len(header) - 2) % 3:
        raise ValueError(f"{path}: header must be 'frame,time_s,<P>_x,<P>_y,<P>_z,...', got {header[:5]}...")
    names = []
    for k in range(2, len(header), 3):
        base = header[k][:-2]
        if [header[k], header[k + 1], header[k + 2]] != [base + "_x", base + "_y", base + "_z"]:
            raise ValueError(f"{path}: header columns {k + 1}-{k + 3} are not <P>_x,<P>_y,<P>_z: {header[k:k + 3]}")
        names.append(base)
    rows = []
    with open(path, "r", encoding="utf-8", errors="replace", newline="") as fh:
        seen_header = False
        for ln, row in enumerate(csv.reader(fh), start=1):
            if not row or row[0].startswith("#"):
                continue
            if not seen_header:
                seen_header = True
                continue
            if len(row) != len(header):
                raise ValueError(f"{path}:{ln}: {len(row)} fields, header has {len(header)}")
            try:
                rows.append([float(v) if v.strip() else np.nan for v in row])
            except ValueError:
                raise ValueError(f"{path}:{ln}: non-numeric field in {row[:4]}...") from None
    if not rows:
        raise ValueError(f"{path}: no data rows")
    a = np.array(rows, dtype=np.float64)
    if np.isnan(a[:, :2]).any():
        raise ValueError(f"{path}: empty 'frame' or 'time_s' cell")
    return XyzCsv(path=path, comments=comments, names=tuple(names), frames=a[:, 0].astype(int), times=a[:, 1],
                  xyz=a[:, 2:].reshape(len(a), len(names), 3))


def load_markers_csv(path: str | Path, unit_scale: float | None = None, up_axis: str = "auto",
                     join_fragments: bool = True, subject: str | None = None) -> MotionClip:
    """Marker CSV -> MotionClip (metres, Z up); see the module doc for units, axes and rate.
    ``meta``: ``format``, ``frame_numbers``, ``comments``, ``unit_scale``, ``units``, ``up_axis``,
    ``up_axis_source``, ``unlabelled``, ``unlabelled_names``, ``unlabelled_duplicates``, and
    ``unlabelled_fragments`` / ``fragments_note`` as for C3D (:mod:`.fragments`)."""
    t = read_xyz_csv(path)
    said = t.stated(r"\bunits?\s*:?\s*(mm|cm|m)\b")
    rate = t.rate()
    if t.stated_rate() is not None:
        check_rate(rate, t.times, str(path), "the stated rate")
    said_up = t.stated(r"\b([XYZ])[\s-]*up\b") or t.stated(r"\bup[\s-]*axis\s*:?\s*([XYZ])\b")
    table = MarkerTable(path=str(path), format="markers_csv", names=t.names, xyz=t.xyz, rate=rate,
                        units=said.lower() if said else None, units_source="the CSV comments",
                        frame_numbers=t.frames, stated_up=said_up, up_source="the CSV comments",
                        meta=dict(comments=t.comments))
    return table_clip(table, unit_scale, up_axis, join_fragments, subject)


def write_markers_csv(path: str | Path, positions: np.ndarray, names: tuple[str, ...] | list[str], rate: float,
                      frame_numbers: np.ndarray | None = None, units: str = "mm", up_axis: str = "Z",
                      comments: tuple[str, ...] = ()) -> Path:
    """Write (F, N, 3) positions (metres, Z up, NaN = missing) in the marker CSV layout, in
    ``units`` and with ``up_axis`` vertical; the comments state both and the rate, so
    :func:`load_markers_csv` reads the file back exactly (to the 6 decimals written)."""
    if units not in CSV_UNITS:
        raise ValueError(f"units must be one of {', '.join(CSV_UNITS)}, got {units!r}")
    P = from_z_up(np.asarray(positions, dtype=np.float64), up_axis) / CSV_UNITS[units]
    F, N, _ = P.shape
    frames = np.arange(F) if frame_numbers is None else np.asarray(frame_numbers)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ["frame", "time_s"] + [f"{n}_{a}" for n in names for a in "xyz"]
    with open(path, "w", newline="", encoding="utf-8") as fh:
        for c in comments:
            fh.write(f"# {c}\n")
        fh.write(f"# units {units}, {up_axis.upper()} up, {rate:g} Hz, {F} frames, {N} points\n")
        w = csv.writer(fh)
        w.writerow(header)
        flat = P.reshape(F, N * 3)
        for i in range(F):
            w.writerow([int(frames[i]), f"{i / rate:.6f}"] + ["" if not np.isfinite(v) else f"{v:.6f}"
                                                                for v in flat[i]])
    return path
