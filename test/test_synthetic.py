"""The synthetic walker/runner: constant limbs, requested speed/heading, determinism."""
import numpy as np
import pytest

from dtm_labeler.motion import BODY14, synthesize

LIMBS = [("lhip", "lknee"), ("rhip", "rknee"), ("lknee", "lankle"), ("rknee", "rankle"),
         ("lshoulder", "lelbow"), ("rshoulder", "relbow"), ("lelbow", "lwrist"), ("relbow", "rwrist"),
         ("lshoulder", "rshoulder"), ("lhip", "rhip"), ("neck", "head")]


def _p(c, n):
    return c.positions[:, BODY14.index(n)]


@pytest.mark.parametrize("gait", ["walk", "run"])
def test_limb_lengths_constant_and_proportional(gait):
    c = synthesize(duration=3.0, gait=gait, height=1.6, seed=1)
    assert c.names == BODY14 and c.n_frames == 360 and c.rate == 120.0 and c.motion_class == gait
    for a, b in LIMBS:
        d = np.linalg.norm(_p(c, a) - _p(c, b), axis=1)
        assert d.std() < 1e-9, (a, b)
    seg = c.meta["segment_lengths"]
    assert np.linalg.norm(_p(c, "lhip") - _p(c, "lknee"), axis=1)[0] == pytest.approx(seg["thigh"])
    big = synthesize(duration=3.0, gait=gait, height=2.0, seed=1)
    assert big.meta["segment_lengths"]["thigh"] / seg["thigh"] == pytest.approx(2.0 / 1.6)


@pytest.mark.parametrize("gait,speed,heading", [("walk", 1.4, 0.0), ("walk", 0.9, 2.5), ("run", 3.5, -1.2)])
def test_speed_and_heading(gait, speed, heading):
    c = synthesize(duration=5.0, rate=100.0, speed=speed, heading=heading, gait=gait, seed=4)
    mid = (_p(c, "lhip") + _p(c, "rhip")) / 2
    d = mid[-1, :2] - mid[0, :2]
    assert np.linalg.norm(d) / (c.duration - 1 / c.rate) == pytest.approx(speed, rel=0.02)
    dh = np.angle(np.exp(1j * (np.arctan2(d[1], d[0]) - heading)))
    assert abs(dh) < 0.03
    # the body faces the direction of travel: lhip is on the left
    lat = _p(c, "lhip")[:, :2] - _p(c, "rhip")[:, :2]
    assert np.all(d[0] * lat[:, 1] - d[1] * lat[:, 0] > 0)


@pytest.mark.parametrize("gait", ["walk", "run"])
def test_plausible_kinematics(gait):
    c = synthesize(duration=4.0, gait=gait, seed=2)
    z = c.positions[..., 2]
    ankles = z[:, [BODY14.index("lankle"), BODY14.index("rankle")]]
    assert 0.02 < ankles.min() < 0.1  # feet reach the floor ...
    assert np.all(ankles.min(axis=1) < 0.1 + (0.12 if gait == "run" else 0.0))  # ... at least one foot near it
    hipz = (_p(c, "lhip")[:, 2] + _p(c, "rhip")[:, 2]) / 2
    assert 0.8 < hipz.mean() < 1.05 and 0.005 < np.ptp(hipz) < 0.25  # pelvis bob
    assert 1.4 < _p(c, "head")[:, 2].mean() < 1.8
    # legs swing in anti-phase; each arm swings opposite to its own leg
    fwd = np.array([1.0, 0.0])
    lk = (_p(c, "lankle")[:, :2] - _p(c, "lhip")[:, :2]) @ fwd
    rk = (_p(c, "rankle")[:, :2] - _p(c, "rhip")[:, :2]) @ fwd
    lw = (_p(c, "lwrist")[:, :2] - _p(c, "lshoulder")[:, :2]) @ fwd
    assert np.corrcoef(lk, rk)[0, 1] < -0.8
    assert np.corrcoef(lk, lw)[0, 1] < -0.7
    # knees only flex forward: the knee is never behind the hip-ankle line
    for s in "lr":
        h, k, a = _p(c, s + "hip"), _p(c, s + "knee"), _p(c, s + "ankle")
        n = np.cross(a - h, np.array([0.0, 1.0, 0.0]))  # sagittal normal pointing forward-ish
        assert np.all(np.einsum("ij,ij->i", k - h, n) >= -1e-9)


def test_deterministic_and_noise():
    a = synthesize(duration=1.0, seed=7, noise_mm=2.0)
    b = synthesize(duration=1.0, seed=7, noise_mm=2.0)
    np.testing.assert_array_equal(a.positions, b.positions)
    c = synthesize(duration=1.0, seed=8, noise_mm=2.0)
    assert not np.allclose(a.positions, c.positions)
    clean = synthesize(duration=1.0, seed=7)
    resid = (a.positions - clean.positions).ravel()
    assert resid.std() == pytest.approx(0.002, rel=0.15) and abs(resid.mean()) < 5e-4
    assert not np.isnan(a.positions).any()


def test_bad_arguments():
    with pytest.raises(ValueError, match="gait"):
        synthesize(gait="hop")
    with pytest.raises(ValueError):
        synthesize(duration=0)
