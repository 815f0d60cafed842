"""Switching test sequences and the four-configuration comparison (Ukita Tables 1-2 style).

**Sequences.** Real recordings of different classes (same or different subjects) are joined at
their most similar poses: for consecutive parts ``A`` then ``B``, the pair ``(i, j)`` with the
smallest root-centred, heading-normalised pose distance (as in
:mod:`dtm_labeler.motion.transitions`) is searched over ``A``'s last frames and ``B``'s first
frames (each part keeps at least ``min_part`` frames); ``A`` is cut after frame ``i`` and ``B``
continues from frame ``j + 1``, turned about the vertical and moved so that its frame ``j``
coincides with ``A``'s frame ``i`` (same heading and horizontal root position; heights are
kept -- both stand on the floor). The result is one continuous stream whose true class
changes at every join; ``classes`` gives the class per frame, ``switches`` the first frame of
every new part.

**Configurations** (rows of the report):

1. ``pooled`` -- one model trained on all actions' training data, :class:`StreamLabeler`;
2. ``hard`` -- one model per action (no synthesized paths), one model at a time; after each
   frame the labeling is scored under every model and the best one labels the next frame;
3. ``bank`` -- the bank without synthesized transitions, :class:`BankLabeler` (population
   spread over the models, migration, smoothed active action);
4. ``bank+transitions`` -- the same with models trained with the synthesized paths.

**Metrics.** Overall accuracy (visible modelled points given their true label); accuracy in
a window of ``+-window`` frames around every switch; frames to recover (first frame after
the switch from which the frame accuracy stays >= ``recover_level`` for ``recover_frames``
frames; a switch never recovered counts as the frames left to the next switch); agreement of
the published active action with the true class (bank configurations and hard switching).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..labeling.corruption import corrupt_clip
from ..labeling.metrics import MetricsAccumulator
from ..model.features import lateral_yaw, rotation_z
from ..motion.clip import MotionClip
from ..motion.transitions import TRUNK_PAIRS, HIPS, normalized_poses, similarity_matrix

CONFIGS = ("pooled", "hard", "bank", "bank+transitions")


@dataclass
class SwitchingSequence:
    clip: MotionClip                      # body14, continuous
    classes: np.ndarray                   # (F,) true class per frame
    switches: list[int]                   # first frame of every part after the first
    parts: list[dict] = field(default_factory=list)

    @property
    def name(self) -> str:
        return " -> ".join(p["class"] for p in self.parts)


def _move(P: np.ndarray, dpsi: float, pivot: np.ndarray, to: np.ndarray) -> np.ndarray:
    """Rotate (F, N, 3) about the vertical through ``pivot`` by dpsi and move pivot to ``to``
    (horizontally)."""
    R = rotation_z(np.array(dpsi))
    out = np.einsum("ij,fnj->fni", R, P - pivot) + pivot
    shift = np.zeros(3)
    shift[:2] = to[:2] - pivot[:2]
    return out + shift


def join_clips(parts: Sequence[MotionClip], min_part: int = 60, search: int = 240) -> SwitchingSequence:
    """Join body14 clips at their most similar poses (see the module doc)."""
    if len(parts) < 1:
        raise ValueError("no parts")
    rate = parts[0].rate
    for p in parts:
        if p.names != parts[0].names:
            raise ValueError("all parts need the same points (body14)")
        if abs(p.rate - rate) > 1e-6:
            raise ValueError("all parts need the same frame rate")
    P = parts[0].positions.copy()
    classes = [parts[0].motion_class] * len(P)
    info = [dict(source=parts[0].source, cls=parts[0].motion_class, start=0, frames=[0, len(P)])]
    switches = []
    for nxt in parts[1:]:
        start_cur = info[-1]["start"]
        lo = max(start_cur + min_part, len(P) - search)
        hi = min(search, nxt.n_frames - min_part)
        if lo >= len(P) or hi <= 0:
            raise ValueError(f"{nxt.source}: parts too short to join with min_part={min_part}")
        Y1 = normalized_poses(P[lo:])
        Y2 = normalized_poses(nxt.positions[:hi])
        S = similarity_matrix(Y1, Y2)
        a, b = np.unravel_index(int(np.argmax(S)), S.shape)
        i, j = lo + int(a), int(b)
        ra = P[i, list(HIPS)].mean(0)
        rb = nxt.positions[j, list(HIPS)].mean(0)
        dpsi = float(lateral_yaw(P[i:i + 1], TRUNK_PAIRS)[0] - lateral_yaw(nxt.positions[j:j + 1], TRUNK_PAIRS)[0])
        moved = _move(nxt.positions, dpsi, rb, ra)
        P = np.concatenate([P[:i + 1], moved[j + 1:]])
        classes = classes[:i + 1] + [nxt.motion_class] * (nxt.n_frames - j - 1)
        info[-1]["frames"][1] = info[-1]["frames"][0] + (i + 1 - info[-1]["start"])
        switches.append(i + 1)
        fr0 = int(nxt.meta.get("frame_range", [0])[0])
        info.append(dict(source=nxt.source, cls=nxt.motion_class, start=i + 1, frames=[j + 1, nxt.n_frames],
                         join_distance_m=float(-S[a, b]), source_frame_offset=fr0))
    clip = MotionClip(P, rate, parts[0].names, source="switching:" + "+".join(p.source.split("/")[-1] for p in parts),
                      motion_class="mixed", meta=dict(classes=classes, switches=switches))
    parts_out = [dict(source=d["source"], **{"class": d["cls"]}, start=d["start"], frames=d["frames"],
                      **{k: v for k, v in d.items() if k in ("join_distance_m",)}) for d in info]
    return SwitchingSequence(clip, np.array(classes, dtype=object), switches, parts_out)


@dataclass
class SequenceRun:
    config: str
    sequence: str
    correct: np.ndarray           # (F,) correct visible points per frame
    points: np.ndarray            # (F,) visible modelled points per frame
    active: list[str]             # (F,) active action ('' when the labeler has none)
    truth_classes: np.ndarray
    switches: list[int]
    accumulator: MetricsAccumulator
    wall_s: float

    @property
    def frame_accuracy(self) -> np.ndarray:
        return np.where(self.points > 0, self.correct / np.maximum(self.points, 1), np.nan)


def run_sequence(labeler, seq: SwitchingSequence, config: str, occlude: int = 0, clutter: int = 0,
                 noise_mm: float = 0.0, seed: int = 0, gap_frames: float = 1.0) -> SequenceRun:
    """Feed a (corrupted, shuffled) switching sequence to ``labeler`` (StreamLabeler or BankLabeler)."""
    stream = corrupt_clip(seq.clip, occlude=occlude, clutter=clutter, noise_mm=noise_mm, seed=seed,
                          gap_frames=gap_frames)
    acc = MetricsAccumulator(seq.clip.names, seq.clip.rate)
    F = len(stream)
    correct, points = np.zeros(F, int), np.zeros(F, int)
    active = []
    t0 = time.perf_counter()
    for k, f in enumerate(stream):
        res = labeler.process(f.xyz, f.stamp, truth=f.label_to_index)
        acc.add_result(f.truth, res, valid=np.isfinite(f.xyz).all(1))
        real = f.truth >= 0
        correct[k] = int((res.labels[real] == f.truth[real]).sum())
        points[k] = int(real.sum())
        active.append(getattr(res, "active_action", ""))
    return SequenceRun(config, seq.name, correct, points, active, seq.classes, list(seq.switches), acc,
                       time.perf_counter() - t0)


def switch_metrics(run: SequenceRun, window: int = 30, recover_level: float = 0.95,
                   recover_frames: int = 10) -> dict:
    """Per-run metrics (see the module doc)."""
    F = len(run.points)
    acc_f = run.frame_accuracy
    win = np.zeros(F, bool)
    rec = []
    bounds = list(run.switches) + [F]
    for s_idx, s in enumerate(run.switches):
        win[max(s - window, 0):min(s + window + 1, F)] = True
        end = bounds[s_idx + 1]
        good = np.nan_to_num(acc_f, nan=1.0) >= recover_level
        r = None
        for t in range(s, end):
            if good[t:min(t + recover_frames, end)].all():
                r = t - s
                break
        rec.append(end - s if r is None else r)
    tot = run.points.sum()
    wp = run.points[win].sum()
    have_active = any(a for a in run.active)
    agree = float(np.mean([a == c for a, c in zip(run.active, run.truth_classes)])) if have_active else None
    return {"frames": F, "accuracy": float(run.correct.sum() / tot) if tot else None,
            "switch_window_accuracy": float(run.correct[win].sum() / wp) if wp else None,
            "frames_to_recover": rec, "mean_frames_to_recover": float(np.mean(rec)) if rec else None,
            "active_action_accuracy": agree, "switches": len(run.switches), "wall_s": run.wall_s}


def pool_metrics(items: list[dict], runs: list[SequenceRun], window: int = 30) -> dict:
    """Pooled over sequences: point-weighted accuracies, all recoveries, frame-weighted agreement."""
    correct = sum(int(r.correct.sum()) for r in runs)
    points = sum(int(r.points.sum()) for r in runs)
    wc = wp = 0
    for r in runs:
        F = len(r.points)
        win = np.zeros(F, bool)
        for s in r.switches:
            win[max(s - window, 0):min(s + window + 1, F)] = True
        wc += int(r.correct[win].sum())
        wp += int(r.points[win].sum())
    rec = [x for it in items for x in it["frames_to_recover"]]
    ag = [(a == c) for r in runs for a, c in zip(r.active, r.truth_classes) if any(r.active)]
    return {"accuracy": correct / points if points else None, "switch_window_accuracy": wc / wp if wp else None,
            "mean_frames_to_recover": float(np.mean(rec)) if rec else None,
            "median_frames_to_recover": float(np.median(rec)) if rec else None,
            "active_action_accuracy": float(np.mean(ag)) if ag else None,
            "frames": int(sum(len(r.points) for r in runs)), "switches": len(rec),
            "wall_s": float(sum(r.wall_s for r in runs))}
