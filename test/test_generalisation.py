"""The generalisation experiment of ``dtm-eval`` on a tiny budget: one cell per variant, the
diagnosis of where the truth loses, the report section and ``--merge``."""
import json

import numpy as np

import pytest


from dtm_labeler.cli.evaluate import _merge_saved
from dtm_labeler.evaluation.plans import make_plan
from dtm_labeler.evaluation import generalisation as gen
from dtm_labeler.evaluation.report import reliability_groups, write_report
from dtm_labeler.training.train import TrainConfig


@pytest.fixture(scope="module")
def cells(data_dir):
    """Subject 55: a lambada model (first 300 frames) labels 0.2 s of a later part of the
    lambada after a 0.25 s calibration window, today's model and the body model."""
    plan = gen.Plan(cases=("D2_halves",), stream_frames=24, single_frames=1, calibration_s=0.25)
    train = gen.load_source(data_dir, "D2@0:0.14", "body14")
    test = gen.load_source(data_dir, "D2@0.5:0.55", "body14")
    out, info = {}, {}
    for variant in ("today", "body"):
        cfg = TrainConfig(mixture="fixed", k_fixed=2, structure="given", seed=0,
                          **(gen.TODAY if variant == "today" else {}))
        model, info[variant] = gen.train_case_model([train], cfg)
        out[variant] = gen.run_variant(model, test, variant, plan, markers=False)
        if variant == "body":
            out["body + calibration"] = gen.run_variant(model, test, "body + calibration", plan, markers=False)
            out["dtm-label default"] = gen.run_variant(model, test, "dtm-label default", plan, markers=False,
                                                       train=[train])
            out["several people"] = gen.run_variant(model, test, "dtm-label default", plan, markers=False)
    return plan, out, info


def test_variants_are_scored_on_the_same_frames(cells):
    plan, out, info = cells
    assert info["body"]["segments"] >= 8 and info["body"]["segment_edges"] >= 8 and info["today"]["segments"] == 0
    for v in gen.VARIANTS:
        r = out[v]
        assert r["calibration_frames"] == 30                      # 0.25 s at 120 Hz
        assert r["stream"]["frames"] == 24 and r["single"]["frames"] == 1
        d = r["diagnosis"]
        assert d["model_errors"] + d["search_errors"] == d["wrong"] <= d["frames"] == 24
    cal = out["body + calibration"]["calibration"]
    assert cal["segments"] == cal["segments_total"] and 0.5 < cal["confirmed_fraction"] <= 1.0
    # dtm-train calibrated the model of one capture to its person; dtm-label keeps that on the capture
    person = out["dtm-label default"]["calibration"]
    assert not person["applied"] and person["person"].startswith("training takes'") and "one capture" in person["person"]
    # a model of several people (no person known): dtm-label self-calibrates on the window, and it holds
    auto = out["several people"]["calibration"]
    assert auto["applied"] and auto["frames"] == 30 and auto["kept_share"] >= 0.9
    assert auto["person"] == "self-calibrated on the window"


def test_report_section_and_merge(cells, tmp_path):
    plan, out, info = cells
    res = {"generalisation": {"plan": gen.plan_dict(plan), "results": {"D2_halves": out},
                              "cases": {"D2_halves": {"group": gen.GROUPS[0], "title": "lambada halves", "note": "",
                                                      "points": "body14", "train": [{"spec": "D2@0:0.14"}],
                                                      "test": {"spec": "D2@0.5:0.55"}, "models": info}}}}
    eplan = vars(make_plan(quick=True))
    meta = {"plan": eplan, "date": "today", "command": "dtm-eval", "wall_s": 1.0, "jobs": 1, "data_dir": "data",
            "machine": {"cpus": 2}, "sections": ["generalisation"]}
    paths = write_report(tmp_path, res, meta)
    text = paths["report"].read_text()
    assert "## Generalisation" in text and "**same person, other take**" in text
    assert "D2@0:0.14 → D2@0.5:0.55" in text and "fig_generalisation.png" in paths["figures"]
    assert (tmp_path / "fig_generalisation.png").stat().st_size > 1000
    assert "By part of the report" in text and "| generalisation: body + calibration |" in text
    # --merge keeps the sections of the saved results that this run did not redo
    saved = json.loads((tmp_path / "results.json").read_text())
    saved["results"]["table3"] = {"kept": True}
    saved["meta"]["sections"] = ["table3", "generalisation"]
    (tmp_path / "results.json").write_text(json.dumps(saved))
    merged, sections = _merge_saved(tmp_path, {"generalisation": {"new": 1}}, ["generalisation"])
    assert merged["table3"] == {"kept": True} and merged["generalisation"] == {"new": 1}
    assert sections == ["table3", "generalisation"]


def test_generic_cases_leave_the_labelled_person_out(data_dir):
    """The generic-model group: each person of the shared data labelled by a model of every
    other person in it -- none of the labelled person's recordings in the training, and the
    marker takes' people give the same 14 body points as the skeletal clips."""
    generic = [c for c in gen.CASES if c.group == gen.GROUPS[3]]
    assert {gen.parse_source(c.test)[0] for c in generic} == {"D3", "W1", "R1", "D2", "mct_dance1", "mct_walk1"}
    for c in generic:
        person = gen.RECORDINGS[gen.parse_source(c.test)[0]][1]
        people = {gen.RECORDINGS[gen.parse_source(s)[0]][1] for s in c.train}
        assert person not in people and len(people) >= 7, c.key
        if person.startswith("MCT"):                 # the MoCap Toolbox takes may be one person
            assert not any(p.startswith("MCT") for p in people), c.key
    skeletal = gen.load_source(data_dir, "W1@0:0.1", "body14")
    for key in gen.MARKER_PEOPLE:
        clip = gen.load_source(data_dir, f"{key}@0:0.2", "body14")
        assert clip.names == skeletal.names, key
        assert np.isfinite(clip.positions).all(-1).mean() > 0.95, key
        # a body, in metres, upright: the head above the ankles by a standing person's height
        head, ankles = clip.names.index("head"), [clip.names.index("lankle"), clip.names.index("rankle")]
        rise = np.nanmedian(clip.positions[:, head, 2] - clip.positions[:, ankles, 2].mean(1))
        assert 1.0 < rise < 2.0, (key, rise)


def test_reliability_groups_pool_by_section_and_variant():
    """The confidence section's breakdown: cells pooled by section, the generalisation section by
    model variant, and everything but its *today* baseline; ECE from the pooled bins."""
    def cell(n, conf, right):
        return {"accuracy": right, "reliability": [[0.9, 1.0, n, conf, right]]}
    cells = [(("markers", "stream", "a"), cell(100, 0.95, 0.95)),
             (("generalisation", "results", "c1", "today", "stream"), cell(100, 0.60, 0.90)),
             (("generalisation", "results", "c1", "body", "stream"), cell(300, 0.90, 0.94)),
             (("generalisation", "results", "c2", "body", "stream"), cell(100, 0.90, 0.98))]
    rows = {g: (k, n, right, conf, ece) for g, k, n, right, conf, ece in reliability_groups(cells)}
    assert list(rows) == ["markers", "generalisation: today", "generalisation: body", "all but generalisation: today"]
    assert rows["generalisation: body"][:2] == (2, 400)
    assert rows["generalisation: body"][2] == pytest.approx(0.95) and rows["generalisation: body"][4] == pytest.approx(0.05)
    assert rows["generalisation: today"][4] == pytest.approx(0.30)
    k, n, right, conf, ece = rows["all but generalisation: today"]
    assert (k, n) == (3, 500) and conf == pytest.approx(0.91) and ece == pytest.approx(abs(0.91 - 0.95))
