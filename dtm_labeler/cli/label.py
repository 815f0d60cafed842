"""``dtm-label``: label recordings as unlabeled streams with a trained model and score the result.

The input's own labels are stripped (only the model's points are kept, derived to the 14 body
points when the model uses them), each frame is optionally corrupted (hidden points, ghost
points, noise) and shuffled, labelled frame by frame by the same engine the ROS node runs, and
the published labels are compared with the input's labels.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from tqdm import tqdm

from ..evaluation.pipeline import ClipRun, label_clip_run, model_clip
from ..evaluation.metrics import Metrics, MetricsAccumulator
from ..labeling.stream import METHODS, MODES, LabelerSettings
from ..model.io import load_model
from ..motion.load import load_clip
from ..search.label_search import GASettings
from ..training.calibrate import CalibrationError, calibrate_from_clip
from .common import CliError, HelpFormatter, expand_inputs, parse_frames, run_main

EPILOG = """examples:
  dtm-train walk.bvh --frames 0:90% --out walk.npz
  dtm-label walk.npz walk.bvh --frames 90%: --json
  dtm-label walk.npz walk.bvh --frames 90%: --occlude 3 --clutter 2 --noise-mm 2 --out labels.csv
  dtm-label walk.npz walk.bvh run.bvh --frames 0:50 --mode single --method greedy
  dtm-train capture.c3d --points all --frames 0:90% --out m41.npz && dtm-label m41.npz capture.c3d --frames 90%:
output (--json): method, mode, frames, labels, accuracy, ghost_rejection, swaps_per_min, search_errors,
  search_error_rate, latency_ms {p50, p99, max, mean}, fps, per_label, inputs (one entry per input).
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dtm-label", formatter_class=HelpFormatter, epilog=EPILOG,
                                description="Label recordings (labels stripped, points shuffled per frame) "
                                            "with a trained triangulated model; score against their own labels.")
    p.add_argument("model", metavar="MODEL", nargs="?", default=None,
                   help="model file from dtm-train (.npz); omitted with --bank")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="labelled recordings (.bvh .amc .c3d .csv) or folders of them")
    p.add_argument("--method", choices=METHODS, default="cbga",
                   help="cbga: constraint-based GA; sga: simple GA; greedy: Song et al. DP; exhaustive: all "
                        "assignments (tiny models only); tracker: carry labels along tracks, search only to start")
    p.add_argument("--mode", choices=MODES, default="stream",
                   help="stream: tracks, warm start and votes over the window; single: every frame on its own")
    p.add_argument("--frames", default="0:100%", help="frame range A:B of every input, integers or percentages")
    p.add_argument("--occlude", type=int, default=0, metavar="K", help="hide K true points per frame")
    p.add_argument("--clutter", type=int, default=0, metavar="K", help="add K ghost points per frame")
    p.add_argument("--noise-mm", type=float, default=0.0, metavar="S", help="Gaussian noise, std per coordinate (mm)")
    p.add_argument("--assume-noise-mm", type=float, default=None, metavar="S",
                   help="measurement noise the labeler is told about (widens the model); default: --noise-mm")
    p.add_argument("--gap-frames", type=float, default=1.0, metavar="G",
                   help="mean length of a simulated occlusion in frames (1: new hidden set every frame)")
    p.add_argument("--window", type=int, default=LabelerSettings.window, metavar="W",
                   help="vote window in frames (stream mode)")
    full = LabelerSettings().full
    p.add_argument("--population", type=int, default=full.population, metavar="P",
                   help="GA population of the full search")
    p.add_argument("--generations", type=int, default=full.max_generations, metavar="G",
                   help="GA generation cap of the full search")
    p.add_argument("--track-ids", action="store_true",
                   help="give the labeler the simulated mocap track ids instead of letting its tracker associate")
    p.add_argument("--seed", type=int, default=0, help="seed of the corruption and of the search")
    p.add_argument("--bank", default=None, metavar="DIR",
                   help="label with a model bank (directory or single-file bank from dtm-train --action ... "
                        "--bank DIR): one model per action used at once; JSON adds active_action_accuracy "
                        "when the inputs' classes are bank actions")
    p.add_argument("--bank-strategy", choices=("spread", "hard"), default="spread",
                   help="spread: population over all action models with migration; hard: one model at a time")
    p.add_argument("--calibrate", default=None, metavar="A:B",
                   help="calibrate the model's body terms to each input on its frames A:B (dtm-calibrate) and "
                        "label and score only the frames after B")
    p.add_argument("--calibrate-labels", choices=("model", "capture"), default="model",
                   help="labels of the calibration frames: the model's own, confirmed by its votes (the input's "
                        "labels are not used), or the input's (an operator-labelled calibration)")
    p.add_argument("--out", default=None, metavar="FILE.csv", help="write per-frame, per-point labels as CSV")
    p.add_argument("--json", action="store_true", help="print one JSON object with the scores")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _settings(args) -> LabelerSettings:
    if args.occlude < 0 or args.clutter < 0 or args.noise_mm < 0:
        raise CliError("--occlude, --clutter and --noise-mm must be >= 0")
    if args.gap_frames < 1:
        raise CliError("--gap-frames must be >= 1")
    full = LabelerSettings().full
    try:
        if args.population is not None or args.generations is not None:
            kw = dict(vars(full))
            if args.population is not None:
                kw["population"] = args.population
            if args.generations is not None:
                kw["max_generations"] = args.generations
            full = GASettings(**kw)
        assumed = args.noise_mm if args.assume_noise_mm is None else args.assume_noise_mm
        return LabelerSettings(method=args.method, mode=args.mode, window=args.window, full=full, seed=args.seed,
                               noise_mm=assumed)
    except ValueError as e:
        raise CliError(str(e)) from None


def _load(args, labels):
    clips = []
    for path in expand_inputs(args.inputs):
        try:
            clip = load_clip(path)
        except (ValueError, KeyError, OSError) as e:
            raise CliError(f"{path}: {e}") from None
        try:
            clip = model_clip(labels, clip)
        except ValueError as e:
            raise CliError(f"{e}") from None
        a, b = parse_frames(args.frames, clip.n_frames)
        clip = clip.slice(a, b)
        clip.meta["frame_range"] = [a, b]
        clips.append(clip)
    return clips


def _calibrated(args, model, clip):
    """(model calibrated on ``--calibrate`` frames of ``clip``, the frames after them, summary);
    the model and clip unchanged without ``--calibrate``."""
    if not args.calibrate:
        return model, clip, None
    a, b = parse_frames(args.calibrate, clip.n_frames)
    if b >= clip.n_frames:
        raise CliError(f"{clip.source}: --calibrate {args.calibrate} leaves no frames to label")
    try:
        cal, summary = calibrate_from_clip(model, clip.slice(a, b), args.calibrate_labels)
    except CalibrationError as e:
        raise CliError(f"{clip.source}: {e}") from None
    rest = clip.slice(b, None)
    first = clip.meta["frame_range"][0]
    rest.meta["frame_range"] = [first + b, clip.meta["frame_range"][1]]
    return cal, rest, dict(summary, frames=[first + a, first + b])


def _fmt(x, spec=".1f", none="n/a"):
    return none if x is None else format(x, spec)


def _pct(x):
    return "n/a" if x is None else f"{100 * x:.2f} %"


def _metrics_json(m: Metrics) -> dict:
    d = m.as_dict()
    d["latency_ms"] = {k: d["latency_ms"][k] for k in ("p50", "p99", "max", "mean")}
    return d


def _write_csv(path: str, runs: list[ClipRun], names: tuple[str, ...], multi: bool) -> None:
    name = lambda i: names[i] if i >= 0 else ""  # noqa: E731
    try:
        fh = open(path, "w", newline="", encoding="utf-8")
    except OSError as e:
        raise CliError(f"--out {path}: {e}") from None
    with fh:
        w = csv.writer(fh)
        w.writerow((["input"] if multi else []) + ["frame", "time", "x", "y", "z", "true_label", "label",
                                                    "confidence", "track_id", "search_label"])
        for run in runs:
            src = Path(run.source).name
            offset = run.settings.get("frame_offset", 0)
            for r in run.records:
                for i in range(r.xyz.shape[0]):
                    x, y, z = r.xyz[i]
                    w.writerow(([src] if multi else []) + [
                        r.index + offset, f"{r.stamp + offset / run.settings.get('rate', 1.0):.6f}",
                        f"{x:.6f}", f"{y:.6f}", f"{z:.6f}", name(int(r.truth[i])), name(int(r.labels[i])),
                        f"{r.confidence[i]:.4f}", int(r.track_ids[i]), name(int(r.search_labels[i]))])


def _main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    settings = _settings(args)
    if args.bank is not None:
        if args.model is not None:
            args.inputs = [args.model] + list(args.inputs)
            args.model = None
        return _bank_main(args, settings)
    if args.model is None:
        raise CliError("MODEL is required (or --bank DIR)")
    try:
        model = load_model(args.model)
    except (OSError, ValueError, KeyError) as e:
        msg = str(e).strip("'\"")
        raise CliError(msg if str(args.model) in msg else f"{args.model}: cannot read model: {msg}") from None
    clips = _load(args, model.labels)
    total = sum(c.n_frames for c in clips)
    bar = tqdm(total=total, desc="labeling", unit="frame", file=sys.stderr, disable=True if args.quiet else None,
               leave=False)

    def progress(done: int, _total: int) -> None:
        bar.update(done - bar.n)

    runs: list[ClipRun] = []
    done = 0
    try:
        for i, clip in enumerate(clips):
            model_i, clip, calibration = _calibrated(args, model, clip)
            run = label_clip_run(model_i, clip, settings, occlude=args.occlude, clutter=args.clutter,
                                 noise_mm=args.noise_mm, seed=args.seed + i, progress=progress,
                                 use_ids=args.track_ids, gap_frames=args.gap_frames,
                                 keep_records=args.out is not None, done=done, total=total)
            run.settings.update(frame_offset=clip.meta["frame_range"][0], rate=clip.rate,
                                frame_range=clip.meta["frame_range"], calibration=calibration)
            runs.append(run)
            done += clip.n_frames
    except ValueError as e:
        raise CliError(str(e)) from None
    finally:
        bar.close()
    pooled = MetricsAccumulator.merge(r.accumulator for r in runs).metrics()
    if args.out:
        _write_csv(args.out, runs, model.labels, multi=len(runs) > 1)

    out = {"method": args.method, "mode": args.mode, "model": str(args.model)} | _metrics_json(pooled)
    out |= {"occlude": args.occlude, "clutter": args.clutter, "noise_mm": args.noise_mm,
            "gap_frames": args.gap_frames, "window": args.window, "seed": args.seed, "track_ids": args.track_ids,
            "inputs": [{"source": r.source, "frame_range": r.settings["frame_range"]} | _metrics_json(r.metrics)
                       | ({"calibration": r.settings["calibration"]} if r.settings.get("calibration") else {})
                       for r in runs]}
    for item in out["inputs"]:
        for k in ("per_label", "label_names", "labels"):
            item.pop(k, None)
    if args.out:
        out["out"] = str(args.out)
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    _print_summary(args, model, pooled, runs)
    return 0


def _bank_main(args, settings) -> int:
    from ..evaluation.switching import label_clip_bank
    from ..labeling.bank_labeler import BankSettings
    from ..model.bank import BankFileError, load_bank
    if settings.method not in ("cbga", "tracker"):
        raise CliError("--bank searches with the CBGA: use --method cbga or tracker")
    try:
        bank = load_bank(args.bank)
    except (BankFileError, OSError) as e:
        raise CliError(str(e)) from None
    clips = _load(args, bank.labels)
    total = sum(c.n_frames for c in clips)
    bar = tqdm(total=total, desc="labeling", unit="frame", file=sys.stderr, disable=True if args.quiet else None,
               leave=False)
    runs: list[ClipRun] = []
    done = 0
    try:
        for i, clip in enumerate(clips):
            run = label_clip_bank(bank, clip, settings, BankSettings(strategy=args.bank_strategy),
                                  occlude=args.occlude, clutter=args.clutter, noise_mm=args.noise_mm,
                                  seed=args.seed + i, progress=lambda d, _t: bar.update(d - bar.n),
                                  use_ids=args.track_ids, gap_frames=args.gap_frames,
                                  keep_records=args.out is not None, done=done, total=total)
            run.settings.update(frame_offset=clip.meta["frame_range"][0], rate=clip.rate,
                                frame_range=clip.meta["frame_range"])
            runs.append(run)
            done += clip.n_frames
    except ValueError as e:
        raise CliError(str(e)) from None
    finally:
        bar.close()
    pooled = MetricsAccumulator.merge(r.accumulator for r in runs).metrics()
    if args.out:
        _write_csv(args.out, runs, bank.labels, multi=len(runs) > 1)
    known = [r for r in runs if r.settings["active_action_accuracy"] is not None]
    agree = (sum(r.settings["active_action_accuracy"] * r.metrics.frames for r in known)
             / sum(r.metrics.frames for r in known)) if known else None
    out = {"method": args.method, "mode": args.mode, "bank": str(args.bank), "actions": bank.actions,
           "bank_strategy": args.bank_strategy} | _metrics_json(pooled)
    out |= {"active_action_accuracy": agree, "occlude": args.occlude, "clutter": args.clutter,
            "noise_mm": args.noise_mm, "gap_frames": args.gap_frames, "window": args.window, "seed": args.seed,
            "track_ids": args.track_ids,
            "inputs": [{"source": r.source, "frame_range": r.settings["frame_range"],
                        "true_class": r.settings["true_class"],
                        "active_action_accuracy": r.settings["active_action_accuracy"],
                        "active_action_frames": r.settings["active_action_frames"]} | _metrics_json(r.metrics)
                       for r in runs]}
    for item in out["inputs"]:
        for k in ("per_label", "label_names", "labels"):
            item.pop(k, None)
    if args.out:
        out["out"] = str(args.out)
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    print(f"bank           {args.bank} ({len(bank.actions)} actions: {', '.join(bank.actions)}; "
          f"{args.bank_strategy})")
    for r in runs:
        fr = r.settings["active_action_frames"]
        print(f"  {Path(r.source).name[:40]:40s} class {r.settings['true_class'] or '?':6s} active "
              + ", ".join(f"{a} {c}" for a, c in fr.items() if c) + f"; agreement {_pct(r.settings['active_action_accuracy'])}")
    args.model = args.bank
    _print_summary(args, bank[bank.actions[0]], pooled, runs)
    return 0


def _print_summary(args, model, m: Metrics, runs: list[ClipRun]) -> None:
    lat = m.latency_ms
    print(f"model          {args.model} ({len(model.labels)} labels)")
    print(f"method         {args.method}, {args.mode} mode" + (f", window {args.window}" if args.mode == "stream"
                                                                 else ""))
    print(f"corruption     occlude {args.occlude}, clutter {args.clutter}, noise {args.noise_mm:g} mm, "
          f"seed {args.seed}")
    if len(runs) > 1:
        print(f"{'input':34s} {'frames':>7s} {'accuracy':>9s} {'swaps/min':>9s} {'errors':>7s} {'p50 ms':>7s}")
        for r in runs:
            rm = r.metrics
            print(f"{Path(r.source).name[:34]:34s} {rm.frames:7d} {_pct(rm.accuracy):>9s} "
                  f"{_fmt(rm.swaps_per_min):>9s} {rm.search_errors:7d} {_fmt(rm.latency_ms['p50']):>7s}")
    else:
        r0, (a, b) = runs[0], runs[0].settings["frame_range"]
        print(f"input          {Path(r0.source).name} frames {a}:{b}")
    print(f"frames         {m.frames} ({m.duration_s:.1f} s of recording)")
    print(f"accuracy       {_pct(m.accuracy)} of {m.points} visible markers; all right in "
          f"{_pct(m.frame_accuracy)} of frames; search alone {_pct(m.search_accuracy)}")
    print("ghosts         " + (f"{_pct(m.ghost_rejection)} of {m.ghosts} left unlabelled" if m.ghosts else "none"))
    print(f"swaps          {m.swaps} ({_fmt(m.swaps_per_min)} per min)")
    print(f"search errors  {m.search_errors} of {m.search_checked} frames ({_pct(m.search_error_rate)})")
    print(f"latency        p50 {_fmt(lat['p50'])} ms, p99 {_fmt(lat['p99'])} ms, max {_fmt(lat['max'])} ms; "
          f"{_fmt(m.fps)} frames/s; full searches in {_pct(m.full_search_rate)} of frames")
    worst = sorted(((v, k) for k, v in m.per_label.items() if v is not None))[:4]
    if worst and worst[0][0] < 1.0:
        print("weakest labels " + ", ".join(f"{k} {100 * v:.1f} %" for v, k in worst))
        pairs = m.confused_pairs(4)
        if pairs:
            print("confusions     " + ", ".join(f"{t}->{p} {c}" for t, p, c in pairs))
    if args.out:
        print(f"wrote          {args.out}")


def main(argv=None) -> int:
    try:
        return run_main(_main, argv)
    except BrokenPipeError:          # e.g. piped into head
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
