"""Model banks: directory and single-file round trips, label checks, damaged banks, and
``dtm-train --action`` adding an action without touching the other model files."""
import json

import numpy as np
import pytest

from dtm_labeler.cli.train import main as train_main
from dtm_labeler.model.bank import (BankFileError, ModelBank, add_to_bank, is_bank, load_bank, save_bank)
from dtm_labeler.model.features import point_states
from dtm_labeler.training.train import TrainConfig, train_model
from dtm_labeler.motion import load_clip

CFG = TrainConfig(mixture="single", structure="given", yaw_jitter_deg=0.0)
WALK = "cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh"
RUN = "cmu_skeletal/bvh_from_fbx/cmu_09_11_run_s09.bvh"


@pytest.fixture(scope="module")
def clips(data_dir):
    return {"walk": load_clip(data_dir / WALK, points="body14").slice(0, 150),
            "run": load_clip(data_dir / RUN, points="body14").slice(0, 100)}


@pytest.fixture(scope="module")
def models(clips):
    return {a: train_model([c], CFG)[0] for a, c in clips.items()}


def _same(m1, m2, clip):
    s = point_states(clip.positions[:20], clip.rate)
    return np.allclose(m1.frame_log_likelihood(s[1:]), m2.frame_log_likelihood(s[1:]))


@pytest.mark.parametrize("single", [False, True])
def test_round_trip(tmp_path, models, clips, single):
    bank = ModelBank(dict(models), records={"walk": {"sources": [{"path": "x.bvh", "frames": [0, 150]}]}})
    path = tmp_path / ("bank.npz" if single else "bank")
    save_bank(bank, path)
    assert is_bank(path)
    back = load_bank(path)
    assert back.actions == ["walk", "run"] and back.labels == models["walk"].labels
    assert back.records["walk"]["sources"][0]["frames"] == [0, 150]
    for a in models:
        assert _same(back[a], models[a], clips[a])
    if not single:
        header = json.loads((path / "bank.json").read_text())
        assert header["format"] == "dtm_labeler.bank" and header["format_version"] == 1
        assert [e["file"] for e in header["actions"]] == ["walk.npz", "run.npz"]


def test_mismatched_labels_are_refused(models, clips):
    sub = train_model([clips["walk"].select(clips["walk"].names[:13])], TrainConfig(mixture="single", structure="greedy"))[0]
    with pytest.raises(BankFileError, match="labels differ"):
        ModelBank({"walk": models["walk"], "odd": sub})
    bank = ModelBank({"walk": models["walk"]})
    with pytest.raises(BankFileError, match="labels differ"):
        bank.add("odd", sub)
    assert bank.actions == ["walk"]
    # same label set in another order is refused too (assignments would mean other labels)
    order = list(clips["walk"].names)[::-1]
    rev = train_model([clips["walk"].select(order)], TrainConfig(mixture="single", structure="greedy"))[0]
    with pytest.raises(BankFileError, match="different order"):
        ModelBank({"walk": models["walk"], "rev": rev})
    with pytest.raises(BankFileError, match="action name"):
        ModelBank({"../evil": models["walk"]})


def test_damaged_banks(tmp_path, models):
    path = save_bank(ModelBank(dict(models)), tmp_path / "b")
    with pytest.raises(BankFileError, match="no bank.json"):
        load_bank(tmp_path)
    # a model replaced behind the bank's back
    good = (path / "run.npz").read_bytes()
    (path / "run.npz").write_bytes(good[:-10] + b"0123456789")
    with pytest.raises(BankFileError, match="checksum"):
        load_bank(path)
    (path / "run.npz").unlink()
    with pytest.raises(BankFileError, match="missing"):
        load_bank(path)
    (path / "run.npz").write_bytes(good)
    load_bank(path)
    idx = path / "bank.json"
    text = idx.read_text()
    for bad, msg in [("{not json", "corrupt"), (text.replace('"format_version": 1', '"format_version": 9'), "version"),
                     (text.replace("dtm_labeler.bank", "other"), "not a model bank"),
                     (json.dumps({"format": "dtm_labeler.bank", "format_version": 1, "actions": []}), "no actions"),
                     (text.replace('"walk.npz"', '"../walk.npz"'), "outside")]:
        idx.write_text(bad)
        with pytest.raises(BankFileError, match=msg):
            load_bank(path)
    idx.write_text(text)
    single = save_bank(load_bank(path), tmp_path / "one.npz")
    data = single.read_bytes()
    single.write_bytes(data[: len(data) // 2])
    with pytest.raises(BankFileError):
        load_bank(single)


def test_dtm_train_action_adds_without_touching_others(tmp_path, data_dir, capsys):
    bank = tmp_path / "bank"
    common = ["--mixture", "single", "--structure", "given", "--quiet", "--frames", "0:50%"]
    assert train_main([str(data_dir / WALK), "--action", "walk", "--bank", str(bank)] + common) == 0
    walk_bytes = (bank / "walk.npz").read_bytes()
    assert train_main([str(data_dir / RUN), "--action", "run", "--bank", str(bank), "--json"] + common) == 0
    assert (bank / "walk.npz").read_bytes() == walk_bytes               # byte-identical
    b = load_bank(bank)
    assert b.actions == ["walk", "run"]
    rec = b.records["run"]
    assert rec["transitions"] and rec["transitions"][0]["with"] == "walk"   # L2: the new model got the paths
    assert rec["synthesized_frames"] > 0 and b.records["walk"]["transitions"] == []
    assert b.records["walk"]["sources"][0]["frames"] == [0, 158]
    # replace run without transitions: walk still untouched
    assert train_main([str(data_dir / RUN), "--action", "run", "--bank", str(bank), "--no-transitions"] + common) == 0
    assert (bank / "walk.npz").read_bytes() == walk_bytes
    assert load_bank(bank).records["run"]["synthesized_frames"] == 0
    # --retrain-neighbours is the explicit opt-in that rewrites the others
    assert train_main([str(data_dir / RUN), "--action", "run", "--bank", str(bank), "--retrain-neighbours"]
                      + common) == 0
    b = load_bank(bank)
    assert (bank / "walk.npz").read_bytes() != walk_bytes
    assert b.records["walk"]["transitions"][0]["with"] == "run"
    # errors: --action without --bank, bad names, points vs transitions
    assert train_main([str(data_dir / RUN), "--action", "run"] + common) == 2
    assert train_main([str(data_dir / RUN), "--action", "a/b", "--bank", str(bank)] + common) == 2
    assert train_main([str(data_dir / RUN), "--action", "x", "--bank", str(bank), "--points", "all"] + common) == 2


def test_add_to_bank_checks_labels(tmp_path, models, clips):
    add_to_bank(tmp_path / "b", "walk", models["walk"])
    sub = train_model([clips["walk"].select(clips["walk"].names[:13])], TrainConfig(mixture="single", structure="greedy"))[0]
    before = (tmp_path / "b" / "bank.json").read_bytes()
    with pytest.raises(BankFileError):
        add_to_bank(tmp_path / "b", "odd", sub)
    assert (tmp_path / "b" / "bank.json").read_bytes() == before
    assert not (tmp_path / "b" / "odd.npz").exists()


def test_dtm_label_with_a_bank(tmp_path, data_dir, models, capsys):
    from dtm_labeler.cli.label import main as label_main
    save_bank(ModelBank(dict(models)), tmp_path / "b")
    rc = label_main(["--bank", str(tmp_path / "b"), str(data_dir / WALK), str(data_dir / RUN), "--frames", "70%:80%",
                     "--json", "--quiet"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["actions"] == ["walk", "run"] and out["bank_strategy"] == "spread"
    assert out["accuracy"] > 0.9 and 0.0 <= out["active_action_accuracy"] <= 1.0
    assert [i["true_class"] for i in out["inputs"]] == ["walk", "run"]
    assert all(sum(i["active_action_frames"].values()) == i["frames"] for i in out["inputs"])
    # errors: missing bank, damaged bank
    assert label_main(["--bank", str(tmp_path / "nope"), str(data_dir / WALK), "--quiet"]) == 2
