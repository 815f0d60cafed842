"""Simulated measurement trouble for labelled clips: occlusions, ghosts, noise, shuffling.

Turns a labelled :class:`~dtm_labeler.motion.MotionClip` into the stream an optical system
would deliver -- an unordered, unlabeled point cloud per frame -- while remembering the truth
for scoring. Pure numpy, no ROS; used by ``dtm-label``, ``dtm-bag make``, the demo and tests.

Per frame, in this order:

* **occlusion** -- ``occlude`` of the visible true points are hidden (fewer if fewer are
  visible). ``gap_frames`` is the mean length of one simulated gap in frames: 1 (default)
  draws the hidden set afresh every frame (the paper's "randomly remove K points"); larger
  values keep a hidden point hidden for a geometric number of frames, topping the set up
  to ``occlude`` as gaps end. Points missing in the clip itself (NaN) stay missing and do
  not count towards ``occlude``.
* **clutter / ghosts** -- exactly ``clutter`` extra points, each one a short-lived track (a
  reflection near the body): born next to a random visible true point at ``ghost_offset_m``
  (uniform range, random direction), it moves with that point (plus a few mm of jitter)
  for ``ghost_life_s`` (uniform range) and is then replaced by a new ghost with a new id.
  Ghosts never carry a true label (truth ``-1``).
* **unlabelled points** -- ``extra`` (F, K, 3) real points of the take that are not the
  model's (a C3D's ``*`` channels, markers the model does not know; see
  :mod:`dtm_labeler.motion.unlabelled`) are delivered where finite, never hidden, truth ``-1``
  like ghosts; each keeps its id while it stays visible. Fixed reflections of the capture
  volume (:func:`static_ghosts`) come the same way.
* **noise** -- i.i.d. Gaussian noise of ``noise_mm`` (std per coordinate, mm) on every point.
* **shuffle** -- the points are permuted randomly, so their order carries no label; the
  truth moves with them.

Track ids imitate a mocap system's: a true point keeps its id while it stays visible and gets
a new one when it reappears after a gap (simulated or in the clip); every ghost has its own.
Ids are handed out in shuffled order, so they carry no label either.

Everything is reproducible: equal arguments and ``seed`` give identical streams.

Example::

    stream = corrupt_clip(clip.select(model.labels), occlude=2, clutter=3, noise_mm=2, seed=1)
    for f in stream:
        res = labeler.process(f.xyz, f.stamp, ids=f.ids)
        ok = res.labels[f.truth >= 0] == f.truth[f.truth >= 0]
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np

from ..motion.clip import MotionClip


@dataclass
class CorruptedFrame:
    """One frame as a measurement system would deliver it (plus the hidden truth)."""

    index: int                    # frame number in the clip
    stamp: float                  # seconds from the clip start (index / rate)
    xyz: np.ndarray               # (n, 3) float64, metres, shuffled
    truth: np.ndarray             # (n,) int64 label index (clip column) per point, -1 = ghost
    ids: np.ndarray               # (n,) int64 persistent track id per point (>= 0, fits uint32)
    label_to_index: np.ndarray    # (M,) int64 row of xyz carrying label m, -1 = missing

    @property
    def n(self) -> int:
        return self.xyz.shape[0]

    @property
    def n_ghosts(self) -> int:
        return int((self.truth < 0).sum())


@dataclass
class CorruptedStream:
    """All frames of a corrupted clip. Iterable, indexable, ``len()`` = frames."""

    frames: list[CorruptedFrame]
    names: tuple[str, ...]        # label names; label index m is ``names[m]``
    rate: float
    source: str
    visible: np.ndarray           # (F, M) bool: true point delivered in that frame
    occluded: np.ndarray          # (F, M) bool: hidden by the simulation (not missing in the clip)
    settings: dict                # the arguments, for reports

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[CorruptedFrame]:
        return iter(self.frames)

    def __getitem__(self, i: int) -> CorruptedFrame:
        return self.frames[i]

    @property
    def n_labels(self) -> int:
        return len(self.names)


def occlusion_mask(available: np.ndarray, k: int, rng: np.random.Generator, gap_frames: float = 1.0) -> np.ndarray:
    """(F, M) bool: which available points to hide so that ``min(k, available)`` are hidden
    per frame. ``gap_frames`` = mean gap length in frames (>= 1; 1 = independent per frame)."""
    available = np.asarray(available, dtype=bool)
    F, M = available.shape
    hidden = np.zeros((F, M), dtype=bool)
    if k <= 0 or F == 0 or M == 0:
        return hidden
    if gap_frames < 1:
        raise ValueError("gap_frames must be >= 1")
    p_end = 1.0 / gap_frames
    current = np.zeros(M, dtype=bool)
    for t in range(F):
        if gap_frames == 1.0:
            current[:] = False
        else:
            current &= rng.random(M) >= p_end          # gaps that go on
        current &= available[t]
        need = min(k, int(available[t].sum())) - int(current.sum())
        if need > 0:
            pool = np.flatnonzero(available[t] & ~current)
            current[rng.choice(pool, size=need, replace=False)] = True
        elif need < 0:                                   # fewer available now: release some
            on = np.flatnonzero(current)
            current[rng.choice(on, size=-need, replace=False)] = False
        hidden[t] = current
    return hidden


def realistic_gaps(n_frames: int, n_points: int, rate: float, missing: float = 0.5, mean_gap_s: float = 0.25,
                   spread: float = 8.0, seed: int = 0) -> np.ndarray:
    """(F, M) bool: True where a marker is occluded, the way a capture's gaps look.

    Each marker gets its own missing share (Beta distributed around ``missing``, concentration
    ``spread``: some markers are hidden most of the time, others rarely), and alternates
    seen and hidden runs whose lengths are log-normal (sigma 1: many flickers of a few frames
    and a tail of occlusions of a second or more); hidden runs have the mean ``mean_gap_s``,
    seen runs the mean that gives the marker its share. Markers start in a random phase."""
    if not 0.0 <= missing < 1.0:
        raise ValueError("missing must be in [0, 1)")
    rng = np.random.default_rng(seed)
    hidden = np.zeros((n_frames, n_points), dtype=bool)
    if missing == 0.0 or n_frames == 0:
        return hidden
    share = np.clip(rng.beta(missing * spread, (1.0 - missing) * spread, size=n_points), 0.02, 0.95)
    gap = max(1.0, mean_gap_s * rate)
    sigma = 1.0
    for p in range(n_points):
        means = (gap, gap * (1.0 - share[p]) / share[p])          # hidden, seen
        state = rng.random() < share[p]
        t = 0
        first = True
        while t < n_frames:
            mean = means[0] if state else means[1]
            length = rng.lognormal(np.log(mean) - sigma ** 2 / 2, sigma)
            if first:                                             # a random phase into the first run
                length *= rng.random()
                first = False
            n = max(1, int(round(length)))
            if state:
                hidden[t:t + n, p] = True
            t += n
            state = not state
    return hidden


def static_ghosts(positions: np.ndarray, count: int, seed: int = 0, floor_share: float = 0.5,
                  reach_m: float = 1.5) -> np.ndarray:
    """(F, count, 3) fixed points, the reflections a capture volume keeps whatever the subject
    does: floor tape, a force plate's edge, a prop. Each sits at one place for the whole take
    (NaN nowhere): horizontally within ``reach_m`` of the body's path (the median of each
    frame's visible points, Z up), on the floor (0-2 cm up) for a ``floor_share`` of them, at
    0-2 m otherwise. Pass as ``corrupt_clip(..., extra=...)``: they are delivered every frame,
    never hidden, truth ``-1``."""
    if count < 0:
        raise ValueError("count must be >= 0")
    P = np.asarray(positions, dtype=np.float64)
    rng = np.random.default_rng(seed)
    path = np.nanmedian(P, axis=1)                                        # (F, 3) the body's path
    lo, hi = np.nanmin(path, axis=0), np.nanmax(path, axis=0)
    xy = rng.uniform(lo[:2] - reach_m, hi[:2] + reach_m, size=(count, 2))
    on_floor = rng.random(count) < floor_share
    z = np.where(on_floor, rng.uniform(0.0, 0.02, count), rng.uniform(0.0, 2.0, count))
    pts = np.column_stack([xy, z]) if count else np.zeros((0, 3))
    return np.broadcast_to(pts, (P.shape[0], count, 3)).copy()


def _ghost_tracks(positions: np.ndarray, visible: np.ndarray, k: int, rate: float, rng: np.random.Generator,
                  offset_m: tuple[float, float], life_s: tuple[float, float], jitter_mm: float):
    """(F, k, 3) ghost positions and (F, k) generation number per slot (a new generation =
    a new ghost track)."""
    F = positions.shape[0]
    out = np.full((F, k, 3), np.nan)
    gen = np.zeros((F, k), dtype=np.int64)
    if k <= 0 or F == 0:
        return out, gen
    anchor = np.full(k, -1)
    offset = np.zeros((k, 3))
    left = np.zeros(k, dtype=np.int64)                   # frames this ghost still lives
    g = np.full(k, -1, dtype=np.int64)
    last = np.full((k, 3), np.nan)
    centre_fallback = np.zeros(3)
    for t in range(F):
        vis = np.flatnonzero(visible[t])
        if vis.size:
            centre_fallback = np.nanmean(positions[t, vis], axis=0)
        for s in range(k):
            if left[s] <= 0:
                g[s] += 1
                anchor[s] = rng.choice(vis) if vis.size else -1
                d = rng.normal(size=3)
                d /= np.linalg.norm(d) + 1e-12
                offset[s] = d * rng.uniform(*offset_m)
                left[s] = max(1, int(round(rng.uniform(*life_s) * rate)))
                last[s] = np.nan
            a = anchor[s]
            if a >= 0 and np.isfinite(positions[t, a]).all():
                p = positions[t, a] + offset[s]
            elif np.isfinite(last[s]).all():
                p = last[s]
            else:
                p = centre_fallback + offset[s]
            if jitter_mm > 0:
                p = p + rng.normal(scale=jitter_mm * 1e-3, size=3)
            out[t, s] = p
            last[s] = p
            gen[t, s] = g[s]
            left[s] -= 1
    return out, gen


def corrupt_clip(clip: MotionClip, occlude: int = 0, clutter: int = 0, noise_mm: float = 0.0, seed: int = 0,
                 shuffle: bool = True, gap_frames: float = 1.0, ghost_offset_m: tuple[float, float] = (0.05, 0.25),
                 ghost_life_s: tuple[float, float] = (0.1, 0.6), ghost_jitter_mm: float = 2.0,
                 extra: np.ndarray | None = None) -> CorruptedStream:
    """The clip as an unlabeled, shuffled stream with ``occlude`` hidden true points and
    ``clutter`` ghost points per frame, the take's own unlabelled points ``extra`` (F, K, 3)
    and ``noise_mm`` Gaussian noise (see the module doc). Label index ``m`` is the clip's
    column ``m`` (select the model's labels first)."""
    if occlude < 0 or clutter < 0 or noise_mm < 0:
        raise ValueError("occlude, clutter and noise_mm must be >= 0")
    if ghost_offset_m[0] < 0 or ghost_offset_m[1] < ghost_offset_m[0]:
        raise ValueError("ghost_offset_m must be a range (lo, hi) with 0 <= lo <= hi")
    if ghost_life_s[0] <= 0 or ghost_life_s[1] < ghost_life_s[0]:
        raise ValueError("ghost_life_s must be a range (lo, hi) with 0 < lo <= hi")
    rng = np.random.default_rng(seed)
    # independent streams per effect, so e.g. adding noise does not change the occlusions
    r_occ, r_ghost, r_noise, r_perm, r_id = (np.random.default_rng(s) for s in rng.integers(0, 2**63, size=5))
    P = clip.positions
    F, M, _ = P.shape
    available = np.isfinite(P).all(axis=2)
    hidden = occlusion_mask(available, int(occlude), r_occ, gap_frames)
    visible = available & ~hidden
    ghosts, gen = _ghost_tracks(P, visible, int(clutter), clip.rate, r_ghost, ghost_offset_m, ghost_life_s,
                                ghost_jitter_mm)
    if extra is None:
        extra = np.zeros((F, 0, 3))
    extra = np.asarray(extra, dtype=np.float64)
    if extra.ndim != 3 or extra.shape[0] != F or extra.shape[2] != 3:
        raise ValueError(f"extra points must be (frames={F}, K, 3), got {extra.shape}")
    K = extra.shape[1]
    extra_seen = np.isfinite(extra).all(axis=2)
    # an extra point's track: a new generation whenever it reappears
    extra_gen = np.cumsum(extra_seen & ~np.vstack([np.zeros((1, K), bool), extra_seen[:-1]]), axis=0)
    gen = np.concatenate([gen, extra_gen], axis=1)
    n_fake = int(clutter) + K

    next_id = int(r_id.integers(1, 1000))
    true_id = np.full(M, -1, dtype=np.int64)
    ghost_id = np.full(n_fake, -1, dtype=np.int64)
    ghost_gen = np.full(n_fake, -1, dtype=np.int64)
    slots = np.arange(n_fake)
    frames: list[CorruptedFrame] = []
    for t in range(F):
        lab = np.flatnonzero(visible[t])
        fake = np.concatenate([ghosts[t], extra[t]], axis=0)          # (clutter + K, 3)
        on = slots[np.concatenate([np.ones(int(clutter), bool), extra_seen[t]])]
        xyz = np.concatenate([P[t, lab], fake[on]], axis=0) if n_fake else P[t, lab].copy()
        truth = np.concatenate([lab, np.full(on.size, -1)]).astype(np.int64)
        if noise_mm > 0:
            xyz = xyz + r_noise.normal(scale=noise_mm * 1e-3, size=xyz.shape)
        order = r_perm.permutation(xyz.shape[0]) if shuffle else np.arange(xyz.shape[0])
        xyz, truth = xyz[order], truth[order]
        # ids: keep while continuously visible; new ones handed out in shuffled order
        true_id[~visible[t]] = -1
        ids = np.empty(xyz.shape[0], dtype=np.int64)
        for i, (m, src) in enumerate(zip(truth, order)):
            if m >= 0:
                if true_id[m] < 0:
                    true_id[m] = next_id
                    next_id += 1
                ids[i] = true_id[m]
            else:
                s = on[src - lab.size]
                if ghost_gen[s] != gen[t, s]:
                    ghost_gen[s] = gen[t, s]
                    ghost_id[s] = next_id
                    next_id += 1
                ids[i] = ghost_id[s]
        l2i = np.full(M, -1, dtype=np.int64)
        real = truth >= 0
        l2i[truth[real]] = np.flatnonzero(real)
        frames.append(CorruptedFrame(index=t, stamp=t / clip.rate, xyz=xyz, truth=truth, ids=ids,
                                     label_to_index=l2i))
    settings = dict(occlude=int(occlude), clutter=int(clutter), noise_mm=float(noise_mm), seed=int(seed),
                    shuffle=bool(shuffle), gap_frames=float(gap_frames), ghost_offset_m=list(ghost_offset_m),
                    ghost_life_s=list(ghost_life_s), ghost_jitter_mm=float(ghost_jitter_mm),
                    unlabelled_points=int(K), unlabelled_samples=int(extra_seen.sum()))
    return CorruptedStream(frames=frames, names=clip.names, rate=clip.rate, source=clip.source, visible=visible,
                           occluded=hidden, settings=settings)


def score_frame(labels: np.ndarray, truth: np.ndarray) -> tuple[int, int, int, int]:
    """``(correct, true_points, ghosts_unlabelled, ghosts)`` for one frame: ``labels`` (n,)
    published label per point (-1 none), ``truth`` (n,) true label (-1 ghost)."""
    labels = np.asarray(labels)
    truth = np.asarray(truth)
    real = truth >= 0
    return (int((labels[real] == truth[real]).sum()), int(real.sum()), int((labels[~real] < 0).sum()),
            int((~real).sum()))
