"""Switching test sequences and the four-configuration comparison (Ukita Tables 1-2 style).

**Sequences.** Real recordings of different classes (same or different subjects) are joined at
their most similar poses: for consecutive parts ``A`` then ``B``, the pair ``(i, j)`` with the
smallest root-centred, heading-normalised pose distance (as in
:mod:`dtm_labeler.training.transitions`) is searched over ``A``'s last frames and ``B``'s first
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

import json
import os
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..jsonable import json_default
from ..labeling.bank_labeler import BankLabeler, BankSettings
from ..labeling.stream import LabelerSettings, StreamLabeler
from ..model.features import lateral_yaw, rotation_z
from ..motion.clip import MotionClip
from ..training.bank_training import build_bank
from ..training.train import TrainConfig, train_model
from ..training.transitions import (HIPS, TRUNK_PAIRS, TransitionSettings, TransitionSource,
                                    normalized_poses, similarity_matrix)
from .corruption import corrupt_clip
from .metrics import MetricsAccumulator
from .pipeline import model_clip, run_labeler

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
        cur_len = len(P) - start_cur
        lo = max(start_cur + max(min_part, cur_len // 2), len(P) - search)
        hi = min(search, nxt.n_frames - min_part, max(nxt.n_frames // 2, 1))
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


# ==================================================================== the experiment
DEFAULT_ACTIONS = {"walk": "cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh",
                   "run": "cmu_skeletal/bvh_from_fbx/cmu_09_11_run_s09.bvh",
                   "dance": "cmu_skeletal/bvh_from_fbx/cmu_55_01_dance-whirl_s55.bvh"}
DEFAULT_ORDERS = (("walk", "run", "dance", "walk"), ("dance", "walk", "run"), ("run", "walk", "dance"))


@dataclass
class ExperimentSettings:
    train_fraction: float = 0.6           # first part of every recording trains, the rest tests
    occlude: int = 2
    clutter: int = 2
    noise_mm: float = 2.0
    gap_frames: float = 8.0
    seeds: tuple[int, ...] = (1, 2, 3)
    window: int = 30
    recover_level: float = 0.95
    recover_frames: int = 10
    min_part: int = 30
    max_dance_frames: int = 300           # the dance test part is long; keep sequences balanced
    incremental: bool = True              # also run the L2-literal bank (paths only to earlier actions)
    train: dict | None = None             # TrainConfig keywords (None: the dtm-train defaults)


def prepare(data_dir, actions: dict | None = None, fraction: float = 0.6, skeletal: bool = True):
    """(training sources per action, held-out test clips per action)."""
    actions = actions or DEFAULT_ACTIONS
    src, test = {}, {}
    for a, rel in actions.items():
        p = Path(data_dir) / rel
        full = TransitionSource.load(p, skeletal=False)
        n = full.clip.n_frames
        k = int(round(fraction * n))
        src[a] = [TransitionSource.load(p, (0, k), skeletal=skeletal)]
        t = full.clip.slice(k, None)
        t.meta["frame_range"] = [k, n]
        t.motion_class = a
        test[a] = t
    return src, test


def build_configs(src: dict, config=None, transitions=None, incremental: bool = True, progress=print) -> dict:
    """Models of the configurations: pooled model, banks without / with synthesized paths."""
    config = config or TrainConfig()
    transitions = transitions or TransitionSettings()
    t = time.perf_counter()
    pooled, _ = train_model([s.clip for v in src.values() for s in v], config)
    progress(f"pooled model {time.perf_counter() - t:.0f} s")
    t = time.perf_counter()
    plain = build_bank(src, config, None)
    progress(f"bank without transitions {time.perf_counter() - t:.0f} s")
    t = time.perf_counter()
    trans = build_bank(src, config, transitions, mode="all")
    progress(f"bank with transitions {time.perf_counter() - t:.0f} s")
    out = {"pooled": pooled, "plain": plain, "trans": trans}
    if incremental:
        out["incremental"] = build_bank(src, config, transitions, mode="incremental")
    return out


def make_labeler(config: str, models: dict, settings=None):
    settings = settings or LabelerSettings()
    if config == "pooled":
        return StreamLabeler(models["pooled"], settings)
    if config == "hard":
        return BankLabeler(models["plain"], settings, BankSettings(strategy="hard"))
    if config == "bank":
        return BankLabeler(models["plain"], settings, BankSettings())
    if config == "bank+transitions":
        return BankLabeler(models["trans"], settings, BankSettings())
    if config == "bank+transitions (L2 incremental)":
        return BankLabeler(models["incremental"], settings, BankSettings())
    raise ValueError(f"unknown configuration {config!r}")


def run_experiment(data_dir, out_dir, settings: ExperimentSettings | None = None, progress=print) -> dict:
    """Train, build sequences, label them with every configuration, write report.md/json/PNG."""
    es = settings or ExperimentSettings()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    src, test = prepare(data_dir, fraction=es.train_fraction)
    if "dance" in test and es.max_dance_frames:
        d = test["dance"]
        test["dance"] = d.slice(0, es.max_dance_frames)
        test["dance"].meta["frame_range"] = [d.meta["frame_range"][0], d.meta["frame_range"][0] + es.max_dance_frames]
    models = build_configs(src, TrainConfig(**(es.train or {})), incremental=es.incremental, progress=progress)
    seqs = [join_clips([test[a] for a in order], min_part=es.min_part) for order in DEFAULT_ORDERS]
    configs = list(CONFIGS) + (["bank+transitions (L2 incremental)"] if es.incremental else [])
    results: dict = {c: {"runs": []} for c in configs}
    runs_by: dict = {c: [] for c in configs}
    example = {}
    for si, seq in enumerate(seqs):
        for seed in es.seeds:
            for c in configs:
                r = run_sequence(make_labeler(c, models), seq, c, es.occlude, es.clutter, es.noise_mm, seed,
                                 es.gap_frames)
                m = switch_metrics(r, es.window, es.recover_level, es.recover_frames)
                m.update(sequence=seq.name, seed=seed)
                results[c]["runs"].append(m)
                runs_by[c].append(r)
                if si == 0 and seed == es.seeds[0]:
                    example[c] = r
                progress(f"{c:34s} {seq.name:28s} seed {seed}: acc {m['accuracy']:.3f} window "
                         f"{m['switch_window_accuracy']:.3f} recover {m['frames_to_recover']} active "
                         f"{m['active_action_accuracy']}")
    for c in configs:
        results[c]["pooled"] = pool_metrics(results[c]["runs"], runs_by[c], es.window)
    trans_info = {a: models["trans"].records[a]["transitions"] for a in models["trans"].actions}
    for v in trans_info.values():
        for t in v:
            t.pop("paths_detail", None)
    payload = {"settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in es.__dict__.items()},
               "actions": {a: DEFAULT_ACTIONS[a] for a in src},
               "train_frames": {a: src[a][0].clip.meta.get("frame_range") for a in src},
               "sequences": [{"name": s.name, "frames": s.clip.n_frames, "switches": s.switches, "parts": s.parts}
                             for s in seqs],
               "transitions": trans_info,
               "incremental_transitions": ({a: [{k: v for k, v in t.items() if k != "paths_detail"}
                                                for t in models["incremental"].records[a]["transitions"]]
                                            for a in models["incremental"].actions} if es.incremental else None),
               "results": results, "wall_s": time.perf_counter() - t_all, "code": _code_version()}
    (out_dir / "results.json").write_text(json.dumps(payload, indent=1, default=json_default))
    _plot(example, seqs[0], configs, results, out_dir / "switching.png")
    (out_dir / "report.md").write_text(_report(payload, configs))
    return payload


def _code_version() -> str:
    if os.environ.get("DTM_CODE_COMMIT"):
        return os.environ["DTM_CODE_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5,
                              cwd=os.path.dirname(__file__)).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def _plot(example: dict, seq: SwitchingSequence, configs, results, path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(configs) + 1, 1, figsize=(10, 1.6 * (len(configs) + 1) + 1), sharex=True)
    acts = sorted(set(seq.classes))
    ymap = {a: i for i, a in enumerate(acts)}
    t = np.arange(seq.clip.n_frames) / seq.clip.rate
    for ax, c in zip(axes[:-1], configs):
        r = example[c]
        ax.plot(t, r.frame_accuracy, lw=0.8, color="C0")
        ax.set_ylim(-0.05, 1.05)
        ax.set_ylabel("acc", fontsize=8)
        ax.set_title(c, fontsize=9, loc="left")
        for s in seq.switches:
            ax.axvline(s / seq.clip.rate, color="k", ls=":", lw=0.8)
        if any(r.active):
            ax2 = ax.twinx()
            ax2.plot(t, [ymap.get(a, np.nan) for a in r.active], color="C3", lw=1.0, drawstyle="steps-post")
            ax2.set_yticks(range(len(acts)))
            ax2.set_yticklabels(acts, fontsize=7)
            ax2.set_ylim(-0.5, len(acts) - 0.5)
    axes[-1].plot(t, [ymap[a] for a in seq.classes], color="k", drawstyle="steps-post")
    axes[-1].set_yticks(range(len(acts)))
    axes[-1].set_yticklabels(acts, fontsize=7)
    axes[-1].set_title("true class", fontsize=9, loc="left")
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(f"{seq.name}: frame accuracy (blue) and active action (red)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _f(x, spec=".3f"):
    return "n/a" if x is None else format(x, spec)


def _report(p: dict, configs) -> str:
    s = p["settings"]
    lines = ["# Action-model bank: switching sequences (Ukita 4.1-4.4 in the labeler)", "",
             "Actions and recordings: " + ", ".join(f"{a} = `{r}`" for a, r in p["actions"].items()) + ".",
             f"Models train on the first {100 * s['train_fraction']:.0f} % of each recording "
             f"({', '.join(f'{a} {fr}' for a, fr in p['train_frames'].items())}); the test sequences use "
             "only the remaining frames (dance test part capped at "
             f"{s['max_dance_frames']} frames), joined at their most similar poses "
             "(`dtm_labeler.evaluation.switching.join_clips`). Walk, run and dance come from three "
             "different subjects (CMU 7, 9, 55).", "",
             f"Corruption per frame: {s['occlude']} hidden points (gaps of {s['gap_frames']:g} frames on "
             f"average), {s['clutter']} ghost points, {s['noise_mm']:g} mm noise; points shuffled; labeler in "
             f"stream mode with default settings. Seeds {s['seeds']} x {len(p['sequences'])} sequences.", "",
             "Sequences: " + "; ".join(f"{q['name']} ({q['frames']} frames, switches at {q['switches']})"
                                       for q in p["sequences"]) + ".", "",
             "## Result (pooled over sequences and seeds)", "",
             f"| configuration | accuracy (sd, min over runs) | accuracy +-{s['window']} frames of a switch | frames to recover "
             f"(mean / median) | active action = true class |",
             "|---|---|---|---|---|"]
    for c in configs:
        m = p["results"][c]["pooled"]
        per = [r["accuracy"] for r in p["results"][c]["runs"] if r["accuracy"] is not None]
        sd = f" (sd {np.std(per, ddof=1):.3f}, min {min(per):.3f})" if len(per) > 1 else ""
        lines.append(f"| {c} | {_f(m['accuracy'])}{sd} | {_f(m['switch_window_accuracy'])} | "
                     f"{_f(m['mean_frames_to_recover'], '.1f')} / {_f(m['median_frames_to_recover'], '.0f')} | "
                     f"{_f(m['active_action_accuracy'])} |")
    lines += ["", f"Frames to recover: first frame after a switch from which the frame accuracy stays >= "
              f"{100 * s['recover_level']:.0f} % for {s['recover_frames']} frames (never: frames to the next switch).",
              "", "![switching](switching.png)", "",
              "## Per sequence", "", "| configuration | sequence | seed | accuracy | window | recover | active |",
              "|---|---|---|---|---|---|---|"]
    for c in configs:
        for m in p["results"][c]["runs"]:
            lines.append(f"| {c} | {m['sequence']} | {m['seed']} | {_f(m['accuracy'])} | "
                         f"{_f(m['switch_window_accuracy'])} | {m['frames_to_recover']} | "
                         f"{_f(m['active_action_accuracy'])} |")
    lines += ["", "## Synthesized transitions (bank+transitions, every model gets the paths to all others)", "",
              "| action | with | accepted paths | synthesized frames | rejected (curvature) |", "|---|---|---|---|---|"]
    for a, ts in p["transitions"].items():
        for t in ts:
            lines.append(f"| {a} | {t['with']} | {t['paths']} | {t['frames']} | {t['rejected']} |")
    lines += ["", "Configurations: **pooled** = one model on all training data (StreamLabeler); **hard** = one "
              "model per action, whole population in the active model, switched to the best-scoring model "
              "after every frame; **bank** = BankLabeler (population spread over the models, migration, "
              "sticky HMM active action) on models without synthesized paths; **bank+transitions** = the same "
              "with every model trained on its data plus the synthesized paths to every other action; "
              "**L2 incremental** = the paper's L1-L3 literally (action i gets the paths to actions j < i only; "
              "order walk, run, dance).", "",
              "No recording in the shared data changes activity with a known per-frame class, so all switching "
              "sequences are joined recordings.", "",
              "## Readings of the paper used here", "",
              "* **Scalability vs. shared transitions (L2).** `dtm-train --action NAME --bank DIR` follows L2 "
              "literally: the *new* model is trained on its recordings plus the paths synthesized to every "
              "action already in the bank; existing model files are not touched (byte-identical, tested). "
              "`--retrain-neighbours` is the explicit opt-in that also retrains the others so the paths join "
              "the training data of *both* models they connect; the batch builder "
              "(`build_bank(mode='all')`, the **bank+transitions** row) does that for every pair. The "
              "L2-literal bank (order walk, run, dance) is the last row: the first model gets no paths.",
              "* **End points.** Local maxima of s(i,j) = -RMS distance per body point of root-centred, "
              "heading-normalised body14 poses, over a 9x9 frame neighbourhood, above a threshold of 0.10 m "
              "or 1.25 x the pair's closest distance (whichever is larger; walk and the whirl dance are never "
              "closer than 0.28 m).",
              "* **In-between count (P1-P2).** Fewest equal steps no longer than y_max; curvature = "
              "|second difference of the angle between consecutive pose vectors| over the whole path "
              "including two real frames each side; widen (i-1, j+1) up to 30 times, else drop the pair.",
              "* **Interpolation.** cgspeed BVH recordings share one hierarchy, so local joint rotations are "
              "slerped (bone vectors interpolated between the two subjects' skeletons, constant for one "
              "skeleton), root by a cubic Hermite with the real root velocities (continuous velocity for the "
              "eq. 12 features).",
              "* **Migration.** p(m->n) = 1 / (1 + exp(-(f_n - f_m) / (tau k))) -- Ukita's "
              "exp(-s_n^2) / (exp(-s_m^2) + exp(-s_n^2)) with the misfit s^2 = -f / (tau k), f the "
              "fitness (log-likelihood relative to clutter) and k the labelled points; tau = 1 nat per point. "
              "Every non-elite individual is a candidate after every generation (a GA individual has no "
              "latent position to test 'nearest sample is synthesized'); each model keeps >= 4 individuals.",
              "* **Active action.** Sticky HMM forward filter over the per-model best fitness tempered to "
              "nats per labelled point / 4, switch rate 1 Hz; the published labeling is the best individual "
              "over all models; the frame after the active action changes gets a full search.", "",
              f"Wall time {p['wall_s']:.0f} s; code {p.get('code') or 'unknown'}."]
    return "\n".join(lines) + "\n"


# ==================================================================== dtm-label --bank
def label_clip_bank(bank, clip: MotionClip, settings=None, bank_settings=None, occlude: int = 0, clutter: int = 0,
                    noise_mm: float = 0.0, seed: int = 0, progress=None, use_ids: bool = False,
                    gap_frames: float = 1.0, keep_records: bool = True, done: int = 0, total: int | None = None):
    """:func:`dtm_labeler.evaluation.pipeline.label_clip_run` with a :class:`BankLabeler`.
    The run's ``settings`` add ``active_actions`` (per frame), ``true_class`` and
    ``active_action_accuracy`` (None when the clip's class is not one of the bank's actions)."""
    mc = model_clip(bank.labels, clip)
    stream = corrupt_clip(mc, occlude=occlude, clutter=clutter, noise_mm=noise_mm, seed=seed, gap_frames=gap_frames)
    active = []
    run = run_labeler(BankLabeler(bank, settings, bank_settings), bank.labels, stream, use_ids, keep_records,
                      progress, done, total, on_frame=lambda res: active.append(res.active_action))
    cls = clip.motion_class
    agree = float(np.mean([a == cls for a in active])) if cls and cls in bank.actions and active else None
    run.settings.update(active_actions=active, true_class=cls, active_action_accuracy=agree,
                        active_action_frames={a: active.count(a) for a in bank.actions})
    return run
