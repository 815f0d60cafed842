"""A second pass over a whole take, offline: every frame searched again from the take's votes.

Live, a frame is labelled from what it shows and from what came before it; the offline votes
(:mod:`.take_votes`) then relabel each track by the frames around it. With half of the markers
hidden at once (a real capture's occlusions) many frames are still wrong after the votes, and
most of them are search errors of the live pass: the model scores the true labeling higher
(HDM05, 50 % hidden: 274 of 600 frames); the live search started from the tracks' first
guesses and had a frame's budget. The voted labels are a better start. This pass searches
every frame again from them with the exact region relabelling of the search's final sweep
(:func:`~dtm_labeler.search.dtm_dp.relabel_regions`: every label's region relabelled given the
rest, each improvement polished, at most ``sweeps`` passes), twice:

* **at each candidate's own facing**, anchored on the start as live (the fitness of
  :mod:`dtm_labeler.search.problem`);
* **at the facing of the take**: every candidate scored at the frame's yaw read from the whole
  take -- each label's trajectory, its gaps filled linearly in time between the frames around
  them (:func:`filled_trajectories`), gives all heading pairs in every frame, as on the frames
  the model was trained on (:func:`take_heading`). A frame that shows few left/right pairs can
  give the true labeling a facing 100+ deg off (one wrist and one hip pair: their sum is not
  the trunk's lateral axis), and it is then scored below a wrong labeling whose pairs happen
  to give a sensible yaw; at the take's facing it is not (HDM05, 50 % hidden: within 6 deg of
  the true facing where the frames' own pairs were up to 95 deg off).

Both frames' results are voted over the take (eq. 32 over +- the same window, each frame's two
results one vote each): a frame one of the searches sends astray is outvoted. Neither search
alone is best everywhere (``benchmarks/bench_captures.py`` and the stored runs behind it,
votes -> own facing / take's facing / both voted): HDM05 41 markers, 50 % hidden, 93.8 ->
96.5 / 96.5 / 96.5 %; the Qualisys walk 92.8 -> 94.1 / 92.4 / 94.0 %; 12 HDM05 upper-body
markers, three 3-s parts: 43.1 -> 50.5 / 60.0 / 61.6 %, 58.8 -> 56.7 / 60.2 / 59.9 %, 85.9 ->
86.9 / 86.2 / 86.1 %. Tried and not kept: iterating the pass (96.5, 96.1, 96.4 %), regions
of 8 labels (96.2 %); after the votes, whole tracks exchanging labels where the sum of the
fitness change over the track's frames gains > 10 nats (a marker back from a gap labelled from
a frame whose neighbours were hidden too): HDM05 41 markers, 50 % hidden, 95.05 -> 96.08 %,
but the Qualisys walk 95.45 -> 92.24 % (from a live pass that also tried other fast-path
moves; the gapped model prefers a hand marker's neighbour
label by 1427 nats over 105 frames, at the take's facing and at each frame's own), and gated
to tracks the votes held at under 0.5, +0.5 and +0.0 points; branching on points the
regions' DP gives to two labels (as the full search's sweep does,
:func:`~dtm_labeler.search.dtm_dp.max_product`): HDM05 41 markers, 50 % hidden, 95.05 ->
94.56 % (the gap-free model's: 88.93 -> 89.66 %), 12 upper-body markers 70.8 -> 65.4 %, twice
the time.

Whole track pieces are relabelled by the take's own rigid marker pairs
(:mod:`.rigid_tracks`: distances that do not change over the take, summed over each piece's
frames, what one partner says clipped): HDM05 41 markers, 50 % hidden, 95.05 -> 98.33 %, the Qualisys
walk 94.81 -> 99.25 %; from the true labels it moves under 0.1 %. It runs twice: last, and
first, on the voted labels the searches start from (and the take's facing is read from): a
search started nearer the truth ends nearer it. Replayed on ``bench_captures.py``'s gapped runs
(13 runs: HDM05 gap seeds 1-4, seed 2 with capture ids only, and the Qualisys walk under search
seeds 0, 2, 3; capture ids / own tracker), last only -> first and last: mean 97.70 -> 98.23 %,
lowest 93.33 -> 94.17 %; 9 higher (the walk with capture ids, seeds 2 and 3: 96.22 -> 98.63,
96.94 -> 98.40 %; HDM05 seed 4, own tracker: 96.53 -> 98.03 %), 1 the same, 3 lower (HDM05
seeds 1 and 2 with capture ids: 99.20 -> 98.70, 99.47 -> 98.68 %; seed 1, own tracker: 99.61
-> 99.54 %; there the searches took again some of the exchanges the model prefers, and the
last pass did not undo them all). Tried with the start's labels as a
third vote beside the two searches: the walk, capture ids, seed 2, 93.10 %.

Last, a wrist bar's two ends exchanged over a stretch of the take are turned back where the
bar's orders, summed over the stretch, say so (:mod:`.bar_flips`: what no distance and no
frame's triangles tell apart; HDM05's whole gapped second halves 95.80 -> 96.52 % and 93.21 ->
94.58 %).

Last of all, whole track pieces are relabelled by the model's fitness summed over their
frames, a move allowed only where the take's rigid pairs do not object (:mod:`.fitness_pieces`:
the votes count frames, not nats; the ungated move of whole tracks above was tried and not
kept), and the rigid-pair pass runs once more, its pairs measured from the moved pieces
(HDM05's gapped halves, draws 1-6: draw 6 own tracker 98.47 -> 98.66 %, draw 3 with capture
ids 96.76 -> 96.79 %, the other cells and the Qualisys walk's draws 1-4 the same). Tried and
not kept: the fitness moves also before the bar flips (draw 5 own tracker 98.49 -> 98.17 %).

The searches keep the live pass's hold (``hold_nats`` after ``hold_s``: eq. 32 read as a hidden
Markov chain over each track's label, :meth:`~dtm_labeler.labeling.fast_path.FastPath._hold_cost`):
a label the start gives a point whose track carries it in at least ``hold_s`` of the take's
frames, and that a search leaves on no point with its point unlabelled, is given back unless
that costs ``hold_nats`` or more (:func:`kept_holds`). Searched without the tracks, a frame
prefers a visible body point as clutter wherever the model explains it a few nats worse than
its absence: ``dtm-train``'s model of subject 7's walk, calibrated to subject 55, hangs the
legs' triangles on the wrists (a walk swings them against each other), and in a whirl the
left wrist costs more than it is worth; the live pass held it (100 %), the searches dropped it
in 1465 of the take's 1806 frames (94.2 %), the pirouette's in 305 of 591 (96.3 %). With the
hold: 100 % both. ``bench_captures``' gapped halves (HDM05 draws 1-6, own tracker and capture
ids; the Qualisys walk's draws 1-4) and the 22-marker rehearsal's draws 1-4: every cell the same.
Lower: a real finger marker fed as a ghost beside a half-hidden wrist (``results/captures.md``'s
end-to-end 22-marker rehearsal), which the searches had taken off the wrist's label in some
frames: 97.95 -> 97.85 %, ghosts rejected 89.4 -> 88.8 % (the losses given back there are
smaller than the whirl's, 2.3 against 5.0 nats at the median: no threshold keeps one and not
the other).

The hold's other half, the clutter state (as live, :meth:`~dtm_labeler.labeling.fast_path.FastPath._hold_cost`):
a label a search gives a point the start leaves unlabelled, on a track the start leaves unlabelled in at least
``hold_s`` of the take's frames (:func:`clutter_points`: a real ghost, a stray or reflected marker), goes back to the
start's point (or to none) unless keeping it gains ``hold_nats`` or more (:func:`kept_clutter`). The end-to-end
22-marker rehearsal capture (a finger marker the model does not know, fed as a `*` channel beside a half-hidden
wrist): ghosts rejected 89.7 -> 93.1 %, accuracy 98.19 % either way; ``bench_captures``' gapped halves (HDM05 draws
1-4, own tracker and capture ids; the Qualisys walk's draws 1-4), the 22-marker draws 1-4 with three fixed
reflections, its ghosts and unnamed-capture sections: the same, or up to +0.02 points.

States: positions and backward-difference velocities along the labeler's tracks (a point
without a previous frame on its track has no velocity, as live). Single-model labelers only
(a bank's frames were scored by different models).
"""
from __future__ import annotations

import copy
from typing import Callable, Sequence

import numpy as np

from ..model.body import Handedness, segment_clusters
from ..model.dtm import TriangulatedModel
from ..model.features import STATE_DIM, lateral_yaw
from ..search.label_search import sweep_regions
from ..search.problem import Background, FrameProblem
from .bar_flips import flip_bars, take_bar_orders
from .config import DEFAULTS
from .fitness_pieces import relabel_by_fitness
from .rest_clock import take_rests
from .rigid_tracks import body_pairs, label_positions, relabel_tracks, rigid_pairs, spread_sample
from .take_votes import take_votes

#: frames of a take (spread over it) on which :func:`person_handedness` judges the person
JUDGE_FRAMES = 1200

__all__ = ["filled_trajectories", "take_heading", "track_states", "take_pass", "person_handedness"]


def filled_trajectories(xyz: Sequence[np.ndarray], labels: Sequence[np.ndarray], n_labels: int) -> np.ndarray:
    """(F, n_labels, 3) position of each label per frame from the frames' labelled points,
    each label's gaps filled linearly in time between the frames that show it (before its
    first / after its last sighting: held); a label never given stays NaN."""
    P = label_positions(xyz, labels, n_labels)
    seen = np.isfinite(P[..., 0])
    t = np.arange(len(xyz))
    for m in np.flatnonzero(seen.any(0) & ~seen.all(0)):
        ok = seen[:, m]
        for c in range(3):
            P[~ok, m, c] = np.interp(t[~ok], t[ok], P[ok, m, c])
    return P


def take_heading(model: TriangulatedModel, xyz: Sequence[np.ndarray], labels: Sequence[np.ndarray],
                 smooth_frames: int = 6) -> np.ndarray:
    """(F,) facing yaw of every frame from the model's heading pairs over the labels' filled
    trajectories (module doc), averaged on the circle over +- ``smooth_frames``; frames
    without any pair: interpolated from the nearest frames that have one."""
    P = filled_trajectories(xyz, labels, model.n_labels)
    yaw = lateral_yaw(P, model.heading_pairs)
    ok = np.isfinite(yaw)
    if not ok.any():
        return np.zeros(len(xyz))
    if not ok.all():
        t = np.arange(yaw.size)
        yaw = np.interp(t, t[ok], np.unwrap(yaw[ok]))
    if smooth_frames > 0:
        z = np.pad(np.exp(1j * yaw), smooth_frames, mode="edge")
        yaw = np.angle(np.convolve(z, np.ones(2 * smooth_frames + 1), mode="valid"))
    return yaw


def track_states(xyz: Sequence[np.ndarray], track_ids: Sequence[np.ndarray], rate: float) -> list[np.ndarray]:
    """Per frame, (n, 6) states of its points: position and the backward-difference velocity
    along the point's track (NaN where its track was not in the frame before, or untracked)."""
    sizes = np.array([len(t) for t in track_ids], dtype=np.int64)
    if sizes.sum() == 0:
        return [np.zeros((0, STATE_DIM)) for _ in sizes]
    fr = np.repeat(np.arange(sizes.size), sizes)
    tid = np.concatenate([np.asarray(t, dtype=np.int64) for t in track_ids])
    pos = np.concatenate([np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in xyz])
    vel = np.full_like(pos, np.nan)
    o = np.lexsort((fr, tid))
    nxt, prv = o[1:], o[:-1]
    same = (tid[nxt] == tid[prv]) & (fr[nxt] == fr[prv] + 1) & (tid[nxt] >= 0)
    vel[nxt[same]] = (pos[nxt[same]] - pos[prv[same]]) * float(rate)
    states = np.concatenate([pos, vel], axis=1)
    return np.split(states, np.cumsum(sizes)[:-1])


def take_pass(model: TriangulatedModel, background: Background, xyz: Sequence[np.ndarray],
              track_ids: Sequence[np.ndarray], labels: Sequence[np.ndarray], rate: float, half_window: int,
              region_size: int = 6, polish_rounds: int = 4, sweeps: int = 2, heading_snap_deg: float = 4.0,
              progress: Callable[[int, int], None] | None = None,
              rigid_tracks: bool = True, fitness_pieces: bool = True, hold_nats: float = DEFAULTS["hold_nats"],
              hold_s: float = DEFAULTS["hold_s"]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per frame, the labels and confidences of its points after the second pass (module doc).
    ``labels``: the take-voted labels the pass starts from (-1 none); ``track_ids``: the
    labeler's track per point (-1 untracked: left unlabelled by the votes); ``progress(done,
    total)`` after every frame of each of the two searches. ``rigid_tracks``: whole track pieces
    relabelled by the take's rigid pairs (:mod:`.rigid_tracks`) before the searches start from
    the labels and again after the votes (a moved point keeps the confidence its votes gave).
    ``fitness_pieces``: last, whole track pieces relabelled by the model's fitness summed over
    their frames where the rigid pairs allow it (:mod:`.fitness_pieces`), then (with
    ``rigid_tracks``) the rigid-pair pass once more; the same. ``hold_nats``, ``hold_s``: the
    live pass's hold, kept by the searches (module doc; ``hold_nats`` 0: none)."""
    F = len(xyz)
    prior = body_pairs(model.body)
    if rigid_tracks:
        labels, _ = relabel_tracks(xyz, track_ids, labels, model.n_labels, prior=prior)
    model = person_handedness(model, xyz, labels, prior)
    states = track_states(xyz, track_ids, rate)
    rests = take_rests(xyz, track_ids, rate)
    yaw = take_heading(model, xyz, labels)
    total = 2 * F

    def counted(k: int, _: int) -> None:
        if progress is not None:
            progress(k, total)
    held = held_labels(track_ids, labels, int(round(hold_s * rate))) if hold_nats > 0 else None
    clutter = clutter_points(track_ids, labels, int(round(hold_s * rate))) if hold_nats > 0 else None
    own = _searched(model, background, states, rests, labels, region_size, polish_rounds, sweeps,
                    heading_snap_deg, None, counted, held, hold_nats, clutter)
    take = _searched(model, background, states, rests, labels, region_size, polish_rounds, sweeps,
                     heading_snap_deg, yaw, lambda k, _: counted(F + k, total), held, hold_nats, clutter)
    # both searches' frames voted together: interleaved as frames 2f and 2f + 1, the window doubled
    # (+1: the last frame of each side keeps both of its results)
    tracks2 = [t for t in track_ids for _ in (0, 1)]
    both = [x for pair in zip(own, take) for x in pair]
    lab2, conf2 = take_votes(tracks2, both, model.n_labels, 2 * half_window + 1)
    lab, conf = lab2[0::2], conf2[0::2]
    if rigid_tracks:
        lab, _ = relabel_tracks(xyz, track_ids, lab, model.n_labels, prior=prior)
    orders = take_bar_orders(model)
    if orders.shape[0]:                          # a bar's ends exchanged over a stretch (.bar_flips)
        lab, _ = flip_bars(xyz, track_ids, lab, orders, model.n_labels,
                           groups=segment_clusters(model.n_labels, model.body.segments))
    if fitness_pieces:
        lab, _ = relabel_by_fitness(model, background, states, rests, take_heading(model, xyz, lab), xyz, track_ids,
                                    lab, (own, take), prior=prior, heading_snap_deg=heading_snap_deg)
        if rigid_tracks:                         # the rigid pairs measured again from the moved pieces
            lab, _ = relabel_tracks(xyz, track_ids, lab, model.n_labels, prior=prior)
    return [model.published(x) for x in lab], conf


def person_handedness(model: TriangulatedModel, xyz: Sequence[np.ndarray], labels: Sequence[np.ndarray],
                      prior=None) -> TriangulatedModel:
    """``model`` with its marker clusters' handedness applied (:class:`~dtm_labeler.model.body.Handedness`)
    when its body is not calibrated but one person's (``prior``: :func:`~.rigid_tracks.body_pairs`
    of it) and the take shows that person (:meth:`~.rigid_tracks.RigidPairs.shows`, measured on
    ``labels``); else ``model`` itself. A shallow copy: the caches are shared.

    Why: a generic body keeps the quadruples but applies them only once calibrated, because
    another lab places a cluster's markers otherwise (CMU 85's right wrist bar against HDM05's).
    A take of the person and session the model was trained on has the same placement. Measured
    on ``benchmarks/bench_captures.py``'s gapped halves (gap seeds 1-4, capture ids / own
    tracker): HDM05 mean 98.29 -> 98.56 % (gap seed 3, own tracker, 97.83 -> 99.26 %), the
    Qualisys walk 97.17 -> 97.12 %; 4 of the 16 cells lower by 0.04-0.52 points."""
    b = model.body
    if b is None or b.calibration or model.body_handedness is not None or not b.quads.shape[0] or prior is None:
        return model
    sample = spread_sample(len(xyz), JUDGE_FRAMES)
    if not sample.size or not rigid_pairs(label_positions([xyz[f] for f in sample], [labels[f] for f in sample],
                                                          model.n_labels)).shows(prior):
        return model
    hand = Handedness(b)
    if not hand.active:
        return model
    out = copy.copy(model)
    out.body_handedness = hand
    return out


def _searched(model, background, states, rests, labels, region_size, polish_rounds, sweeps, heading_snap_deg,
              yaw: np.ndarray | None, progress, held: Sequence[np.ndarray] | None = None,
              hold_nats: float = 0.0, clutter: Sequence[np.ndarray] | None = None) -> list[np.ndarray]:
    """Per frame, the labels (-1 none) of its points after the region sweeps from ``labels``:
    at each candidate's own facing (``yaw`` None), else every candidate at ``yaw[f]``. ``held``
    (per frame, (n,) bool; None: no hold): the points whose start label their track holds (:func:`held_labels`);
    a search that leaves such a label on no point and its point unlabelled gives it back unless
    that costs ``hold_nats`` or more (:func:`kept_holds`). ``clutter`` (per frame, (n,) bool): the
    points on tracks the start leaves unlabelled for ``hold_s`` (:func:`clutter_points`), whose labels
    from a search go back unless keeping them gains ``hold_nats`` or more (:func:`kept_clutter`)."""
    out = []
    for f, st in enumerate(states):
        lab = np.asarray(labels[f], dtype=np.int64)
        problem = FrameProblem(model, st, background, heading_snap_deg=heading_snap_deg, rest_s=rests[f])
        ind = problem.empty_assignment()
        ok = lab >= 0
        ind[lab[ok]] = np.flatnonzero(ok)
        if problem.n:
            if yaw is None:
                problem.anchor_heading(ind)
            else:
                problem.anchor, problem.snap = float(yaw[f]), np.pi      # every candidate at the take's facing
            start = ind.copy()
            ind, fit, _ = sweep_regions(problem, ind, float(problem.fitness(ind)[0]), sweeps, region_size, polish_rounds)
            if held is not None:
                ind = kept_holds(problem, start, ind, fit, np.asarray(held[f], dtype=bool), hold_nats)
                if clutter is not None:
                    ind = kept_clutter(problem, start, ind, float(problem.fitness(ind[None])[0]),
                                       np.asarray(clutter[f], dtype=bool), hold_nats)
        res = np.full(problem.n, -1, dtype=np.int64)
        given = ind < problem.n
        res[ind[given]] = np.flatnonzero(given)
        out.append(res)
        progress(f + 1, len(states))
    return out


def kept_clutter(problem: FrameProblem, start: np.ndarray, ind: np.ndarray, fit: float, clutter: np.ndarray,
                 hold_nats: float) -> np.ndarray:
    """``ind`` with each label it gives a ``clutter`` point (left unlabelled by ``start``)
    given back to ``start``'s point (or left on no point, where that point is taken or there was
    none) where the fitness loses under ``hold_nats`` (the smallest loss first, one at a time)."""
    n = problem.n

    def back(cur: np.ndarray, labels: list[int]) -> np.ndarray:
        taken = np.zeros(n + 1, dtype=bool)
        taken[cur[cur < n]] = True
        return np.array([start[l] if start[l] < n and not taken[start[l]] else n for l in labels])
    return _given_back(problem, ind, fit, [int(l) for l in np.flatnonzero(ind < n) if clutter[ind[l]]], back,
                       hold_nats)


def clutter_points(track_ids: Sequence[np.ndarray], labels: Sequence[np.ndarray], hold_frames: int) -> list[np.ndarray]:
    """Per frame, (n,) whether each point is left unlabelled (``labels`` -1) on a track
    (``track_ids``, -1 untracked) left unlabelled in at least ``hold_frames`` frames of the take."""
    tids, labs = _flat(track_ids), _flat(labels)
    idle = (tids >= 0) & (labs < 0)
    return _per_frame(idle & (_counted(tids, idle) >= hold_frames), track_ids)


def held_labels(track_ids: Sequence[np.ndarray], labels: Sequence[np.ndarray], hold_frames: int) -> list[np.ndarray]:
    """Per frame, (n,) whether each point's label (``labels``, -1 none) is one its track
    (``track_ids``, -1 untracked) carries in at least ``hold_frames`` frames of the take."""
    tids, labs = _flat(track_ids), _flat(labels)
    ok = (tids >= 0) & (labs >= 0)
    keys = tids * (int(labs.max(initial=0)) + 1) + labs
    return _per_frame(ok & (_counted(keys, ok) >= hold_frames), track_ids)


def _flat(per_frame: Sequence[np.ndarray]) -> np.ndarray:
    """Per-frame integer arrays concatenated."""
    return np.concatenate([np.asarray(x, dtype=np.int64) for x in per_frame]) if len(per_frame) else np.zeros(0, int)


def _counted(keys: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """For each entry where ``ok``, how many ``ok`` entries share its key (0 elsewhere)."""
    uniq, counts = np.unique(keys[ok], return_counts=True)
    n_of = np.zeros(keys.size, dtype=np.int64)
    n_of[ok] = counts[np.searchsorted(uniq, keys[ok])]
    return n_of


def _per_frame(flat: np.ndarray, like: Sequence[np.ndarray]) -> list[np.ndarray]:
    return np.split(flat, np.cumsum([len(t) for t in like])[:-1])


def kept_holds(problem: FrameProblem, start: np.ndarray, ind: np.ndarray, fit: float, held: np.ndarray,
               hold_nats: float) -> np.ndarray:
    """``ind`` with each label that ``start`` gave a ``held`` point and ``ind`` leaves on no
    point, that point left unlabelled, given back where the fitness loses under ``hold_nats``
    (the label with the smallest loss first, one at a time)."""
    n = problem.n
    free = np.ones(n + 1, dtype=bool)
    free[ind[ind < n]] = False
    dropped = [int(l) for l in np.flatnonzero((ind == n) & (start < n)) if held[start[l]] and free[start[l]]]
    return _given_back(problem, ind, fit, dropped, lambda cur, labels: start[labels], hold_nats)


def _given_back(problem: FrameProblem, ind: np.ndarray, fit: float, labels: list[int], to, hold_nats: float
                ) -> np.ndarray:
    """``ind`` with ``labels`` moved, one at a time, each to ``to(current, labels)``'s point: the
    move that loses least first, while it loses under ``hold_nats``."""
    labels = list(labels)
    while labels:
        cand = np.repeat(ind[None], len(labels), 0)
        cand[np.arange(len(labels)), labels] = to(ind, labels)
        f = problem.fitness(cand)
        k = int(np.argmax(f))
        if f[k] <= fit - hold_nats:
            break
        ind, fit = cand[k], float(f[k])
        labels.pop(k)
    return ind
