"""Cheap checks of a model or bank file before anything in it is loaded.

A model file is an ``.npz`` (zip) archive of ``.npy`` arrays. :func:`check_model_file` reads the
zip directory and the few header bytes of every member (``numpy.lib.format``: shape and dtype),
and the small JSON header, without decompressing any array: a file is rejected, with the
reason, when it is not a regular file, not a zip archive, holds a non-``.npy`` member or an
object array (pickle), or declares arrays far beyond a model's plausible size -- a 1.6 MB
archive may hold a 1.5 GB array of zeros, which ``np.load`` would allocate and fill before
any validation could refuse it. Labels are read from the header, so ``expected_labels`` is
checked before loading too. A bank is a directory with ``bank.json`` (each model file checked)
or a single ``.npz`` holding model archives as byte arrays (the outer members checked here; the
inner archives, bounded by that, are checked again when they are opened).

Sizes allowed: :data:`MAX_ARRAY_BYTES` per array, :data:`MAX_FILE_BYTES` in all (a 41-marker
model with 8 components per triangle holds ~0.8 MB of arrays). The node runs the check in its
parameter callback (a few kB read, ~1 ms) and again right before loading, in its loader thread.
"""
from __future__ import annotations

import io
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional, Tuple

import numpy as np
from numpy.lib import format as npformat

__all__ = ["ModelCheck", "check_model_file", "MAX_ARRAY_BYTES", "MAX_FILE_BYTES", "MAX_HEADER_BYTES"]

MAX_ARRAY_BYTES = 64 * 2 ** 20        # one array
MAX_FILE_BYTES = 256 * 2 ** 20        # all arrays of a file (a bank holds several models)
MAX_HEADER_BYTES = 4 * 2 ** 20        # the JSON header
_BANK_JSON = "bank.json"


@dataclass(frozen=True)
class ModelCheck:
    kind: str                         # "model" | "bank"
    labels: Tuple[str, ...]
    array_bytes: int                  # bytes the arrays take once loaded


def _members(z: zipfile.ZipFile, where: str):
    """(name, shape, dtype) of every .npy member, from its header only."""
    out = []
    for info in z.infolist():
        if not info.filename.endswith(".npy"):
            raise ValueError(f"{where}: member {info.filename!r} is not a numpy array")
        with z.open(info) as f:
            try:
                version = npformat.read_magic(f)
                reader = npformat.read_array_header_1_0 if version == (1, 0) else npformat.read_array_header_2_0
                shape, _, dtype = reader(f, max_header_size=10_000)
            except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
                raise ValueError(f"{where}: member {info.filename!r} has no readable array header ({e})") from None
        if dtype.hasobject:
            raise ValueError(f"{where}: member {info.filename!r} is an object array (pickle); refused")
        out.append((info.filename[:-4], tuple(shape), dtype))
    return out


def _sizes(members, where: str) -> int:
    total = 0
    for name, shape, dtype in members:
        nbytes = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
        if nbytes > MAX_ARRAY_BYTES:
            raise ValueError(f"{where}: array {name!r} of shape {shape} ({nbytes / 2 ** 20:.0f} MB) is far "
                             f"beyond a model's size (limit {MAX_ARRAY_BYTES // 2 ** 20} MB); refused")
        total += nbytes
    if total > MAX_FILE_BYTES:
        raise ValueError(f"{where}: arrays total {total / 2 ** 20:.0f} MB, beyond a model's size "
                         f"(limit {MAX_FILE_BYTES // 2 ** 20} MB); refused")
    return total


def _json_member(z: zipfile.ZipFile, name: str, members, where: str) -> dict:
    shape = {m[0]: m[1] for m in members}.get(name)
    if shape is None:
        raise ValueError(f"{where}: no {name} entry; not a dtm_labeler model file")
    if int(np.prod(shape)) > MAX_HEADER_BYTES:
        raise ValueError(f"{where}: {name} of {int(np.prod(shape))} bytes is too large; refused")
    with z.open(name + ".npy") as f:
        arr = npformat.read_array(f, allow_pickle=False)
    try:
        doc = json.loads(bytes(np.asarray(arr, dtype=np.uint8)).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{where}: corrupt {name} ({e})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{where}: {name} is not a JSON object")
    return doc


def _check_npz(path: Path) -> Tuple[str, Tuple[str, ...], int]:
    where = str(path)
    if not path.is_file():
        raise ValueError(f"{where}: " + ("not a regular file" if path.exists() else "no such model file"))
    return _check_archive(path, where)


def _check_archive(source, where: str, inner: bool = False) -> Tuple[str, Tuple[str, ...], int]:
    """(kind, labels, array bytes) of an .npz given as a path or a file-like object."""
    try:
        with zipfile.ZipFile(source) as z:
            members = _members(z, where)
            total = _sizes(members, where)
            names = {m[0] for m in members}
            if "bank_json" in names and not inner:
                doc = _json_member(z, "bank_json", members, where)
                for name in sorted(names - {"bank_json"}):          # the models inside, each an .npz
                    with z.open(name + ".npy") as f:
                        blob = npformat.read_array(f, allow_pickle=False)
                    total += _check_archive(io.BytesIO(blob.tobytes()), f"{where}[{name}]", inner=True)[2]
                return "bank", tuple(str(x) for x in doc.get("labels") or []), total
            doc = _json_member(z, "header", members, where)
    except zipfile.BadZipFile as e:
        raise ValueError(f"{where}: not a dtm_labeler model file ({e})") from None
    if total > MAX_FILE_BYTES:
        raise ValueError(f"{where}: arrays total {total / 2 ** 20:.0f} MB; refused")
    return "model", tuple(str(x) for x in doc.get("labels", [])), total


def _check_bank_dir(path: Path) -> Tuple[str, Tuple[str, ...], int]:
    index = path / _BANK_JSON
    if not index.is_file():
        raise ValueError(f"{path}: no {_BANK_JSON}; not a model bank")
    if index.stat().st_size > MAX_HEADER_BYTES:
        raise ValueError(f"{index}: too large for a bank index; refused")
    try:
        doc = json.loads(index.read_text(encoding="utf-8"))
        files = [path / str(e.get("file", f"{e['name']}.npz")) for e in doc["actions"]]
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"{index}: corrupt bank index ({type(e).__name__}: {e})") from None
    labels: Tuple[str, ...] = ()
    total = 0
    for f in files:
        kind, lab, n = _check_npz(f)
        labels, total = labels or lab, total + n
    if total > MAX_FILE_BYTES:
        raise ValueError(f"{path}: models total {total / 2 ** 20:.0f} MB; refused")
    return "bank", labels, total


def check_model_file(path: str | os.PathLike, expected_labels: Optional[Iterable[str]] = None,
                     bank: bool = False) -> ModelCheck:
    """Check a model (``bank=False``) or a bank file/directory before loading it; raises
    ValueError naming the file and the problem (see the module doc)."""
    p = Path(path)
    if bank and p.is_dir():
        kind, labels, total = _check_bank_dir(p)
    else:
        kind, labels, total = _check_npz(p)
    if bank and kind != "bank":
        raise ValueError(f"{p}: a single model, not a bank (use it as model_path)")
    if not bank and kind != "model":
        raise ValueError(f"{p}: a model bank, not a model (use use_bank:=true bank_path:={p})")
    expected = list(expected_labels or [])
    if expected and labels and list(labels) != expected:
        from .params import check_labels
        check_labels(labels, expected, where=f"{kind} {p}")
    return ModelCheck(kind, labels, total)
