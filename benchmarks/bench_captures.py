#!/usr/bin/env python
"""Real captures in, labelled captures out (issue 14): gappy training, real ghosts, unnamed C3D ->
labelled C3D, archives with --jobs / --dask.

Sections (``--only``):

* ``gaps``    -- gapped copies of the shared takes (:func:`realistic_gaps`: 50 % of the samples
  hidden, each marker with its own share, log-normal gaps of mean 0.25 s), written as C3D.
  A model is trained on the first half of the gapped take (at most the last
  ``TRAIN_FRAMES`` frames of it) and labels its second half (the first ``LABEL_FRAMES``
  frames): the gapped stream with the capture's trajectory continuity as track ids
  (``--track-ids``: what the trajectories of a C3D carry), the gapped stream with the
  labeler's own tracker, and the full (gap-free) second half; the same for a model trained
  on the gap-free first half, to tell training from labeling.
* ``gapseeds`` -- the gapped-half row (gapped model, gapped second half, ``dtm-label``'s
  default) under other draws of the gaps (``--gap-seeds``, default 2, 3, 4): how much one draw
  moves the figure. A draw whose training half shows a marker too rarely trains without it,
  as ``dtm-train``'s refusal says (``--points all,-NAME``); the second half keeps it, an
  unlabelled point there. Not in the default ``--only``.
* ``labelseeds`` -- the same row (gaps of seed 1) under other seeds of the labeler's searches
  (``--label-seeds``), for takes whose other gap draws cannot train (``--label-seed-takes``,
  default the 170-frame Qualisys walk). Not in the default ``--only``.
* ``ghosts``  -- real markers as ghosts: a take's markers are split into the model's and
  "unknown" ones; the unknown ones are written as ``*`` channels of a C3D of the second
  half (real trajectories next to the body), which ``dtm-label`` feeds to the labeler as
  unlabelled points. Accuracy and ghost rejection.
* ``gapghosts`` -- the two above at once, as issue 14's target capture is: the ``ghosts`` section's
  unknown markers as ``*`` channels of the gapped second half (the gaps drawn over every marker,
  the ``*`` channels' too: they are the same capture's markers), the gapped first half's model of
  the other markers, ``dtm-label``'s default (``--gap-seeds``' draws and seed 1), both trackings.
  The first half is a C3D with the same ``*`` channels, trained as ``dtm-train`` does: the ones
  that ride on the body become anonymous points (``training/anonymous.py``; ``ANONYMOUS=0`` in
  the environment: ``--ignore-unlabelled``). Not in the default ``--only``.
* ``reflections`` -- fixed reflections of the capture volume (:func:`static_ghosts`: floor tape,
  a prop; 3 of them) as ``*`` channels of the gapped second half, the gapped first half's model;
  the HDM05 take, a draw of 22 of its markers (fewer markers: a hand's are more often all hidden)
  and the Qualisys walk; the same second half without them beside. Not in the default ``--only``.
* ``fragments`` -- the gapped second half as a system's auto-labelling leaves it: after a gap a
  marker often comes back unlabelled for 0.1-0.5 s before it is named again (:func:`broken_trajectories`:
  those stretches as ``*`` channels), the gapped first half's model; labelled with the fragments joined
  to their markers (the loaders' default, ``motion/fragments.py``), kept apart (scored as ghosts), and
  the unbroken half beside. Not in the default ``--only``.
* ``unnamed`` -- the HDM05 take's second half with its names stripped (only ``*`` channels,
  trajectories cut into pieces of ~1.5 s spread over channels, as an unlabelled export looks)
  through ``dtm-label MODEL unnamed.c3d --out labelled.c3d`` (the console script, a
  subprocess); the share of true samples that the labelled C3D holds in the channel of
  their name; the file checked with ezc3d (POINT:LABELS / UNITS / RATE).
* ``archive`` -- ``dtm-label`` over a folder of takes, serial vs ``--jobs 2`` vs ``--dask
  local`` (subprocesses): wall time and identical figures.

Writes results/captures.json and results/captures.md.

    .venv/bin/python benchmarks/bench_captures.py [--quick] [--only gaps,ghosts,unnamed,archive]
    .venv/bin/python benchmarks/bench_captures.py --only gapseeds --update
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("DTM_DATA_DIR", REPO.parent / "shared" / "data"))
RESULTS = REPO / "results"
BIN = Path(sys.executable).parent

from dtm_labeler.evaluation.archive import LabelJob, label_take  # noqa: E402
from dtm_labeler.evaluation.corruption import realistic_gaps, static_ghosts  # noqa: E402
from dtm_labeler.labeling.stream import LabelerSettings  # noqa: E402
from dtm_labeler.labeling.take_restarts import RESTART_S  # noqa: E402
from dtm_labeler.model.io import model_to_bytes, save_model  # noqa: E402
from dtm_labeler.motion.c3d_write import write_c3d  # noqa: E402
from dtm_labeler.motion.load import load_clip  # noqa: E402
from dtm_labeler.motion.pointsets import AllBut, to_point_set  # noqa: E402
from dtm_labeler.training.anonymous import with_riding_markers  # noqa: E402
from dtm_labeler.training.calibrate import calibrate_on_takes  # noqa: E402
from dtm_labeler.training.gaps import RarelySeen  # noqa: E402
from dtm_labeler.training.train import TrainConfig, train_model  # noqa: E402

TAKES = {
    "hdm05": ("markers_c3d/hdm05_bd_05-01_01_120.c3d", "HDM05 bd 05-01 (41 markers, 120 Hz, 5920 frames)"),
    "qualisys": ("markers_c3d/qualisys_walk_55markers.c3d", "Qualisys walk (55 markers, 200 Hz, 340 frames)"),
    "cmu85_02": ("markers_c3d/cmu_85_02_jumptwist_s85_41markers.c3d", "CMU 85_02 jump-twist (41 markers, 120 Hz)"),
}
GAPS = dict(missing=0.5, mean_gap_s=0.25, spread=20.0, seed=1)
GAP_S = {"qualisys": 0.1}     # its 170 training frames (0.85 s) hold few 0.25 s gaps: every marker would be
                              # seen in under 20 frames of it
TRAIN_FRAMES, LABEL_FRAMES = 1500, 600
TAKE_VOTES_S = 1.0            # dtm-label's default --take-votes
SWEEP = (0.1, 0.25, 0.5)
CONFIG = dict(seed=0, k_max=3)
CALIBRATE = os.environ.get("CALIBRATE", "1") != "0"     # dtm-train's default for one capture (:func:`train`)
#: ``gapghosts``: the training half's '*' trajectories that ride on the body learnt as anonymous points
#: (dtm-train's default; ``ANONYMOUS=0``: ``--ignore-unlabelled``, as before 2026-12-07)
ANONYMOUS = os.environ.get("ANONYMOUS", "1") != "0"
#: reflections: (take, markers drawn or None for all, missing shares); the draw of 22 markers is seed 5's
REFLECTION_CASES = (("hdm05", None, (0.5,)), ("hdm05", 22, (0.25, 0.5)), ("qualisys", None, (0.5,)))
REFLECTIONS = 3
# markers the model does not know, written as '*' channels (real trajectories next to the body)
UNKNOWN = {"hdm05": ["LFIN", "RFIN", "LTOE", "RTOE", "RBAC", "T10"],
           "qualisys": ["L_WAND1", "L_WAND2", "L_WAND3", "L_WAND4", "R_WAND1", "R_WAND2", "R_WAND3", "R_WAND4"]}


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def halves(n: int, train_cap: int, label_cap: int) -> tuple[slice, slice]:
    half = n // 2
    return slice(max(0, half - train_cap), half), slice(half, min(n, half + label_cap))


def gapped(clip, **kw):
    P = clip.positions.copy()
    P[realistic_gaps(clip.n_frames, clip.n_points, clip.rate, **kw)] = np.nan
    return clip._replace(positions=P)


def write_take(path: Path, clip, names=None) -> Path:
    return write_c3d(path, clip.positions, list(names or clip.names), clip.rate)


def train(clip, **over):
    """A model of one capture as ``dtm-train`` makes it: calibrated to the capture's person (its
    ``--calibrate auto`` for one capture; ``CALIBRATE=0`` in the environment: the generic body)."""
    t0 = time.perf_counter()
    model, summary = train_model([clip], TrainConfig(**(CONFIG | over)))
    if CALIBRATE and model.body is not None:
        model = calibrate_on_takes(model, [clip])
    return model, summary, time.perf_counter() - t0


def train_leaving_out(clip, row: dict, what: str):
    """:func:`train` on a gapped clip; markers the coverage check finds too rarely seen are left
    out, as ``dtm-train``'s message says (``--points all,-NAME``), and named in ``row['left_out']``.
    Sets ``row['train_s']``."""
    try:
        model, _, row["train_s"] = train(clip)
    except RarelySeen as e:
        row["left_out"] = list(e.names)
        log(f"{what}: {e}; training without {', '.join(e.names)}")
        model, _, row["train_s"] = train(to_point_set(clip, AllBut(e.names)))
    return model


def label(model, path: Path, **kw):
    """One take through dtm-label's path (``take_votes_s`` as its ``--take-votes``, default 0 here:
    the labels as published live); ``live_accuracy`` = before the take votes. With
    ``--calibrate off``: the models here are of the take's own person (trained on its first
    half); dtm-label's default self-calibration is for a model of other people
    (``results/captures.md``, "dtm-label's own default on the gapped halves")."""
    kw.setdefault("settings", LabelerSettings())
    kw.setdefault("restart_s", RESTART_S)          # dtm-label's default --restarts (takes over 10 s only)
    job = LabelJob(index=0, source=str(path), **kw)
    r = label_take(job, model_to_bytes(model))
    if r.error:
        raise RuntimeError(r.error)
    m = r.metrics
    live = r.causal.metrics().accuracy if r.causal is not None else m.accuracy
    voted = r.voted.metrics().accuracy if r.voted is not None else None
    return {"frames": m.frames, "accuracy": m.accuracy, "live_accuracy": live, "voted_accuracy": voted,
            "take_votes_s": job.take_votes_s, "take_pass": r.voted is not None,
            "ghosts": m.ghosts, "ghost_rejection": m.ghost_rejection,
            "search_errors": m.search_errors, "full_search_rate": m.full_search_rate,
            "p50_ms": m.latency_ms["p50"], "p99_ms": m.latency_ms["p99"], "wall_s": r.wall_s,
            "unlabelled_points": r.unlabelled_points, "anonymous_points": r.anonymous_points,
            "fragments_joined": r.fragments_joined}


# -- sections ---------------------------------------------------------------------------------------
#: how a take's points are tracked: the capture's trajectories as ids, or the labeler's own tracker
TRACKING = (("capture ids", dict(use_ids=True)), ("own tracker", {}))


def label_tracked(model, path: Path, **kw) -> dict:
    """:func:`label` once per way of tracking (:data:`TRACKING`), by its name."""
    return {tag: label(model, path, **kw, **tk) for tag, tk in TRACKING}


def gapped_halves(key: str, quick: bool, seed: int | None = None):
    """(clip, train frames, label frames, gap settings, gapped clip) of one take."""
    rel, _ = TAKES[key]
    clip = load_clip(DATA / rel)
    tr, la = halves(clip.n_frames, 600 if quick else TRAIN_FRAMES, 120 if quick else LABEL_FRAMES)
    gaps = GAPS | {"mean_gap_s": GAP_S.get(key, GAPS["mean_gap_s"])} | ({} if seed is None else {"seed": seed})
    return clip, tr, la, gaps, gapped(clip, **gaps)


def run_gaps(tmp: Path, keys, quick: bool) -> dict:
    out = {}
    for key in keys:
        title = TAKES[key][1]
        clip, tr, la, gaps, gap = gapped_halves(key, quick)
        test_gappy = write_take(tmp / f"{key}_gappy_test.c3d", gap.slice(la.start, la.stop))
        test_clean = write_take(tmp / f"{key}_clean_test.c3d", clip.slice(la.start, la.stop))
        res = {"title": title, "mean_gap_s": gaps["mean_gap_s"],
               "train_frames": [tr.start, tr.stop], "label_frames": [la.start, la.stop],
               "missing_train": float(np.isnan(gap.slice(tr.start, tr.stop).positions[..., 0]).mean()),
               "missing_test": float(np.isnan(gap.slice(la.start, la.stop).positions[..., 0]).mean()),
               "complete_train_frames": int((~np.isnan(gap.slice(tr.start, tr.stop).positions[..., 0])).all(1).sum())}
        for mkind, src in (("gappy", gap), ("clean", clip)):
            model, summary, secs = train(src.slice(tr.start, tr.stop))
            save_model(model, tmp / f"{key}_{mkind}.npz")
            cov = np.array(list(summary.coverage.values()))
            res[f"model_{mkind}"] = {"train_s": secs, "scored_on": summary.structure_scored_on,
                                     "coverage_min": float(cov.min()), "coverage_median": float(np.median(cov)),
                                     "components": summary.components}
            log(f"gaps {key}: trained on {mkind} in {secs:.0f} s ({summary.structure_scored_on})")
            for tag, path, kw in (("gappy, capture ids", test_gappy, dict(use_ids=True, take_votes_s=TAKE_VOTES_S)),
                                  ("gappy, own tracker", test_gappy, dict(take_votes_s=TAKE_VOTES_S)),
                                  ("gap-free", test_clean, dict(take_votes_s=TAKE_VOTES_S))):
                r = label(model, path, **kw)
                res[f"model_{mkind}"][tag] = r
                log(f"gaps {key}: {mkind} model, {tag}: live {100 * r['live_accuracy']:.2f} %, "
                    f"take votes {100 * r['accuracy']:.2f} % "
                    f"({r['search_errors']} search errors / {r['frames']})")
        if key == keys[0]:          # where labeling gapped streams breaks: the gap-free model, fewer gaps
            res["sweep"] = {}
            for miss in SWEEP:
                test = write_take(tmp / f"{key}_sweep.c3d", gapped(clip, **(gaps | {"missing": miss})).slice(
                    la.start, la.stop))
                res["sweep"][miss] = label_tracked(model, test)
                log(f"gaps {key} sweep {miss}: " + ", ".join(f"{t} {100 * r['accuracy']:.2f} %"
                                                             for t, r in res["sweep"][miss].items()))
        out[key] = res
    return out


def run_gap_seeds(tmp: Path, keys, seeds, quick: bool) -> dict:
    """The gapped-half row under other draws of the gaps: the gapped first half trains, the gapped
    second half is labelled by `dtm-label`'s default (``--calibrate off``) with capture ids and with
    its own tracker.
    How much one draw moves the figure (a 170-frame take: one trajectory piece is 1 %)."""
    out = {}
    for key in keys:
        out[key] = {}
        for seed in seeds:
            _, tr, la, _, gap = gapped_halves(key, quick, seed)
            row = {"missing_test": float(np.isnan(gap.slice(la.start, la.stop).positions[..., 0]).mean())}
            model = train_leaving_out(gap.slice(tr.start, tr.stop), row, f"gap seeds {key} {seed}")
            test = write_take(tmp / f"{key}_seed{seed}_test.c3d", gap.slice(la.start, la.stop))
            row.update(label_tracked(model, test, take_votes_s=TAKE_VOTES_S))
            out[key][seed] = row
            log(f"gap seeds {key} {seed}: capture ids {100 * row['capture ids']['accuracy']:.2f} %, "
                f"own tracker {100 * row['own tracker']['accuracy']:.2f} %")
    return out


def run_label_seeds(tmp: Path, keys, seeds, quick: bool) -> dict:
    """The gapped-half row (the gaps of seed 1) under other seeds of the labeler's searches: for
    a take whose other gap draws leave the first half untrainable (the 170-frame Qualisys walk)."""
    out = {}
    for key in keys:
        _, tr, la, _, gap = gapped_halves(key, quick)
        model, _, _ = train(gap.slice(tr.start, tr.stop))
        test = write_take(tmp / f"{key}_labelseeds_test.c3d", gap.slice(la.start, la.stop))
        out[key] = {}
        for seed in seeds:
            out[key][seed] = label_tracked(model, test, take_votes_s=TAKE_VOTES_S, settings=LabelerSettings(seed=seed))
            log(f"label seeds {key} {seed}: " + ", ".join(f"{t} {100 * r['accuracy']:.2f} %"
                                                          for t, r in out[key][seed].items()))
    return out


def run_ghosts(tmp: Path, keys, quick: bool) -> dict:
    out = {}
    for key in keys:
        rel, title = TAKES[key]
        clip = load_clip(DATA / rel)
        known = [n for n in clip.names if n not in UNKNOWN[key]]
        tr, la = halves(clip.n_frames, 600 if quick else TRAIN_FRAMES, 120 if quick else LABEL_FRAMES)
        model, _, secs = train(clip.select(known).slice(tr.start, tr.stop))
        test = clip.select(known + UNKNOWN[key]).slice(la.start, la.stop)
        path = write_take(tmp / f"{key}_ghosts.c3d", test, known + [f"*{i}" for i in range(len(UNKNOWN[key]))])
        r = label(model, path) | {"title": title, "model_labels": len(known), "ghost_markers": UNKNOWN[key],
                                  "train_s": secs}
        r["without_ghosts"] = label(model, path, keep_unlabelled=False)
        log(f"ghosts {key}: accuracy {100 * r['accuracy']:.2f} %, ghosts rejected {100 * r['ghost_rejection']:.2f} % "
            f"of {r['ghosts']} (without them: {100 * r['without_ghosts']['accuracy']:.2f} %)")
        out[key] = r
    return out


def run_gap_ghosts(tmp: Path, keys, seeds, quick: bool) -> dict:
    """Real markers as ``*`` channels of a gapped second half (module doc, ``gapghosts``)."""
    out = {}
    for key in keys:
        out[key] = {}
        clip = load_clip(DATA / TAKES[key][0])
        known = [n for n in clip.names if n not in UNKNOWN[key]]
        for seed in seeds:
            _, tr, la, _, gap = gapped_halves(key, quick, seed)
            row = {"missing_test": float(np.isnan(gap.slice(la.start, la.stop).positions[..., 0]).mean()),
                   "model_labels": len(known), "ghost_markers": UNKNOWN[key]}
            stars = known + [f"*{i}" for i in range(len(UNKNOWN[key]))]
            train_take = load_clip(write_take(tmp / f"{key}_gapghosts_train{seed}.c3d",
                                              gap.select(known + UNKNOWN[key]).slice(tr.start, tr.stop), stars))
            if ANONYMOUS:                    # dtm-train's default: the '*' trajectories that ride on the body
                (train_take,), riding = with_riding_markers([train_take])
                row["anonymous"] = {r.channel: r.name for r in riding}
            try:
                model = train_leaving_out(train_take, row, f"gap ghosts {key} {seed}")
            except ValueError as e:          # e.g. the short Qualisys walk: triangles seen together too rarely
                row["error"] = str(e)
                out[key][seed] = row
                log(f"gap ghosts {key} {seed}: not trained: {e}")
                continue
            test = gap.select(known + UNKNOWN[key]).slice(la.start, la.stop)
            path = write_take(tmp / f"{key}_gapghosts{seed}.c3d", test, stars)
            row.update(label_tracked(model, path, take_votes_s=TAKE_VOTES_S))
            row["without_ghosts"] = label(model, path, keep_unlabelled=False, take_votes_s=TAKE_VOTES_S)
            out[key][seed] = row
            log(f"gap ghosts {key} {seed}: " + ", ".join(
                f"{t} {100 * row[t]['live_accuracy']:.2f} -> {100 * row[t]['accuracy']:.2f} %, ghosts rejected "
                f"{100 * row[t]['ghost_rejection']:.2f} % of {row[t]['ghosts']}" for t, _ in TRACKING)
                + f"; without them (own tracker) {100 * row['without_ghosts']['accuracy']:.2f} %")
    return out


def broken_trajectories(positions: np.ndarray, rate: float, share: float = 0.4, seed: int = 0):
    """What a system's auto-labelling leaves of a gapped take: after a gap, with probability
    ``share``, the marker comes back unlabelled for 0.1-0.5 s (at most all but one frame of its
    run: the system labels it again after) before it is named again. Returns the named channels
    with those stretches hidden, and one ``*`` channel per stretch (F, K, 3)."""
    rng = np.random.default_rng(seed)
    P = positions.copy()
    F, N, _ = P.shape
    stars = []
    for j in range(N):
        seen = np.isfinite(P[:, j, 0])
        starts = np.flatnonzero(seen[1:] & ~seen[:-1]) + 1          # back from a gap
        for a in starts:
            run = int(np.argmin(seen[a:])) if not seen[a:].all() else F - a
            n = min(int(rng.uniform(0.1, 0.5) * rate), run - 1)
            if n < 1 or rng.random() >= share:
                continue
            ch = np.full((F, 3), np.nan)
            ch[a:a + n] = P[a:a + n, j]
            P[a:a + n, j] = np.nan
            stars.append(ch)
    return P, (np.stack(stars, 1) if stars else np.zeros((F, 0, 3)))


def run_fragments(tmp: Path, keys, quick: bool) -> dict:
    """Fragments of named markers as ``*`` channels of the gapped second half (module doc,
    ``fragments``): joined to their markers (the loaders' default) and kept apart."""
    out = {}
    for key in keys:
        _, tr, la, _, gap = gapped_halves(key, quick)
        row = {}
        model = train_leaving_out(gap.slice(tr.start, tr.stop), row, f"fragments {key}")
        test = gap.slice(la.start, la.stop)
        named, stars = broken_trajectories(test.positions, test.rate)
        path = write_c3d(tmp / f"{key}_fragments.c3d", np.concatenate([named, stars], 1),
                         list(test.names) + [f"*{i}" for i in range(stars.shape[1])], test.rate)
        row.update({"fragments": int(stars.shape[1]), "fragment_samples": int(np.isfinite(stars[..., 0]).sum()),
                    "unbroken": label(model, write_take(tmp / f"{key}_unbroken.c3d", test), take_votes_s=TAKE_VOTES_S),
                    "joined": label(model, path, take_votes_s=TAKE_VOTES_S),
                    "apart": label(model, path, take_votes_s=TAKE_VOTES_S, load={"join_fragments": False})})
        out[key] = row
        log(f"fragments {key}: {row['fragments']} stretches, {row['fragment_samples']} samples; " + ", ".join(
            f"{w} {100 * row[w]['accuracy']:.2f} %, ghosts {row[w]['ghosts']} rejected {pct(row[w]['ghost_rejection'])}"
            for w in ("unbroken", "joined", "apart")))
    return out


def run_reflections(tmp: Path, quick: bool) -> dict:
    """Fixed reflections beside the gapped second half (module doc), and the same half without them."""
    out = {}
    for key, drawn, shares in REFLECTION_CASES:
        clip = load_clip(DATA / TAKES[key][0])
        if drawn is not None:
            rng = np.random.default_rng(5)
            clip = clip.select([clip.names[i] for i in sorted(rng.choice(clip.n_points, drawn, replace=False))])
        tr, la = halves(clip.n_frames, 600 if quick else TRAIN_FRAMES, 120 if quick else LABEL_FRAMES)
        for miss in shares:
            name = f"{key}{'' if drawn is None else f' ({drawn} markers)'}, {100 * miss:.0f} % hidden"
            gap = gapped(clip, **(GAPS | {"missing": miss, "mean_gap_s": GAP_S.get(key, GAPS["mean_gap_s"])}))
            row = {"labels": clip.n_points}
            model = train_leaving_out(gap.slice(tr.start, tr.stop), row, f"reflections {name}")
            test = gap.slice(la.start, la.stop)
            refl = static_ghosts(clip.slice(la.start, la.stop).positions, REFLECTIONS, seed=1)
            path = write_c3d(tmp / "reflections.c3d", np.concatenate([test.positions, refl], 1),
                             list(test.names) + [f"*{i}" for i in range(REFLECTIONS)], test.rate)
            row["with"] = label_tracked(model, path, take_votes_s=TAKE_VOTES_S)
            row["without"] = label_tracked(model, write_take(tmp / "no_reflections.c3d", test),
                                           take_votes_s=TAKE_VOTES_S)
            for w in ("with", "without"):
                log(f"reflections {name}, {w}: " + ", ".join(
                    f"{t} {100 * r['live_accuracy']:.2f} -> {100 * r['accuracy']:.2f} %"
                    for t, r in row[w].items()))
            out[name] = row
    return out


def strip_names(clip, rng, mean_segment_s: float = 1.5):
    """The clip as an unlabelled export: every trajectory cut into pieces (~mean_segment_s),
    each piece in a random free '*' channel. Returns (positions (F, C, 3), C)."""
    F, N, _ = clip.positions.shape
    C = 2 * N
    out = np.full((F, C, 3), np.nan)
    busy = np.zeros((F, C), bool)
    seg = max(1, int(mean_segment_s * clip.rate))
    for p in rng.permutation(N):
        t = 0
        while t < F:
            n = int(rng.integers(seg // 2, 2 * seg))
            free = np.flatnonzero(~busy[t:t + n].any(0))
            c = int(rng.choice(free))
            out[t:t + n, c] = clip.positions[t:t + n, p]
            busy[t:t + n, c] = True
            t += n
    used = busy.any(0)
    return out[:, used], int(used.sum())


def run_unnamed(tmp: Path, quick: bool) -> dict:
    import ezc3d
    rel, title = TAKES["hdm05"]
    clip = load_clip(DATA / rel)
    tr, la = halves(clip.n_frames, 600 if quick else TRAIN_FRAMES, 120 if quick else LABEL_FRAMES)
    model, _, secs = train(clip.slice(tr.start, tr.stop))
    model_path = save_model(model, tmp / "hdm05_named.npz")
    test = clip.slice(la.start, la.stop)
    pts, C = strip_names(test, np.random.default_rng(3))
    unnamed = write_c3d(tmp / "hdm05_unnamed.c3d", pts, [f"*{i}" for i in range(C)], test.rate)
    labelled = tmp / "hdm05_labelled.c3d"
    t0 = time.perf_counter()
    p = subprocess.run([str(BIN / "dtm-label"), str(model_path), str(unnamed), "--out", str(labelled), "--json",
                        "--quiet"], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode:
        raise RuntimeError(p.stderr)
    d = json.loads(p.stdout)
    c = ezc3d.c3d(str(labelled))
    pt = c["parameters"]["POINT"]
    back = load_clip(labelled)
    right = total = 0
    per = {}
    for name in test.names:
        want = test.positions[:, test.index(name)]
        got = back.positions[:, back.index(name)]
        seen = np.isfinite(want).all(1)
        ok = seen & np.isfinite(got).all(1) & (np.abs(got - want).max(1) < 1e-4)
        right += int(ok.sum())
        total += int(seen.sum())
        per[name] = float(ok.sum() / max(seen.sum(), 1))
    return {"title": title, "train_frames": [tr.start, tr.stop], "label_frames": [la.start, la.stop],
            "input_channels": C, "train_s": secs, "wall_s": wall, "samples": total, "named_right": right / total,
            "weakest": dict(sorted(per.items(), key=lambda kv: kv[1])[:5]),
            "labels": list(pt["LABELS"]["value"][:3]) + ["..."], "n_labels": len(pt["LABELS"]["value"]),
            "units": pt["UNITS"]["value"][0], "rate": float(pt["RATE"]["value"][0]),
            "first_frame": int(c["header"]["points"]["first_frame"]), "json_accuracy": d["accuracy"],
            "unlabelled_points": d["inputs"][0]["unlabelled_points"]}


def run_archive(tmp: Path, quick: bool, repeats: int) -> dict:
    rel, _ = TAKES["hdm05"]
    clip = load_clip(DATA / rel)
    tr, _ = halves(clip.n_frames, 600 if quick else TRAIN_FRAMES, 0)
    model, _, _ = train(clip.slice(tr.start, tr.stop))
    model_path = save_model(model, tmp / "archive_model.npz")
    folder = tmp / "archive"
    n_takes, frames = (4, 60) if quick else (6, 600)          # 5 s takes: a run is mostly labelling
    starts = np.linspace(clip.n_frames // 2, clip.n_frames - frames, n_takes).astype(int)
    for i, a in enumerate(starts):
        write_take(folder / f"take{i}.c3d", clip.slice(a, a + frames))
    runs: dict = {}
    for name, extra in (("serial", []), ("--jobs 2", ["--jobs", "2"]), ("--dask local --jobs 2",
                                                                       ["--dask", "local", "--jobs", "2"])):
        walls, cpus, d = [], [], None
        for _ in range(repeats):
            r0, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
            p = subprocess.run([str(BIN / "dtm-label"), str(model_path), str(folder), "--json", "--quiet"] + extra,
                               capture_output=True, text=True)
            walls.append(time.perf_counter() - t0)
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpus.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
            if p.returncode:
                raise RuntimeError(p.stderr)
            d = json.loads(p.stdout)
        runs[name] = {"wall_s": walls, "best_s": min(walls), "cpu_s": cpus, "load": os.getloadavg()[0],
                      "figures": {k: d[k] for k in ("frames", "points", "correct", "accuracy", "ghosts", "swaps",
                                                    "search_errors")},
                      "per_take": [x["accuracy"] for x in d["inputs"]],
                      "workers": sorted({x["worker"] for x in d["inputs"]})}
        log(f"archive {name}: best of {repeats} {min(walls):.1f} s")
    base = runs["serial"]["best_s"]
    for name, r in runs.items():
        r["speedup"] = base / r["best_s"]
        r["same_figures"] = r["figures"] == runs["serial"]["figures"] and r["per_take"] == runs["serial"]["per_take"]
    return {"takes": n_takes, "frames_per_take": frames, "runs": runs}


# -- report -----------------------------------------------------------------------------------------
def pct(x) -> str:
    return "–" if x is None else f"{100 * x:.2f}"


def write_md(res: dict, meta: dict) -> str:
    L = ["# Captures: gappy training, real ghosts, unnamed C3D -> labelled C3D, archives", "",
         f"{meta['machine']}; other jobs share the machine. Sections run: "
         + "; ".join(f"{name} {r['date']} (commit {r['commit']}, load average {r['load_start']:.1f} -> "
                     f"{r['load_end']:.1f}{'' if r.get('calibrate', False) else ', models of a generic body'})"
                     for name, r in meta.get("runs", {}).items()) + ".", ""]
    if "gaps" in res:
        g = GAPS
        L += ["## Training on gappy captures", "",
              f"Gapped copies: {100 * g['missing']:.0f} % of the samples hidden (each marker its own share, Beta "
              f"spread {g['spread']:g}), log-normal gaps of mean {g['mean_gap_s']} s (the 1.7 s Qualisys take: "
              f"{GAP_S['qualisys']} s; sigma 1: flickers and occlusions of a second or more), seed 1. Train on the first half (at most its last "
              f"{TRAIN_FRAMES} frames), label the second half (its first {LABEL_FRAMES} frames), stream mode, "
              "default settings. *capture ids*: the trajectories' continuity as track ids (what a C3D's "
              "trajectories carry; `--track-ids`); *own tracker*: no ids. Each cell: the labels as published "
              f"live (votes over past frames) → votes over ±{TAKE_VOTES_S:g} s around each frame (`--take-votes`) "
              "→ `dtm-label`'s default with `--calibrate off`, the second pass over the take (every frame searched again at the take's "
              "facing, voted again; then whole trajectory pieces relabelled by the take's rigid marker pairs).", "",
              "| take | hidden (train / test) | complete train frames | model | train s | structure on | "
              "coverage min / median | gappy, capture ids % | gappy, own tracker % | gap-free % |",
              "|---|---|---:|---|---:|---|---|---:|---:|---:|"]
        for key, r in res["gaps"].items():
            for mk in ("gappy", "clean"):
                m = r[f"model_{mk}"]
                L.append(f"| {key} | {100 * r['missing_train']:.0f} / {100 * r['missing_test']:.0f} % | "
                         f"{r['complete_train_frames']} of {r['train_frames'][1] - r['train_frames'][0]} | "
                         f"{'gapped' if mk == 'gappy' else 'gap-free'} first half | {m['train_s']:.0f} | "
                         f"{m['scored_on']} | {100 * m['coverage_min']:.0f} / {100 * m['coverage_median']:.0f} % | "
                         + " | ".join(f"{pct(m[t].get('live_accuracy', m[t]['accuracy']))} → "
                                      + (f"{pct(m[t]['voted_accuracy'])} → " if m[t].get('voted_accuracy') else "")
                                      + f"{pct(m[t]['accuracy'])} "
                                      f"({m[t]['search_errors']} err)"
                                      for t in ("gappy, capture ids", "gappy, own tracker", "gap-free")) + " |")
        L += ["", "err = frames where the model scores the true labeling above the published one (search errors).", ""]
        for key, r in res["gaps"].items():
            if "sweep" not in r:
                continue
            L += [f"Labeling gapped streams of {key} with the gap-free model (same gap lengths, fewer gaps):", "",
                  "| hidden | capture ids % | own tracker % | search errors (ids) |", "|---:|---:|---:|---:|"]
            for miss, v in r["sweep"].items():
                L.append(f"| {100 * float(miss):.0f} % | {pct(v['capture ids']['accuracy'])} | "
                         f"{pct(v['own tracker']['accuracy'])} | {v['capture ids']['search_errors']} of "
                         f"{v['capture ids']['frames']} |")
            L.append("")
    if "gapseeds" in res:
        L += ["Other draws of the gaps (same settings, `--gap-seeds`; seed 1 is the table above), the "
              "gapped first half's model, `dtm-label`'s default with `--calibrate off`:", "",
              "| take | gap seed | hidden (test) | capture ids % | own tracker % |", "|---|---:|---:|---:|---:|"]
        for key, rows in res["gapseeds"].items():
            cells = {t: [] for t in ("capture ids", "own tracker")}
            first = res.get("gaps", {}).get(key, {}).get("model_gappy")
            if first is not None:
                for t, tag in (("capture ids", "gappy, capture ids"), ("own tracker", "gappy, own tracker")):
                    cells[t].append(first[tag]["accuracy"])
            for seed, r in rows.items():
                if "refused" in r:                   # a run before the left-out markers were
                    L.append(f"| {key} | {seed} | {100 * r['missing_test']:.0f} % | training refused: "
                             f"{r['refused'].split(';')[0]} | |")
                    continue
                note = (f" (trained without {', '.join(r['left_out'])}: seen in too few frames; "
                        "`--points all,-NAME`)") if r.get("left_out") else ""
                L.append(f"| {key} | {seed}{note} | {100 * r['missing_test']:.0f} % | {pct(r['capture ids']['accuracy'])} | "
                         f"{pct(r['own tracker']['accuracy'])} |")
                for t in cells:
                    cells[t].append(r[t]["accuracy"])
            if cells["capture ids"]:
                L.append(f"| {key} | all ({len(cells['capture ids'])}) | | " + " | ".join(
                    f"min {pct(min(v))}, mean {pct(float(np.mean(v)))}" for v in cells.values()) + " |")
        L.append("")
    if res.get("labelseeds"):
        L += ["The same row under other seeds of the labeler's searches (`--seed`; the gaps of seed 1, the "
              "gapped first half's model; 0 is the table above):", "",
              "| take | search seed | capture ids % | own tracker % |", "|---|---:|---:|---:|"]
        for key, rows in res["labelseeds"].items():
            for seed, r in rows.items():
                L.append(f"| {key} | {seed} | {pct(r['capture ids']['accuracy'])} | "
                         f"{pct(r['own tracker']['accuracy'])} |")
        L.append("")
    if res.get("fragments"):
        L += ["## Fragments of named markers in `*` channels", "",
              "The gapped second half (gap seed 1) as a system's auto-labelling leaves it: after a gap a marker "
              "comes back unlabelled for 0.1-0.5 s (40 % of its returns) before it is named again, those stretches "
              "as `*` channels; the gapped first half's model, `dtm-label`'s default, own tracker. *joined*: the "
              "loaders join a `*` run that continues a named marker (`motion/fragments.py`, the default); "
              "*apart*: `join_fragments=False`, the fragments scored as ghosts; *unbroken*: the same half with "
              "the stretches in their named channels.", "",
              "| take | stretches (samples) | joined to their markers | unbroken: accuracy % | joined: accuracy %, "
              "ghosts, rejected % | apart: accuracy %, ghosts, rejected % |", "|---|---|---:|---:|---|---|"]
        for key, r in res["fragments"].items():
            L.append(f"| {key} | {r['fragments']} ({r['fragment_samples']}) | {r['joined']['fragments_joined']} | "
                     f"{pct(r['unbroken']['accuracy'])} | " + " | ".join(
                         f"{pct(r[w]['accuracy'])}, {r[w]['ghosts']}, {pct(r[w]['ghost_rejection'])}"
                         for w in ("joined", "apart")) + " |")
        L.append("")
    if "reflections" in res:
        L += ["## Fixed reflections beside gapped takes", "",
              f"{REFLECTIONS} fixed points (floor tape, a prop: half on the floor, the rest up to 2 m, within 1.5 m of "
              "the body's path) as `*` channels of the gapped second half (gap seed 1), the gapped first half's "
              "model, `dtm-label`'s default (`--calibrate off`); the same half without them beside. Each cell: as "
              "published live -> after the pass over the take (accuracy %), and the reflections' samples left "
              "unlabelled.", "",
              "| take | capture ids | own tracker | without reflections: capture ids / own tracker |",
              "|---|---|---|---|"]
        for name, row in res["reflections"].items():
            cells = [f"{pct(row['with'][t]['live_accuracy'])} -> {pct(row['with'][t]['accuracy'])}, "
                     f"{pct(row['with'][t]['ghost_rejection'])} rejected" for t in ("capture ids", "own tracker")]
            cells.append(" / ".join(f"{pct(row['without'][t]['live_accuracy'])} -> {pct(row['without'][t]['accuracy'])}"
                                    for t in ("capture ids", "own tracker")))
            note = f" (without {', '.join(row['left_out'])}: seen too rarely)" if row.get("left_out") else ""
            L.append(f"| {name}{note} | " + " | ".join(cells) + " |")
        L.append("")
    if "ghosts" in res:
        L += ["## Real ghosts from `*` channels", "",
              "Markers the model does not know, written as `*` channels of the second half's C3D (real "
              "trajectories next to the body); model on the other markers of the first half.", "",
              "| take | model labels | `*` channels (real markers) | frames | accuracy % | ghosts | rejected % | "
              "accuracy without them % |", "|---|---:|---|---:|---:|---:|---:|---:|"]
        for key, r in res["ghosts"].items():
            L.append(f"| {key} | {r['model_labels']} | {', '.join(r['ghost_markers'])} | {r['frames']} | "
                     f"{pct(r['accuracy'])} | {r['ghosts']} | {pct(r['ghost_rejection'])} | "
                     f"{pct(r['without_ghosts']['accuracy'])} |")
        L.append("")
    if res.get("gapghosts"):
        L += ["## Real ghosts from `*` channels in gapped captures", "",
              "The `*` channels of *Real ghosts from `*` channels* in the gapped halves of *Training on gappy "
              f"captures* ({100 * GAPS['missing']:.0f} % of every marker's samples hidden, the `*` channels' too): the gapped first half's model of the other markers, `dtm-label`'s "
              "default on the gapped second half. Each cell: as published live -> final (accuracy %), ghosts "
              "rejected (final).", "",
              "| take | gap seed | hidden (test) | `*` samples | capture ids | own tracker | "
              "own tracker without the `*` channels % |", "|---|---:|---:|---:|---|---|---:|"]
        for key, rows in res["gapghosts"].items():
            for seed, r in rows.items():
                note = f" (trained without {', '.join(r['left_out'])})" if r.get("left_out") else ""
                if "error" in r:
                    L.append(f"| {key} | {seed} | {100 * r['missing_test']:.0f} % | | not trained: {r['error']} | | |")
                    continue
                cells = [f"{pct(r[t]['live_accuracy'])} -> **{pct(r[t]['accuracy'])}**, "
                         f"{pct(r[t]['ghost_rejection'])} rejected" for t in ("capture ids", "own tracker")]
                L.append(f"| {key} | {seed}{note} | {100 * r['missing_test']:.0f} % | {r['own tracker']['ghosts']} | "
                         + " | ".join(cells) + f" | {pct(r['without_ghosts']['accuracy'])} |")
        L.append("")
    if "unnamed" in res:
        u = res["unnamed"]
        L += ["## Unnamed C3D -> labelled C3D", "",
              f"{u['title']}: model on frames {u['train_frames'][0]}:{u['train_frames'][1]} (named); frames "
              f"{u['label_frames'][0]}:{u['label_frames'][1]} written with only `*` channels "
              f"({u['input_channels']} channels: trajectories cut into ~1.5 s pieces spread over channels), then "
              "`dtm-label MODEL unnamed.c3d --out labelled.c3d` (console script).", "",
              f"- true samples in the channel of their name: **{pct(u['named_right'])} %** of {u['samples']}",
              "- weakest: " + ", ".join(f"{k} {100 * v:.1f} %" for k, v in u["weakest"].items()),
              f"- labelled C3D (ezc3d): {u['n_labels']} POINT:LABELS ({', '.join(u['labels'])}), UNITS "
              f"{u['units']}, RATE {u['rate']:g}, first frame {u['first_frame']}; JSON accuracy "
              f"{u['json_accuracy']} (no names in the input: not scored), {u['unlabelled_points']} unnamed "
              f"input channels; {u['wall_s']:.1f} s", ""]
    if "archive" in res:
        a = res["archive"]
        L += ["## Archives: `--jobs`, `--dask local`", "",
              f"`dtm-label MODEL folder/ --json` over {a['takes']} HDM05 takes of {a['frames_per_take']} frames "
              "(subprocesses; best wall time of the repeats). CPU s = user + system time of the run and its "
              "workers: CPU / wall is the number of cores the run got.", "",
              "| run | wall s (each) | CPU s (each) | best s | speed-up | same figures as serial | workers | "
              "load after |", "|---|---|---|---:|---:|---|---:|---:|"]
        for name, r in a["runs"].items():
            L.append(f"| {name} | {', '.join(f'{w:.1f}' for w in r['wall_s'])} | "
                     f"{', '.join(f'{c:.1f}' for c in r.get('cpu_s', [])) or '–'} | {r['best_s']:.1f} | "
                     f"{r['speedup']:.2f}x | {'yes' if r['same_figures'] else 'NO'} | {len(r['workers'])} | "
                     f"{r['load']:.1f} |")
        L.append("")
    return "\n".join(L)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small budgets (smoke test)")
    ap.add_argument("--only", default="gaps,ghosts,unnamed,archive")
    ap.add_argument("--gap-takes", default="hdm05,qualisys")
    ap.add_argument("--gap-seeds", default="2,3,4", help="gapseeds: the gap draws (seeds) besides the gaps section's 1")
    ap.add_argument("--label-seeds", default="1,2,3", help="labelseeds: the labeler's search seeds besides 0")
    ap.add_argument("--label-seed-takes", default="qualisys")
    ap.add_argument("--ghost-takes", default="hdm05,qualisys")
    ap.add_argument("--repeats", type=int, default=2, help="archive runs per variant")
    ap.add_argument("--out", default=str(RESULTS / "captures"), help="output stem (.json, .md)")
    ap.add_argument("--update", action="store_true",
                    help="keep the other sections of an existing OUT.json (rerun some sections only)")
    args = ap.parse_args(argv)
    only = set(args.only.split(","))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                            text=True).stdout.strip()
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "commit": commit, "load_start": os.getloadavg()[0],
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
            "command": "benchmarks/bench_captures.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    res: dict = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if "gaps" in only:
            res["gaps"] = run_gaps(tmp, args.gap_takes.split(","), args.quick)
        if "gapseeds" in only:
            res["gapseeds"] = run_gap_seeds(tmp, args.gap_takes.split(","),
                                            [int(x) for x in args.gap_seeds.split(",")], args.quick)
        if "labelseeds" in only:
            res["labelseeds"] = run_label_seeds(tmp, args.label_seed_takes.split(","),
                                                [int(x) for x in args.label_seeds.split(",")], args.quick)
        if "ghosts" in only:
            res["ghosts"] = run_ghosts(tmp, args.ghost_takes.split(","), args.quick)
        if "gapghosts" in only:
            res["gapghosts"] = run_gap_ghosts(tmp, args.ghost_takes.split(","),
                                              [1] + [int(x) for x in args.gap_seeds.split(",")], args.quick)
        if "reflections" in only:
            res["reflections"] = run_reflections(tmp, args.quick)
        if "fragments" in only:
            res["fragments"] = run_fragments(tmp, args.gap_takes.split(","), args.quick)
        if "unnamed" in only:
            res["unnamed"] = run_unnamed(tmp, args.quick)
            log(f"unnamed: {100 * res['unnamed']['named_right']:.2f} % of true samples named right")
        if "archive" in only:
            res["archive"] = run_archive(tmp, args.quick, args.repeats)
    meta["load_end"] = os.getloadavg()[0]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta["calibrate"] = CALIBRATE
    runs = {name: {k: meta[k] for k in ("date", "commit", "load_start", "load_end", "calibrate")} for name in res}
    if args.update and out.with_suffix(".json").is_file():
        old = json.loads(out.with_suffix(".json").read_text())
        runs = old["meta"].get("runs", {}) | runs
        res = old["results"] | res
    meta["runs"] = runs
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "results": res}, indent=1, default=float))
    md = write_md(res, meta)
    out.with_suffix(".md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
