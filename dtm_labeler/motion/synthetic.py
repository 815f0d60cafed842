"""Synthetic articulated walking / running figure (BODY14, metres, Z up).

For demos and fast unit tests only (accuracy is measured on real recordings).

Model: planar (sagittal) leg and arm chains hung from a rigid trunk; segment lengths
are fixed fractions of body height (Winter's anthropometric table), so every limb
length is exactly constant. Per stride phase ``phi`` (left leg; right leg ``phi + pi``):

* hip flexion ``a0 + A sin(phi)``; knee flexion peaks in swing (``phi ~ 0``, while the
  thigh swings forward); shoulders swing opposite to the same-side leg; elbows flex
  more while the arm swings forward;
* the pelvis height is set each frame so that the lower ankle is at ankle height (stance
  foot on the floor), which yields the double-frequency pelvis bob; running adds a
  flight-phase lift; a small lateral pelvis sway at stride frequency;
* constant forward speed along ``heading`` (radians about +Z, 0 = +X), stride frequency
  rising with speed.
"""
from __future__ import annotations

import numpy as np

from .clip import MotionClip
from .pointsets import BODY14

# fractions of body height (Winter 2009, Fig. 4.1) and gait parameters per gait
_SEG = dict(thigh=0.245, shank=0.246, ankle=0.039, hip_half_width=0.05, trunk=0.288, shoulder_half=0.118,
            neck_up=0.0, head_up=0.07, upper_arm=0.186, forearm=0.146)
_GAIT = {  # hip offset/amp, knee base/amp, arm amp, elbow base/amp, trunk lean (rad), flight lift (m per m height)
    "walk": dict(hip0=0.05, hipA=0.38, knee0=0.08, kneeA=1.0, armA=0.35, elb0=0.25, elbA=0.25, lean=0.03, lift=0.0),
    "run": dict(hip0=0.12, hipA=0.60, knee0=0.35, kneeA=1.55, armA=0.55, elb0=1.35, elbA=0.25, lean=0.12,
                lift=0.03),
}
_DEFAULT_SPEED = {"walk": 1.3, "run": 3.2}


def stride_frequency(speed: float, height: float = 1.75) -> float:
    """Strides per second: ~0.9 Hz at 1.3 m/s, ~1.45 Hz at 3.5 m/s for a 1.75 m person."""
    return (0.55 + 0.27 * speed) * np.sqrt(1.75 / height)


def synthesize(duration: float = 4.0, rate: float = 120.0, speed: float | None = None, heading: float = 0.0,
               gait: str = "walk", height: float = 1.75, noise_mm: float = 0.0, seed: int = 0,
               start_xy: tuple[float, float] = (0.0, 0.0)) -> MotionClip:
    """A BODY14 MotionClip of a figure walking/running at ``speed`` m/s (default 1.3 walk,
    3.2 run) along ``heading`` (radians about Z), for ``duration`` s at ``rate`` Hz.
    ``height``: body height in m (all lengths scale with it). ``noise_mm``: std of i.i.d.
    Gaussian noise per coordinate, in mm. ``seed`` fixes the start phase, small amplitude
    variations and the noise; equal arguments give identical clips.
    ``meta``: ``segment_lengths`` (m), ``stride_hz``, ``speed``, ``heading``, ``gait``.
    """
    if gait not in _GAIT:
        raise ValueError(f"gait must be one of {sorted(_GAIT)}, got {gait!r}")
    if duration <= 0 or rate <= 0 or height <= 0:
        raise ValueError("duration, rate and height must be positive")
    rng = np.random.default_rng(seed)
    g = {k: v * (1.0 + 0.05 * rng.uniform(-1, 1)) for k, v in _GAIT[gait].items()}  # per-seed style
    v = _DEFAULT_SPEED[gait] if speed is None else float(speed)
    L = {k: f * height for k, f in _SEG.items()}
    n = max(int(round(duration * rate)), 1)
    t = np.arange(n) / rate
    f = stride_frequency(v, height) if v > 0 else 0.8
    phi_l = 2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)

    def leg(phi):  # (n, 2) knee and ankle in sagittal (forward, up) relative to the hip joint
        hip = g["hip0"] + g["hipA"] * np.sin(phi)
        knee = g["knee0"] + g["kneeA"] * (0.5 + 0.5 * np.cos(phi - 0.3)) ** 3
        k = L["thigh"] * np.stack([np.sin(hip), -np.cos(hip)], axis=1)
        a = k + L["shank"] * np.stack([np.sin(hip - knee), -np.cos(hip - knee)], axis=1)
        return k, a

    def arm(phi_leg):  # shoulder swings opposite to the same-side leg
        sh = -g["armA"] * np.sin(phi_leg)
        el = g["elb0"] + g["elbA"] * (0.5 - 0.5 * np.sin(phi_leg))
        e = L["upper_arm"] * np.stack([np.sin(sh), -np.cos(sh)], axis=1)
        w = e + L["forearm"] * np.stack([np.sin(sh + el), -np.cos(sh + el)], axis=1)
        return e, w

    (kl, al), (kr, ar) = leg(phi_l), leg(phi_l + np.pi)
    (el, wl), (er, wr) = arm(phi_l), arm(phi_l + np.pi)
    lowest = np.minimum(al[:, 1], ar[:, 1])  # most negative ankle height below the hips
    pelvis_z = L["ankle"] - lowest
    if g["lift"] > 0:  # flight phase: lift the whole body around double-support instants
        pelvis_z = pelvis_z + g["lift"] * height * np.abs(np.cos(phi_l)) ** 4
    sway = 0.012 * height / 1.75 * np.sin(phi_l)

    def place(sag, lateral):  # sagittal (fwd, up) rel. to a pelvis-frame anchor -> body (fwd, left, up)
        return np.stack([sag[:, 0], np.full(n, lateral), sag[:, 1]], axis=1)

    lean = g["lean"]
    up = np.array([np.sin(lean), 0.0, np.cos(lean)])  # trunk axis (leaning forward)
    hw, sw = L["hip_half_width"], L["shoulder_half"]
    neck = L["trunk"] * up
    head = neck + L["head_up"] * up
    sh_l, sh_r = neck + [0, sw, 0], neck + [0, -sw, 0]
    body = {
        "lhip": np.tile([0.0, hw, 0.0], (n, 1)), "rhip": np.tile([0.0, -hw, 0.0], (n, 1)),
        "lknee": place(kl, hw), "rknee": place(kr, -hw), "lankle": place(al, hw), "rankle": place(ar, -hw),
        "neck": np.tile(neck, (n, 1)), "head": np.tile(head, (n, 1)),
        "lshoulder": np.tile(sh_l, (n, 1)), "rshoulder": np.tile(sh_r, (n, 1)),
        "lelbow": sh_l + place(el, 0.0), "relbow": sh_r + place(er, 0.0),
        "lwrist": sh_l + place(wl, 0.0), "rwrist": sh_r + place(wr, 0.0),
    }
    P = np.stack([body[p] for p in BODY14], axis=1)  # (n, 14, 3) in body frame, origin = pelvis centre
    P[..., 1] += sway[:, None]
    P[..., 2] += pelvis_z[:, None]
    P[..., 0] += (v * t)[:, None]
    c, s = np.cos(heading), np.sin(heading)
    world = P.copy()
    world[..., 0] = c * P[..., 0] - s * P[..., 1] + start_xy[0]
    world[..., 1] = s * P[..., 0] + c * P[..., 1] + start_xy[1]
    if noise_mm > 0:
        world = world + rng.normal(0.0, noise_mm / 1000.0, world.shape)
    seg = dict(thigh=L["thigh"], shank=L["shank"], upper_arm=L["upper_arm"], forearm=L["forearm"],
               hip_width=2 * hw, shoulder_width=2 * sw)
    return MotionClip(positions=world, rate=rate, names=BODY14, source=f"synthetic:{gait}:seed={seed}",
                      motion_class=gait, meta=dict(format="synthetic", segment_lengths=seg, stride_hz=f, speed=v,
                                                   heading=heading, gait=gait, height=height, seed=seed))
