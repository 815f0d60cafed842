"""Model files: one ``.npz`` archive, never a pickle, with a versioned JSON header.

Layout (all entries plain numeric arrays; loaded with ``allow_pickle=False``)::

    header            uint8   UTF-8 JSON: format, format_version, labels, structure,
                              heading pairs, settings, provenance, per-triangle K
    tri<t>_weights    (K,)    float64
    tri<t>_means      (K,15)  float64
    tri<t>_covariances(K,15,15) float64
    body_pairs        (P,2)   int64     body terms (version 2, when the header's "body" is set;
    body_kind         (P,)    int64     see dtm_labeler.model.body): label pairs, segment /
    body_lo, body_hi  (P,)    float64   reach, allowed distance range (m), within- and
    body_within_sd,   (P,)    float64   between-person spread (m)
    body_between_sd
    body_quads        (Q,4)   int64     the marker clusters' handedness (version 3): neighbouring
    body_quad_sign    (Q,)    float64   label quadruples and the sign of their signed volume
    body_twists       (K,5)   int64     the trunk's twist limits (version 4): shoulder axis (left,
                                        mid or -1, right) and hip axis (left, right) labels
    body_rigid_pairs  (R,2)   int64     the trained person's rigid marker pairs (version 5): label
    body_rigid_length (R,)    float64   pairs, median length and robust spread (m)
    body_rigid_spread (R,)    float64
    body_orders       (K,3)   int64     the marker bars' order (version 6): a label and the bar's
                                        end it lies nearer, then the other end
    body_reach_off_edges (P,) int64     1 where a reach limit holds off the DTM's edges too (version 8)
    body_take_orders  (K',3)  int64     more bar orders, from the bar's side of the body, read over a
                                        take's stretches by the offline pass (version 9)
    broad_weights     (T,)    float64   broad part of each triangle's conditional (version 2, when
    broad<t>_mean     (15,)   float64   the header's "broad" is true; see dtm_labeler.model.body)
    broad<t>_covariance (15,15) float64

Versions: 2 adds the body terms and the broad components (issue 13); 3 the clusters' handedness
(:class:`~dtm_labeler.model.body.Handedness`); 4 the trunk's twist limit
(:class:`~dtm_labeler.model.body.TrunkTwist`); 5 the trained person's rigid marker pairs
(:attr:`~dtm_labeler.model.body.BodyModel.rigid_pairs`, read by the offline take pass only); 6 the
marker bars' order (:class:`~dtm_labeler.model.body.BarOrder`); 7 a calibrated model's body before
its calibration (``generic_body_*``, the same arrays as ``body_*``; the header's ``"generic_body"``
is set: :attr:`~dtm_labeler.model.dtm.TriangulatedModel.generic_body`); 8 which reach limits hold
off the DTM's edges (:attr:`~dtm_labeler.model.body.BodyModel.reach_off_edges`); 9 the take pass's
bar orders (:attr:`~dtm_labeler.model.body.BodyModel.take_orders`). Version 1
files still load, as models without body terms, version 2 files as bodies without handedness, version 3
files as bodies without twist limits, version 4 files as bodies without the person's rigid pairs,
version 5 files as bodies without bar orders, version 6 files without the generic body, version 7
files with every reach limit held off the edges, version 8 files without the take pass's bar orders (all
score exactly as they did;
``provenance["format_version_read"]`` says which). A file that is
not a model, has an unknown format version, or whose arrays disagree with the header raises
:class:`ModelFileError` naming the file and the problem.
"""
from __future__ import annotations

import io
import json
import os
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from .body import BodyModel, BroadMotion
from .dtm import TriangulatedModel
from .mixture import GaussianMixture
from .structure import Structure

FORMAT_NAME = "dtm_labeler.model"
FORMAT_VERSION = 9
READABLE_VERSIONS = (1, 2, 3, 4, 5, 6, 7, 8, 9)
GENERIC = "generic_"                     # prefix of the generic body's arrays (version 7)


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
        "provenance": {k: v for k, v in model.provenance.items() if k != "format_version_read"},
        "body": None if model.body is None else {"pairs": int(model.body.pairs.shape[0]),
                                                 "calibration": model.body.calibration},
        "broad": model.broad is not None,
        "generic_body": model.generic_body is not None,
    }
    arrays = {"header": np.frombuffer(json.dumps(header, indent=1).encode(), dtype=np.uint8)}
    for t, mix in enumerate(model.mixtures):
        for key, arr in mix.to_arrays().items():
            arrays[f"tri{t}_{key}"] = np.asarray(arr, dtype=np.float64)
    if model.body is not None:
        arrays.update(model.body.to_arrays())
    if model.broad is not None:
        arrays.update(model.broad.to_arrays())
    if model.generic_body is not None:
        arrays.update({GENERIC + k: v for k, v in model.generic_body.to_arrays().items()})
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
    except (zipfile.BadZipFile, zlib.error, NotImplementedError, ValueError, OSError, EOFError, SyntaxError,
            tokenize.TokenError) as e:
        # zlib.error: damaged deflate data; NotImplementedError: damaged compression-method field;
        # SyntaxError / TokenError: a damaged .npy header dict (numpy parses it as a Python literal)
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
    if version not in READABLE_VERSIONS:
        raise ModelFileError(f"{where}: format version {version} is not supported "
                             f"(this build reads versions {', '.join(map(str, READABLE_VERSIONS))}); "
                             "retrain with dtm-train")
    try:
        labels = [str(x) for x in header["labels"]]
        structure = Structure(tuple(tuple(t) for t in header["structure"]), len(labels))
        mixtures = []
        for t in range(structure.n_triangles):
            keys = [k for k in arrays if k.startswith(f"tri{t}_")]
            if not keys:
                raise ModelFileError(f"{where}: no mixture stored for triangle {t}")
            mixtures.append(GaussianMixture.from_arrays({k[len(f'tri{t}_'):]: arrays[k] for k in keys}))
        body_info = header.get("body") if version >= 2 else None
        body = None
        if body_info is not None:
            if not isinstance(body_info, dict):
                raise ModelFileError(f"{where}: header entry 'body' must be an object or null")
            body = BodyModel.from_arrays(arrays, len(labels), body_info.get("calibration"))
        broad = BroadMotion.from_arrays(arrays, structure.n_triangles) if version >= 2 and header.get("broad") else None
        generic = None
        if version >= 7 and header.get("generic_body"):
            generic = BodyModel.from_arrays({k[len(GENERIC):]: v for k, v in arrays.items() if k.startswith(GENERIC)},
                                            len(labels))
        provenance = dict(header.get("provenance", {}))
        if version != FORMAT_VERSION:
            provenance["format_version_read"] = version
        return TriangulatedModel(labels=tuple(labels), structure=structure, mixtures=mixtures, body=body, broad=broad,
                                 generic_body=generic,
                                 heading_pairs=np.asarray(header.get("heading_pairs", []), dtype=np.int64),
                                 mirror_pairs=(np.asarray(header["mirror_pairs"], dtype=np.int64)
                                               if "mirror_pairs" in header else None),
                                 settings=dict(header.get("settings", {})),
                                 provenance=provenance)
    except ModelFileError:
        raise
    except (KeyError, TypeError, ValueError) as e:
        raise ModelFileError(f"{where}: inconsistent model ({type(e).__name__}: {e})") from None
