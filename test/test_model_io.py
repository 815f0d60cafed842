"""Model files: round trip, no pickle, and every kind of corruption gives ModelFileError."""
import io
import json
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from dtm_labeler.model import io as mio
from dtm_labeler.model.io import ModelFileError, load_model, model_from_arrays, model_to_bytes, save_model
from dtm_labeler.training.train import TrainConfig, canonical_states, train_model
from dtm_labeler.motion.synthetic import synthesize


@pytest.fixture(scope="module")
def trained():
    clips = [synthesize(duration=1.5, seed=s, heading=h, noise_mm=2) for s, h in [(0, 0.0), (1, 2.0)]]
    model, _ = train_model(clips, TrainConfig(mixture="fixed", k_fixed=2, structure="given", broad_component=True))
    test = synthesize(duration=0.3, seed=9, heading=-1.0, noise_mm=2)
    return model, canonical_states(test, model.heading_pairs)


def _arrays(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _write(path, arrays):
    np.savez(path, **arrays)
    return path


def test_round_trip_identical_log_likelihoods(trained, tmp_path):
    model, states = trained
    path = save_model(model, tmp_path / "sub" / "m.npz")
    assert path.is_file() and not list(path.parent.glob("*.tmp"))        # atomic write leaves no temp file
    back = load_model(path)
    assert back.labels == model.labels
    assert back.structure == model.structure
    assert np.array_equal(back.heading_pairs, model.heading_pairs)
    assert back.settings == model.settings
    assert back.provenance["config"] == json.loads(json.dumps(model.provenance["config"]))
    for a, b in zip(model.mixtures, back.mixtures):
        for k in ("weights", "means", "covariances"):
            assert np.array_equal(getattr(a, k), getattr(b, k))
    ll = model.frame_log_likelihood(states)
    assert np.isfinite(ll[1:]).all()
    assert np.array_equal(back.frame_log_likelihood(states), ll)
    # states with missing points too
    s = states.copy()
    s[::2, 3] = np.nan
    assert np.array_equal(back.frame_log_likelihood(s), model.frame_log_likelihood(s))
    # bytes are deterministic for the same model
    assert model_to_bytes(back) == model_to_bytes(load_model(path))


def test_file_is_plain_numeric_npz(trained, tmp_path):
    model, _ = trained
    path = save_model(model, tmp_path / "m.npz")
    arrays = _arrays(path)                          # would raise on any object (pickled) array
    assert "header" in arrays
    for k, a in arrays.items():
        assert a.dtype != object and np.issubdtype(a.dtype, np.number), (k, a.dtype)
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            assert info.filename.endswith(".npy")
            assert b"pickle" not in zf.read(info)[:128].lower()
    header = json.loads(bytes(arrays["header"]).decode())
    assert header["format"] == "dtm_labeler.model" and header["format_version"] == 9 and header["generic_body"] is False
    assert header["components"] == [2] * 12 and header["broad"] and header["body"]["pairs"] == 91
    assert arrays["body_rigid_pairs"].shape == (0, 2)           # joint centres: no rigid marker pairs
    assert ({f"tri{t}_{k}" for t in range(12) for k in ("weights", "means", "covariances")} | {"header"}
            | {f"body_{k}" for k in ("pairs", "kind", "lo", "hi", "within_sd", "between_sd", "quads", "quad_sign",
                                    "twists", "rigid_pairs", "rigid_length", "rigid_spread", "orders",
                                    "reach_off_edges", "take_orders")} | {"broad_weights"}
            | {f"broad{t}_{k}" for t in range(12) for k in ("mean", "covariance")}) == set(arrays)


def _corrupt_cases(good):
    header = json.loads(bytes(good["header"]).decode())

    def with_header(**changes):
        h = dict(header, **changes)
        return dict(good, header=np.frombuffer(json.dumps(h).encode(), dtype=np.uint8))

    def drop(*keys):
        return {k: v for k, v in good.items() if k not in keys}

    def replace(key, value):
        return dict(good, **{key: value})

    m0 = good["tri0_means"]
    c0 = good["tri0_covariances"]
    return {
        "wrong format name": (with_header(format="something.else"), "does not name format"),
        "wrong version": (with_header(format_version=10), "format version 10 is not supported"),
        "body arrays missing": (drop("body_lo"), "body terms lack"),
        "body pair out of range": (replace("body_pairs", good["body_pairs"] + 50), "inconsistent model"),
        "twist label out of range": (replace("body_twists", good["body_twists"] + 50), "inconsistent model"),
        "rigid pair out of range": (dict(good, body_rigid_pairs=np.array([[0, 99]]), body_rigid_length=np.array([0.1]),
                                         body_rigid_spread=np.array([0.003])), "inconsistent model"),
        "rigid pair without a length": (dict(good, body_rigid_pairs=np.array([[0, 1]])), "inconsistent model"),
        "bar order out of range": (replace("body_orders", np.array([[0, 1, 99]])), "inconsistent model"),
        "bar order repeats a label": (replace("body_orders", np.array([[0, 1, 1]])), "inconsistent model"),
        "take bar order out of range": (replace("body_take_orders", np.array([[0, 1, 99]])), "inconsistent model"),
        "reach flags not one per pair": (replace("body_reach_off_edges", np.ones(3, dtype=np.int64)),
                                         "inconsistent model"),
        "reach flag not 0 or 1": (replace("body_reach_off_edges", good["body_reach_off_edges"] + 2),
                                  "inconsistent model"),
        "broad arrays missing": (drop("broad3_covariance"), "broad components lack"),
        "broad weight not in (0, 1)": (replace("broad_weights", good["broad_weights"] + 1.0), "inconsistent model"),
        "no header": (drop("header"), "no header"),
        "header not json": (replace("header", np.frombuffer(b"\xff\xfe{", dtype=np.uint8)), "corrupt header"),
        "header a list": (replace("header", np.frombuffer(b"[1, 2]", dtype=np.uint8)), "does not name format"),
        "missing triangle": (drop("tri5_weights", "tri5_means", "tri5_covariances"),
                             "no mixture stored for triangle 5"),
        "missing key": (drop("tri3_covariances"), "inconsistent model"),
        "means wrong dim": (replace("tri0_means", m0[:, :14]), "inconsistent model"),
        "both wrong dim": (dict(good, tri0_means=m0[:, :14], tri0_covariances=c0[:, :14, :14]), "dimension 14"),
        "weights count": (replace("tri2_weights", np.array([1.0])), "inconsistent model"),
        "nan covariance": (replace("tri1_covariances", np.full_like(c0, np.nan)), "inconsistent model"),
        "not pd": (replace("tri1_covariances", -c0), "inconsistent model"),
        "labels missing": (with_header(labels=None), "inconsistent model"),
        "too few labels": (with_header(labels=header["labels"][:-1]), "inconsistent model"),
        "invalid structure": (with_header(structure=[[0, 1, 1]] + header["structure"][1:]), "repeats a vertex"),
        "heading pair out of range": (with_header(heading_pairs=[[0, 99]]), "heading pair"),
        "text array": (replace("tri0_weights", np.array(["a", "b"])), "inconsistent model"),
    }


def test_corrupt_contents_raise_readable_errors(trained, tmp_path):
    model, _ = trained
    good = _arrays(save_model(model, tmp_path / "good.npz"))
    assert load_model(_write(tmp_path / "again.npz", good)).labels == model.labels      # writer is fine
    for name, (arrays, message) in _corrupt_cases(good).items():
        path = _write(tmp_path / (name.replace(" ", "_") + ".npz"), arrays)
        with pytest.raises(ModelFileError) as e:
            load_model(path)
        assert message in str(e.value), (name, str(e.value))
        assert path.name in str(e.value), name                     # names the file


def test_corrupt_bytes_raise_model_file_error(trained, tmp_path):
    model, _ = trained
    data = model_to_bytes(model)
    rng = np.random.default_rng(0)
    cases = {
        "truncated": data[: len(data) // 2],
        "truncated_tail": data[:-10],
        "random": rng.integers(0, 256, 5000, dtype=np.uint8).tobytes(),
        "empty": b"",
        "text": b"this is not a model\n",
        "flipped": data[:200] + bytes(b ^ 0xFF for b in data[200:400]) + data[400:],
    }
    for name, blob in cases.items():
        p = tmp_path / f"{name}.npz"
        p.write_bytes(blob)
        with pytest.raises(ModelFileError, match=p.name):
            load_model(p)
    with pytest.raises(ModelFileError, match="no such model file"):
        load_model(tmp_path / "nope.npz")
    with pytest.raises(ModelFileError):
        load_model(tmp_path)                                       # a directory


def test_pickled_object_array_is_refused(trained, tmp_path):
    model, _ = trained
    good = _arrays(save_model(model, tmp_path / "good.npz"))
    bad = dict(good, tri0_weights=np.array([{"evil": 1}, None], dtype=object))
    path = tmp_path / "pickled.npz"
    np.savez(path, **bad)                                          # allow_pickle on write by default
    with pytest.raises(ModelFileError):
        load_model(path)


def test_model_from_arrays_direct():
    with pytest.raises(ModelFileError, match="mine: no header"):
        model_from_arrays({}, "mine")
    assert mio.FORMAT_VERSION == 9 and mio.READABLE_VERSIONS == (1, 2, 3, 4, 5, 6, 7, 8, 9)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_fuzzed_files_load_or_raise_model_file_error(trained, tmp_path, data):
    """Any damage (bit flips, truncation, overwritten blocks) either still loads a valid model
    or raises ModelFileError -- never zlib.error, NotImplementedError, KeyError, ..."""
    model, _ = trained
    blob = bytearray(model_to_bytes(model))
    kind = data.draw(st.sampled_from(["flip", "truncate", "block"]))
    if kind == "flip":
        for i in data.draw(st.lists(st.integers(0, len(blob) - 1), min_size=1, max_size=4)):
            blob[i] ^= 1 << data.draw(st.integers(0, 7))
    elif kind == "truncate":
        blob = blob[: data.draw(st.integers(0, len(blob) - 1))]
    else:
        i = data.draw(st.integers(0, len(blob) - 40))
        blob[i:i + 40] = data.draw(st.binary(min_size=40, max_size=40))
    p = tmp_path / "fuzz.npz"
    p.write_bytes(bytes(blob))
    try:
        back = load_model(p)
    except ModelFileError as e:
        assert p.name in str(e)
    else:
        assert back.labels == model.labels


def test_a_damaged_npy_header_raises_model_file_error(trained, tmp_path):
    """A member whose .npy header dict is damaged (numpy parses it as a Python literal: a
    SyntaxError or tokenize.TokenError, found by the fuzz test above) is a ModelFileError."""
    model, _ = trained
    src = zipfile.ZipFile(io.BytesIO(model_to_bytes(model)))
    for cut in (b"'shape'", b"'descr'"):
        out = tmp_path / "damaged.npz"
        with zipfile.ZipFile(out, "w") as z:
            for info in src.infolist():
                data = src.read(info)
                z.writestr(info.filename, data.replace(cut, cut[:-1], 1) if info.filename == "header.npy" else data)
        with pytest.raises(ModelFileError, match="damaged.npz: not a dtm_labeler model file"):
            load_model(out)
