#!/usr/bin/env python
"""Labeling engine benchmark: per-frame latency, throughput and accuracy (library, no ROS).

Cases (within-sequence: train on the first 90 % of each recording, label frames of the last 10 %):

* ``body14``  -- the paper's 14 points derived from the CMU walk 07_01, run 09_11 and dance 55_01
  BVHs, one model for the three; test frames = the last 10 % of each (capped per clip).
* ``markers41`` -- the 41 markers of the CMU 85_02 jump-twist C3D (``--points all``).

Each case runs in ``stream`` mode (tracks, warm start, votes) and ``single`` mode (every frame
searched from scratch), clean and with 3 occluded points / 3 ghost points / both (+1 mm noise),
all through :func:`dtm_labeler.evaluation.pipeline.label_clips` (the same path as ``dtm-label``).

Latency = wall time of ``StreamLabeler.process`` per frame (p50 / p99 / max), fps = frames per
second of summed latency; ``cpu ms/frame`` = process CPU time per frame, which is what to
compare between runs on a busy machine (the load average is recorded). Accuracy, ghost
rejection, swaps per minute and search-error rate alongside.

Writes results/labeling_bench.json and results/labeling_bench.md; prints the table.

    .venv/bin/python benchmarks/bench_labeling.py [--quick] [--cases body14 markers41] [--modes stream single]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("DTM_DATA_DIR", REPO.parent / "shared" / "data"))
RESULTS = REPO / "results"

CASES = {
    "body14": dict(paths=["cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh",
                          "cmu_skeletal/bvh_from_fbx/cmu_09_11_run_s09.bvh",
                          "cmu_skeletal/bvh_from_fbx/cmu_55_01_dance-whirl_s55.bvh"], points="body14"),
    "markers41": dict(paths=["markers_c3d/cmu_85_02_jumptwist_s85_41markers.c3d"], points="all"),
}
CONDITIONS = [  # name, occlude, clutter, noise_mm
    ("clean", 0, 0, 0.0),
    ("occlude 3", 3, 0, 0.0),
    ("clutter 3", 0, 3, 0.0),
    ("occl 3 + clutter 3 + 1 mm", 3, 3, 1.0),
]
# frames labelled per clip: (stream, single); single mode searches every frame from scratch
FRAMES = {"body14": (60, 20), "markers41": (60, 8)}
QUICK_FRAMES = {"body14": (20, 5), "markers41": (15, 3)}


def _code_hash() -> str:
    h = hashlib.sha1()
    for sub in ("model", "search"):
        for p in sorted((REPO / "dtm_labeler" / sub).glob("*.py")):
            h.update(p.read_bytes())
    return h.hexdigest()[:12]


def load_case(name: str):
    from dtm_labeler.cli.common import load_inputs
    spec = CASES[name]
    clips = load_inputs([str(DATA / p) for p in spec["paths"]], spec["points"])
    return clips


def model_for(name: str, clips, retrain: bool = False):
    """Trained on the first 90 % of every clip; cached in results/tmp keyed by data + code."""
    from dtm_labeler.model.io import load_model, save_model
    from dtm_labeler.training.train import TrainConfig, train_model
    key = json.dumps([name, CASES[name], [c.n_frames for c in clips], _code_hash()], sort_keys=True)
    path = RESULTS / "tmp" / f"bench_labeling_{name}_{hashlib.sha1(key.encode()).hexdigest()[:12]}.npz"
    if path.is_file() and not retrain:
        return load_model(path), None
    t = time.perf_counter()
    model, _ = train_model([c.slice(0, split(c)) for c in clips], TrainConfig(seed=0))
    seconds = time.perf_counter() - t
    path.parent.mkdir(parents=True, exist_ok=True)
    save_model(model, path)
    return model, seconds


def split(clip) -> int:
    return int(round(0.9 * clip.n_frames))


def run_one(model, clips, mode: str, cond, frames: int, seed: int) -> dict:
    from dtm_labeler.evaluation.pipeline import label_clips
    from dtm_labeler.labeling.stream import LabelerSettings
    label, occ, clu, noise = cond
    tests = [c.slice(split(c), split(c) + frames) for c in clips]
    c0 = time.process_time()
    w0 = time.perf_counter()
    m, runs = label_clips(model, tests, LabelerSettings(mode=mode, seed=seed), occlude=occ, clutter=clu,
                          noise_mm=noise, seed=seed)
    cpu = time.process_time() - c0
    wall = time.perf_counter() - w0
    lat = m.latency_ms
    return dict(condition=label, mode=mode, occlude=occ, clutter=clu, noise_mm=noise, frames=m.frames,
                labels=len(model.labels), accuracy=m.accuracy, frame_accuracy=m.frame_accuracy,
                ghost_rejection=m.ghost_rejection, swaps_per_min=m.swaps_per_min, search_errors=m.search_errors,
                search_error_rate=m.search_error_rate, full_search_rate=m.full_search_rate,
                latency_ms={k: lat[k] for k in ("p50", "p99", "max", "mean")}, fps=m.fps,
                cpu_ms_per_frame=1e3 * cpu / max(m.frames, 1), wall_s=wall,
                per_clip=[dict(source=Path(r.source).name, frames=r.metrics.frames, accuracy=r.metrics.accuracy,
                               latency_p50=r.metrics.latency_ms["p50"]) for r in runs])


def fmt(x, spec=".1f"):
    return "–" if x is None else format(x, spec)


def pct(x):
    return "–" if x is None else f"{100 * x:.1f}"


def table(rows: list[dict]) -> list[str]:
    out = ["| case | labels | mode | condition | frames | accuracy % | ghosts rejected % | swaps/min | "
           "search errors % | full searches % | p50 ms | p99 ms | max ms | fps | cpu ms/frame |",
           "|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lat = r["latency_ms"]
        out.append(f"| {r['case']} | {r['labels']} | {r['mode']} | {r['condition']} | {r['frames']} | "
                   f"{pct(r['accuracy'])} | {pct(r['ghost_rejection'])} | {fmt(r['swaps_per_min'], '.0f')} | "
                   f"{pct(r['search_error_rate'])} | {pct(r['full_search_rate'])} | {fmt(lat['p50'])} | "
                   f"{fmt(lat['p99'])} | {fmt(lat['max'])} | {fmt(r['fps'])} | {fmt(r['cpu_ms_per_frame'])} |")
    return out


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    ap.add_argument("--modes", nargs="+", choices=["stream", "single"], default=["stream", "single"])
    ap.add_argument("--quick", action="store_true", help="few frames per case (smoke run)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--retrain", action="store_true", help="ignore cached models")
    ap.add_argument("--out", default=str(RESULTS / "labeling_bench"), help="output path without suffix")
    args = ap.parse_args(argv)
    if not (DATA / "index.csv").is_file():
        print(f"real data not found at {DATA} (set DTM_DATA_DIR)", file=sys.stderr)
        return 2
    frames = QUICK_FRAMES if args.quick else FRAMES
    load0 = os.getloadavg()
    rows, training = [], {}
    for case in args.cases:
        clips = load_case(case)
        model, secs = model_for(case, clips, args.retrain)
        training[case] = dict(labels=len(model.labels), train_frames=[split(c) for c in clips],
                              sources=[Path(c.source).name for c in clips], train_seconds=secs)
        print(f"# {case}: {len(model.labels)} labels, model "
              + ("from cache" if secs is None else f"trained in {secs:.1f} s"), flush=True)
        for mode in args.modes:
            n = frames[case][0 if mode == "stream" else 1]
            for cond in CONDITIONS:
                r = run_one(model, clips, mode, cond, n, args.seed) | {"case": case}
                rows.append(r)
                print(table([r])[-1], flush=True)
    load1 = os.getloadavg()
    meta = dict(date=time.strftime("%Y-%m-%d %H:%M"), machine=platform.machine(), cpus=os.cpu_count(),
                python=platform.python_version(), commit=git_commit(), load_average_start=list(load0),
                load_average_end=list(load1), quick=args.quick, seed=args.seed, frames_per_clip=frames)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(dict(meta=meta, training=training, results=rows), indent=1))
    md = ["# Labeling engine benchmark (library, per frame)", "",
          f"{meta['date']}, commit {meta['commit']}, {meta['machine']}, {meta['cpus']} cores, Python "
          f"{meta['python']}; load average {load0[0]:.1f} at start, {load1[0]:.1f} at end "
          "(other jobs share the machine: compare cpu ms/frame, not wall latency).", "",
          "Within-sequence: model trained on the first 90 % of each recording, frames from the last 10 % "
          f"labelled (per clip: stream {frames['body14'][0]} / single {frames['body14'][1]} frames for body14, "
          f"stream {frames['markers41'][0]} / single {frames['markers41'][1]} for markers41). body14 = walk "
          "07_01 + run 09_11 + dance 55_01 BVHs (one model); markers41 = CMU 85_02 jump-twist C3D, all 41 "
          "markers. Default LabelerSettings, method cbga, seed "
          f"{args.seed}, no track ids given (the labeler's tracker associates).", "",
          "Latency = wall time of `StreamLabeler.process` per frame; fps = frames / summed latency; "
          "search errors = frames where the true labeling scores higher than the chosen one.", ""]
    md += table(rows)
    md += ["", "Per clip (accuracy %, p50 ms):", ""]
    for r in rows:
        md.append(f"- {r['case']} {r['mode']} {r['condition']}: " + "; ".join(
            f"{c['source']} {c['frames']} fr {pct(c['accuracy'])} % {fmt(c['latency_p50'])} ms" for c in r["per_clip"]))
    out.with_suffix(".md").write_text("\n".join(md) + "\n")
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
