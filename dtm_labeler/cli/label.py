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
from ..evaluation.switching import label_clip_bank
from ..evaluation.metrics import Metrics, MetricsAccumulator
from ..labeling import config
from ..labeling.bank_labeler import BankSettings, bank_settings_from_params
from ..labeling.config import LabelerSettings
from ..model.bank import BankFileError, load_bank
from ..model.io import load_model
from ..motion.load import load_clip
from ..training.calibrate import CalibrationError, calibrate_from_clip
from .common import CliError, HelpFormatter, add_corruption_arguments, expand_inputs, parse_frames, run_main

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
    p.add_argument("--frames", default="0:100%", help="frame range A:B of every input, integers or percentages")
    add_corruption_arguments(p)
    p.add_argument("--track-ids", action="store_true",
                   help="give the labeler the simulated mocap track ids instead of letting its tracker associate")
    p.add_argument("--bank", default=None, metavar="DIR",
                   help="label with a model bank (directory or single-file bank from dtm-train --action ... "
                        "--bank DIR): one model per action used at once; JSON adds active_action_accuracy "
                        "when the inputs' classes are bank actions")
    config.add_arguments(p, layers=("labeler", "bank"))
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


def _settings(args) -> tuple[LabelerSettings, BankSettings]:
    """Labeler and bank settings: ``--params-file``, then the flags given; the labeler is told
    the noise the stream is given (``--noise-mm``) unless ``--assume-noise-mm`` says otherwise."""
    try:
        values = config.params_from_args(args, layers=("labeler", "bank"))
        values.setdefault("noise_mm", args.noise_mm)
        return config.settings_from_params(values), bank_settings_from_params(values)
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
    settings, bank_settings = _settings(args)
    if args.bank is not None:
        if args.model is not None:
            args.inputs = [args.model] + list(args.inputs)
            args.model = None
        return _bank_main(args, settings, bank_settings)
    if args.model is None:
        raise CliError("MODEL is required (or --bank DIR)")
    try:
        model = load_model(args.model)
    except (OSError, ValueError, KeyError) as e:
        msg = str(e).strip("'\"")
        raise CliError(msg if str(args.model) in msg else f"{args.model}: cannot read model: {msg}") from None

    def label_one(clip, **kw):
        model_i, rest, calibration = _calibrated(args, model, clip)
        run = label_clip_run(model_i, rest, settings, **kw)
        run.settings.update(frame_range=rest.meta["frame_range"], calibration=calibration)
        return run

    runs, pooled = _label_all(args, settings, model.labels, label_one)
    out = {"method": settings.method, "mode": settings.mode, "model": str(args.model)} | _metrics_json(pooled)
    if _report(args, settings, out, runs, ["calibration"] if args.calibrate else []):
        _print_summary(args, settings, model, pooled, runs)
    return 0


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


def _label_all(args, settings, labels, label_one):
    """Every input through ``label_one(clip, **corruption, seed, progress, ...)`` (input ``i``
    corrupted with ``seed + i``), one progress bar; returns the runs and the pooled metrics;
    ``--out`` written."""
    clips = _load(args, labels)
    total = sum(c.n_frames for c in clips)
    bar = tqdm(total=total, desc="labeling", unit="frame", file=sys.stderr, disable=True if args.quiet else None,
               leave=False)
    runs: list[ClipRun] = []
    done = 0
    try:
        for i, clip in enumerate(clips):
            run = label_one(clip, occlude=args.occlude, clutter=args.clutter, noise_mm=args.noise_mm,
                            seed=settings.seed + i, progress=lambda d, _t: bar.update(d - bar.n),
                            use_ids=args.track_ids, gap_frames=args.gap_frames,
                            keep_records=args.out is not None, done=done, total=total)
            frames = run.settings.get("frame_range") or clip.meta["frame_range"]    # (after a calibration window)
            run.settings.update(frame_offset=frames[0], rate=clip.rate, frame_range=frames)
            runs.append(run)
            done += clip.n_frames
    except ValueError as e:
        raise CliError(str(e)) from None
    finally:
        bar.close()
    if args.out:
        _write_csv(args.out, runs, tuple(labels), multi=len(runs) > 1)
    return runs, MetricsAccumulator.merge(r.accumulator for r in runs).metrics()


def _report(args, settings, out: dict, runs: list[ClipRun], input_keys: list[str]) -> bool:
    """Complete the JSON object (corruption, settings, one entry per input with ``input_keys``
    of its run settings) and print it with ``--json``; True when a text summary is due."""
    out |= {"occlude": args.occlude, "clutter": args.clutter, "noise_mm": args.noise_mm,
            "gap_frames": args.gap_frames, "window": settings.window, "seed": settings.seed,
            "track_ids": args.track_ids,
            "inputs": [{"source": r.source, "frame_range": r.settings["frame_range"]}
                       | {k: r.settings[k] for k in input_keys} | _metrics_json(r.metrics) for r in runs]}
    for item in out["inputs"]:
        for k in ("per_label", "label_names", "labels"):
            item.pop(k, None)
    if args.out:
        out["out"] = str(args.out)
    if args.json:
        print(json.dumps(out, indent=1))
        return False
    return True


def _bank_main(args, settings, bank_settings) -> int:
    try:
        bank = load_bank(args.bank)
    except (BankFileError, OSError) as e:
        raise CliError(str(e)) from None
    runs, pooled = _label_all(args, settings, bank.labels,
                              lambda clip, **kw: label_clip_bank(bank, clip, settings, bank_settings, **kw))
    known = [r for r in runs if r.settings["active_action_accuracy"] is not None]
    agree = (sum(r.settings["active_action_accuracy"] * r.metrics.frames for r in known)
             / sum(r.metrics.frames for r in known)) if known else None
    out = {"method": settings.method, "mode": settings.mode, "bank": str(args.bank), "actions": bank.actions,
           "bank_strategy": bank_settings.strategy} | _metrics_json(pooled) | {"active_action_accuracy": agree}
    if not _report(args, settings, out, runs, ["true_class", "active_action_accuracy", "active_action_frames"]):
        return 0
    print(f"bank           {args.bank} ({len(bank.actions)} actions: {', '.join(bank.actions)}; "
          f"{bank_settings.strategy})")
    for r in runs:
        fr = r.settings["active_action_frames"]
        print(f"  {Path(r.source).name[:40]:40s} class {r.settings['true_class'] or '?':6s} active "
              + ", ".join(f"{a} {c}" for a, c in fr.items() if c) + f"; agreement {_pct(r.settings['active_action_accuracy'])}")
    args.model = args.bank
    _print_summary(args, settings, bank[bank.actions[0]], pooled, runs)
    return 0


def _print_summary(args, settings, model, m: Metrics, runs: list[ClipRun]) -> None:
    lat = m.latency_ms
    print(f"model          {args.model} ({len(model.labels)} labels)")
    print(f"method         {settings.method}, {settings.mode} mode" + (f", window {settings.window}" if settings.mode == "stream"
                                                                 else ""))
    print(f"corruption     occlude {args.occlude}, clutter {args.clutter}, noise {args.noise_mm:g} mm, "
          f"seed {settings.seed}")
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
