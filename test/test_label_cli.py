"""``dtm-label`` as a user runs it: a subprocess on a model trained from a real recording. The
usage errors run ``main`` in this process (the same parser, messages and exit status, without
an interpreter start each); one of them also runs as a subprocess."""
import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

from dtm_labeler.model.io import save_model
from dtm_labeler.training.train import TrainConfig, train_model
from dtm_labeler.motion import load_clip, to_point_set

WALK = "cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh"
TEST_FRAMES = "90%:"          # 316 motion frames: 284..315 -> 32 frames


def _cmd() -> list[str]:
    script = Path(sys.executable).parent / "dtm-label"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "dtm_labeler.cli.label"]


def run_label(*args, check_rc=0):
    p = subprocess.run(_cmd() + [str(a) for a in args], capture_output=True, text=True, timeout=300)
    if check_rc is not None:
        assert p.returncode == check_rc, f"rc={p.returncode}\nstdout:\n{p.stdout}\nstderr:\n{p.stderr}"
    return p


def label_in_process(capsys, *args) -> tuple[int, str]:
    """``dtm-label ARGS`` through :func:`dtm_labeler.cli.label.main`: (exit status, stderr)."""
    from dtm_labeler.cli.label import main
    try:
        rc = main([str(a) for a in args])
    except SystemExit as e:                       # argparse's usage errors
        rc = e.code
    return rc, capsys.readouterr().err


@pytest.fixture(scope="session")
def walk_path(data_dir) -> Path:
    return data_dir / WALK


@pytest.fixture(scope="session")
def walk_model(walk_path, tmp_path_factory) -> Path:
    clip = to_point_set(load_clip(walk_path), "body14")
    clip = clip.slice(0, int(round(0.9 * clip.n_frames)))
    model, _ = train_model([clip], TrainConfig(seed=0))
    return save_model(model, tmp_path_factory.mktemp("models") / "walk14.npz")


@pytest.fixture(scope="session")
def joint_model(walk_path, tmp_path_factory) -> Path:
    """A small model on raw BVH joint names (not derivable from marker files)."""
    clip = load_clip(walk_path).select(["LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg"]).slice(0, 200)
    model, _ = train_model([clip], TrainConfig(seed=0, structure="greedy", mixture="single"))
    return save_model(model, tmp_path_factory.mktemp("models") / "joints4.npz")


@pytest.fixture(scope="session")
def corrupted_json(walk_model, walk_path):
    p = run_label(walk_model, walk_path, "--frames", TEST_FRAMES, "--occlude", 1, "--clutter", 2,
                  "--noise-mm", 1, "--seed", 3, "--json")
    return json.loads(p.stdout)


def test_json_keys_and_types(corrupted_json):
    d = corrupted_json
    for key, typ in [("method", str), ("mode", str), ("frames", int), ("labels", int), ("accuracy", float),
                     ("ghost_rejection", float), ("swaps_per_min", float), ("search_errors", int),
                     ("search_error_rate", float), ("latency_ms", dict), ("fps", float), ("per_label", dict),
                     ("inputs", list)]:
        assert key in d, key
        assert isinstance(d[key], typ), (key, d[key])
    assert d["method"] == "cbga" and d["mode"] == "stream"
    assert d["frames"] == 32 and d["labels"] == 14
    assert set(d["latency_ms"]) >= {"p50", "p99", "max"}
    assert 0 < d["latency_ms"]["p50"] <= d["latency_ms"]["p99"] <= d["latency_ms"]["max"]
    assert d["fps"] > 0
    assert 0 <= d["search_errors"] <= d["frames"]
    assert 0.0 <= d["ghost_rejection"] <= 1.0
    assert d["swaps_per_min"] >= 0
    assert len(d["per_label"]) == 14 and "lknee" in d["per_label"]
    assert d["inputs"][0]["source"].endswith("cmu_07_01_walk_s07.bvh")
    assert d["inputs"][0]["frame_range"] == [284, 316]
    assert d["occlude"] == 1 and d["clutter"] == 2 and d["noise_mm"] == 1.0


def test_json_sanity_labels_mostly_right(corrupted_json):
    # one hidden point, two ghosts, 1 mm noise on a walk seen in training: labels mostly right
    assert corrupted_json["accuracy"] > 0.8
    assert corrupted_json["ghost_rejection"] > 0.5


def test_clean_stream_is_labelled_and_ghost_rejection_null(walk_model, walk_path):
    d = json.loads(run_label(walk_model, walk_path, "--frames", TEST_FRAMES, "--json", "--quiet").stdout)
    assert d["ghost_rejection"] is None
    assert d["accuracy"] > 0.95
    assert d["swaps_per_min"] < 60


def test_single_mode_greedy(walk_model, walk_path):
    d = json.loads(run_label(walk_model, walk_path, "--frames", "300:304", "--mode", "single", "--method",
                             "greedy", "--json").stdout)
    assert d["mode"] == "single" and d["method"] == "greedy" and d["frames"] == 4
    assert d["accuracy"] > 0.9


def test_csv_rows(walk_model, walk_path, tmp_path):
    out = tmp_path / "labels.csv"
    p = run_label(walk_model, walk_path, "--frames", "300:306", "--occlude", 2, "--clutter", 1, "--out-points", out)
    assert "accuracy" in p.stdout and "latency" in p.stdout          # human summary
    with open(out, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["frame", "time", "x", "y", "z", "true_label", "label", "confidence", "track_id",
                             "search_label"]
    assert len(rows) == 6 * (14 - 2 + 1)
    frames = sorted({int(r["frame"]) for r in rows})
    assert frames == list(range(300, 306))
    assert float(rows[0]["time"]) == pytest.approx(300 / 120.0, abs=1e-5)
    names = {"head", "neck", "lshoulder", "rshoulder", "lelbow", "relbow", "lwrist", "rwrist", "lhip", "rhip",
             "lknee", "rknee", "lankle", "rankle"}
    for r in rows:
        assert r["true_label"] in names | {""}
        assert r["label"] in names | {""}
        assert 0.0 <= float(r["confidence"]) <= 1.0
        assert abs(float(r["z"])) < 3.0
    per_frame = {}
    for r in rows:
        per_frame.setdefault(r["frame"], []).append(r["true_label"])
    for labs in per_frame.values():
        assert labs.count("") == 1                      # one ghost per frame
        assert len(set(labs) - {""}) == 12              # 12 distinct visible markers


def test_two_inputs_pool_frames(walk_model, walk_path, data_dir):
    run_path = data_dir / "cmu_skeletal/bvh_from_fbx/cmu_09_11_run_s09.bvh"
    d = json.loads(run_label(walk_model, walk_path, run_path, "--frames", "0:5", "--mode", "single",
                             "--json").stdout)
    assert d["frames"] == 10 and len(d["inputs"]) == 2
    assert [x["frames"] for x in d["inputs"]] == [5, 5]


@pytest.mark.parametrize("args, message", [
    (["--frames", "90"], "--frames"),
    (["--frames", "50%:10%"], "selects no frames"),
    (["--occlude", "-1"], ">= 0"),
    (["--window", "0"], "window"),
])
def test_bad_options_exit_2(walk_model, walk_path, args, message, capsys):
    rc, err = label_in_process(capsys, walk_model, walk_path, *args)
    assert rc == 2 and message in err, err


def test_missing_files_exit_2(walk_model, walk_path, tmp_path, capsys):
    p = run_label(walk_model, tmp_path / "nope.bvh", check_rc=2)
    assert "no such file" in p.stderr and "Traceback" not in p.stderr
    rc, err = label_in_process(capsys, tmp_path / "nope.npz", walk_path)
    assert rc == 2 and "nope.npz" in err, err
    rc, err = label_in_process(capsys, walk_path, walk_path)           # not a model file
    assert rc == 2 and "model" in err, err


def test_model_labels_not_in_input_exit_2(joint_model, data_dir, capsys):
    rc, err = label_in_process(capsys, joint_model, data_dir / "markers_csv/mct_walk1_28markers_60hz.csv")
    assert rc == 2 and "LeftUpLeg" in err, err


def test_exhaustive_too_large_exit_2(walk_model, walk_path, capsys):
    rc, err = label_in_process(capsys, walk_model, walk_path, "--frames", "0:2", "--method", "exhaustive")
    assert rc == 2 and "exhaustive" in err, err


def test_exhaustive_on_small_model(joint_model, walk_path):
    d = json.loads(run_label(joint_model, walk_path, "--frames", "250:260", "--method", "exhaustive",
                             "--mode", "single", "--json").stdout)
    assert d["labels"] == 4 and d["frames"] == 10
    assert d["search_errors"] == 0                    # exhaustive finds the optimum by construction
