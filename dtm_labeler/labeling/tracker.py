"""Frame-to-frame point association, so every point gets a track id and (when it was seen
before) a velocity for the eq. 12 features.

Constant-velocity prediction, a gate that widens with the track's speed and with the time
since it was last seen, and optimal assignment (``scipy.optimize.linear_sum_assignment``).
When the input carries ids (a mocap system's unlabelled trajectories), a point keeps the
track of its id; a point with an id never seen before may still continue a track that lost
its point (the systems start a new id when a marker comes back from an occlusion -- with
flickering markers, every few frames): it is associated with the tracks left over by the same
gated assignment, and its id becomes an alias of that track. An id that was seen before and
whose track ended (a C3D channel, a trajectory that keeps its id through a long gap) is the same
marker coming back: it starts a track of its own again, never another marker's (the last
``RETIRED_IDS`` such ids are remembered). On HDM05's gapped second half with the channels as ids
(``benchmarks/bench_captures.py``), re-used ids had continued other markers' tracks: 131 of 11800
samples on a track that held another marker, 0 with this rule (the gapped Qualisys walk 137 -> 121:
the rest are ids first seen beside a coasting track); the benchmark's labels did not change.
The gate of a track seen ``dt`` ago is ``known_gate_m + gate_speed_factor |v| dt`` at the
stream's own frame interval when its velocity is known (seen twice or more), ``gate_m`` for a
track seen once: a known velocity predicts the point to a few millimetres, while a point seen
once may have moved several centimetres. The smaller radius keeps a neighbour of a dense cluster
(a hand, a foot, a wand) from taking over a coasting track. Second halves of the shared takes
with half of their samples in gaps (``benchmarks/bench_captures.py``, gap seed 1), samples on a
track that held another marker before, one radius of 6 cm -> 3 cm for known velocities: Qualisys
55-marker walk 183 -> 13 of 4679, HDM05 70 -> 44 of 11800 (gap seed 3: 46 -> 12), CMU 85_02
298 -> 115 of 7772; 4 cm for known velocities: 35, 67, 231.
When the update comes ``x`` later than that interval after the previous one (frames were skipped by a slow consumer, or lost) every gate grows by ``accel_mps2 x^2 / 2`` -- how far an acceleration can
take a marker off its constant-velocity prediction -- and, for a track whose velocity is not
known yet (seen once), by ``new_track_speed_mps x``: the tracks survive the skip instead of all
breaking (which would force a fresh search, and a slower frame, and more skips). When the input carries track ids
they are used instead. New, lost and re-appearing points are normal: a new track has no
velocity (NaN, marginalised by the model), a lost one coasts for ``max_misses`` frames.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.optimize import linear_sum_assignment

from .rest_clock import RestClock


#: the longest skip the gates are widened for (a longer pause is a gap: the stream is reset)
MAX_SKIP_S = 0.25


_OUTSIDE = 1e6               # cost of a pair outside the gate (never chosen unless forced)
#: :func:`member` compares every pair up to this many (else it sorts, as ``np.isin`` does)
MEMBER_PAIRS = 1 << 16
#: how many ids of ended tracks are remembered (module doc)
RETIRED_IDS = 4096


@njit(cache=True, nogil=True)
def gated_cost(pos, vel, last_t, gate, t, xyz, match):  # pragma: no cover - compiled
    """(K, n) distance of every point from every track's constant-velocity prediction at ``t``;
    ``_OUTSIDE`` beyond the track's gate, for points already matched (``match >= 0``) and for
    tracks they hold."""
    K, n = pos.shape[0], xyz.shape[0]
    cost = np.full((K, n), _OUTSIDE)
    held = np.zeros(K, dtype=np.bool_)
    for c in range(n):
        if match[c] >= 0:
            held[match[c]] = True
    for r in range(K):
        if held[r]:
            continue
        dt = t - last_t[r]
        px = pos[r, 0] + vel[r, 0] * dt
        py = pos[r, 1] + vel[r, 1] * dt
        pz = pos[r, 2] + vel[r, 2] * dt
        for c in range(n):
            if match[c] >= 0:
                continue
            d = np.sqrt((px - xyz[c, 0]) ** 2 + (py - xyz[c, 1]) ** 2 + (pz - xyz[c, 2]) ** 2)
            if d <= gate[r]:
                cost[r, c] = d
    return cost


def member(values: np.ndarray, among: np.ndarray) -> np.ndarray:
    """``np.isin(values, among)`` for the hot path's small integer arrays: one broadcast
    comparison (a few microseconds) where ``np.isin`` sorts both arrays (the retired ids held
    up to :data:`RETIRED_IDS`: ~3 % of a live node's time at 14 points, py-spy)."""
    values, among = np.asarray(values), np.asarray(among)
    if values.size * among.size > MEMBER_PAIRS:
        return np.isin(values, among)
    return (values.reshape(-1, 1) == among.reshape(1, -1)).any(1).reshape(values.shape)


def warm_up() -> None:
    """Load (or compile) :func:`gated_cost` and the rest clock's kernel now: lazily, the stream's
    second frame paid it (20-50 ms, the first frame with tracks to match), a live node's budget
    several times over."""
    one = np.zeros((1, 3))
    gated_cost(one, one, np.zeros(1), np.ones(1), 0.0, one, np.full(1, -1, dtype=np.int64))
    clock = RestClock()
    clock.update(np.zeros(1, dtype=np.int64), one, 0.0)
    clock.update(np.zeros(1, dtype=np.int64), one, 0.01)


@dataclass
class TrackerSettings:
    gate_m: float = 0.06               # base association radius (metres) of a track seen once
    known_gate_m: float = 0.03         # ... of a track whose velocity is known
    gate_speed_factor: float = 0.5     # + this x predicted travel in the frame
    max_misses: int = 12               # frames a lost track coasts before deletion
    accel_mps2: float = 50.0           # + accel dt^2 / 2: what acceleration adds to the prediction error
    new_track_speed_mps: float = 2.0   # a track seen once may have moved this fast

    def __post_init__(self) -> None:
        if not (self.gate_m > 0 and self.known_gate_m > 0) or min(
                self.gate_speed_factor, self.max_misses, self.accel_mps2, self.new_track_speed_mps) < 0:
            raise ValueError("gate_m and known_gate_m must be > 0; gate_speed_factor, max_misses, "
                             "accel_mps2, new_track_speed_mps >= 0")


@dataclass
class TrackUpdate:
    track_ids: np.ndarray      # (n,) int64
    states: np.ndarray         # (n, 6) position + velocity (NaN if the track is new)
    new: np.ndarray            # (n,) bool, track started this frame
    lost: np.ndarray           # ids of tracks deleted this frame
    rest_s: np.ndarray | None = None   # (n,) seconds each point has stayed put (:class:`.rest_clock.RestClock`)
    unseen_s: np.ndarray | None = None  # (n,) seconds each point's track coasted unseen (0: seen last frame, or new)


class Tracker:
    def __init__(self, settings: TrackerSettings | None = None):
        self.settings = settings or TrackerSettings()
        self.reset()

    def reset(self) -> None:
        self.alias_in = np.zeros(0, dtype=np.int64)     # input ids (sorted) that continue a track ...
        self.alias_to = np.zeros(0, dtype=np.int64)     # ... and the track ids they continue
        self.retired = np.zeros(0, dtype=np.int64)      # input ids of ended tracks, oldest first
        self.ids = np.zeros(0, dtype=np.int64)
        self.pos = np.zeros((0, 3))
        self.vel = np.zeros((0, 3))
        self.last_t = np.zeros(0)
        self.born = np.zeros(0)                        # stream time each track began
        self.misses = np.zeros(0, dtype=np.int64)
        self.known = np.zeros(0, dtype=bool)           # velocity estimated (seen twice or more)
        self._next_id = 0
        self.t = None
        self.frame_dt = None                           # running typical interval between updates
        self.rest = RestClock()                        # how long each track has stayed put

    def predicted(self, t: float) -> np.ndarray:
        dt = (t - self.last_t)[:, None]
        return self.pos + self.vel * dt               # finite: an unknown velocity is held as 0

    def gate(self, t: float) -> np.ndarray:
        """(K,) association radius of every track at time ``t`` (see the module doc)."""
        s = self.settings
        dt = t - self.last_t
        # skipped time: how much longer than usual since the tracker's last update (not since each
        # track was last seen: an occluded marker's coasting track keeps its ordinary gate)
        extra = min(max(t - self.t - self.frame_dt, 0.0), MAX_SKIP_S) if self.frame_dt and self.t is not None else 0.0
        speed = s.gate_speed_factor * np.linalg.norm(self.vel, axis=1)
        return (np.where(self.known, s.known_gate_m, s.gate_m) + speed * dt + 0.5 * s.accel_mps2 * extra * extra
                + np.where(self.known, 0.0, s.new_track_speed_mps * extra))

    def update(self, xyz: np.ndarray, t: float, ids: np.ndarray | None = None) -> TrackUpdate:
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        n = xyz.shape[0]
        match = np.full(n, -1, dtype=np.int64)        # index into current tracks
        if ids is not None:
            ids = np.asarray(ids, dtype=np.int64).reshape(-1)
            if self.alias_in.size:
                pos = np.minimum(np.searchsorted(self.alias_in, ids), self.alias_in.size - 1)
                ids = np.where(self.alias_in[pos] == ids, self.alias_to[pos], ids)
            if self.ids.size and n:
                rows, hit = self._rows(ids)
                match[hit] = rows[hit]
        if self.ids.size and n and (ids is None or (match < 0).any()):
            cost = gated_cost(self.pos, self.vel, self.last_t, self.gate(t), t, xyz, match)
            if ids is not None and self.retired.size:       # a known marker back: never an alias
                free = np.flatnonzero(match < 0)
                cost[:, free[member(ids[free], self.retired)]] = _OUTSIDE
            r, c = linear_sum_assignment(cost)
            ok = cost[r, c] < _OUTSIDE
            if ids is not None and ok.any():           # new ids that continue a track
                self._add_alias(ids[c[ok]], self.ids[r[ok]])
            match[c[ok]] = r[ok]
        m = match >= 0
        states = np.full((n, 6), np.nan)
        states[:, :3] = xyz
        mm = match[m]
        dt = t - self.last_t[mm]
        unseen = np.zeros(n)
        unseen[m] = np.where(self.misses[mm] > 0, dt, 0.0)     # a coasting track found again
        v = np.divide(xyz[m] - self.pos[mm], dt[:, None], out=np.full((mm.size, 3), np.nan), where=dt[:, None] > 0)
        states[m, 3:] = v
        track_ids = np.empty(n, dtype=np.int64)
        track_ids[m] = self.ids[mm]
        new = ~m
        n_new = int(new.sum())
        if ids is not None:
            track_ids[new] = ids[new]
            if n:
                self._next_id = max(self._next_id, int(ids.max()) + 1)
        else:
            track_ids[new] = np.arange(self._next_id, self._next_id + n_new)
            self._next_id += n_new
        # the track table: matched tracks move on, the others coast, old ones go, new ones come
        self.pos[mm] = xyz[m]
        finite = np.isfinite(v).all(1)
        self.vel[mm] = np.where(finite[:, None], v, 0.0)
        self.known[mm] = finite
        self.last_t[mm] = t
        self.misses += 1
        self.misses[mm] = 0
        keep = self.misses <= self.settings.max_misses
        lost = self.ids[~keep]
        if lost.size:
            ended = lost
            if self.alias_in.size:
                live = ~member(self.alias_to, lost)
                ended = np.concatenate([lost, self.alias_in[~live]])
                self.alias_in, self.alias_to = self.alias_in[live], self.alias_to[live]
            if ids is not None:
                self.retired = np.concatenate([self.retired, ended])[-RETIRED_IDS:]
            self.ids, self.pos, self.vel, self.known = self.ids[keep], self.pos[keep], self.vel[keep], self.known[keep]
            self.last_t, self.born, self.misses = self.last_t[keep], self.born[keep], self.misses[keep]
        if n_new:
            self.ids = np.concatenate([self.ids, track_ids[new]])
            self.pos = np.concatenate([self.pos, xyz[new]])
            self.vel = np.concatenate([self.vel, np.zeros((n_new, 3))])
            self.known = np.concatenate([self.known, np.zeros(n_new, dtype=bool)])
            self.last_t = np.concatenate([self.last_t, np.full(n_new, t)])
            self.born = np.concatenate([self.born, np.full(n_new, t)])
            self.misses = np.concatenate([self.misses, np.zeros(n_new, dtype=np.int64)])
        if self.t is not None and t > self.t:                 # the typical interval: a slow running median
            step = t - self.t
            fdt = self.frame_dt
            self.frame_dt = step if fdt is None else fdt + 0.05 * min(max(step - fdt, -fdt), fdt)
        self.t = t
        rest, _ = self.rest.update(track_ids, xyz, t)
        return TrackUpdate(track_ids, states, new, lost, rest, unseen)

    def _rows(self, track_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the track table holding ``track_ids`` (1-d) and which ids it holds."""
        track_ids = np.asarray(track_ids, dtype=np.int64).reshape(-1)
        if not self.ids.size:
            return np.zeros(track_ids.size, dtype=np.int64), np.zeros(track_ids.size, dtype=bool)
        order = np.argsort(self.ids)
        pos = np.minimum(np.searchsorted(self.ids[order], track_ids), self.ids.size - 1)
        return order[pos], self.ids[order[pos]] == track_ids

    def began(self, track_ids: np.ndarray) -> np.ndarray:
        """Stream time each of ``track_ids`` began; NaN for ids the tracker does not hold (ended
        tracks, input ids that continue one)."""
        rows, hit = self._rows(track_ids)
        return np.where(hit, self.born[rows] if self.born.size else np.nan, np.nan)

    def coasting(self, track_ids: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Of ``track_ids``: the stream time each was last seen, where it is predicted at ``t``
        (constant velocity) and whether its velocity is known (seen twice or more), (K,),
        (K, 3) and (K,); NaN (and False) for ids the tracker does not hold."""
        rows, hit = self._rows(track_ids)
        last = np.full(hit.size, np.nan)
        pred = np.full((hit.size, 3), np.nan)
        known = np.zeros(hit.size, dtype=bool)
        r = rows[hit]
        last[hit] = self.last_t[r]
        pred[hit] = self.predicted(t)[r]
        known[hit] = self.known[r]
        return last, pred, known

    def _add_alias(self, new_ids: np.ndarray, track_ids: np.ndarray) -> None:
        keys = np.concatenate([self.alias_in, new_ids])
        vals = np.concatenate([self.alias_to, track_ids])
        order = np.argsort(keys, kind="stable")
        self.alias_in, self.alias_to = keys[order], vals[order]

    def position_of(self, track_id: int, t: float) -> np.ndarray:
        """Predicted position of a (possibly coasting) track (or of an input id that continues
        one), NaN if unknown."""
        a = np.flatnonzero(self.alias_in == track_id)
        if a.size:
            track_id = int(self.alias_to[a[0]])
        i = np.flatnonzero(self.ids == track_id)
        if i.size == 0:
            return np.full(3, np.nan)
        i = i[0]
        return self.pos[i] + self.vel[i] * (t - self.last_t[i])      # :meth:`predicted`'s row
