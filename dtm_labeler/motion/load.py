"""One entry point for every recording format: :func:`load_clip`.

Dispatch on extension: ``.bvh``; ``.asf`` (paired with the same-stem ``.amc``) or
``.amc`` (skeleton: ``asf_path=`` keyword, else same-stem ``.asf``, else the only
``.asf`` in the folder); ``.c3d``; ``.csv`` (MoCap Toolbox marker CSV, OptiTrack Motive's
CSV export or derived joint-positions CSV, told apart by the header); ``.trc`` (Cortex,
OpenSim); ``.tsv`` (QTM's 3D export). FBX is not supported (use the lossless
``bvh_from_fbx`` conversions). Every clip is metres, Z up, NaN = missing.

``motion_class``: the ``class`` column of the ``index.csv`` found in the file's folder
or one of its parents when the file is listed there, reduced to its first word
(``"dance (breakdance)" -> "dance"``, ``"other (jump twist)" -> "other"``; the full
text is kept in ``meta['index_class']``); else the first filename word starting with
walk / run / danc (-> ``walk``/``run``/``dance``); else ``""``.
"""
from __future__ import annotations

import csv
import functools
import re
from pathlib import Path
from typing import Iterable, Sequence

from .asf_amc import find_asf_for, load_asf_amc
from .bvh import load_bvh
from .c3d import load_c3d
from .clip import MotionClip
from .markers_csv import load_markers_csv, read_header
from .motive_csv import is_motive_csv, load_motive_csv
from .pointsets import to_point_set
from .positions_csv import POSITIONS16, load_positions_csv
from .qtm_tsv import load_qtm_tsv
from .sanity import check_body_units
from .trc import load_trc

UNITS_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "inch": 0.0254}

# index.csv kinds that hold motion (FBX excluded: not readable here; derived positions CSVs
# and .asf skeletons excluded: they duplicate the BVH / AMC recordings)
DEFAULT_KINDS = ("skeleton_bvh", "motion_amc", "markers_c3d", "markers_csv")


#: the marker formats: every point a measured marker; the capture options (units, vertical,
#: subject) apply
MARKER_SUFFIXES = (".c3d", ".csv", ".trc", ".tsv")


def csv_kind(path: str | Path) -> str:
    """``'positions'`` (derived joint positions, metres, Y up), ``'motive'`` (OptiTrack Motive's
    export) or ``'markers'`` (MoCap Toolbox layout)."""
    with open(path, "r", encoding="utf-8-sig", errors="replace") as fh:
        if is_motive_csv(fh.readline()):
            return "motive"
    comments, header = read_header(path)
    names = {h.strip()[:-2] for h in header[2:]}
    if names and names <= set(POSITIONS16):
        return "positions"
    if any("derived joint positions" in c.lower() for c in comments):
        return "positions"
    return "markers"


@functools.lru_cache(maxsize=8)
def _read_index(index_path: str) -> dict[str, dict[str, str]]:
    with open(index_path, newline="", encoding="utf-8") as fh:
        return {row["path"]: row for row in csv.DictReader(fh)}


def index_entry(path: str | Path) -> dict[str, str] | None:
    """The ``index.csv`` row listing ``path`` (searching the file's parent folders)."""
    p = Path(path).resolve()
    for d in p.parents:
        idx = d / "index.csv"
        if idx.is_file():
            try:
                rel = p.relative_to(d).as_posix()
            except ValueError:
                continue
            row = _read_index(str(idx)).get(rel)
            if row is not None:
                return row
    return None


def class_from_name(path: str | Path) -> str:
    """walk / run / dance from the first matching filename word, else ''."""
    for tok in re.split(r"[^a-z]+", Path(path).stem.lower()):
        if tok.startswith("walk"):
            return "walk"
        if tok in ("run", "runs", "running", "runner", "jog", "jogging"):
            return "run"
        if tok.startswith("danc"):
            return "dance"
    return ""


def motion_class_of(path: str | Path) -> tuple[str, str]:
    """(class, full index text or '') for ``path`` (see module doc)."""
    row = index_entry(path)
    if row is not None and row.get("class", "").strip():
        full = row["class"].strip()
        return re.split(r"[\s(]+", full)[0].lower(), full
    return class_from_name(path), ""


def capture_options(kw: dict, ext: str) -> dict:
    """The user-level options ``up_axis`` ('auto'/X/Y/Z) and ``units`` (mm/cm/m/inch, None =
    the file's) turned into the keywords of the loader of ``ext``: marker files (C3D, CSV)
    take both; BVH takes a forced Y/Z vertical and units; ASF/AMC take units (their
    vertical is Y by convention); derived joint-position CSVs are metres, Y up."""
    kw = dict(kw)
    up = kw.pop("up_axis", None)
    units = kw.pop("units", None)
    if units is not None:
        if units not in UNITS_M:
            raise ValueError(f"units must be one of {', '.join(UNITS_M)}, got {units!r}")
        kw.setdefault("unit_scale", UNITS_M[units])
    forced = up is not None and str(up).lower() != "auto"
    if ext in (".c3d", ".trc", ".tsv") or kw.get("csv_kind") in ("markers", "motive"):
        if up is not None:
            kw["up_axis"] = up
    elif forced and ext == ".bvh":
        kw["up_axis"] = up
    elif forced and str(up).upper() != "Y":
        raise ValueError(f"--up-axis {up}: {ext} files are Y up by convention")
    return kw


def load_clip(path: str | Path, points: str | Sequence[str] = "all", **kw) -> MotionClip:
    """Load any supported recording. ``points``: see :func:`pointsets.to_point_set`.

    Keywords go to the format loader (``unit_scale``, ``drop_tpose``, ``up_axis``,
    ``include_end_sites`` for BVH; ``unit_scale``, ``rate`` for ASF/AMC plus ``asf_path``;
    ``up_axis``, ``unit_scale``, ``join_fragments``, ``subject`` for the marker formats (C3D,
    marker and Motive CSV, TRC, QTM TSV; ``include_unlabelled`` for C3D); ``csv_kind`` =
    'markers'/'motive'/'positions' to skip CSV detection); ``up_axis`` and ``units`` are read as
    user options first (:func:`capture_options`). ``marker_set`` goes to ``to_point_set``.
    Skeletal recordings are checked for human units like marker files
    (:func:`.sanity.check_body_units`) unless ``unit_scale`` is given.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such recording: {path}")
    marker_set = kw.pop("marker_set", None)
    ext = path.suffix.lower()
    if ext == ".csv" and "csv_kind" not in kw:
        kw["csv_kind"] = csv_kind(path)
    if ext != ".amc":
        kw.pop("asf_path", None)
    if ext not in MARKER_SUFFIXES or kw.get("subject") is None:
        kw.pop("subject", None)                  # one subject per skeletal file
    kw = capture_options(kw, ext)
    if ext == ".bvh":
        clip = load_bvh(path, **kw)
    elif ext == ".asf":
        amc = path.with_suffix(".amc")
        if not amc.is_file():
            raise ValueError(f"{path}: no motion file {amc.name} next to the skeleton")
        clip = load_asf_amc(path, amc, **kw)
    elif ext == ".amc":
        asf = kw.pop("asf_path", None) or find_asf_for(path)
        clip = load_asf_amc(asf, path, **kw)
    elif ext == ".c3d":
        clip = load_c3d(path, **kw)
    elif ext == ".csv":
        kind = kw.pop("csv_kind", None) or csv_kind(path)
        if kind == "positions":
            clip = load_positions_csv(path, **{k: v for k, v in kw.items() if k == "up_axis"})
        elif kind == "markers":
            clip = load_markers_csv(path, **kw)
        elif kind == "motive":
            clip = load_motive_csv(path, **kw)
        else:
            raise ValueError(f"{path}: csv_kind must be 'markers', 'motive' or 'positions', got {kind!r}")
    elif ext == ".trc":
        clip = load_trc(path, **kw)
    elif ext == ".tsv":
        clip = load_qtm_tsv(path, **kw)
    elif ext == ".fbx":
        raise ValueError(f"{path}: FBX is not supported; load the BVH conversion (bvh_from_fbx/) instead")
    else:
        raise ValueError(f"{path}: unsupported recording type {ext!r} (.bvh .asf .amc .c3d .csv .trc .tsv)")
    if ext in (".bvh", ".asf", ".amc") and "unit_scale" not in kw:
        check_body_units(clip.positions, clip.meta.get("unit_scale", 1.0), "", str(path))
    cls, full = motion_class_of(path)
    clip.source = str(path)
    clip.motion_class = cls
    if full:
        clip.meta["index_class"] = full
    return to_point_set(clip, points, marker_set=marker_set)


def load_clips(paths: Iterable[str | Path], points: str | Sequence[str] = "all", **kw) -> list[MotionClip]:
    """:func:`load_clip` for each path (same keywords for all)."""
    return [load_clip(p, points=points, **dict(kw)) for p in paths]


def find_recordings(data_dir: str | Path, kinds: Sequence[str] | None = DEFAULT_KINDS,
                    classes: Sequence[str] | None = None) -> dict[str, list[Path]]:
    """Recordings listed in ``<data_dir>/index.csv`` grouped by class (first word of the
    ``class`` column, as in :func:`motion_class_of`), each list sorted by path.
    ``kinds``: ``index.csv`` kinds to include (None: all); ``classes``: keep only these."""
    data_dir = Path(data_dir)
    idx = data_dir / "index.csv"
    if not idx.is_file():
        raise FileNotFoundError(f"{idx} not found")
    out: dict[str, list[Path]] = {}
    for rel, row in _read_index(str(idx.resolve())).items():
        if kinds is not None and row.get("kind") not in kinds:
            continue
        cls = re.split(r"[\s(]+", row.get("class", "").strip())[0].lower()
        if classes is not None and cls not in classes:
            continue
        out.setdefault(cls, []).append(data_dir / rel)
    return {k: sorted(v) for k, v in sorted(out.items())}
