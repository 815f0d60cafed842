"""QTM's 3D TSV export (Qualisys Track Manager, ``.tsv``) -> MotionClip.

Layout (tab-separated text): header lines of one upper-case key and its values
(``FILE_VERSION``, ``NO_OF_FRAMES``, ``NO_OF_CAMERAS``, ``NO_OF_MARKERS``, ``FREQUENCY``,
``DESCRIPTION``, ``TIME_STAMP``, ``DATA_INCLUDED``, ``EVENT`` lines, ``MARKER_NAMES`` with one
name per trajectory, ``TRAJECTORY_TYPES``), then, when QTM wrote it, a column line ``Frame
Time <M> X <M> Y <M> Z ...``, then one row per frame: the frame number and time when QTM was
asked for them, and X Y Z per trajectory (read by their names in the column line, so other
columns, such as a per-frame trajectory type, are passed over). Files without the header lines (QTM's option) name
no markers and are refused. 2D, 6DOF and skeleton exports hold no marker trajectories and
are refused with what they are.

What the file states: the rate (``FREQUENCY``; ``EXT`` for an external timebase, then the
``Time`` column) and that the numbers are millimetres (QTM exports 3D data in mm). A missing
sample is an empty cell, ``NaN`` or, in older versions, 0 0 0. The vertical is the lab's
choice in QTM's calibration, not written to the file: it is found from the body
(:mod:`.axes`; ``--up-axis`` forces it), and where the body cannot tell, Z, QTM's default. QTM's ``Unidentified N`` / ``Discarded N`` trajectories
are unlabelled points (:mod:`.naming`).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .clip import MotionClip
from .marker_table import MarkerTable, missing_zeros, numeric_rows, rate_from_times, table_clip
from .sanity import check_rate

_KEY = re.compile(r"[A-Z][A-Z0-9_]*")


def is_qtm_tsv(first_line: str) -> bool:
    """Whether a file's first line opens a QTM TSV export's header."""
    key = first_line.split("\t", 1)[0].strip()
    return key in ("FILE_VERSION", "NO_OF_FRAMES")


def holds_markers(path: str | Path, max_lines: int = 200) -> bool:
    """Whether a ``.tsv`` file is a QTM export of 3D marker trajectories (its header has a
    ``MARKER_NAMES`` line): a folder of captures also holds QTM's analog, force, 6DOF and
    skeleton exports beside each take (``_a.tsv``, ``_f_1.tsv``, ``_6d.tsv``, ``_s_*.tsv``)."""
    try:
        with open(path, "r", encoding="utf-8-sig", errors="replace") as fh:
            first = fh.readline()
            if not is_qtm_tsv(first):
                return False
            for _ in range(max_lines):
                key = fh.readline().split("\t", 1)[0].strip()
                if key == "MARKER_NAMES":
                    return True
                if key and not _KEY.fullmatch(key):
                    return False
    except OSError:
        return False
    return False


def read_qtm_tsv(path: str | Path) -> MarkerTable:
    """Parse a QTM 3D TSV export into a :class:`~.marker_table.MarkerTable` (mm, file axes)."""
    where = str(path)
    with open(path, "r", encoding="utf-8-sig", errors="replace") as fh:
        lines = fh.read().splitlines()
    header: dict[str, list[str]] = {}
    events: list[list[str]] = []
    i = 0
    while i < len(lines):
        cells = lines[i].split("\t")
        key = cells[0].strip()
        if not key:
            i += 1
            continue
        if not _KEY.fullmatch(key):
            break
        if key == "EVENT":
            events.append([c.strip() for c in cells[1:]])
        else:
            header[key] = [c.strip() for c in cells[1:]]
        i += 1
    if not header:
        raise ValueError(f"{where}: no QTM header lines (NO_OF_FRAMES, FREQUENCY, MARKER_NAMES ...); export the "
                         "TSV with 'Include TSV header'")
    included = (header.get("DATA_INCLUDED") or ["3D"])[0].upper()
    if included != "3D" or "MARKER_NAMES" not in header:
        what = included if included != "3D" else "no MARKER_NAMES line"
        raise ValueError(f"{where}: a QTM TSV export without 3D marker trajectories ({what}); export the 3D data")
    names = list(header["MARKER_NAMES"])
    while names and not names[-1]:
        names.pop()
    n = len(names)
    declared = _int(header.get("NO_OF_MARKERS"))
    if declared is not None and declared != n:
        raise ValueError(f"{where}: NO_OF_MARKERS is {declared} but MARKER_NAMES lists {n}")
    if n == 0:
        raise ValueError(f"{where}: MARKER_NAMES lists no trajectory")
    columns = None
    if i < len(lines) and lines[i].split("\t", 1)[0].strip().lower() == "frame":
        columns = [c.strip() for c in lines[i].split("\t")]
        i += 1
    rows = [ln for ln in lines[i:] if ln.strip()]
    if columns is not None:                              # the trajectories' columns by name
        while columns and not columns[-1]:
            columns.pop()
        front = [c for c in ("Frame", "Time") if c in columns]
        use = [columns.index(c) for c in front] + list(_xyz_columns(columns, names, where).reshape(-1))
        a = numeric_rows(rows, len(columns), where, first_line=i + 1, usecols=use)
    else:                                                # no column line: the width tells
        width = len(rows[0].rstrip("\t").split("\t")) if rows else 0
        front = ["Frame", "Time"] if width == 3 * n + 2 else []
        a = numeric_rows(rows, len(front) + 3 * n, where, first_line=i + 1)
    xyz = missing_zeros(a[:, len(front):].reshape(len(a), n, 3))
    frames = a[:, front.index("Frame")] if "Frame" in front else None
    frames = frames.astype(int) if frames is not None and np.isfinite(frames).all() else None
    times = a[:, front.index("Time")] if "Time" in front else None
    freq = (header.get("FREQUENCY") or [""])[0]
    rate = _float(freq)
    if rate is None:                                     # EXT: an external timebase
        rate = rate_from_times(times, where, f"FREQUENCY is {freq!r}")
    elif times is not None and np.isfinite(times).all():
        check_rate(rate, times, where, "FREQUENCY")
    declared_frames = _int(header.get("NO_OF_FRAMES"))
    meta = dict(qtm_header={k: "\t".join(v) for k, v in header.items() if k != "MARKER_NAMES"}, qtm_events=events)
    if declared_frames is not None and declared_frames != len(a):
        meta["qtm_note"] = f"NO_OF_FRAMES says {declared_frames}, the file holds {len(a)} rows"
    return MarkerTable(path=where, format="qtm_tsv", names=tuple(names), xyz=xyz, rate=rate, units="mm",
                       units_source="QTM's TSV export", frame_numbers=frames, meta=meta)


def _xyz_columns(columns: list[str], names: list[str], where: str) -> np.ndarray:
    """(N, 3) column indices of each trajectory's X, Y, Z in QTM's column line (``<M> X`` ...;
    other columns -- frame, time, a per-frame type -- are skipped). Where the line does not
    name them so, the trajectories are the last 3N columns."""
    at = {c: k for k, c in enumerate(columns)}
    named = [[at.get(f"{m} {a}") for a in "XYZ"] for m in names]
    if all(k is not None for row in named for k in row):
        return np.array(named, dtype=int)
    lead = len(columns) - 3 * len(names)
    if lead < 0:
        raise ValueError(f"{where}: the column line has {len(columns)} columns for {len(names)} trajectories")
    return lead + np.arange(3 * len(names)).reshape(len(names), 3)


def _int(v: list[str] | None) -> int | None:
    f = _float((v or [""])[0])
    return None if f is None else int(f)


def _float(text: str) -> float | None:
    try:
        f = float(text)
    except (TypeError, ValueError):
        return None
    return f if np.isfinite(f) and f > 0 else None


def load_qtm_tsv(path: str | Path, unit_scale: float | None = None, up_axis: str = "auto",
                 join_fragments: bool = True, subject: str | None = None) -> MotionClip:
    """QTM 3D TSV -> MotionClip (metres, Z up; the module doc and :func:`.marker_table.table_clip`).
    ``meta`` adds ``qtm_header`` (the header lines), ``qtm_events`` and ``qtm_note`` where the
    header's frame count disagrees with the rows."""
    return table_clip(read_qtm_tsv(path), unit_scale, up_axis, join_fragments, subject)
