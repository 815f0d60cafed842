"""Archives (issue 14, part c): many takes with --jobs (local processes) and --dask local (a real
LocalCluster); the same figures as a serial run, one entry per take."""
import contextlib
import io
import json
import os

import numpy as np
import pytest

from dtm_labeler.cli.label import main as label_main
from dtm_labeler.evaluation.archive import JobRunner
from dtm_labeler.model.io import save_model
from dtm_labeler.motion.c3d_write import write_c3d
from dtm_labeler.motion.load import load_clip
from dtm_labeler.training.train import TrainConfig, train_model

UPPER = ["LFHD", "RFHD", "C7", "CLAV", "LSHO", "RSHO", "LELB", "RELB", "LWRA", "RWRA", "LFWT", "RFWT"]
SAME = ("frames", "points", "correct", "accuracy", "ghosts", "ghost_rejection", "swaps", "search_errors",
        "search_checked", "per_label")


@pytest.fixture(scope="module")
def archive(data_dir, tmp_path_factory):
    """A model of 12 HDM05 markers and an archive of 4 short takes (2 in a sub-folder), each
    with the two knee markers as '*' ghosts."""
    hdm = load_clip(data_dir / "markers_c3d/hdm05_bd_05-01_01_120.c3d")
    root = tmp_path_factory.mktemp("archive")
    model, _ = train_model([hdm.select(UPPER).slice(1200, 1900)], TrainConfig(seed=0, k_max=2, structure="greedy"))
    model_path = save_model(model, root / "upper12.npz")
    takes = root / "takes"
    for i, a in enumerate((1950, 2100, 2250, 2400)):
        c = hdm.select(UPPER + ["LKNE", "RKNE"]).slice(a, a + 30)
        write_c3d(takes / ("sub" if i >= 2 else ".") / f"take{i}.c3d", c.positions, UPPER + ["*0", "*1"], c.rate)
    return model_path, takes


def _run(*args) -> dict:
    """``dtm-label ARGS --json --quiet`` in this process: its JSON, and its exit status as ``rc``."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = label_main([str(a) for a in args] + ["--json", "--quiet"])
    out = json.loads(buf.getvalue())
    out["rc"] = rc
    return out


@pytest.fixture(scope="module")
def serial(archive) -> dict:
    """The archive labelled in this process, one take after another (what --jobs and --dask
    must reproduce); run once for the module."""
    return _run(*archive)


def _same_figures(a: dict, b: dict) -> None:
    assert a["rc"] == b["rc"] == 0 and len(a["inputs"]) == len(b["inputs"]) == 4
    assert [x["source"] for x in a["inputs"]] == [x["source"] for x in b["inputs"]]
    for key in SAME:
        assert a[key] == b[key], key
        for x, y in zip(a["inputs"], b["inputs"]):
            assert key == "per_label" or x[key] == y[key], key
    me = f":{os.getpid()}"
    assert all(x["worker"].endswith(me) for x in a["inputs"])
    workers = {x["worker"] for x in b["inputs"]}                   # other processes labelled the takes
    assert not any(w.endswith(me) for w in workers) and 1 <= len(workers) <= 2


def test_jobs_give_the_serial_figures(archive, serial, tmp_path):
    model, takes = archive
    assert serial["ghosts"] == 4 * 30 * 2 and serial["accuracy"] > 0.8
    jobs = _run(model, takes, "--jobs", 2, "--out", tmp_path / "labelled", "--out-format", "csv")
    _same_figures(serial, jobs)
    written = sorted(p.relative_to(tmp_path / "labelled").as_posix() for p in (tmp_path / "labelled").rglob("*.csv"))
    assert written == ["sub/take2.csv", "sub/take3.csv", "take0.csv", "take1.csv"]
    back = load_clip(tmp_path / "labelled" / "sub" / "take3.csv")
    assert back.names == tuple(UPPER) and back.n_frames == 30


def test_dask_local_gives_the_serial_figures(archive, serial):
    model, takes = archive
    _same_figures(serial, _run(model, takes, "--jobs", 2, "--dask", "local"))


def test_a_bad_take_does_not_stop_the_archive(archive, tmp_path):
    model, takes = archive
    bad = tmp_path / "broken.c3d"
    bad.write_bytes(b"not a c3d file")
    out = _run(model, takes / "take0.c3d", bad, "--jobs", 2)
    assert out["rc"] == 1 and out["errors"] == 1
    assert "cannot read C3D" in out["inputs"][1]["error"] and out["inputs"][0]["frames"] == 30
    assert out["frames"] == 30


def test_job_runner_keeps_order_and_reports_progress():
    seen = []
    with JobRunner(workers=2) as r:
        out = r.map(pow, [2, 3, 4, 5], 2, progress=lambda d, t, res: seen.append((d, t)))
        again = r.map(pow, [6], 2)
    assert out == [4, 9, 16, 25] and again == [36]
    assert [d for d, _ in seen] == [1, 2, 3, 4] and {t for _, t in seen} == {4}
    np.testing.assert_equal(JobRunner().map(pow, [7], 2), [49])
