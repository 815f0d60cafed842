#!/usr/bin/env python
"""dtm-label's default subject calibration (``--calibrate auto``) on the generalisation cells.

For every case of ``dtm-eval``'s generalisation section (models trained as there, with the
generic body ``dtm-train`` makes), the test take's start -- the eval's calibration window (the first
5 s, at most a third of the take) and the 360 (41 markers) or 480 frames after it -- is
labelled in stream mode as ``dtm-label`` feeds it (labels stripped, points shuffled), once with
the model as it is (``--calibrate off``) and once with the default: the generic body
self-calibrated on the clip's first 5 s (a clip shorter than 15 s: its first third and all of its
first 5 s both, the better reproduced kept) and kept when the calibrated model keeps >= 90 % of
the labels the model confirmed there (:func:`dtm_labeler.training.calibrate.auto_calibrate`).
Accuracy over every frame of the window and after it (the labels as published live: no take
votes). Writes results/auto_calibration.{json,md}.

``--short 80,150,240``: short takes instead -- only the test take's first N frames, as a user
labels a short trial (``dtm-label`` calibrates on its first third or all of it, the better
reproduced kept); writes results/auto_calibration_short.{json,md}.

    .venv/bin/python benchmarks/bench_auto_calibration.py [--cases loso_5,loso_9] [--short 80,150]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("DTM_DATA_DIR", REPO.parent / "shared" / "data"))
RESULTS = REPO / "results"

from dtm_labeler.evaluation import generalisation as G  # noqa: E402
from dtm_labeler.evaluation.archive import AUTO_CALIBRATION_S  # noqa: E402
from dtm_labeler.evaluation.pipeline import label_clip_run  # noqa: E402
from dtm_labeler.labeling.stream import LabelerSettings  # noqa: E402


def run_case(case: G.Case) -> dict:
    train, test = G.case_clips(DATA, case)
    model, _ = G.train_case_model(train, G.train_config(case, "body", 0))
    window = G.calibration_frames(test, AUTO_CALIBRATION_S)
    n = window + (360 if case.points != "body14" else 480)
    clip = test.slice(0, n)
    off = label_clip_run(model, clip, LabelerSettings(seed=0), seed=0, keep_records=False)
    auto = label_clip_run(model, clip, LabelerSettings(seed=0), seed=0, keep_records=False,
                          calibrate_s=AUTO_CALIBRATION_S)
    return dict(group=case.group, title=case.title, frames=clip.n_frames, window=window, off=off.metrics.accuracy,
                auto=auto.metrics.accuracy, calibration=auto.settings["calibration"])


def head_commit() -> str:
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                          text=True).stdout.strip()


def run_short(case: G.Case, lengths: list[int]) -> dict:
    """The test take's first N frames for each N: accuracy off and auto, and the calibration."""
    train, test = G.case_clips(DATA, case)
    model, _ = G.train_case_model(train, G.train_config(case, "body", 0))
    out = dict(group=case.group, title=case.title, takes={})
    for n in lengths:
        clip = test.slice(0, min(n, test.n_frames))
        off = label_clip_run(model, clip, LabelerSettings(seed=0), seed=0, keep_records=False)
        auto = label_clip_run(model, clip, LabelerSettings(seed=0), seed=0, keep_records=False,
                              calibrate_s=AUTO_CALIBRATION_S)
        out["takes"][str(clip.n_frames)] = dict(off=off.metrics.accuracy, auto=auto.metrics.accuracy,
                                                calibration=auto.settings["calibration"],
                                                weakest=sorted((v, k) for k, v in auto.metrics.per_label.items()
                                                               if v is not None)[:2])
    return out


def write_short_md(res: dict, meta: dict) -> str:
    lengths = sorted({int(n) for r in res.values() for n in r["takes"]})
    L = ["# dtm-label's default subject calibration on short takes", "",
         f"{meta['when']}, commit {meta['commit']}, 2 cores. Each case of the generalisation section "
         "(models as there); the test take's first N frames labelled as `dtm-label` feeds a short "
         "trial, with the model as it is (off) and with the default self-calibration (auto: the "
         "take's first third or all of it, the better reproduced kept; applied only when the "
         "calibrated model keeps >= 90 % of the labels the model confirmed). Stream accuracy over "
         "every frame, labels as published live. `benchmarks/bench_auto_calibration.py --short`.", "",
         "| group | case | " + " | ".join(f"{n} frames off / auto %" for n in lengths) + " | weakest labels (auto, longest) |",
         "|---|---|" + "---:|" * len(lengths) + "---|"]
    for r in res.values():
        cells = []
        for n in lengths:
            t = r["takes"].get(str(n))
            cells.append("-" if t is None else f"{100 * t['off']:.1f} / {100 * t['auto']:.1f}"
                         + ("" if t["calibration"].get("applied") else " (not applied)"))
        last = r["takes"][max(r["takes"], key=int)]
        weak = ", ".join(f"{k} {100 * v:.0f} %" for v, k in last["weakest"] if v < 0.995) or "-"
        L.append(f"| {r['group']} | {r['title']} | " + " | ".join(cells) + f" | {weak} |")
    return "\n".join(L) + "\n"


def write_md(res: dict, meta: dict) -> str:
    L = ["# dtm-label's default subject calibration (`--calibrate auto`)", "",
         f"{meta['when']}, commit {meta['commit']}, 2 cores. {__doc__.split(chr(10) + chr(10))[1]}", ""]
    older = {k: c for k, c in meta.get("commits", {}).items() if c != meta["commit"] and k in res}
    if older:
        L += ["Rows kept from an earlier run (`--merge`): " + "; ".join(f"{res[k]['title']} (commit {c})"
                                                                       for k, c in older.items()) + ".", ""]
    L += [
         "| group | case | frames (calibration frames) | off % | auto % | calibration | kept % |",
         "|---|---|---:|---:|---:|---|---:|"]
    for r in res.values():
        c = r["calibration"]
        L.append(f"| {r['group']} | {r['title']} | {r['frames']} ({r['calibration'].get('frames')}) | {100 * r['off']:.2f} | "
                 f"{100 * r['auto']:.2f} | {'applied' if c['applied'] else 'not applied'} | "
                 f"{100 * c['kept_share']:.1f} |" if 'kept_share' in c else
                 f"| {r['group']} | {r['title']} | {r['frames']} ({r['calibration'].get('frames')}) | {100 * r['off']:.2f} | "
                 f"{100 * r['auto']:.2f} | not applied: {c.get('reason', '')} | - |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(c.key for c in G.CASES))
    ap.add_argument("--merge", action="store_true", help="keep the cases of results/auto_calibration.json "
                    "that this run does not redo (their rows keep the commit they were measured at)")
    ap.add_argument("--short", default="", help="comma-separated take lengths (frames): short takes instead")
    args = ap.parse_args(argv)
    keys = args.cases.split(",")
    if args.short:
        return main_short([c for c in G.CASES if c.key in keys], [int(x) for x in args.short.split(",")])
    res, kept = {}, {}
    if args.merge and (RESULTS / "auto_calibration.json").is_file():
        old = json.loads((RESULTS / "auto_calibration.json").read_text())
        kept = {k: old["meta"].get("commits", {}).get(k, old["meta"]["commit"]) for k in old["cases"] if k not in keys}
        res = {k: v for k, v in old["cases"].items() if k in kept}
    for case in (c for c in G.CASES if c.key in keys):
        t = time.perf_counter()
        res[case.key] = r = run_case(case)
        print(f"{case.key}: {100 * r['off']:.2f} -> {100 * r['auto']:.2f} % "
              f"({'applied' if r['calibration']['applied'] else 'not applied'}, "
              f"kept {r['calibration'].get('kept_share', float('nan')):.3f}; {time.perf_counter() - t:.0f} s)",
              flush=True)
    commit = head_commit()
    meta = {"when": time.strftime("%Y-%m-%d %H:%M"), "commit": commit,
            "commits": {**{k: commit for k in res if k not in kept}, **kept}}
    res = {c.key: res[c.key] for c in G.CASES if c.key in res}          # the section's order
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "auto_calibration.json").write_text(json.dumps({"meta": meta, "cases": res}, indent=1))
    (RESULTS / "auto_calibration.md").write_text(write_md(res, meta))
    print(write_md(res, meta))
    return 0


def main_short(cases: list, lengths: list[int]) -> int:
    res = {}
    for case in cases:
        t = time.perf_counter()
        res[case.key] = r = run_short(case, lengths)
        print(f"{case.key}: " + ", ".join(f"{n}: {100 * x['off']:.1f} -> {100 * x['auto']:.1f} %"
                                         for n, x in r["takes"].items())
              + f" ({time.perf_counter() - t:.0f} s)", flush=True)
    commit = head_commit()
    meta = {"when": time.strftime("%Y-%m-%d %H:%M"), "commit": commit, "lengths": lengths}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "auto_calibration_short.json").write_text(json.dumps({"meta": meta, "cases": res}, indent=1))
    (RESULTS / "auto_calibration_short.md").write_text(write_short_md(res, meta))
    print(write_short_md(res, meta))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
