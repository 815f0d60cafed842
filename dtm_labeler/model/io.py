"""Model files: one ``.npz`` archive, never a pickle, with a versioned JSON header.

Layout (all entries plain numeric arrays; loaded with ``allow_pickle=False``)::

    header            uint8   UTF-8 JSON: format, format_version, labels, structure,
                              heading pairs, settings, provenance, per-triangle K
    tri<t>_weights    (K,)    float64
    tri<t>_means      (K,15)  float64
    tri<t>_covariances(K,15,15) float64

A file that is not a model, has another format version, or whose arrays disagree with the
header raises :class:`ModelFileError` naming the file and the problem.
"""
from __future__ import annotations

import io
import json
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from .dtm import TriangulatedModel
from .mixture import GaussianMixture
from .structure import Structure

FORMAT_NAME = "dtm_labeler.model"
FORMAT_VERSION = 1


class ModelFileError(ValueError):
    """A model file that cannot be used, with the reason."""


def model_to_bytes(model: TriangulatedModel) -> bytes:
    header = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "labels": list(model.labels),
        "structure": [list(t) for t in model.structure.triangles],
        "heading_pairs": model.heading_pairs.tolist(),
        "mirror_pairs": model.mirror_pairs.tolist(),
        "components": model.components_per_triangle(),
        "settings": model.settings,
        "provenance": model.provenance,
    }
    arrays = {"header": np.frombuffer(json.dumps(header, indent=1).encode(), dtype=np.uint8)}
    for t, mix in enumerate(model.mixtures):
        for key, arr in mix.to_arrays().items():
            arrays[f"tri{t}_{key}"] = np.asarray(arr, dtype=np.float64)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def save_model(model: TriangulatedModel, path: str | os.PathLike) -> Path:
    """Write atomically (temp file + rename) so a running node never reads half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(model_to_bytes(model))
    os.replace(tmp, path)
    return path


def load_model(path: str | os.PathLike) -> TriangulatedModel:
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: no such model file")
    return _load(path, str(path))


def model_from_bytes(data: bytes, where: str = "model") -> TriangulatedModel:
    """A model from the bytes of a model file (:func:`model_to_bytes`)."""
    return _load(io.BytesIO(data), where)


def _load(source, where: str) -> TriangulatedModel:
    try:
        with np.load(source, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, zlib.error, NotImplementedError, ValueError, OSError, EOFError) as e:
        # zlib.error: damaged deflate data; NotImplementedError: damaged compression-method field
        raise ModelFileError(f"{where}: not a dtm_labeler model file ({e})") from None
    return model_from_arrays(arrays, where)


def model_from_arrays(arrays: dict, where: str = "model") -> TriangulatedModel:
    if "header" not in arrays:
        raise ModelFileError(f"{where}: no header entry; not a dtm_labeler model file")
    try:
        header = json.loads(bytes(np.asarray(arrays["header"], dtype=np.uint8)).decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ModelFileError(f"{where}: corrupt header ({e})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise ModelFileError(f"{where}: header does not name format {FORMAT_NAME!r}")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise ModelFileError(f"{where}: format version {version} is not supported "
                             f"(this build reads version {FORMAT_VERSION}); retrain with dtm-train")
    try:
        labels = [str(x) for x in header["labels"]]
        structure = Structure(tuple(tuple(t) for t in header["structure"]), len(labels))
        mixtures = []
        for t in range(structure.n_triangles):
            keys = [k for k in arrays if k.startswith(f"tri{t}_")]
            if not keys:
                raise ModelFileError(f"{where}: no mixture stored for triangle {t}")
            mixtures.append(GaussianMixture.from_arrays({k[len(f'tri{t}_'):]: arrays[k] for k in keys}))
        return TriangulatedModel(labels=tuple(labels), structure=structure, mixtures=mixtures,
                                 heading_pairs=np.asarray(header.get("heading_pairs", []), dtype=np.int64),
                                 mirror_pairs=(np.asarray(header["mirror_pairs"], dtype=np.int64)
                                               if "mirror_pairs" in header else None),
                                 settings=dict(header.get("settings", {})),
                                 provenance=dict(header.get("provenance", {})))
    except ModelFileError:
        raise
    except (KeyError, TypeError, ValueError) as e:
        raise ModelFileError(f"{where}: inconsistent model ({type(e).__name__}: {e})") from None
