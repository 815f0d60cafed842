"""dtm-eval: the Tables 1-2 model tests, one Table-3 cell, Fig. 10 curves and the CLI end to end
on a small real subset (CMU walk 07_01)."""
import json

import numpy as np
import pytest

from dtm_labeler.cli.evaluate import main as eval_main
from dtm_labeler.evaluation import experiments as ex
from dtm_labeler.evaluation import model_tests as mt
from dtm_labeler.motion import load_clip


@pytest.fixture(scope="module")
def walk(data_dir):
    clip = load_clip(data_dir / mt.SEQUENCES[0].path, points="body14")
    train, test, cut = mt.split_clip(clip)
    models = {k: mt.train_kind(train, k)[0] for k in mt.MIXTURE_KINDS}
    return dict(clip=clip, train=train, test=test, cut=cut, models=models)


def _fractions(xs):
    xs = np.asarray(xs, dtype=float)
    return xs.size > 0 and np.all((xs >= 0) & (xs <= 1))


def test_split_is_nine_tenths(walk):
    assert walk["train"].n_frames == walk["cut"]
    assert walk["train"].n_frames + walk["test"].n_frames == walk["clip"].n_frames
    assert abs(walk["test"].n_frames - 0.1 * walk["clip"].n_frames) <= 1


def test_tables12_on_walk(walk):
    clip, cut = walk["clip"], walk["cut"]
    states = mt.held_out_states(clip, walk["models"]["mdl"].labels, np.arange(cut, clip.n_frames))
    assert states.shape[1:] == (14, 6) and states.shape[0] >= 20
    res = mt.triangle_tests(walk["models"], states)
    assert res["candidates_method1"] == 14 * 13 * 12
    for kind in mt.MIXTURE_KINDS:
        r = res[kind]
        for key in ("method1", "method1_12", "method2"):
            assert len(r[key]) == 12 and _fractions(r[key])
        assert all(rank >= 1 for rank in r["method1_mean_rank"])
        # restricting the candidates to the 12 true triples can only make method 1 easier
        assert all(a >= b - 1e-12 for a, b in zip(r["method1_12"], r["method1"]))
    # mixtures chosen by MDL model the walk at least as well as one Gaussian per triangle
    assert res["mdl"]["mean_method1"] >= res["single"]["mean_method1"]
    assert res["mdl"]["mean_method1"] > 0.8 and res["mdl"]["mean_method2"] > 0.8


def test_table3_cell_single_and_stream(walk):
    model = walk["models"]["mdl"]
    frames = ex.spread_frames(walk["test"].n_frames, 3)
    assert list(frames) == sorted(set(frames)) and frames.min() >= 1
    cell = ex.label_single(model, walk["test"], frames, "cbga", seed=0)
    assert cell["frames"] == len(frames)
    assert cell["points"] == 14 * len(frames)
    assert 0.0 <= cell["accuracy"] <= 1.0 and cell["accuracy"] > 0.8
    assert cell["search_checked"] == len(frames) and 0 <= cell["search_errors"] <= len(frames)
    assert cell["latency_ms"]["p50"] > 0
    occluded = ex.label_single(model, walk["test"], frames, "cbga", occlude=2, seed=0)
    assert occluded["points"] == 12 * len(frames)
    st = ex.label_stream(model, walk["test"].slice(0, 8), "cbga", window=3, seed=0)
    assert st["frames"] == 8 and 0.0 <= st["accuracy"] <= 1.0


def test_generation_curves(walk):
    r = ex.generation_curves(walk["models"]["mdl"], walk["test"], [4], generations=5, population=16, seed=0)
    for k in ("mean_cbga", "mean_sga"):
        assert len(r[k]) == 6 and all(np.diff(r[k]) >= -1e-9)       # best-so-far never drops (elitism)
    assert np.isfinite(r["mean_truth"])


def test_cli_quick_tables12(data_dir, tmp_path):
    out = tmp_path / "eval"
    rc = eval_main(["--quick", "--only", "tables12", "--data", str(data_dir), "--out", str(out), "--jobs", "1",
                    "--quiet"])
    assert rc == 0
    text = (out / "report.md").read_text()
    for needle in ("## Tables 1-2", "Table 1 — method 1", "Table 2 — method 2", "| Methods | W1 ours",
                   "| JG |", "| JMG |", "| JMGW |", "paper W1", "How to reproduce"):
        assert needle in text, needle
    for png in ("fig8_method1_per_triangle.png", "fig9_method2_per_triangle.png"):
        p = out / png
        assert p.is_file() and p.stat().st_size > 1000
        assert f"]({png})" in text
    data = json.loads((out / "results.json").read_text())
    t12 = data["results"]["tables12"]
    assert "W1" in t12
    for kind in mt.MIXTURE_KINDS:
        assert 0.0 <= t12["W1"][kind]["mean_method1"] <= 1.0
    assert data["meta"]["sections"] == ["tables12"]


def test_cli_rejects_unknown_section(data_dir, tmp_path, capsys):
    assert eval_main(["--only", "tables13", "--data", str(data_dir), "--out", str(tmp_path)]) == 2
    assert "unknown section" in capsys.readouterr().err
    assert eval_main(["--data", str(tmp_path / "nowhere"), "--out", str(tmp_path)]) == 2
