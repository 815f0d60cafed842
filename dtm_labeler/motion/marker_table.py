"""A marker table read from a text export, turned into a MotionClip by the rules every marker format shares.

A marker file says, besides its numbers, four things (or leaves them to the reader): the
units, the vertical, the rate and which channels are unnamed. A reader of one layout (the
marker CSV, TRC, QTM's TSV, Motive's CSV) parses its file into a :class:`MarkerTable` -- the
numbers in the file's units and axes, and what the file states -- and :func:`table_clip`
applies what the C3D loader applies, so one take reads the same from any format:

* units: as stated (a user's ``--units`` first), else the format's default; checked
  against a body's size (:func:`.sanity.check_body_units`) unless forced;
* the vertical: ``--up-axis``, else the file's word (overruled by a body lying along
  another axis), else the body's long axis, else the format's convention where the body
  cannot tell (an upper-body marker set is about as wide as tall; :func:`.axes.resolve_up_axis`);
* channels: named points, unnamed ones and copies (:func:`.naming.split_channels`), the
  unnamed runs that continue a named marker across its gap joined to it (:mod:`.fragments`).

:func:`numeric_rows` is the shared parser of the data block: delimited numbers, an empty
cell or ``NaN`` text for a missing value, a short row's tail missing.
"""
from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .axes import resolve_up_axis, to_z_up
from .clip import MotionClip
from .fragments import fragments_note, join_channel_fragments
from .naming import split_channels
from .sanity import check_body_units

#: metres per unit of the length units marker files state (C3D's POINT:UNITS among them)
UNITS_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "dm": 0.1}


@dataclass
class MarkerTable:
    """One export's marker channels as its file holds them."""

    path: str
    format: str                          # ``meta['format']`` of the clip
    names: tuple[str, ...]               # channel labels as written
    xyz: np.ndarray                      # (F, N, 3) in the file's units and axes, NaN = missing
    rate: float                          # Hz
    units: str | None = None             # mm / cm / m as the file states them, None: not stated
    default_units: str = "mm"            # the format's units when the file says nothing
    units_source: str = "the file"       # where ``units`` was read, for messages
    frame_numbers: np.ndarray | None = None
    stated_up: str | None = None         # X / Y / Z as the file states the vertical
    up_source: str = "the file"
    default_up: str = "Z"                # the format's convention, where neither file nor body tells
    meta: dict = field(default_factory=dict)   # the format's own entries (header fields, comments)


def numeric_rows(lines: Sequence[str], width: int, where: str, sep: str = "\t", first_line: int = 1,
                 usecols: Sequence[int] | None = None) -> np.ndarray:
    """Parse delimited numeric rows into a (len(lines), ``width``) float array: an empty cell
    or ``NaN`` is NaN; a row shorter than ``width`` has its last cells missing (exporters drop
    trailing empty cells); a longer row may only carry empty cells past ``width``.
    ``usecols``: only these columns are read (the others may hold text), in this order."""
    fixed = []
    for k, line in enumerate(lines):
        cells = line.rstrip("\r\n").split(sep)
        if len(cells) > width:
            if any(c.strip() for c in cells[width:]):
                raise ValueError(f"{where}:{first_line + k}: {len(cells)} fields, the header has {width}")
            cells = cells[:width]
        cells += [""] * (width - len(cells))
        if usecols is not None:
            cells = [cells[c] for c in usecols]
        fixed.append(sep.join(c if c.strip() else "nan" for c in cells))
    if not fixed:
        raise ValueError(f"{where}: no data rows")
    try:
        a = np.loadtxt(io.StringIO("\n".join(fixed)), delimiter=sep, dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise ValueError(f"{where}: a data row holds text where numbers belong ({e})") from None
    return a.reshape(len(fixed), width if usecols is None else len(usecols))


def table_clip(t: MarkerTable, unit_scale: float | None = None, up_axis: str = "auto", join_fragments: bool = True,
               subject: str | None = None) -> MotionClip:
    """``t`` as a MotionClip (metres, Z up, named points; the rules of the module doc).
    ``meta``: ``format``, ``frame_numbers``, ``unit_scale``, ``units``, ``raw_labels`` (the named
    points' labels as written), ``up_axis``,
    ``up_axis_source`` (+ ``up_axis_note``), ``unlabelled``, ``unlabelled_names``,
    ``unlabelled_duplicates``, ``unlabelled_fragments`` / ``fragments_note`` where unnamed runs
    were joined, and the table's own ``meta``."""
    units = (t.units or t.default_units).lower()
    if unit_scale is None and units not in UNITS_M:
        raise ValueError(f"{t.path}: {t.units_source} gives the units as {t.units!r}, not understood; "
                         "pass --units mm|cm|m")
    forced_units = unit_scale is not None
    scale = float(unit_scale) if forced_units else UNITS_M[units]
    xyz = np.array(t.xyz, dtype=np.float64) * scale
    split = split_channels(t.names, xyz, t.path, subject)
    lab = split.named
    body = xyz[:, lab] if len(lab) >= 5 else xyz
    up = resolve_up_axis(body, up_axis, file_axis=t.stated_up, file_source=t.up_source, default=t.default_up,
                         where=t.path)
    xyz = to_z_up(xyz, up.axis)
    if not forced_units:
        check_body_units(xyz[:, lab] if len(lab) >= 5 else xyz, scale, units, t.path)
    xyz, fragments = join_channel_fragments(xyz, split, t.rate) if join_fragments else (xyz, [])
    meta = dict(t.meta)
    meta.update(format=t.format, frame_numbers=t.frame_numbers, unit_scale=scale, raw_labels=tuple(split.raw),
                units=next((u for u, v in UNITS_M.items() if abs(v / scale - 1) < 1e-9), "mm"),
                up_axis=up.axis, up_axis_source=up.source, unlabelled=xyz[:, split.unnamed].copy(),
                unlabelled_names=tuple(split.unnamed_names), unlabelled_duplicates=split.duplicates)
    if up.note:
        meta["up_axis_note"] = up.note
    if fragments:
        meta["unlabelled_fragments"] = [f.as_dict() for f in fragments]
        meta["fragments_note"] = fragments_note(fragments)
    return MotionClip(positions=xyz[:, lab], rate=t.rate, names=tuple(split.names), source=t.path, meta=meta)


def rate_from_times(times: np.ndarray | None, where: str, why: str) -> float:
    """The frame rate (Hz) the time column gives, for a file whose header does not (``why``)."""
    if times is None or len(times) < 2 or not times[-1] > times[0]:
        raise ValueError(f"{where}: {why} and no usable time column gives the frame rate")
    return round((len(times) - 1) / (times[-1] - times[0]), 3)


def missing_zeros(xyz: np.ndarray) -> np.ndarray:
    """``xyz`` with samples at exactly (0, 0, 0) -- the gap code of C3D and of QTM's older
    exports; no real marker sits on the origin to the micrometre -- set to NaN."""
    xyz = np.array(xyz, dtype=np.float64)
    xyz[np.all(xyz == 0.0, axis=-1)] = np.nan
    return xyz
