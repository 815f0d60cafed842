"""Real captures in, labelled captures out: '*' channels, the C3D/CSV round trip, naming rules,
vertical axis and unit checks (issue 14, part a)."""
import json

import ezc3d
import numpy as np
import pytest

from dtm_labeler.cli.label import main as label_main
from dtm_labeler.cli.train import main as train_main
from dtm_labeler.evaluation.corruption import corrupt_clip
from dtm_labeler.evaluation.labelled_capture import CaptureFormat, assemble
from dtm_labeler.model.io import save_model
from dtm_labeler.motion.asf_amc import find_asf_for
from dtm_labeler.motion.axes import from_z_up, resolve_up_axis, to_z_up
from dtm_labeler.motion.c3d import load_c3d
from dtm_labeler.motion.c3d_write import write_c3d
from dtm_labeler.motion.load import load_clip
from dtm_labeler.motion.markers_csv import write_markers_csv
from dtm_labeler.motion.naming import cmu_subject, common_names, one_subject, split_channels
from dtm_labeler.motion.unlabelled import model_input
from dtm_labeler.training.train import TrainConfig, train_model

HDM = "markers_c3d/hdm05_bd_05-01_01_120.c3d"
QUALISYS = "markers_c3d/qualisys_walk_55markers.c3d"
UPPER = ["LFHD", "RFHD", "C7", "CLAV", "LSHO", "RSHO", "LELB", "RELB", "LWRA", "RWRA", "LFWT", "RFWT"]
GHOSTS = ["LKNE", "RKNE"]                       # real markers the small model does not know


@pytest.fixture(scope="module")
def hdm(data_dir):
    return load_clip(data_dir / HDM)


@pytest.fixture(scope="module")
def upper_model(hdm, tmp_path_factory):
    model, _ = train_model([hdm.select(UPPER).slice(1200, 1900)], TrainConfig(seed=0, k_max=2, structure="greedy"))
    return save_model(model, tmp_path_factory.mktemp("models") / "upper12.npz")


def _unnamed_take(hdm, path, a=2000, b=2060, seed=0):
    """The HDM05 markers UPPER + GHOSTS of frames a:b as a C3D of '*' channels only, in a
    shuffled channel order (names stripped), trajectories cut into pieces across channels."""
    clip = hdm.select(UPPER + GHOSTS).slice(a, b)
    rng = np.random.default_rng(seed)
    P = clip.positions
    F, N, _ = P.shape
    cut = F // 2                                  # each marker changes channel half way
    out = np.full((F, 2 * N, 3), np.nan)
    first = rng.permutation(2 * N)[:N]
    second = rng.permutation(np.setdiff1d(np.arange(2 * N), first))
    out[:cut, first] = P[:cut]
    out[cut:, second] = P[cut:]
    write_c3d(path, out, [f"*{i}" for i in range(2 * N)], clip.rate)
    return clip


# -- loaders: '*' channels, copies, naming ----------------------------------------------------------
def test_star_channels_and_copies(tmp_path):
    rng = np.random.default_rng(1)
    F = 20
    P = rng.normal(size=(F, 6, 3)) * 100 + 1000
    P[:, 3] = P[:, 0]                                     # Bastian:*0 copies A
    P[5:9, 4] = np.nan                                    # a gap in a ghost
    labels = ["S:A", "S:B", "S:C", "Bastian:*0", "*7", ""]
    f = tmp_path / "stars.c3d"
    write_c3d(f, to_z_up(P, "Z") * 1e-3, labels, 100.0, up_axis="Z")
    c = load_c3d(f)
    assert c.names == ("A", "B", "C")
    assert c.meta["unlabelled_names"] == ("Bastian:*0", "*7", "*5")
    assert c.meta["unlabelled_duplicates"] == {"Bastian:*0": "A"}
    mi = model_input(c, ["A", "B"])
    assert mi.named and mi.extra_names == ("C", "*7", "*5")          # unknown marker C + two ghosts, no copy
    assert mi.extra.shape == (F, 3, 3)
    assert model_input(c, ["A", "B"], keep_unlabelled=False).n_extra == 0
    s = corrupt_clip(mi.clip, extra=mi.extra, seed=3)
    assert [f.n_ghosts for f in s] == [3 - (5 <= t < 9) for t in range(F)]
    gid = [set(fr.ids[fr.truth < 0]) for fr in s]
    assert gid[4] != gid[9] and len(gid[4] & gid[9]) == 2           # the ghost back from its gap: a new id
    split = split_channels(["x:*1", "*2", "M"], np.stack([P[:, 1], P[:, 1], P[:, 2]], 1))
    assert split.duplicates == {"*2": "x:*1"} and split.independent == [0]


def test_common_names_rules():
    assert common_names([["a", "b", "c"], ["c", "a", "b"]]) == (["a", "b", "c"], "")
    names, note = common_names([["a", "b", "c", "d"], ["b", "c", "a"]], ["t1.c3d", "t2.c3d"])
    assert names == ["a", "b", "c"] and "leaving out 1 (d)" in note and "t2.c3d" in note
    with pytest.raises(ValueError, match="share no point name.*t1.*x"):
        common_names([["x", "y"], ["a", "b"]], ["t1", "t2"])


def test_training_aligns_channel_orders_and_sets(hdm):
    a = hdm.select(UPPER).slice(0, 300)
    b = hdm.select(UPPER[::-1] + ["LKNE"]).slice(300, 600)
    model, summary = train_model([a, b], TrainConfig(seed=0, k_max=1, structure="greedy", augment_copies=0))
    assert model.labels == tuple(UPPER)
    assert len(summary.notes) == 1 and "LKNE" in summary.notes[0]
    c = hdm.select(["LKNE", "RKNE", "LANK"])
    c.source = "knees.c3d"
    with pytest.raises(ValueError, match="share no point name"):
        train_model([a, c], TrainConfig(seed=0, k_max=1, structure="greedy"))


def test_cmu_take_names_tell_one_subject(data_dir):
    """CMU's own take names and the shared data's ``cmu_`` names say whose takes they are; other
    names do not (dtm-train calibrates to one person only when the names tell)."""
    assert cmu_subject("93_04") == "93" and cmu_subject("cmu_85_12_breakdance_s85_41markers") == "85"
    assert cmu_subject("cmu_s05_pirouette-dance") is None and cmu_subject("hdm05_bd_05-01_01_120") is None
    c3d = data_dir / "markers_c3d"
    assert one_subject([c3d / "cmu_85_02_jumptwist_s85_41markers.c3d",
                        c3d / "cmu_85_12_breakdance_s85_41markers.c3d"]) == "CMU subject 85"
    assert one_subject([c3d / "cmu_85_02_jumptwist_s85_41markers.c3d", c3d / "hdm05_bd_05-01_01_120.c3d"]) is None


def test_cmu_subject_skeleton_and_asf_flag(data_dir, tmp_path):
    src = data_dir / "cmu_skeletal/asf_amc"
    (tmp_path / "55.asf").write_bytes((src / "cmu_55_02_lambada-dance_s55.asf").read_bytes())
    (tmp_path / "05.asf").write_bytes((src / "cmu_s05_pirouette-dance.asf").read_bytes())
    amc = tmp_path / "55_02.amc"
    amc.write_text("\n".join((src / "cmu_55_02_lambada-dance_s55.amc").read_text().splitlines()[:3 + 29 * 40]))
    assert find_asf_for(amc) == tmp_path / "55.asf"                      # CMU naming: subject 55
    other = tmp_path / "lambada.amc"
    other.write_bytes(amc.read_bytes())
    with pytest.raises(ValueError, match="--asf"):
        find_asf_for(other)
    out = tmp_path / "m.npz"
    assert train_main([str(other), "--out", str(out), "--quiet", "--structure", "given", "--mixture", "single"]) == 2
    assert train_main([str(other), "--asf", str(tmp_path / "55.asf"), "--out", str(out), "--quiet",
                       "--structure", "given", "--mixture", "single"]) == 0


# -- vertical axis and units ----------------------------------------------------------------------
def test_y_up_c3d_reads_like_the_z_up_one(hdm, tmp_path):
    clip = hdm.slice(0, 120)                   # a T-pose (as wide as tall): the floor tells the vertical
    with_screen, without = tmp_path / "yup_screen.c3d", tmp_path / "yup.c3d"
    write_c3d(with_screen, clip.positions, clip.names, clip.rate, up_axis="Y")
    write_c3d(without, clip.positions, clip.names, clip.rate, up_axis="Y", write_screen=False)
    c = ezc3d.c3d(str(with_screen))
    assert c["parameters"]["POINT"]["Y_SCREEN"]["value"] == ["+Y"]
    raw = np.transpose(c["data"]["points"][:3], (2, 1, 0))
    assert np.nanmedian(np.ptp(raw, axis=1), axis=0).argmax() == 1           # the file's own Y is vertical
    for f, source in ((with_screen, "POINT:Y_SCREEN"), (without, "body")):
        y = load_clip(f)
        assert (y.meta["up_axis"], y.meta["up_axis_source"]) == ("Y", source)
        np.testing.assert_allclose(y.positions, clip.positions, atol=1e-5)
    wrong = tmp_path / "wrong_screen.c3d"       # a file claiming X is up: the body overrules it, with a note
    write_c3d(wrong, clip.positions, clip.names, clip.rate, up_axis="Z")
    c = ezc3d.c3d(str(wrong))
    c["parameters"]["POINT"]["Y_SCREEN"]["value"] = ("+X",)
    c.write(str(wrong))
    w = load_clip(wrong)
    assert w.meta["up_axis"] == "Z" and "long axis is Z" in w.meta["up_axis_note"]
    forced = load_clip(wrong, up_axis="X")
    np.testing.assert_allclose(forced.positions, to_z_up(from_z_up(clip.positions, "Z"), "X"), atol=1e-5)


def test_units_that_cannot_be_a_body(hdm, tmp_path):
    clip = hdm.slice(0, 60)
    f = tmp_path / "mm_said_m.c3d"
    write_c3d(f, clip.positions * 1000.0, clip.names, clip.rate, units="m")   # millimetre numbers, 'm' declared
    with pytest.raises(ValueError, match=r"look like mm \(pass --units mm\)"):
        load_clip(f)
    np.testing.assert_allclose(load_clip(f, units="mm").positions, clip.positions, atol=1e-5)


def test_rate_disagreeing_with_stamps(tmp_path):
    f = tmp_path / "rate.csv"
    rows = "\n".join(f"{i},{i / 120:.6f},1,2,3" for i in range(10))
    f.write_text("# units mm, Z up, 60 Hz\nframe,time_s,A_x,A_y,A_z\n" + rows + "\n")
    with pytest.raises(ValueError, match="60 Hz but the time stamps advance 8.333 ms"):
        load_clip(f)


def test_csv_round_trip_keeps_units_axes_and_star_columns(hdm, tmp_path):
    clip = hdm.select(UPPER).slice(100, 160)
    P = clip.positions.copy()
    P[3:7, 2] = np.nan
    f = tmp_path / "t.csv"
    write_markers_csv(f, np.concatenate([P, hdm.select(GHOSTS).slice(100, 160).positions], 1),
                      list(UPPER) + ["*0", "*1"], clip.rate, units="cm", up_axis="Y")
    back = load_clip(f)
    assert back.names == tuple(UPPER) and back.meta["unlabelled_names"] == ("*0", "*1")
    assert (back.meta["units"], back.meta["up_axis"], back.rate) == ("cm", "Y", 120.0)
    np.testing.assert_allclose(back.positions, P, atol=1e-7)


def test_star_channel_allocation_follows_tracks():
    fmt = CaptureFormat(rate=100.0)
    z = np.zeros((1, 3))
    frames = [(np.r_[z, z + 1], np.array([0, -1]), np.array([5, 9])),      # track 9 unlabelled -> *0
              (np.r_[z + 1, z + 2], np.array([-1, -1]), np.array([9, 7])),  # 9 keeps *0, 7 gets *1
              (np.r_[z + 2], np.array([-1]), np.array([7])),                # 9 gone: *0 free; 7 keeps *1
              (np.r_[z + 3, z + 4], np.array([-1, -1]), np.array([7, 3]))]  # 3 takes the free *0
    cap = assemble(frames, ["a"], 4, fmt)
    assert cap.names == ("a", "*0", "*1")
    np.testing.assert_array_equal(np.isfinite(cap.positions[..., 0]),
                                  [[True, True, False], [False, True, True], [False, False, True],
                                   [False, True, True]])
    assert cap.positions[3, 1, 0] == 4 and cap.positions[3, 2, 0] == 3


# -- dtm-label: unnamed take in, labelled C3D out -------------------------------------------------
def test_unnamed_c3d_to_labelled_c3d(hdm, upper_model, tmp_path, capsys):
    clip = _unnamed_take(hdm, tmp_path / "unnamed.c3d")
    out = tmp_path / "labelled.c3d"
    assert label_main([str(upper_model), str(tmp_path / "unnamed.c3d"), "--out", str(out), "--json", "--quiet"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["accuracy"] is None and d["inputs"][0]["named"] is False          # nothing to score against
    assert d["inputs"][0]["unlabelled_points"] == 28 and d["frames"] == clip.n_frames
    c = ezc3d.c3d(str(out))
    pt = c["parameters"]["POINT"]
    labels = pt["LABELS"]["value"]
    assert labels[:len(UPPER)] == UPPER and all(x.startswith("*") for x in labels[len(UPPER):])
    assert pt["UNITS"]["value"] == ["mm"] and pt["RATE"]["value"][0] == 120.0
    assert c["header"]["points"]["frame_rate"] == 120.0
    back = load_clip(out)
    right = total = 0
    for name in UPPER:
        want, got = clip.positions[:, clip.index(name)], back.positions[:, back.index(name)]
        right += int((np.abs(got - want).max(-1) < 1e-4).sum())
        total += clip.n_frames
    assert right / total > 0.9                                    # the true samples carry their names
    ghosts = back.meta["unlabelled"].reshape(-1, 3)
    ghosts = ghosts[np.isfinite(ghosts).all(1)]
    knees = clip.select(GHOSTS).positions.reshape(-1, 3)
    hit = (np.abs(ghosts[:, None] - knees[None]).max(-1) < 1e-4).any(1)
    assert ghosts.shape[0] >= 0.9 * knees.shape[0] and hit.mean() > 0.9      # the unknown markers stay *N


def test_named_take_scores_star_ghosts_and_drop_unlabelled(hdm, upper_model, tmp_path, capsys):
    clip = hdm.select(UPPER).slice(2000, 2060)
    ghosts = hdm.select(GHOSTS).slice(2000, 2060).positions
    f = tmp_path / "named.c3d"
    write_c3d(f, np.concatenate([clip.positions, ghosts], 1), [f"Subj:{n}" for n in UPPER] + ["Subj:*0", "*1"],
              clip.rate)
    # --calibrate off: the default's self-calibration (test_calibrate_cli) is not what this tests
    assert label_main([str(upper_model), str(f), "--json", "--quiet", "--out", str(tmp_path / "o.csv"),
                       "--calibrate", "off"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["ghosts"] == 2 * clip.n_frames and d["ghost_rejection"] > 0.9 and d["accuracy"] > 0.9
    assert d["inputs"][0]["unlabelled_points"] == 2
    back = load_clip(tmp_path / "o.csv")
    assert back.names == tuple(UPPER) and back.meta["units"] == "mm"
    assert label_main([str(upper_model), str(f), "--json", "--quiet", "--drop-unlabelled", "--calibrate", "off"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["ghosts"] == 0 and d["ghost_rejection"] is None


def test_model_outputs_in_the_point_block_are_not_markers(hdm, upper_model, tmp_path, capsys):
    """A processed trial (Nexus' Plug-in Gait, Visual3D) stores joint angles, moments and powers
    as POINT channels listed in POINT:ANGLES / MOMENTS / POWERS: they are left out (named in
    ``meta['model_outputs']``), never read as markers or fed to the labeler as ghosts."""
    clip = hdm.select(UPPER).slice(2000, 2060)
    F = clip.n_frames
    rng = np.random.default_rng(0)
    angles = rng.normal(0, 30, (F, 2, 3)) / 1000.0            # degrees, written into the mm block as they are
    outputs = ["Subj:LKneeAngles", "Subj:RHipAngles", "Subj:LAnkleMoment", "Subj:LHipPower"]
    extra = np.concatenate([angles, rng.normal(0, 500, (F, 1, 3)) / 1000.0, rng.normal(0, 2, (F, 1, 3)) / 1000.0], 1)
    f = write_c3d(tmp_path / "processed.c3d", np.concatenate([clip.positions, extra], 1),
                  [f"Subj:{n}" for n in UPPER] + outputs, clip.rate)
    c = ezc3d.c3d(str(f))
    c.add_parameter("POINT", "ANGLES", ["LKneeAngles", "RHipAngles"])      # listed without the prefix
    c.add_parameter("POINT", "MOMENTS", ["Subj:LAnkleMoment"])
    c.add_parameter("POINT", "POWERS", ["LHipPower"])
    c.write(str(f))
    back = load_clip(f)
    assert back.names == tuple(UPPER) and back.meta["unlabelled_names"] == ()
    assert back.meta["model_outputs"] == tuple(outputs)
    np.testing.assert_allclose(back.positions, clip.positions, atol=1e-9)
    assert label_main([str(upper_model), str(f), "--json", "--quiet", "--calibrate", "off"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["ghosts"] == 0 and d["inputs"][0]["unlabelled_points"] == 0 and d["accuracy"] > 0.9


def test_other_names_refused_unless_ignored(upper_model, data_dir, capsys):
    take = str(data_dir / QUALISYS)
    assert label_main([str(upper_model), take, "--frames", "0:5", "--quiet"]) == 2
    assert "--ignore-names" in capsys.readouterr().err
    assert label_main([str(upper_model), take, "--frames", "0:5", "--quiet", "--ignore-names", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["inputs"][0]["unlabelled_points"] == 55 and d["accuracy"] is None


def test_resolve_up_axis_needs_a_body():
    few = np.random.default_rng(0).normal(size=(10, 3, 3))
    assert resolve_up_axis(few).axis == "Z" and resolve_up_axis(few).source == "default"
    assert resolve_up_axis(few, file_axis="-Y").axis == "Y"


def test_bag_make_feeds_star_ghosts_and_label_writes_c3d(hdm, upper_model, tmp_path, capsys):
    from dtm_labeler.cli.bag import main as bag_main
    clip = hdm.select(UPPER).slice(2000, 2040)
    f = tmp_path / "take.c3d"
    write_c3d(f, np.concatenate([clip.positions, hdm.select(GHOSTS).slice(2000, 2040).positions], 1),
              list(UPPER) + ["*0", "*1"], clip.rate)
    assert bag_main(["make", str(f), "--points", "all", "--out", str(tmp_path / "bag"), "--json"]) == 0
    made = json.loads(capsys.readouterr().out)
    assert made["ghosts_per_frame"] == 2.0 and made["corruption"]["unlabelled_points"] == 2
    out = tmp_path / "labelled.c3d"
    assert bag_main(["label", str(upper_model), str(tmp_path / "bag"), "--out", str(out), "--json", "--quiet"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["ghosts"] == 80 and d["ghost_rejection"] > 0.9 and d["accuracy"] > 0.9
    back = load_clip(out)
    assert back.names == tuple(UPPER) and back.rate == 120.0 and back.n_frames == 40
    ok = np.abs(back.positions - clip.positions).max(-1) < 1e-4          # float32 in the bag
    assert ok.mean() > 0.9


def test_half_the_markers_hidden_stream(hdm, upper_model):
    """A take with half its samples hidden in realistic gaps (log-normal, mean 0.25 s):
    frames that show few labels must not teach the running fitness level (before: the level
    sank, the accept margin grew, a wrong labeling was carried with no search -- 31 % here)."""
    from dtm_labeler.evaluation.corruption import realistic_gaps
    from dtm_labeler.evaluation.pipeline import run_stream
    from dtm_labeler.model.io import load_model
    model = load_model(upper_model)
    clip = hdm.select(list(model.labels)).slice(2000, 2240)
    hidden = realistic_gaps(clip.n_frames, clip.n_points, clip.rate, missing=0.5, mean_gap_s=0.25, seed=1)
    assert 0.4 < hidden.mean() < 0.6
    P = clip.positions.copy()
    P[hidden] = np.nan
    m = run_stream(model, corrupt_clip(clip._replace(positions=P), seed=0), use_ids=True).metrics
    assert m.accuracy >= 0.85, m.accuracy


def test_a_capture_of_two_subjects_is_labelled_one_subject_at_a_time(hdm, upper_model, tmp_path, capsys):
    """Two actors under prefixes with the same marker names: refused without --subject (naming
    both); with it, that subject's markers are the points and the other actor's are unlabelled
    points, rejected as any other person beside the body would be."""
    from dtm_labeler.motion.naming import subjects
    a = hdm.select(UPPER).slice(2000, 2120)
    b = hdm.select(UPPER).slice(3000, 3120).positions + [1.5, 0.0, 0.0]       # another actor, 1.5 m away
    f = tmp_path / "two.c3d"
    write_c3d(f, np.concatenate([a.positions, b], 1), [f"Anna:{n}" for n in UPPER] + [f"Ben:{n}" for n in UPPER],
              a.rate)
    assert subjects([f"Anna:{n}" for n in UPPER] + [f"Ben:{n}" for n in UPPER] + ["Bat:tip"]) == ["Anna", "Ben"]
    with pytest.raises(ValueError, match="2 subjects .*Anna, Ben.*--subject"):
        load_clip(f)
    got = load_clip(f, subject="Ben")
    assert got.names == tuple(UPPER) and np.allclose(got.positions, b, equal_nan=True)
    assert got.meta["unlabelled"].shape[1] == len(UPPER) and got.meta["unlabelled_names"][0] == "Anna:LFHD"
    assert label_main([str(upper_model), str(f), "--subject", "Anna", "--json", "--quiet", "--calibrate", "off"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["accuracy"] > 0.9 and d["ghosts"] == len(UPPER) * a.n_frames and d["ghost_rejection"] > 0.95
    assert label_main([str(upper_model), str(f), "--subject", "Carl", "--quiet"]) != 0
    assert "no channel of subject 'Carl' (subjects: Anna, Ben)" in capsys.readouterr().err
