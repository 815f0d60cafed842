"""``dtm-calibrate`` and ``dtm-label --calibrate`` as a user runs them (their ``main`` with a
command line, on real recordings)."""
import json

import numpy as np
import pytest

from dtm_labeler.cli.calibrate import main as calibrate_main
from dtm_labeler.cli.label import main as label_main
from dtm_labeler.model.body import SEGMENT
from dtm_labeler.model.io import load_model, save_model
from dtm_labeler.motion import load_clip
from dtm_labeler.training.train import TrainConfig, train_model

LAMBADA = "cmu_skeletal/asf_amc/cmu_55_02_lambada-dance_s55.amc"
PIROUETTE = "cmu_skeletal/asf_amc/cmu_s05_pirouette-dance.amc"
FAST = dict(mixture="fixed", k_fixed=2, structure="given", seed=0)


class _Run:
    def __init__(self, stdout, stderr):
        self.stdout, self.stderr = stdout, stderr


@pytest.fixture
def run(capsys):
    def go(tool, *args, rc=0):
        main = {"dtm-calibrate": calibrate_main, "dtm-label": label_main}[tool]
        got = main([str(a) for a in args])
        out = capsys.readouterr()
        assert got == rc, f"rc={got}\nstdout:\n{out.out}\nstderr:\n{out.err}"
        return _Run(out.out, out.err)
    return go


@pytest.fixture(scope="module")
def models(data_dir, tmp_path_factory):
    clip = load_clip(data_dir / LAMBADA, points="body14").slice(0, 360)
    out = tmp_path_factory.mktemp("calib")
    body, _ = train_model([clip], TrainConfig(**FAST))
    v1, _ = train_model([clip], TrainConfig(**FAST, body_terms=False, broad_component=False))
    return save_model(body, out / "body.npz"), save_model(v1, out / "v1.npz"), out


def test_dtm_calibrate_sets_the_new_persons_lengths(models, data_dir, run):
    """Subject 5's forearm is 5 cm shorter than subject 55's: after calibration on 2 s of the
    pirouette (the capture's own labels) the segment lengths are subject 5's."""
    model_path, _, out = models
    p = run("dtm-calibrate", model_path, data_dir / PIROUETTE, "--frames", "0:240", "--labels", "capture",
             "--out", out / "s5.npz", "--json")
    summary = json.loads(p.stdout)
    assert summary["source"] == "capture labels" and summary["segments"] == summary["segments_total"] > 8
    assert summary["frame_range"] == [0, 240]
    before, after = load_model(model_path), load_model(out / "s5.npz")
    clip = load_clip(data_dir / PIROUETTE, points="body14").select(after.labels).slice(0, 240)
    seg = after.body.kind == SEGMENT
    u, v = after.body.pairs[seg, 0], after.body.pairs[seg, 1]
    true = np.median(np.linalg.norm(clip.positions[:, u] - clip.positions[:, v], axis=-1), axis=0)
    assert np.allclose(after.body.lo[seg], true) and np.allclose(after.body.hi[seg], true)
    assert np.abs(before.body.lo[seg] - true).max() > 0.03
    assert after.provenance["calibration"]["capture"].endswith("cmu_s05_pirouette-dance.amc")


def test_dtm_label_calibrate_scores_the_rest(models, data_dir, run):
    model_path, _, _ = models
    """The first 40 frames of the range calibrate (labelled by the model itself), the 30 after
    them are labelled and scored."""
    p = run("dtm-label", model_path, data_dir / LAMBADA, "--frames", "1000:1070", "--calibrate", "0:40", "--json",
            "--quiet")
    out = json.loads(p.stdout)
    item = out["inputs"][0]
    assert item["frame_range"] == [1040, 1070] and out["frames"] == 30
    cal = item["calibration"]
    assert cal["source"] == "self-labelled" and cal["frames"] == [1000, 1040] and 0.8 < cal["confirmed_fraction"] <= 1
    assert cal["segments"] == cal["segments_total"] and abs(cal["scale"] - 1) < 0.02    # the same person
    assert out["accuracy"] > 0.9


def test_v1_model_cannot_be_calibrated(models, data_dir, run):
    _, v1_path, out = models
    p = run("dtm-calibrate", v1_path, data_dir / PIROUETTE, "--frames", "0:60", "--out", out / "x.npz", rc=2)
    assert "no body terms" in p.stderr
    p = run("dtm-label", v1_path, data_dir / PIROUETTE, "--frames", "0:60", "--calibrate", "0:60", rc=2)
    assert "leaves no frames" in p.stderr


def test_dtm_train_calibrate_makes_the_takes_person_model(data_dir, tmp_path, capsys):
    """``dtm-train --calibrate``: the model comes out calibrated to the training takes' person
    (segment terms applied), with lengths measured on those takes."""
    from dtm_labeler.cli.train import main as train_main
    out = tmp_path / "m.npz"
    args = [str(data_dir / LAMBADA), "--frames", "0:360", "--mixture", "fixed", "--k-fixed", "2",
            "--structure", "given", "--quiet"]
    assert train_main(args + ["--out", str(out), "--calibrate", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    cal = summary["calibration"]
    assert cal["source"] == "training takes" and cal["frames"] == 360 and cal["segments"] > 0
    model = load_model(out)
    assert model.body.calibration and model.provenance["calibration"]["source"] == "training takes"
    assert SEGMENT in model.body.applied_kinds
    assert train_main(args + ["--out", str(tmp_path / "g.npz")]) == 0
    generic = load_model(tmp_path / "g.npz")
    assert not generic.body.calibration and SEGMENT not in generic.body.applied_kinds
    capsys.readouterr()
