"""MoCap Toolbox marker CSV (``markers_csv/*.csv``) -> MotionClip (metres, Z up).

Layout: ``#`` comment lines, then the header ``frame,time_s,<M>_x,<M>_y,<M>_z,...``;
values in **mm**, **Z up**; an empty cell is a missing sample. The rate is read from
a ``<number> Hz`` phrase in the comments, else from the ``time_s`` column.

:func:`read_xyz_csv` is the shared low-level parser (also used by
:mod:`dtm_labeler.motion.positions_csv`).
"""
from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .clip import MotionClip


@dataclass
class XyzCsv:
    path: str
    comments: list[str]
    names: tuple[str, ...]
    frames: np.ndarray  # (F,) frame numbers from the 'frame' column
    times: np.ndarray  # (F,) seconds
    xyz: np.ndarray  # (F, N, 3) file units/axes, NaN = empty cell

    def rate(self) -> float:
        for c in self.comments:
            m = re.search(r"(\d+(?:\.\d+)?)\s*Hz\b", c)
            if m:
                return float(m.group(1))
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


def load_markers_csv(path: str | Path, unit_scale: float = 1e-3) -> MotionClip:
    """MoCap Toolbox CSV (mm, Z up) -> MotionClip (metres, Z up).
    ``meta``: ``format``, ``frame_numbers``, ``comments``, ``unit_scale``."""
    t = read_xyz_csv(path)
    return MotionClip(positions=t.xyz * unit_scale, rate=t.rate(), names=t.names, source=str(path),
                      meta=dict(format="markers_csv", frame_numbers=t.frames, comments=t.comments,
                                unit_scale=unit_scale))
