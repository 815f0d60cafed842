"""BODY14 derivation, marker-set detection and left/right naming."""
import numpy as np
import pytest

from dtm_labeler.motion import BODY14, MotionClip, load_clip, to_point_set
from dtm_labeler.motion.pointsets import (MARKER_SETS, derive_body14, detect_marker_set, left_right_pairs,
                                          mirror_name, side_of)

FILES = {
    "cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh": "cgspeed",
    "cmu_skeletal/bvh_from_fbx/cmu_09_11_run_s09.bvh": "cgspeed",
    "cmu_skeletal/asf_amc/cmu_55_02_lambada-dance_s55.amc": "asf",
    "cmu_skeletal/positions_csv/cmu_s05_pirouette-dance.csv": "body14",
    "markers_c3d/qualisys_walk_55markers.c3d": "qualisys55",
    "markers_c3d/cmu_85_02_jumptwist_s85_41markers.c3d": "cmu41",
    "markers_c3d/cmu_85_12_breakdance_s85_41markers.c3d": "cmu41",
    "markers_c3d/hdm05_bd_05-01_01_120.c3d": "cmu41",
    "markers_csv/mct_walk1_28markers_60hz.csv": "mct28",
    "markers_csv/mct_dance1_28markers_60hz.csv": "mct28",
}


@pytest.fixture(scope="module")
def raw(data_dir):
    return {rel: load_clip(data_dir / rel) for rel in FILES}


def test_body14_order():
    assert BODY14 == ("head", "neck", "lshoulder", "rshoulder", "lelbow", "relbow", "lwrist", "rwrist",
                      "lhip", "rhip", "lknee", "rknee", "lankle", "rankle")
    for key, table in MARKER_SETS.items():
        assert tuple(table) == BODY14, key


def _seg(c, a, b):
    return np.nanmedian(np.linalg.norm(c.positions[:, c.index(a)] - c.positions[:, c.index(b)], axis=1))


@pytest.mark.parametrize("rel", list(FILES))
def test_body14_from_every_file(raw, rel):
    c = raw[rel]
    assert detect_marker_set(c.names) == FILES[rel]
    b = to_point_set(c, "body14")
    assert b.names == BODY14 and b.n_frames == c.n_frames and b.rate == c.rate
    assert b.meta["marker_set"] == FILES[rel] and b.motion_class == c.motion_class
    assert b.missing.mean() <= c.missing.mean() * 4 + 1e-12
    for side in "lr":
        assert 0.30 < _seg(b, side + "hip", side + "knee") < 0.55
        assert 0.30 < _seg(b, side + "knee", side + "ankle") < 0.55
        assert 0.20 < _seg(b, side + "shoulder", side + "elbow") < 0.45
        assert 0.10 < _seg(b, side + "elbow", side + "wrist") < 0.35
    assert 0.20 < _seg(b, "lshoulder", "rshoulder") < 0.50
    assert 0.10 < _seg(b, "lhip", "rhip") < 0.40
    z = b.positions[..., 2]
    assert np.nanmedian(z[:, BODY14.index("head")]) > np.nanmedian(z[:, BODY14.index("lhip")]) + 0.3


def test_body14_values_match_sources(raw, data_dir):
    bvh = to_point_set(raw["cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh"], "body14")
    ref = load_clip(data_dir / "cmu_skeletal/positions_csv/cmu_07_01_walk_s07.csv", points="body14")
    assert np.abs(bvh.positions - ref.positions).max() < 2e-5
    q = raw["markers_c3d/qualisys_walk_55markers.c3d"]
    b = to_point_set(q, "body14")
    np.testing.assert_allclose(b.positions[:, BODY14.index("lknee")],
                               (q.positions[:, q.index("L_FLE")] + q.positions[:, q.index("L_FME")]) / 2)
    np.testing.assert_allclose(b.positions[:, BODY14.index("rshoulder")], q.positions[:, q.index("R_SAJ")])


@pytest.mark.parametrize("rel", ["cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh",
                                 "cmu_skeletal/bvh_from_fbx/cmu_09_11_run_s09.bvh",
                                 "markers_c3d/qualisys_walk_55markers.c3d",
                                 "markers_csv/mct_walk1_28markers_60hz.csv"])
def test_left_is_left_of_walking_direction(raw, rel):
    """Handedness check of the Z-up conversion: lhip lies to the left of the direction of travel."""
    b = to_point_set(raw[rel], "body14")
    mid = (b.positions[:, BODY14.index("lhip")] + b.positions[:, BODY14.index("rhip")]) / 2
    k = max(int(b.rate / 4), 1)
    fwd = mid[k:, :2] - mid[:-k, :2]
    lat = (b.positions[:, BODY14.index("lhip")] - b.positions[:, BODY14.index("rhip")])[:-k, :2]
    cross = fwd[:, 0] * lat[:, 1] - fwd[:, 1] * lat[:, 0]
    ok = np.isfinite(cross)
    assert (cross[ok] > 0).mean() > 0.9


def test_mean_missing_if_any_source_missing():
    names = MARKER_SETS["mct28"]
    src = sorted({s for v in names.values() for s in v})
    P = np.random.default_rng(0).normal(size=(4, len(src), 3))
    P[1, src.index("Head_BR")] = np.nan
    P[2, src.index("Knee_L")] = np.nan
    c = MotionClip(P, rate=60.0, names=src)
    b = derive_body14(c)
    assert b.meta["marker_set"] == "mct28"
    miss = b.missing
    assert miss[1].tolist() == [p == "head" for p in BODY14]
    assert miss[2].tolist() == [p == "lknee" for p in BODY14]
    assert not miss[[0, 3]].any()
    np.testing.assert_allclose(b.positions[0, BODY14.index("neck")],
                               P[0, [src.index("Shoulder_L"), src.index("Shoulder_R")]].mean(axis=0))


def test_to_point_set_variants(raw):
    c = raw["markers_c3d/cmu_85_02_jumptwist_s85_41markers.c3d"]
    assert to_point_set(c, "all") is c
    sel = to_point_set(c, ["LSHO", "C7"])
    assert sel.names == ("LSHO", "C7")
    mixed = to_point_set(c, ["lknee", "T10", "head"])
    np.testing.assert_array_equal(mixed.positions[:, 0], c.positions[:, c.index("LKNE")])
    np.testing.assert_array_equal(mixed.positions[:, 1], c.positions[:, c.index("T10")])
    with pytest.raises(ValueError, match="points must be"):
        to_point_set(c, "body15")
    with pytest.raises(ValueError, match="no known marker set"):
        to_point_set(c.select(["LSHO", "C7"]), "body14")
    with pytest.raises(ValueError, match="unknown marker set"):
        to_point_set(c, "body14", marker_set="nope")


@pytest.mark.parametrize("name,mirror", [
    ("LeftArm", "RightArm"), ("RightUpLeg", "LeftUpLeg"), ("left_knee", "right_knee"), ("L_SAJ", "R_SAJ"),
    ("R_HDF", "L_HDF"), ("Shoulder_L", "Shoulder_R"), ("Head_FL", "Head_FR"), ("Hip_BR", "Hip_BL"),
    ("LSHO", "RSHO"), ("RWRB", "LWRB"), ("LHipJoint", "RHipJoint"), ("LThumb", "RThumb"), ("lhip", "rhip"),
    ("rhumerus", "lhumerus"), ("lshoulder", "rshoulder"), ("head", None), ("CLAV", None), ("T10", None),
])
def test_mirror_name(name, mirror):
    assert mirror_name(name) == mirror
    if mirror is not None:
        assert mirror_name(mirror) == name
        assert {side_of(name), side_of(mirror)} == {"L", "R"}


def test_left_right_pairs_on_real_sets(raw):
    p14 = left_right_pairs(BODY14)
    assert p14 == [("lshoulder", "rshoulder"), ("lelbow", "relbow"), ("lwrist", "rwrist"), ("lhip", "rhip"),
                   ("lknee", "rknee"), ("lankle", "rankle")]
    cmu = left_right_pairs(raw["markers_c3d/cmu_85_02_jumptwist_s85_41markers.c3d"].names)
    assert len(cmu) == 18 and ("LFHD", "RFHD") in cmu and all(a[0] == "L" and b[0] == "R" for a, b in cmu)
    q = left_right_pairs(raw["markers_c3d/qualisys_walk_55markers.c3d"].names)
    assert len(q) == 25 and ("L_IAS", "R_IAS") in q and ("L_HDF", "R_HDF") in q
    m = left_right_pairs(raw["markers_csv/mct_walk1_28markers_60hz.csv"].names)
    assert len(m) == 13 and ("Head_BL", "Head_BR") in m
    asf = left_right_pairs(raw["cmu_skeletal/asf_amc/cmu_55_02_lambada-dance_s55.amc"].names)
    assert ("lhipjoint", "rhipjoint") in asf and not any("back" in a for a, _ in asf)
    bvh = left_right_pairs(raw["cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh"].names)
    assert ("LeftHand_end", "RightHand_end") not in bvh and ("LThumb", "RThumb") in bvh
    assert len(bvh) == 15  # 12 joint pairs + 3 end-site pairs


def test_all_but_some_points(raw):
    """``--points all,-NAME,...``: every point of the take but those; an unknown name or a
    malformed spec is refused with what to write."""
    from dtm_labeler.cli.common import CliError, point_spec
    from dtm_labeler.motion.pointsets import AllBut
    clip = raw["markers_c3d/qualisys_walk_55markers.c3d"]
    drop = list(clip.names[:2])
    spec = point_spec("all," + ",".join("-" + n for n in drop))
    assert spec == AllBut(tuple(drop))
    out = to_point_set(clip, spec)
    assert list(out.names) == [n for n in clip.names if n not in drop]
    np.testing.assert_array_equal(out.positions, clip.select(list(out.names)).positions)
    with pytest.raises(ValueError, match="no point named NOPE to leave out"):
        to_point_set(clip, AllBut(("NOPE",)))
    for bad in ("all,-", "all,LFHD", "all,-A,B"):
        with pytest.raises(CliError, match="starts with '-'"):
            point_spec(bad)
