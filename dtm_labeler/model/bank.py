"""A model bank: one independently trained :class:`TriangulatedModel` per action (Ukita 4.1, 4.4).

Storage, either

* a **directory** (what ``dtm-train --action NAME --bank DIR`` maintains)::

      DIR/bank.json          format "dtm_labeler.bank", format_version, labels, actions
                             [{name, file, sha256, sources, transitions, ...}], created/updated
      DIR/<action>.npz       one ordinary model file per action (dtm_labeler.model.io)

  Adding or replacing one action rewrites only ``<action>.npz`` and ``bank.json``; every other
  model file stays byte-identical (the paper's L2: no re-optimisation of existing models);
* or a **single file** ``*.npz`` (``bank_json`` entry + ``model_<action>`` entries holding each
  model file's bytes), convenient for shipping to a robot.

Validation on load: format name and version, every listed model file present and with the
recorded SHA-256 (a model replaced behind the bank's back is an error, not a surprise), every
model readable, and the **same labels in the same order** in every model (individuals are
moved between models at run time, so an assignment must mean the same in each). Every
problem raises :class:`BankFileError` naming the file and the reason.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import io
import json
import os
import re
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .dtm import TriangulatedModel
from .io import ModelFileError, load_model, model_from_arrays, model_to_bytes
from ..jsonable import json_default

BANK_FORMAT = "dtm_labeler.bank"
BANK_VERSION = 1
BANK_JSON = "bank.json"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


class BankFileError(ModelFileError):
    """A bank that cannot be used, with the reason."""


def check_action_name(name: str) -> str:
    if not isinstance(name, str) or not _NAME.match(name) or name.endswith(".npz") or name == BANK_JSON:
        raise BankFileError(f"action name {name!r}: use letters, digits, '_', '-', '.' (max 64, no path)")
    return name


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


@dataclass
class ModelBank:
    """Ordered ``action -> model`` map plus per-action records (sources, transitions)."""

    models: dict[str, TriangulatedModel] = field(default_factory=dict)
    records: dict[str, dict] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for a in self.models:
            check_action_name(a)
            self.records.setdefault(a, {})
        self.validate()

    # -- access -------------------------------------------------------------------------
    @property
    def actions(self) -> list[str]:
        return list(self.models)

    @property
    def labels(self) -> tuple[str, ...]:
        if not self.models:
            return ()
        return next(iter(self.models.values())).labels

    @property
    def n_labels(self) -> int:
        return len(self.labels)

    def __len__(self) -> int:
        return len(self.models)

    def __getitem__(self, action: str) -> TriangulatedModel:
        try:
            return self.models[action]
        except KeyError:
            raise KeyError(f"no action {action!r} in the bank (have {', '.join(self.models) or 'none'})") from None

    def __contains__(self, action: str) -> bool:
        return action in self.models

    def validate(self) -> None:
        """Same labels (same order) in every model."""
        ref = None
        for a, m in self.models.items():
            if ref is None:
                ref = (a, m.labels)
            elif m.labels != ref[1]:
                diff = sorted(set(m.labels) ^ set(ref[1]))
                why = f"labels differ ({', '.join(diff[:6])})" if diff else "same labels in a different order"
                raise BankFileError(f"action {a!r}: {why} from action {ref[0]!r}; every model in a bank "
                                    "must use the same label set (train all with the same --points)")

    def add(self, action: str, model: TriangulatedModel, record: dict | None = None) -> None:
        """Add or replace one action (checked against the others' labels)."""
        check_action_name(action)
        ModelBank({**{a: m for a, m in self.models.items() if a != action}, action: model})  # raises on mismatch
        self.models[action] = model
        self.records[action] = dict(record or {})

    def remove(self, action: str) -> None:
        self[action]
        del self.models[action]
        self.records.pop(action, None)

    def header(self) -> dict:
        return {"format": BANK_FORMAT, "format_version": BANK_VERSION, "labels": list(self.labels),
                "actions": [dict(self.records.get(a, {}), name=a) for a in self.models],
                **{k: v for k, v in self.meta.items() if k not in ("format", "format_version", "labels", "actions")}}


# ==================================================================== directory banks
def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def save_bank(bank: ModelBank, path: str | os.PathLike, only: list[str] | None = None) -> Path:
    """Write a bank. ``path`` ending in ``.npz``: single file; otherwise a directory.

    Directory: model files are written only for ``only`` (default: every action whose file
    is missing or differs); unchanged files are not touched. ``bank.json`` is written last,
    atomically, so a reader never sees a listed model that is not there yet.
    """
    path = Path(path)
    if path.suffix.lower() == ".npz":
        return _save_single(bank, path)
    path.mkdir(parents=True, exist_ok=True)
    header = bank.header()
    header.setdefault("created", now_iso())
    header["updated"] = now_iso()
    for entry in header["actions"]:
        a = entry["name"]
        fname = f"{a}.npz"
        target = path / fname
        if only is not None and a not in only and target.is_file():
            data = target.read_bytes()
        else:
            data = model_to_bytes(bank.models[a])
            if not (target.is_file() and target.read_bytes() == data):
                _write_atomic(target, data)
        entry["file"] = fname
        entry["sha256"] = _sha(data)
        bank.records[a] = {k: v for k, v in entry.items() if k != "name"}
    _write_atomic(path / BANK_JSON, json.dumps(header, indent=1, default=json_default).encode())
    return path


def add_to_bank(path: str | os.PathLike, action: str, model: TriangulatedModel, record: dict | None = None) -> ModelBank:
    """Add/replace one action in the directory bank at ``path`` (created if absent). Only
    ``<action>.npz`` and ``bank.json`` are written."""
    path = Path(path)
    if path.suffix.lower() == ".npz":
        raise BankFileError(f"{path}: actions are added to a bank directory, not a single-file bank")
    bank = load_bank(path) if (path / BANK_JSON).is_file() else ModelBank()
    bank.add(action, model, record)
    save_bank(bank, path, only=[action])
    return bank


def _parse_header(data: bytes, where: str) -> dict:
    try:
        header = json.loads(data.decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise BankFileError(f"{where}: corrupt bank index ({e})") from None
    if not isinstance(header, dict) or header.get("format") != BANK_FORMAT:
        raise BankFileError(f"{where}: not a model bank (format is not {BANK_FORMAT!r})")
    if header.get("format_version") != BANK_VERSION:
        raise BankFileError(f"{where}: bank format version {header.get('format_version')} is not supported "
                            f"(this build reads version {BANK_VERSION})")
    actions = header.get("actions")
    if not isinstance(actions, list) or not actions:
        raise BankFileError(f"{where}: the bank lists no actions")
    names = []
    for e in actions:
        if not isinstance(e, dict) or "name" not in e:
            raise BankFileError(f"{where}: malformed action entry {e!r}")
        names.append(check_action_name(e["name"]))
    if len(set(names)) != len(names):
        raise BankFileError(f"{where}: an action is listed twice")
    return header


def _finish(header: dict, models: dict[str, TriangulatedModel], where: str) -> ModelBank:
    try:
        bank = ModelBank(models=models, records={e["name"]: {k: v for k, v in e.items() if k != "name"}
                                                 for e in header["actions"]},
                         meta={k: v for k, v in header.items() if k not in ("actions",)})
    except BankFileError as e:
        raise BankFileError(f"{where}: {e}") from None
    if header.get("labels") and list(bank.labels) != list(header["labels"]):
        raise BankFileError(f"{where}: models' labels differ from the labels listed in the bank index")
    return bank


def load_bank(path: str | os.PathLike) -> ModelBank:
    """Read a bank directory (``bank.json`` + model files) or a single-file ``.npz`` bank."""
    path = Path(path)
    if path.is_file():
        return _load_single(path)
    index = path / BANK_JSON
    if not index.is_file():
        raise BankFileError(f"{path}: no {BANK_JSON}; not a model bank (create one with dtm-train --action NAME "
                            f"--bank {path})")
    header = _parse_header(index.read_bytes(), str(index))
    models = {}
    for e in header["actions"]:
        f = path / str(e.get("file", f"{e['name']}.npz"))
        if f.parent.resolve() != path.resolve():
            raise BankFileError(f"{index}: action {e['name']!r} points outside the bank ({e.get('file')})")
        if not f.is_file():
            raise BankFileError(f"{index}: model file {f.name} of action {e['name']!r} is missing")
        data = f.read_bytes()
        if "sha256" in e and _sha(data) != e["sha256"]:
            raise BankFileError(f"{f}: checksum differs from {BANK_JSON} (file changed or damaged); "
                                f"re-add the action with dtm-train --action {e['name']} --bank {path}")
        models[e["name"]] = load_model(f)
    return _finish(header, models, str(path))


# ==================================================================== single-file banks
def _save_single(bank: ModelBank, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    header = bank.header()
    header.setdefault("created", now_iso())
    arrays = {}
    for e in header["actions"]:
        data = model_to_bytes(bank.models[e["name"]])
        e["file"] = f"model_{e['name']}"
        e["sha256"] = _sha(data)
        arrays[e["file"]] = np.frombuffer(data, dtype=np.uint8)
    arrays["bank_json"] = np.frombuffer(json.dumps(header, indent=1, default=json_default).encode(), dtype=np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    _write_atomic(path, buf.getvalue())
    return path


def _load_single(path: Path) -> ModelBank:
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, zlib.error, NotImplementedError, ValueError, OSError, EOFError) as e:
        raise BankFileError(f"{path}: not a model bank file ({e})") from None
    if "bank_json" not in arrays:
        raise BankFileError(f"{path}: no bank_json entry; not a model bank (a single model? use it as MODEL)")
    header = _parse_header(bytes(np.asarray(arrays["bank_json"], dtype=np.uint8)), str(path))
    models = {}
    for e in header["actions"]:
        key = e.get("file", f"model_{e['name']}")
        if key not in arrays:
            raise BankFileError(f"{path}: model of action {e['name']!r} is missing")
        data = bytes(np.asarray(arrays[key], dtype=np.uint8))
        if "sha256" in e and _sha(data) != e["sha256"]:
            raise BankFileError(f"{path}: model of action {e['name']!r} is damaged (checksum)")
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                inner = {k: z[k] for k in z.files}
        except (zipfile.BadZipFile, zlib.error, NotImplementedError, ValueError, OSError, EOFError) as err:
            raise BankFileError(f"{path}: model of action {e['name']!r} unreadable ({err})") from None
        models[e["name"]] = model_from_arrays(inner, f"{path}[{e['name']}]")
    return _finish(header, models, str(path))


def is_bank(path: str | os.PathLike) -> bool:
    """True for a bank directory or a single-file bank (cheap check, no validation)."""
    path = Path(path)
    if path.is_dir():
        return (path / BANK_JSON).is_file()
    if path.is_file() and path.suffix.lower() == ".npz":
        try:
            with zipfile.ZipFile(path) as z:
                return "bank_json.npy" in z.namelist()
        except (zipfile.BadZipFile, OSError):
            return False
    return False


__all__ = ["ModelBank", "BankFileError", "save_bank", "load_bank", "add_to_bank", "is_bank", "check_action_name",
           "BANK_FORMAT", "BANK_VERSION"]
