"""What every stream labeler shares: the per-frame input handling around the search.

:class:`TrackedLabeler` holds the stream state (tracker, vote book, the label each track
carries, last stamp, body centre and heading) and the steps before and after a search:
sanitising the cloud, time checks, bounding the points, tracking (:meth:`_begin`); warm-start
seeds from the tracks (:meth:`_seeds`); the targeted hill-climb of a carried-over labeling
(:meth:`_hill_climb`); the fitness of the true labeling for evaluation
(:meth:`_truth_fitness`); votes and bookkeeping after the search (:meth:`_publish`).
:class:`~dtm_labeler.labeling.stream.StreamLabeler` (one model) and
:class:`~dtm_labeler.labeling.bank_labeler.BankLabeler` (one model per action) differ only
in how they search and when they accept.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..search import label_ops
from ..search.dtm_dp import regions_of, relabel_regions
from ..search.label_search import polish, targeted_moves
from ..search.problem import FrameProblem
from .tracker import TrackUpdate


@dataclass
class FrameInput:
    """One cloud after sanitising and tracking."""

    n_in: int                 # points received
    finite: np.ndarray        # (n_in,) bool
    keep: np.ndarray          # input indices that enter the search
    pts: np.ndarray           # (n, 3) their positions
    upd: TrackUpdate          # track ids and states of the kept points
    reason: str               # why the window was reset, if it was
    n_ignored: int            # finite points beyond max_points
    dt: float | None          # seconds since the previous frame


def scatter(values: np.ndarray, keep: np.ndarray, n_in: int, fill) -> np.ndarray:
    """Per-kept-point values back to input order (``fill`` for dropped points)."""
    out = np.full(n_in, fill, dtype=np.asarray(values).dtype)
    out[keep] = values
    return out


class TrackedLabeler:
    """Base of the stream labelers (see the module doc); subclasses set ``settings``,
    ``tracker`` and ``votes`` and implement ``process``."""

    def _reset_stream(self) -> None:
        self.tracker.reset()
        self.votes.reset()
        self.track_label: dict[int, int] = {}      # label each track carries (also while coasting)
        self.last_stamp = None
        self.heading = None
        self.centre = None
        self._since_search = 0                     # frames since the last GA search (or reset)
        self._frame_no = 0
        self._new_tracks = np.zeros(0, dtype=np.int64)   # tracks started last frame
        self._event_points = np.zeros(0, dtype=np.int64)

    def predicted_position(self, track_id: int, stamp: float) -> np.ndarray:
        """(3,) position the tracker predicts for a (possibly coasting) track at ``stamp``; NaN
        when the track is unknown (never seen, or deleted after ``max_misses``)."""
        return self.tracker.position_of(int(track_id), stamp)

    def _note_search(self) -> None:
        """A GA search chose this frame's labeling: region checks are due for a while."""
        self._since_search = 0

    def _region_checks_due(self, M: int) -> bool:
        """Region checks run for one pass over the regions after a GA search or a reset
        (a search may land on a locally wrong labeling that tracking then carries on), and
        on every ``region_every``-th frame in between (a slow background check); steady
        frames otherwise cost only the hill-climb."""
        s = self.settings
        return self._since_search < M or (s.region_every > 0 and self._frame_no % s.region_every == 0)

    def _begin(self, xyz: np.ndarray, stamp: float, ids: np.ndarray | None, n_labels: int) -> FrameInput:
        s = self.settings
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        finite = np.isfinite(xyz).all(1)
        reason, dt = "", None
        if self.last_stamp is not None:
            dt = stamp - self.last_stamp
            if stamp < self.last_stamp:
                reason = "time went backwards"
            elif dt > s.max_gap_s:
                reason = f"gap of {dt:.2f} s"
            elif stamp == self.last_stamp:
                reason = "repeated stamp"
        if reason:
            self.reset()
        self.last_stamp = stamp
        keep = np.flatnonzero(finite)
        max_pts = s.max_points or 2 * n_labels + 8
        n_ignored = 0
        if keep.size > max_pts:        # bounded work: the points nearest the body's last centre
            ref = self.centre if self.centre is not None else np.median(xyz[keep], axis=0)
            d = np.linalg.norm(xyz[keep] - ref, axis=1)
            n_ignored = keep.size - max_pts
            keep = np.sort(keep[np.argsort(d)[:max_pts]])
        pts = xyz[keep]
        upd = self.tracker.update(pts, stamp, None if ids is None else np.asarray(ids)[keep])
        # points whose velocity is first known this frame (their track began last frame)
        self._event_points = np.flatnonzero(np.isin(upd.track_ids, self._new_tracks))
        self._new_tracks = upd.track_ids[upd.new]
        return FrameInput(xyz.shape[0], finite, keep, pts, upd, reason, n_ignored, dt)

    def _seeds(self, track_ids: np.ndarray, n: int, M: int) -> np.ndarray | None:
        """Warm start: the labels the tracks carried last frame (vectorised lookup); None when
        fewer than half of the frame's labels can be carried (a fresh search is due)."""
        if not self.track_label:
            return None
        seed = np.full(M, n, dtype=np.int64)
        tids = np.fromiter(self.track_label.keys(), dtype=np.int64, count=len(self.track_label))
        labs = np.fromiter(self.track_label.values(), dtype=np.int64, count=len(self.track_label))
        order = np.argsort(tids)
        pos = np.minimum(np.searchsorted(tids[order], track_ids), tids.size - 1)
        hit = tids[order][pos] == track_ids
        seed[labs[order][pos[hit]]] = np.flatnonzero(hit)
        if 2 * int(hit.sum()) < min(M, n):
            return None                  # most tracks are new (e.g. the input's ids restarted): search afresh
        if self.settings.method == "tracker":
            return seed[None]
        return label_ops.repair(seed[None], n, self.rng, fill=False)

    def _close_label_pairs(self, problem: FrameProblem, ind: np.ndarray) -> np.ndarray:
        """Pairs of labels whose points are closer than ``swap_radius_m`` (where the tracker
        may have swapped two markers that passed each other)."""
        have = np.flatnonzero(ind < problem.n)
        d = problem.dist[np.ix_(ind[have], ind[have])]
        i, j = np.nonzero(np.triu(d < self.settings.swap_radius_m, 1))
        return np.stack([have[i], have[j]], axis=1)

    def _hill_climb(self, problem: FrameProblem, seed: np.ndarray) -> tuple[np.ndarray, float, int]:
        """Steepest ascent of a carried-over labeling over its targeted moves (mirror,
        left/right and close-pair swaps, labels onto free points)."""
        n = problem.n
        close = self._close_label_pairs(problem, seed)

        def moves(ind):
            free = np.flatnonzero(~label_ops.used_mask(ind[None], n)[0])
            return targeted_moves(ind, n, problem.mirror_pairs, free, close,
                                  problem.allowed(ind) if free.size else None)

        ind, f, evals = polish(problem, seed, None, self.settings.fast_rounds, neighbours=moves)
        if self.settings.region_checks > 0 and problem.M > 3:
            centres = self._event_centres(problem, ind)
            if self._region_checks_due(problem.M):
                self._region_cursor = (getattr(self, "_region_cursor", -1) + 1) % problem.M
                centres = [self._region_cursor] + [c for c in centres if c != self._region_cursor]
            if centres:
                ind, f, e = self._region_checks(problem, ind, f, moves, centres[:self.settings.region_checks])
                evals += e
        return ind, f, evals

    def _event_centres(self, problem: FrameProblem, ind: np.ndarray) -> list[int]:
        """Labels where this frame's labeling is least settled: for each point whose track
        began last frame, its label, or the label of the nearest labelled point if it has
        none. Appearing points -- a marker back from a gap, a ghost -- are where a carried
        labeling goes wrong. They are checked once, in the frame their velocity is first
        known: in the frame a point appears its velocity is unknown (marginalised), the
        check would see half the evidence, and checking in both frames doubled the frames
        that pay for a check (measured before the compiled term kernel: p99 6.0 -> 5.3 ms
        at 14 points, 9.7 -> 8.5 ms at 41 markers with 3 gaps + 2 ghosts; accuracy
        98.4 -> 98.2 % and 92.5 -> 92.5 %)."""
        pts = self._event_points
        if pts.size == 0:
            return []
        have = np.flatnonzero(ind < problem.n)
        if have.size == 0:
            return []
        label_of = np.full(problem.n + 1, -1, dtype=np.int64)
        label_of[ind[have]] = have
        out = []
        for p in pts:
            lab = label_of[p]
            if lab < 0:
                lab = have[int(np.argmin(problem.dist[p, ind[have]]))]
            if lab not in out:
                out.append(int(lab))
        return out

    def _region_checks(self, problem: FrameProblem, ind: np.ndarray, f: float, moves,
                       centres: list[int]) -> tuple[np.ndarray, float, int]:
        """Exact relabelling of the body regions around ``centres`` given the rest
        (:func:`relabel_regions`): a wrong labeling that tracking carries on -- e.g. labels
        shifted one marker along a limb -- is put right; measured about 3-4 ms per region at
        41 markers."""
        def refine(x, fx):
            return polish(problem, x, fx, self.settings.fast_rounds, neighbours=moves)
        return relabel_regions(problem, ind, f, regions_of(problem.model, self.settings.region_size),
                               centres, refine)

    @staticmethod
    def _truth_fitness(problem: FrameProblem, truth: np.ndarray | None, inp: FrameInput) -> float:
        """Fitness of the true labeling (``truth``: input index per label, -1 missing)."""
        if truth is None:
            return float("nan")
        n = problem.n
        pos = np.full(inp.n_in + 1, n, dtype=np.int64)
        pos[inp.keep] = np.arange(inp.keep.size)
        tr = np.asarray(truth, dtype=np.int64)
        return float(problem.fitness(np.where(tr < 0, n, pos[np.where(tr < 0, inp.n_in, tr)])[None])[0])

    def _publish(self, problem: FrameProblem, assignment: np.ndarray, inp: FrameInput):
        """Votes (eq. 32) and bookkeeping after the search. Returns (assignment with -1 for
        missing, this frame's search labels per point, published labels, confidences)."""
        n = problem.n
        assign = np.where(assignment >= n, -1, assignment)
        search_labels = np.full(n, -1, dtype=np.int64)
        present = assign >= 0
        search_labels[assign[present]] = np.flatnonzero(present)
        upd = inp.upd
        self.votes.add(upd.track_ids, search_labels)
        if self.settings.mode == "stream":
            pub, conf = self.votes.publish(upd.track_ids, search_labels)
        else:
            pub, conf = search_labels.copy(), (search_labels >= 0).astype(float)
        # the next frame starts from this frame's search result, not from the votes: a
        # correction must not be undone by the window's older majority. Labels stay with
        # their tracks while they coast (occluded for a few frames).
        published = {int(t): int(lab) for t, lab in zip(upd.track_ids, search_labels) if lab >= 0}
        taken = set(published.values())
        seen = set(int(t) for t in upd.track_ids)
        lost = set(int(t) for t in upd.lost)
        self.track_label = {t: lab for t, lab in self.track_label.items()
                            if t not in seen and t not in lost and lab not in taken}
        self.track_label.update(published)
        self._since_search += 1
        self._frame_no += 1
        if present.any():
            self.centre = inp.pts[assign[present]].mean(0)
            self.heading = float(problem.yaw(np.where(assign < 0, n, assign)[None])[0])
        return assign, search_labels, pub, conf
