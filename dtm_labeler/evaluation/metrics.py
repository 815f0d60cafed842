"""Scores for labelled streams: accuracy, ghost rejection, swaps, search errors, latency.

Pure numpy. A :class:`MetricsAccumulator` is fed frame by frame (the offline pipeline,
``dtm-label`` and the node-side benchmark share it) and summarised as :class:`Metrics`.

Definitions (per frame, over the points that were actually in the input and finite):

* **accuracy** -- fraction of visible true markers (points whose true label is a model label)
  that were published with their true label. Points left unlabelled count as wrong.
* **ghost_rejection** -- fraction of clutter points (true label ``-1``) left unlabelled;
  ``None`` when no clutter point was seen.
* **swaps_per_min** -- a swap is a visible true marker whose published label changes from
  one non-empty label to a different non-empty label between consecutive frames in which
  that marker is visible; counted per minute of recording (frames / rate).
* **search_errors** -- frames where the true labeling is more likely under the model than
  the chosen one: ``truth_fitness > log_likelihood + 1e-6`` (frames without a finite
  ``truth_fitness`` are not checked). **search_errors_held**: of them, the frames whose truth
  the fast path's priors (the trajectories' and the clusters' memory of eq. 32 read as a hidden
  Markov chain, :meth:`~dtm_labeler.labeling.fast_path.FastPath._move_cost`) charge more than
  it gains: ``truth_fitness - truth_prior <= log_likelihood + 1e-6`` -- the labeler's objective
  preferred what it published (the memory held it; whether rightly is the accuracy's question),
  where the others are labelings the search did not reach. **search_error_kinds**: of the search
  errors with the search's own labels given, the frames in which the search's labeling put a
  label on a clutter point (``ghost``: a ghost holding a hidden marker's label, most often),
  left a visible true marker unlabelled (``left_out``) or gave one another label
  (``relabelled``: swaps, a limb's chain read one marker along); a frame counts under each kind
  it shows. What a search error is made of says where to look: a ghost's label wants a release,
  a chain shifted a region check.
* **latency** -- per-frame processing time (p50 / p99 / max, ms); **fps** -- frames per
  second of total processing time (sum of the per-frame latencies unless a wall time is
  given).
* **calibration_error** -- expected calibration error of the published confidences: labels
  published are put in ``CONFIDENCE_BINS`` equal-width bins by confidence; the count-weighted
  mean over bins of ``|mean confidence - fraction right|`` (0 = a consumer can read the
  confidence as a probability). **reliability** lists the bins (range, labels, mean
  confidence, fraction right).
* **confusion** -- ``(M + 1, M + 1)`` counts, rows = true label, columns = published
  label; index ``M`` is "clutter" for rows and "unlabelled" for columns.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

SEARCH_ERROR_TOL = 1e-6
#: what a search-error frame's labeling got wrong (module doc, *search_error_kinds*), and its words
SEARCH_ERROR_KINDS = {"ghost": "a label on a ghost", "left_out": "a marker left out",
                      "relabelled": "a marker relabelled"}
CONFIDENCE_BINS = 10


def accuracy(true_labels: np.ndarray, published: np.ndarray) -> float | None:
    """Fraction of points with a true label (>= 0) published with that label; None if none."""
    t, p = np.asarray(true_labels), np.asarray(published)
    vis = t >= 0
    return float((p[vis] == t[vis]).mean()) if vis.any() else None


def ghost_rejection(true_labels: np.ndarray, published: np.ndarray) -> float | None:
    """Fraction of clutter points (true label -1) left unlabelled (-1); None without clutter."""
    t, p = np.asarray(true_labels), np.asarray(published)
    ghost = t < 0
    return float((p[ghost] < 0).mean()) if ghost.any() else None


def is_search_error(truth_fitness: float, log_likelihood: float, tol: float = SEARCH_ERROR_TOL) -> bool:
    """The true labeling scores better than the chosen one (NaN truth -> False)."""
    return bool(np.isfinite(truth_fitness) and truth_fitness > log_likelihood + tol)


def percentile_summary(latency_ms: Sequence[float]) -> dict[str, float | None]:
    x = np.asarray(latency_ms, dtype=float)
    if x.size == 0:
        return {"p50": None, "p99": None, "max": None, "mean": None}
    return {"p50": float(np.percentile(x, 50)), "p99": float(np.percentile(x, 99)),
            "max": float(x.max()), "mean": float(x.mean())}


@dataclass
class Metrics:
    """Summary of a labelled stream (see the module doc for the definitions)."""

    labels: list[str]
    frames: int
    duration_s: float
    points: int                    # visible true markers scored
    correct: int
    accuracy: float | None
    frame_accuracy: float | None   # frames where every visible true marker got its label
    search_accuracy: float | None  # same as accuracy for the per-frame search result (before votes)
    ghosts: int
    ghost_rejection: float | None
    swaps: int
    swaps_per_min: float | None
    search_errors: int
    search_checked: int
    search_error_rate: float | None
    latency_ms: dict[str, float | None]
    fps: float | None
    full_search_rate: float | None
    per_label: dict[str, float | None]
    confusion: np.ndarray = field(repr=False)
    calibration_error: float | None = None
    reliability: list = field(default_factory=list)     # [lo, hi, labels, mean confidence, fraction right]
    search_errors_held: int = 0    # of the search errors, frames the fast path's priors held (module doc)
    search_error_kinds: dict = field(default_factory=dict)   # frames per kind of wrong label (module doc)

    def as_dict(self, confusion: bool = False) -> dict:
        """JSON-ready dict (confusion matrix only when asked: it is (M+1)^2 numbers)."""
        d = {k: getattr(self, k) for k in (
            "frames", "duration_s", "points", "correct", "accuracy", "frame_accuracy", "search_accuracy",
            "ghosts", "ghost_rejection", "swaps", "swaps_per_min", "search_errors", "search_errors_held",
            "search_error_kinds", "search_checked", "search_error_rate", "latency_ms", "fps", "full_search_rate", "calibration_error", "reliability",
            "per_label")}
        d["labels"] = len(self.labels)
        d["label_names"] = list(self.labels)
        if confusion:
            d["confusion"] = self.confusion.tolist()
        return d

    def confused_pairs(self, top: int = 5) -> list[tuple[str, str, int]]:
        """The most frequent (true, published) mistakes; 'clutter' / 'unlabelled' for index M."""
        M = len(self.labels)
        names = list(self.labels) + ["clutter"]
        cols = list(self.labels) + ["unlabelled"]
        c = self.confusion.copy()
        c[np.arange(M + 1), np.arange(M + 1)] = 0
        order = np.argsort(c, axis=None)[::-1][:top]
        out = []
        for k in order:
            i, j = divmod(int(k), M + 1)
            if c[i, j] > 0:
                out.append((names[i], cols[j], int(c[i, j])))
        return out


class MetricsAccumulator:
    """Feed one frame at a time with :meth:`add`; read :meth:`metrics` at any point.

    ``labels`` are the model's label names (index = label id); ``rate`` the recording's frame
    rate in Hz (for swaps per minute). Accumulators of different clips combine with
    :meth:`merge` (durations add up; swaps are never counted across clips).
    """

    def __init__(self, labels: Sequence[str], rate: float):
        if not rate > 0:
            raise ValueError("rate must be positive")
        self.labels = [str(x) for x in labels]
        self.M = len(self.labels)
        self.rate = float(rate)
        self.confusion = np.zeros((self.M + 1, self.M + 1), dtype=np.int64)
        self.search_confusion_diag = 0          # correct search labels
        self.search_points = 0
        self.frames = 0
        self.duration_s = 0.0
        self.frames_all_correct = 0
        self.frames_with_points = 0
        self.swaps = 0
        self.search_errors = 0
        self.search_errors_held = 0
        self.search_error_kinds = np.zeros(len(SEARCH_ERROR_KINDS), dtype=np.int64)
        self.search_checked = 0
        self.full_searches = 0
        self.full_known = 0
        self.latencies: list[float] = []
        self.conf_bins = np.zeros((CONFIDENCE_BINS, 3))     # labels, summed confidence, right
        self.wall_s: float | None = None
        self._last = np.full(self.M, -1, dtype=np.int64)     # published label at last visible frame

    # -- feeding ----------------------------------------------------------------------------
    def add(self, true_labels: np.ndarray, published: np.ndarray, *, latency_ms: float | None = None,
            log_likelihood: float = float("nan"), truth_fitness: float = float("nan"),
            search_labels: np.ndarray | None = None, full_search: bool | None = None,
            valid: np.ndarray | None = None, confidence: np.ndarray | None = None,
            truth_prior: float = 0.0) -> None:
        """One frame. ``true_labels`` / ``published`` (n,) label index per input point, -1 =
        clutter / unlabelled; ``valid`` (n,) bool: points that really were in the input
        (finite); others are ignored; ``truth_prior``: nats the fast path's priors charge the
        true labeling beyond the chosen one (module doc, *search_errors_held*)."""
        t = np.asarray(true_labels, dtype=np.int64).reshape(-1)
        p = np.asarray(published, dtype=np.int64).reshape(-1)
        if t.shape != p.shape:
            raise ValueError(f"true labels {t.shape} and published labels {p.shape} differ in length")
        if ((t >= self.M) | (p >= self.M)).any():
            raise ValueError(f"label index out of range for {self.M} labels")
        if valid is not None:
            v = np.asarray(valid, dtype=bool).reshape(-1)
            t, p = t[v], p[v]
            if search_labels is not None:
                search_labels = np.asarray(search_labels).reshape(-1)[v]
            if confidence is not None:
                confidence = np.asarray(confidence, dtype=float).reshape(-1)[v]
        marked = t[t >= 0]
        if np.unique(marked).size != marked.size:
            raise ValueError("a true label occurs on more than one point")
        ti = np.where(t < 0, self.M, t)
        pi = np.where(p < 0, self.M, p)
        np.add.at(self.confusion, (ti, pi), 1)
        vis = t >= 0
        if vis.any():
            self.frames_with_points += 1
            self.frames_all_correct += int((p[vis] == t[vis]).all())
        if search_labels is not None:
            s = np.asarray(search_labels, dtype=np.int64)
            self.search_points += int(vis.sum())
            self.search_confusion_diag += int((s[vis] == t[vis]).sum())
        # swaps: compare with the label published at this marker's previous visible frame
        cur = np.full(self.M, -2, dtype=np.int64)            # -2 = not visible this frame
        cur[t[vis]] = p[vis]
        seen = cur != -2
        prev = self._last
        self.swaps += int((seen & (prev >= 0) & (cur >= 0) & (prev != cur)).sum())
        self._last = np.where(seen, cur, prev)
        if confidence is not None:
            pub = p >= 0
            c = np.clip(np.asarray(confidence, dtype=float)[pub], 0.0, 1.0)
            b = np.minimum((c * CONFIDENCE_BINS).astype(np.int64), CONFIDENCE_BINS - 1)
            np.add.at(self.conf_bins, b, np.stack([np.ones_like(c), c, (p[pub] == t[pub]).astype(float)], 1))
        # search errors, latency
        if np.isfinite(truth_fitness):
            self.search_checked += 1
            missed = is_search_error(truth_fitness, log_likelihood)
            self.search_errors += int(missed)
            self.search_errors_held += int(missed and not is_search_error(truth_fitness - truth_prior, log_likelihood))
            if missed and search_labels is not None:          # ``s``: the search's labels, read above
                self.search_error_kinds += [((t < 0) & (s >= 0)).any(), (vis & (s < 0)).any(),
                                            (vis & (s >= 0) & (s != t)).any()]
        if latency_ms is not None:
            self.latencies.append(float(latency_ms))
        if full_search is not None:
            self.full_known += 1
            self.full_searches += int(bool(full_search))
        self.frames += 1
        self.duration_s += 1.0 / self.rate

    def add_result(self, true_labels: np.ndarray, result, valid: np.ndarray | None = None) -> None:
        """One frame from a :class:`~dtm_labeler.labeling.stream.FrameResult`-like object."""
        self.add(true_labels, result.labels, latency_ms=result.latency_ms,
                 log_likelihood=result.log_likelihood, truth_fitness=result.truth_fitness,
                 search_labels=result.search_labels, full_search=result.full_search, valid=valid,
                 confidence=result.confidence, truth_prior=getattr(result, "truth_prior", 0.0))

    def break_continuity(self) -> None:
        """Forget the last published labels (a new, unrelated stream follows)."""
        self._last[:] = -1

    @classmethod
    def merge(cls, parts: Iterable["MetricsAccumulator"]) -> "MetricsAccumulator":
        parts = list(parts)
        if not parts:
            raise ValueError("nothing to merge")
        out = cls(parts[0].labels, parts[0].rate)
        for a in parts:
            if a.labels != out.labels:
                raise ValueError("accumulators have different labels")
            out.confusion += a.confusion
            out.conf_bins += a.conf_bins
            out.search_error_kinds += a.search_error_kinds
            for k in ("search_confusion_diag", "search_points", "frames", "duration_s", "frames_all_correct",
                      "frames_with_points", "swaps", "search_errors", "search_errors_held", "search_checked", "full_searches",
                      "full_known"):
                setattr(out, k, getattr(out, k) + getattr(a, k))
            out.latencies.extend(a.latencies)
            if a.wall_s is not None:
                out.wall_s = (out.wall_s or 0.0) + a.wall_s
        return out

    # -- summary ----------------------------------------------------------------------------
    def metrics(self) -> Metrics:
        M, c = self.M, self.confusion
        diag = np.diag(c)[:M]
        rows = c[:M].sum(1)
        points = int(rows.sum())
        correct = int(diag.sum())
        ghosts = int(c[M].sum())
        proc_s = self.wall_s if self.wall_s is not None else sum(self.latencies) / 1e3
        fps = self.frames / proc_s if self.latencies or self.wall_s is not None else None
        if fps is not None and not np.isfinite(fps):
            fps = None
        ratio = lambda a, b: (float(a) / b) if b else None  # noqa: E731
        return Metrics(
            labels=list(self.labels), frames=self.frames, duration_s=self.duration_s, points=points,
            correct=correct, accuracy=ratio(correct, points),
            frame_accuracy=ratio(self.frames_all_correct, self.frames_with_points),
            search_accuracy=ratio(self.search_confusion_diag, self.search_points),
            ghosts=ghosts, ghost_rejection=ratio(int(c[M, M]), ghosts), swaps=self.swaps,
            swaps_per_min=ratio(self.swaps * 60.0, self.duration_s),
            search_errors=self.search_errors, search_errors_held=self.search_errors_held,
            search_error_kinds=dict(zip(SEARCH_ERROR_KINDS, self.search_error_kinds.tolist())),
            search_checked=self.search_checked,
            search_error_rate=ratio(self.search_errors, self.search_checked),
            latency_ms=percentile_summary(self.latencies), fps=fps,
            full_search_rate=ratio(self.full_searches, self.full_known),
            per_label={name: ratio(int(diag[i]), int(rows[i])) for i, name in enumerate(self.labels)},
            confusion=c.copy(), **self._reliability())

    def _reliability(self) -> dict:
        n, csum, right = self.conf_bins.T
        total = n.sum()
        if total == 0:
            return {"calibration_error": None, "reliability": []}
        used = n > 0
        ece = float((n[used] * np.abs(csum[used] / n[used] - right[used] / n[used])).sum() / total)
        rows = [[b / CONFIDENCE_BINS, (b + 1) / CONFIDENCE_BINS, int(n[b]), float(csum[b] / n[b]), float(right[b] / n[b])]
                for b in np.flatnonzero(used)]
        return {"calibration_error": ece, "reliability": rows}
