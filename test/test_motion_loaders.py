"""Loaders on the real shared recordings (../shared/data) and on small files written here."""
import numpy as np
import pytest

from dtm_labeler.motion import MotionClip, find_recordings, load_clip, load_clips
from dtm_labeler.motion.asf_amc import find_asf_for
from dtm_labeler.motion.bvh import load_bvh, read_bvh
from dtm_labeler.motion.c3d import load_c3d
from dtm_labeler.motion.load import class_from_name, csv_kind
from dtm_labeler.motion.markers_csv import load_markers_csv

SK = "cmu_skeletal"
BVH = {s: f"{SK}/bvh_from_fbx/{s}.bvh"
       for s in ("cmu_07_01_walk_s07", "cmu_09_11_run_s09", "cmu_55_01_dance-whirl_s55")}
AMC = {s: f"{SK}/asf_amc/{s}.amc" for s in ("cmu_55_02_lambada-dance_s55", "cmu_s05_pirouette-dance")}
C3D = {
    "qualisys": "markers_c3d/qualisys_walk_55markers.c3d",
    "jumptwist": "markers_c3d/cmu_85_02_jumptwist_s85_41markers.c3d",
    "breakdance": "markers_c3d/cmu_85_12_breakdance_s85_41markers.c3d",
    "hdm05": "markers_c3d/hdm05_bd_05-01_01_120.c3d",
}
MCT = {"walk1": "markers_csv/mct_walk1_28markers_60hz.csv", "dance1": "markers_csv/mct_dance1_28markers_60hz.csv"}

CSV_TO_BVH = dict(root="Hips", lhip="LeftUpLeg", rhip="RightUpLeg", lknee="LeftLeg", rknee="RightLeg",
                  lankle="LeftFoot", rankle="RightFoot", neck="Neck", head="Head", headtop="Head_end",
                  lshoulder="LeftArm", rshoulder="RightArm", lelbow="LeftForeArm", relbow="RightForeArm",
                  lwrist="LeftHand", rwrist="RightHand")
CSV_TO_ASF = dict(root="root", lhip="lhipjoint", rhip="rhipjoint", lknee="lfemur", rknee="rfemur",
                  lankle="ltibia", rankle="rtibia", neck="thorax", head="upperneck", headtop="head",
                  lshoulder="lclavicle", rshoulder="rclavicle", lelbow="lhumerus", relbow="rhumerus",
                  lwrist="lradius", rwrist="rradius")


@pytest.fixture(scope="module")
def clips(data_dir):
    """Every shared recording loaded once (all points), keyed by a short name."""
    out = {}
    for k, rel in {**BVH, **AMC, **C3D, **MCT}.items():
        out[k] = load_clip(data_dir / rel)
    for k in (*BVH, *AMC):
        out["csv:" + k] = load_clip(data_dir / f"{SK}/positions_csv/{k}.csv")
    return out


# ------------------------------------------------------------------ FK vs derived CSVs
@pytest.mark.parametrize("stem,table", [(s, CSV_TO_BVH) for s in BVH] + [(s, CSV_TO_ASF) for s in AMC])
def test_fk_matches_derived_positions(clips, stem, table):
    fk, ref = clips[stem], clips["csv:" + stem]
    assert ref.names == tuple(table)
    np.testing.assert_array_equal(fk.meta["frame_numbers"], ref.meta["frame_numbers"])
    got = fk.select([table[j] for j in ref.names]).positions
    err = np.abs(got - ref.positions).max()
    # the CSVs carry 5 decimals (10 um): anything beyond rounding would be an FK bug
    assert err < 2e-5, f"{stem}: max FK error {err * 1000:.4f} mm"


# ------------------------------------------------------------------ hand-checked facts
@pytest.mark.parametrize("key,frames,rate,n_points", [
    ("cmu_07_01_walk_s07", 316, 120, 38), ("cmu_09_11_run_s09", 165, 120, 38),
    ("cmu_55_01_dance-whirl_s55", 1806, 120, 38),
    ("cmu_55_02_lambada-dance_s55", 2180, 120, 31), ("cmu_s05_pirouette-dance", 591, 120, 31),
    ("qualisys", 340, 200, 55), ("jumptwist", 810, 120, 41), ("breakdance", 4499, 120, 41), ("hdm05", 5920, 120, 41),
    ("walk1", 351, 60, 28), ("dance1", 1500, 60, 28),
])
def test_frame_counts_and_rates(clips, key, frames, rate, n_points):
    c = clips[key]
    assert isinstance(c, MotionClip)
    assert (c.n_frames, c.rate, c.n_points) == (frames, rate, n_points)


def test_bvh_tpose_dropped_and_frame_numbers(clips, data_dir):
    c = clips["cmu_07_01_walk_s07"]
    assert c.meta["dropped_tpose"] and c.meta["frame_numbers"][0] == 1
    assert abs(c.meta["unit_scale"] - 0.0254 / 0.45) < 1e-12
    raw = load_bvh(data_dir / BVH["cmu_07_01_walk_s07"], drop_tpose=False)
    assert raw.n_frames == 317
    np.testing.assert_allclose(raw.positions[1:], c.positions)
    # frame 0 is the T-pose: wrists level with shoulders, far apart
    p = raw.positions[0]
    lw, rw, ls = (p[raw.index(n)] for n in ("LeftHand", "RightHand", "LeftArm"))
    assert abs(lw[2] - ls[2]) < 0.1 and np.linalg.norm(lw - rw) > 1.2
    assert len(read_bvh(data_dir / BVH["cmu_07_01_walk_s07"]).joints) == 31 + 7


def test_labels_prefix_stripped_and_unlabelled_kept(clips, data_dir):
    h = clips["hdm05"]
    assert "LFHD" in h.names and not any(":" in n or n.startswith("*") for n in h.names)
    assert h.meta["unlabelled_names"] == ("*0", "*1", "*2")
    assert h.meta["unlabelled"].shape == (5920, 3, 3)
    assert h.meta["raw_labels"][0].startswith("Bastian:")
    # data quirk: the three '*' points are bit-identical copies of labelled markers, not clutter
    assert h.meta["unlabelled_duplicates"] == {"*0": "LFWT", "*1": "CLAV", "*2": "LFHD"}
    assert set(clips["jumptwist"].names) == set(clips["hdm05"].names)  # the same 41-marker set
    full = load_c3d(data_dir / C3D["hdm05"], include_unlabelled=True)
    assert full.n_points == 44 and full.names[-3:] == ("*0", "*1", "*2")
    np.testing.assert_array_equal(full.positions[:, -3:], h.meta["unlabelled"])


def test_missing_fractions(clips):
    assert abs(clips["walk1"].missing.mean() - 0.0027) < 0.0003
    for k in ("dance1", "qualisys", "jumptwist", "breakdance", "hdm05", "cmu_07_01_walk_s07"):
        assert not clips[k].missing.any(), k


@pytest.mark.parametrize("key", [*BVH, *AMC])
def test_bone_lengths_constant(clips, key):
    c = clips[key]
    parents = c.meta["parents"]
    lengths = np.stack([np.linalg.norm(c.positions[:, j] - c.positions[:, p], axis=1)
                        for j, p in enumerate(parents) if p >= 0], axis=1)
    assert lengths.std(axis=0).max() < 1e-4
    assert lengths.max() > 0.2  # a real skeleton, not collapsed


@pytest.mark.parametrize("key,hips", [
    ("cmu_07_01_walk_s07", ("LeftUpLeg", "RightUpLeg")), ("cmu_09_11_run_s09", ("LeftUpLeg", "RightUpLeg")),
    ("cmu_55_01_dance-whirl_s55", ("LeftUpLeg", "RightUpLeg")),
    ("cmu_55_02_lambada-dance_s55", ("lhipjoint", "rhipjoint")),
    ("cmu_s05_pirouette-dance", ("lhipjoint", "rhipjoint")),
])
def test_z_up_heights(clips, key, hips):
    c = clips[key]
    hipz = (c.positions[:, c.index(hips[0]), 2] + c.positions[:, c.index(hips[1]), 2]) / 2
    assert 0.8 < hipz.mean() < 1.1
    ankles = [n for n in ("LeftFoot", "RightFoot", "ltibia", "rtibia") if n in c.names]
    assert c.positions[:, [c.index(a) for a in ankles], 2].min() < 0.15
    assert c.positions[:, :, 2].min() > -0.05  # nothing far below the floor


@pytest.mark.parametrize("key,speed", [("cmu_07_01_walk_s07", 1.33), ("cmu_09_11_run_s09", 3.56)])
def test_cmu_gait_speed(clips, key, speed):
    c = clips[key]
    mid = (c.positions[:, c.index("LeftUpLeg"), :2] + c.positions[:, c.index("RightUpLeg"), :2]) / 2
    v = np.linalg.norm(np.diff(mid, axis=0), axis=1).mean() * c.rate
    assert abs(v - speed) < 0.1, v  # measured 1.36 / 3.50 m/s


def test_marker_files_z_up(clips):
    for k in ("qualisys", "jumptwist", "hdm05", "walk1", "dance1"):
        z = clips[k].positions[..., 2]
        assert np.nanmin(z) > -0.05 and 1.4 < np.nanmax(z) < 2.2, k
    h = clips["hdm05"]  # standing in place: pelvis constant ~1.0 m
    pz = h.positions[:, [h.index(n) for n in ("LFWT", "RFWT", "LBWT", "RBWT")], 2].mean(axis=1)
    assert abs(pz.mean() - 1.0) < 0.06 and pz.std() < 0.05
    q = clips["qualisys"]  # walks along +X
    d = np.nanmean(q.positions[-1] - q.positions[0], axis=0)
    assert d[0] / q.duration > 1.2 and abs(d[1]) < 0.3


# ------------------------------------------------------------------ dispatch, classes, index
def test_load_clip_dispatch_and_classes(clips, data_dir):
    assert clips["cmu_07_01_walk_s07"].motion_class == "walk"
    assert clips["cmu_09_11_run_s09"].motion_class == "run"
    assert clips["breakdance"].motion_class == "dance"
    assert clips["breakdance"].meta["index_class"] == "dance (breakdance)"
    assert clips["jumptwist"].motion_class == "other"
    assert clips["csv:cmu_07_01_walk_s07"].motion_class == "walk"
    via_asf = load_clip(data_dir / f"{SK}/asf_amc/cmu_s05_pirouette-dance.asf")
    np.testing.assert_array_equal(via_asf.positions, clips["cmu_s05_pirouette-dance"].positions)
    assert via_asf.source.endswith(".asf") and via_asf.motion_class == "dance"
    assert csv_kind(data_dir / MCT["walk1"]) == "markers"
    assert csv_kind(data_dir / f"{SK}/positions_csv/cmu_09_11_run_s09.csv") == "positions"
    two = load_clips([data_dir / MCT["walk1"], data_dir / C3D["qualisys"]], points="body14")
    assert [c.n_points for c in two] == [14, 14]
    with pytest.raises(ValueError, match="FBX"):
        load_clip(data_dir / f"{SK}/fbx/cmu_07_01_walk_s07.fbx")


def test_find_recordings(data_dir):
    r = find_recordings(data_dir)
    assert set(r) == {"walk", "run", "dance", "other"}
    assert {p.name for p in r["walk"]} == {"cmu_07_01_walk_s07.bvh", "qualisys_walk_55markers.c3d",
                                           "mct_walk1_28markers_60hz.csv"}
    assert r["walk"] == sorted(r["walk"])
    assert all(p.is_file() for v in r.values() for p in v)
    assert sum(map(len, r.values())) == 11
    assert not any(p.suffix in (".fbx", ".asf") for v in r.values() for p in v)
    only_c3d = find_recordings(data_dir, kinds=["markers_c3d"])
    assert sum(map(len, only_c3d.values())) == 4
    assert list(find_recordings(data_dir, classes=["run"])) == ["run"]


def test_class_from_name():
    assert class_from_name("/x/subject3_Walking_fast.c3d") == "walk"
    assert class_from_name("trial_run2.bvh") == "run"
    assert class_from_name("salsa-dancing.csv") == "dance"
    assert class_from_name("pirouette.c3d") == ""  # no substring matches inside words


# ------------------------------------------------------------------ gaps and malformed files (tmp files)
def _write_c3d(path, labels, pts_m, units="m", rate=100.0):
    import ezc3d
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    data = np.ones((4, len(labels), pts_m.shape[0]))
    data[:3] = np.transpose(pts_m, (2, 1, 0))
    c["data"]["points"] = data
    c.write(str(path))


def test_c3d_gaps_units_and_up_axis(tmp_path):
    F = 6
    pts = np.arange(F * 3 * 3, dtype=float).reshape(F, 3, 3) + 1.0  # mm
    pts[1, 0] = np.nan
    pts[2, 1] = 0.0
    pts[3, 1, 0] = 0.0  # a single zero coordinate is not a gap
    f = tmp_path / "gaps.c3d"
    _write_c3d(f, ["Sub:A", "Sub:B", "*7"], pts, units="mm", rate=250.0)
    c = load_c3d(f)
    assert c.names == ("A", "B") and c.rate == 250.0 and c.meta["unlabelled_names"] == ("*7",)
    assert c.meta["unlabelled_duplicates"] == {}
    assert c.missing.sum() == 2 and c.missing[1, 0] and c.missing[2, 1]
    np.testing.assert_allclose(c.positions[0, 0], pts[0, 0] / 1000)
    assert not c.missing[3, 1]
    y = load_c3d(f, up_axis="Y")
    np.testing.assert_allclose(y.positions[0, 0], [pts[0, 0, 0] / 1000, -pts[0, 0, 2] / 1000, pts[0, 0, 1] / 1000])
    fcm = tmp_path / "cm.c3d"
    _write_c3d(fcm, ["A"], pts[:, :1], units="cm")
    np.testing.assert_allclose(load_c3d(fcm).positions[0, 0], pts[0, 0] / 100)
    x = load_c3d(f, up_axis="X")           # X up: (x, y, z) -> (y, z, x)
    np.testing.assert_allclose(x.positions[0, 0], [pts[0, 0, 1] / 1000, pts[0, 0, 2] / 1000, pts[0, 0, 0] / 1000])
    with pytest.raises(ValueError, match="up_axis"):
        load_c3d(f, up_axis="W")


def test_markers_csv_gaps(tmp_path):
    f = tmp_path / "tiny.csv"
    f.write_text("# tiny file\n# units mm, Z up, 50 Hz\nframe,time_s,A_x,A_y,A_z,Knee_L_x,Knee_L_y,Knee_L_z\n"
                 "1,0.00,1000,2000,3000,1,2,3\n2,0.02,,,,4,5,6\n3,0.04,1,2,3,7,,9\n")
    c = load_clip(f)
    assert c.names == ("A", "Knee_L") and c.rate == 50.0 and c.n_frames == 3
    np.testing.assert_allclose(c.positions[0, 0], [1.0, 2.0, 3.0])
    assert c.missing.tolist() == [[False, False], [True, False], [False, True]]
    f2 = tmp_path / "norate.csv"
    f2.write_text("frame,time_s,A_x,A_y,A_z\n1,0.0,1,2,3\n2,0.01,1,2,3\n3,0.02,1,2,3\n")
    assert load_markers_csv(f2).rate == 100.0


def test_malformed_files_raise_with_location(tmp_path, data_dir):
    bad = tmp_path / "bad.csv"
    bad.write_text("frame,time_s,A_x,A_y,A_z\n1,0.0,1,2,3\n2,0.01,1,x,3\n")
    with pytest.raises(ValueError, match=r"bad\.csv:3"):
        load_clip(bad)
    hdr = tmp_path / "hdr.csv"
    hdr.write_text("frame,time_s,A_x,A_y,B_z\n1,0,1,2,3\n")
    with pytest.raises(ValueError, match="hdr.csv"):
        load_clip(hdr)
    bvh = tmp_path / "bad.bvh"
    bvh.write_text("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xposition Yposition Qrotation\n}\n"
                   "MOTION\nFrames: 1\nFrame Time: 0.01\n0 0 0\n")
    with pytest.raises(ValueError, match=r"bad\.bvh:5: unknown channel"):
        load_clip(bvh)
    short = tmp_path / "short.bvh"
    short.write_text("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xposition Yposition Zposition\n}\n"
                     "MOTION\nFrames: 2\nFrame Time: 0.01\n0 0 0\n0 0\n")
    with pytest.raises(ValueError, match="short.bvh"):
        load_clip(short)
    asf = data_dir / f"{SK}/asf_amc/cmu_s05_pirouette-dance.asf"
    amc = tmp_path / "x.amc"
    amc.write_text(":FULLY-SPECIFIED\n:DEGREES\n1\nroot 0 0 0 0 0 0\nlfemur 1 2\n")
    with pytest.raises(ValueError, match=r"x\.amc:5: bone 'lfemur' has 3 dof"):
        load_clip(amc, asf_path=asf)
    with pytest.raises(ValueError, match="no x.asf"):
        find_asf_for(amc)


def test_small_bvh_generic_channels(tmp_path):
    """Non-cgspeed BVH in cm with XYZ rotation order and an End Site."""
    f = tmp_path / "arm.bvh"
    f.write_text("HIERARCHY\nROOT Base\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition "
                 "Xrotation Yrotation Zrotation\n JOINT Elbow\n {\n  OFFSET 0 100 0\n  CHANNELS 3 Xrotation Yrotation "
                 "Zrotation\n  End Site\n  {\n   OFFSET 0 50 0\n  }\n }\n}\nMOTION\nFrames: 2\nFrame Time: 0.02\n"
                 "0 0 0 0 0 0 0 0 0\n10 0 0 0 0 90 90 0 0\n")
    c = load_bvh(f)
    assert c.names == ("Base", "Elbow", "Elbow_end") and c.rate == 50.0 and not c.meta["dropped_tpose"]
    assert c.meta["unit_scale"] == 0.01
    # frame 0: chain straight up (+Y in file = +Z after conversion)
    np.testing.assert_allclose(c.positions[0], [[0, 0, 0], [0, 0, 1.0], [0, 0, 1.5]], atol=1e-12)
    # frame 1: root +10 cm X, Z-rot 90 deg turns +Y into -X; then elbow X-rot 90 turns local +Y into local +Z
    # local +Z, rotated by root Rz(90): stays +Z (file) -> -Y after Y-up -> Z-up conversion
    np.testing.assert_allclose(c.positions[1], [[0.1, 0, 0], [-0.9, 0, 0], [-0.9, -0.5, 0]], atol=1e-12)
