"""OptiTrack Motive's CSV export -> MotionClip.

Layout: a first line of keys and values (``Format Version,1.23,Take Name,...,Export Frame
Rate,120,...,Length Units,Meters,Coordinate Space,Global``), a blank line, header rows
naming every column -- ``Type`` (Marker, Rigid Body, Rigid Body Marker, Bone, Bone Marker),
``Name`` (``Skeleton:LFHD``, ``Unlabeled 1001``), ``ID``, one row saying what each column
holds (Position, Rotation, Marker Quality, ...) and ``Frame,Time (Seconds),X,Y,Z,...`` -- then
one row per frame, an empty cell where a marker was not seen.

Only ``Marker`` position columns are read: they are the measured markers, labelled or not.
A rigid body's or a bone's "markers" are Motive's *constraints*, where its solver expects
a marker, filled in while the marker is occluded (Motive's documentation), so they are not
measurements and are left out, as are rigid bodies and bones.

What the file states: the rate (``Export Frame Rate``, else ``Capture Frame Rate``; checked
against the time column) and the units (``Length Units``; Motive's older exports, which lack
it, wrote metres). Motive's default vertical is Y, but the export can change the axes, and
the file does not say: it is found from the body (:mod:`.axes`), and where the body cannot
tell (a marker set of the upper body), Y. ``Unlabeled N`` markers
are unlabelled points (:mod:`.naming`).
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from .clip import MotionClip
from .marker_table import MarkerTable, numeric_rows, rate_from_times, table_clip
from .sanity import check_rate

LENGTH_UNITS = {"meters": "m", "millimeters": "mm", "centimeters": "cm"}


def is_motive_csv(first_line: str) -> bool:
    """Whether a file's first line opens a Motive CSV export."""
    return first_line.lstrip("\ufeff").startswith("Format Version")


def _label(row: list[str]) -> str:
    """A header row's label (``Type``, ``Name``, ``ID``): Motive puts it in the first or second cell."""
    for c in row[:2]:
        if c.strip():
            return c.strip().lower()
    return ""


def _padded(row: list[str], width: int) -> list[str]:
    """A header row's cells, stripped, to ``width`` (Motive ends rows at their last named column)."""
    return [c.strip() for c in row] + [""] * (width - len(row))


def read_motive_csv(path: str | Path) -> MarkerTable:
    """Parse a Motive CSV export into a :class:`~.marker_table.MarkerTable` (file units and axes)."""
    where = str(path)
    with open(path, "r", encoding="utf-8-sig", errors="replace", newline="") as fh:
        lines = fh.read().splitlines()
    if not lines or not is_motive_csv(lines[0]):
        raise ValueError(f"{where}: not a Motive CSV export (the first line does not start with 'Format Version')")
    first = next(csv.reader([lines[0]]))
    info = {first[k].strip(): first[k + 1].strip() for k in range(0, len(first) - 1, 2) if first[k].strip()}
    rows: dict[str, list[str]] = {}
    kinds: list[str] | None = None
    i = 1
    while i < len(lines):
        row = next(csv.reader([lines[i]])) if lines[i].strip() else []
        i += 1
        if not row:
            continue
        if row[0].strip().lower() == "frame":
            axes = [c.strip().upper() for c in row]
            break
        label = _label(row)
        if label in ("type", "name", "id"):
            rows[label] = row
        else:
            kinds = row                                   # Position / Rotation / Marker Quality ...
    else:
        raise ValueError(f"{where}: no 'Frame,Time,...' header row")
    if "type" not in rows or "name" not in rows:
        raise ValueError(f"{where}: the header rows give no Type or Name row")
    width = len(axes)
    types, names, kinds = (_padded(r, width) for r in (rows["type"], rows["name"], kinds or []))
    cols, channel_names = [], []
    for c in range(2, width - 2):
        if types[c] == "Marker" and kinds[c] in ("Position", "") and axes[c:c + 3] == ["X", "Y", "Z"] \
                and names[c] == names[c + 1] == names[c + 2]:
            cols.append(c)
            channel_names.append(names[c])
    if not cols:
        found = sorted({t for t in types[2:] if t})
        raise ValueError(f"{where}: no Marker position columns (columns of {', '.join(found) or 'nothing'}); export "
                         "with Markers on")
    a = numeric_rows(lines[i:], width, where, sep=",", first_line=i + 1) if any(ln.strip() for ln in lines[i:]) \
        else np.zeros((0, width))
    a = a[~np.all(np.isnan(a), axis=1)]
    if not len(a):
        raise ValueError(f"{where}: no data rows")
    idx = np.array(cols)[:, None] + np.arange(3)
    xyz = a[:, idx]                                          # (F, N, 3)
    rate = _rate(info)
    times = a[:, 1]
    if rate is None:
        rate = rate_from_times(times, where, "the first line gives no frame rate")
    elif np.isfinite(times).all():
        check_rate(rate, times, where, "the export frame rate")
    said = info.get("Length Units", "")
    units = LENGTH_UNITS.get(said.lower(), said.lower() or None) if said else "m"
    frames = a[:, 0].astype(int) if np.isfinite(a[:, 0]).all() else None
    return MarkerTable(path=where, format="motive_csv", names=tuple(channel_names), xyz=xyz, rate=rate,
                       units=units, units_source="Motive's Length Units", frame_numbers=frames, default_up="Y",
                       meta=dict(motive_header=info))


def _rate(info: dict[str, str]) -> float | None:
    for key in ("Export Frame Rate", "Capture Frame Rate"):
        try:
            r = float(info.get(key, ""))
        except ValueError:
            continue
        if np.isfinite(r) and r > 0:
            return r
    return None


def load_motive_csv(path: str | Path, unit_scale: float | None = None, up_axis: str = "auto",
                    join_fragments: bool = True, subject: str | None = None) -> MotionClip:
    """Motive CSV -> MotionClip (metres, Z up; the module doc and :func:`.marker_table.table_clip`).
    ``meta`` adds ``motive_header`` (the first line's keys and values)."""
    return table_clip(read_motive_csv(path), unit_scale, up_axis, join_fragments, subject)
