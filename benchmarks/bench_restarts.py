#!/usr/bin/env python
"""Fresh starts over a take (``dtm-label --restarts``) on whole gapped halves of a capture.

``bench_captures.py``'s gapped halves label the first 600 frames (5 s) of the second half. Here a
take's gapped first half trains as ``dtm-train`` does (all of it; markers it shows too rarely
left out, as its message says) and ``dtm-label``'s default labels the whole gapped second half
(HDM05: 2960 frames, 24.7 s) with its own tracker, once without fresh starts (``--restarts 0``)
and once with them (``--restarts`` SECONDS, default dtm-label's), under several draws of the gaps
(50 % of the samples hidden, log-normal gaps of mean 0.25 s: ``bench_captures.GAPS``). Each
draw runs in its own process (``--jobs``).

Writes OUT.json, OUT.md and OUT.png (accuracy along the second half, every draw both ways).

    .venv/bin/python benchmarks/bench_restarts.py [--quick] [--gap-seeds 1,2,3,4,5,6] [--jobs 2]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO))

import bench_captures as BC  # noqa: E402
from dtm_labeler.evaluation.archive import LabelJob, label_take  # noqa: E402
from dtm_labeler.labeling.stream import LabelerSettings  # noqa: E402
from dtm_labeler.labeling.take_restarts import RESTART_S  # noqa: E402
from dtm_labeler.model.io import model_to_bytes  # noqa: E402
from dtm_labeler.motion.load import load_clip  # noqa: E402

#: accuracy along the second half is read over pieces of this many seconds
PIECE_S = 2.5


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _pieces(records, rate: float) -> list[float]:
    """Accuracy of the final labels over consecutive pieces of ``PIECE_S`` seconds."""
    step = max(1, int(round(PIECE_S * rate)))
    out = []
    for a in range(0, len(records), step):
        n = right = 0
        for r in records[a:a + step]:
            t = r.truth >= 0
            n += int(t.sum())
            right += int((r.labels == r.truth)[t].sum())
        out.append(right / n if n else float("nan"))
    return out


def draw(key: str, seed: int, restart_s: float, quick: bool) -> dict:
    """One gap draw: train on the gapped first half, label the gapped second half both ways."""
    clip = load_clip(BC.DATA / BC.TAKES[key][0])
    half = clip.n_frames // 2
    train, test = (slice(half - 600, half), slice(half, half + 1440)) if quick else \
        (slice(0, half), slice(half, clip.n_frames))
    gap = BC.gapped(clip, **(BC.GAPS | {"mean_gap_s": BC.GAP_S.get(key, BC.GAPS["mean_gap_s"]), "seed": seed}))
    row: dict = {"key": key, "seed": seed, "train_frames": [train.start, train.stop],
                 "label_frames": [test.start, test.stop], "rate": clip.rate,
                 "missing_test": float(np.isnan(gap.slice(test.start, test.stop).positions[..., 0]).mean())}
    model = BC.train_leaving_out(gap.slice(train.start, train.stop), row, f"restarts {key} {seed}")
    data = model_to_bytes(model)
    with tempfile.TemporaryDirectory() as d:
        path = BC.write_take(Path(d) / "test.c3d", gap.slice(test.start, test.stop))
        for tag, rs in (("off", 0.0), ("on", restart_s)):
            r = label_take(LabelJob(index=0, source=str(path), settings=LabelerSettings(),
                                    take_votes_s=BC.TAKE_VOTES_S, restart_s=rs, keep_records=True), data)
            if r.error:
                raise RuntimeError(r.error)
            row[tag] = {"accuracy": r.metrics.accuracy, "live_accuracy": r.causal.metrics().accuracy,
                        "wall_s": r.wall_s, "restarts": r.restarts, "pieces": _pieces(r.records, clip.rate)}
            log(f"{key} draw {seed}, restarts {tag}: live {100 * row[tag]['live_accuracy']:.2f} %, "
                f"final {100 * row[tag]['accuracy']:.2f} %, {r.wall_s:.0f} s")
    return row


def write_md(rows: list[dict], meta: dict, png: str) -> str:
    rs = meta["restart_s"]
    L = ["# Fresh starts over a take (`dtm-label --restarts`), whole gapped halves", "",
         f"{meta['machine']}; {meta['date']}, commit {meta['commit']}, load average {meta['load_start']:.1f} -> "
         f"{meta['load_end']:.1f}; `{meta['command']}`.", "",
         "The gapped first half (50 % of the samples hidden, gaps of mean 0.25 s) trains as `dtm-train` does; "
         "`dtm-label`'s default (votes over +-1 s, the take pass, its own tracker) labels the whole gapped "
         f"second half without fresh starts and with one every {rs:g} s. Final labels; *live*: the first "
         "labeler's, as the node would publish them (the same both ways).", "",
         "| take | draw | frames labelled | hidden | live % | final, no restarts % | final, restarts % | "
         "restarts kept | wall s (off / on) |",
         "|---|---:|---:|---:|---:|---:|---:|---|---|"]
    for r in rows:
        kept = [f"{s['start_s']:.0f} s ({s['gain_per_frame']:+.0f})" for s in r["on"]["restarts"] if s["kept"]]
        L.append(f"| {r['key']} | {r['seed']} | {r['label_frames'][1] - r['label_frames'][0]} | "
                 f"{100 * r['missing_test']:.0f} % | {100 * r['off']['live_accuracy']:.2f} | "
                 f"{100 * r['off']['accuracy']:.2f} | **{100 * r['on']['accuracy']:.2f}** | "
                 f"{', '.join(kept) or 'none'} of {len(r['on']['restarts'])} | "
                 f"{r['off']['wall_s']:.0f} / {r['on']['wall_s']:.0f} |")
    for key in sorted({r["key"] for r in rows}):
        k = [r for r in rows if r["key"] == key]
        L.append(f"| {key} | mean | | | {100 * np.mean([r['off']['live_accuracy'] for r in k]):.2f} | "
                 f"{100 * np.mean([r['off']['accuracy'] for r in k]):.2f} | "
                 f"**{100 * np.mean([r['on']['accuracy'] for r in k]):.2f}** | | |")
    L += ["", "Restarts kept: restart point (nats per frame the fresh start fits better over its frames).", "",
          f"![accuracy along the second half]({png})", ""]
    return "\n".join(L)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9, 4.5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, r in enumerate(rows):
        c = colours[i % len(colours)]
        for tag, style in (("off", ":"), ("on", "-")):
            p = 100 * np.array(r[tag]["pieces"])
            t = (np.arange(p.size) + 0.5) * PIECE_S
            ax.plot(t, p, style, color=c, marker="o" if tag == "on" else None, ms=3,
                    label=f"{r['key']} draw {r['seed']}" if tag == "on" else None)
    ax.set_xlabel(f"seconds into the second half (accuracy over {PIECE_S:g} s pieces)")
    ax.set_ylabel("final labels right, %")
    ax.set_ylim(0, 101)
    ax.set_title("dtm-label on whole gapped halves: dotted without fresh starts, solid with them")
    ax.legend(fontsize=8, ncol=3, loc="lower left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="600 training frames, 1440 labelled, one draw")
    ap.add_argument("--takes", default="hdm05")
    ap.add_argument("--gap-seeds", default="1,2,3,4,5,6")
    ap.add_argument("--restarts", type=float, default=RESTART_S, metavar="SECONDS")
    ap.add_argument("--jobs", type=int, default=2, help="draws labelled at once (processes)")
    ap.add_argument("--out", default=str(REPO / "results" / "take_restarts"), help="output stem")
    args = ap.parse_args(argv)
    seeds = [1] if args.quick else [int(s) for s in args.gap_seeds.split(",")]
    if args.quick:
        args.restarts = min(args.restarts, 5.0)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                            text=True).stdout.strip()
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "commit": commit, "load_start": os.getloadavg()[0],
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
            "command": "benchmarks/bench_restarts.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "restart_s": args.restarts}
    todo = [(k, s) for k in args.takes.split(",") for s in seeds]
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = [pool.submit(draw, k, s, args.restarts, args.quick) for k, s in todo]
        rows = [f.result() for f in futures]
    meta["load_end"] = os.getloadavg()[0]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1, default=float))
    plot(rows, out.with_suffix(".png"))
    md = write_md(rows, meta, out.with_suffix(".png").name)
    out.with_suffix(".md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
