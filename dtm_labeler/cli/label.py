"""``dtm-label``: label captures as unlabeled streams with a trained model; score them, write them labelled.

Each take's own labels are stripped (the model's points are kept, derived to the 14 body
points when the model uses them); its unlabelled points (C3D ``*`` channels, unnamed CSV
columns, markers the model does not know) join the stream as points that must stay
unlabelled; each frame is optionally corrupted (hidden points, ghost points, noise) and
shuffled, labelled frame by frame by the same engine the ROS node runs, and the published
labels are compared with the take's labels (when it has names). ``--out`` writes the labelled
capture (C3D or CSV, the input's rate, units and axes). Folders and many takes run as one job
per take: here, in ``--jobs N`` local processes, or on a dask cluster (``--dask``).
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from tqdm import tqdm

from ..evaluation.archive import LabelJob, TakeResult, default_workers, label_take, run_jobs
from ..evaluation.labelled_capture import OUTPUT_SUFFIXES
from ..evaluation.pipeline import ClipRun, model_clip
from ..evaluation.switching import label_clip_bank
from ..evaluation.metrics import SEARCH_ERROR_KINDS, Metrics, MetricsAccumulator
from ..labeling import config
from ..labeling.bank_labeler import BankSettings, bank_settings_from_params
from ..labeling.config import LabelerSettings
from ..labeling.take_restarts import RESTART_S
from ..model.bank import BankFileError, load_bank
from ..model.io import load_model
from ..motion.load import load_clip
from .common import (CliError, HelpFormatter, add_capture_options, add_corruption_arguments, capture_kwargs,
                     expand_inputs, expand_inputs_rel, parse_frames, run_main)

EPILOG = """examples:
  dtm-train walk.bvh --frames 0:90% --out walk.npz
  dtm-label walk.npz walk.bvh --frames 90%: --json
  dtm-label walk.npz walk.bvh --frames 90%: --occlude 3 --clutter 2 --noise-mm 2 --out-points labels.csv
  dtm-label walk.npz walk.bvh run.bvh --frames 0:50 --mode single --method greedy
  dtm-train capture.c3d --points all --frames 0:90% --out m41.npz && dtm-label m41.npz capture.c3d --frames 90%:
  dtm-label m41.npz unlabelled.c3d --out labelled.c3d            # '*' channels in, named channels out
  dtm-label m41.npz archive/ --out labelled/ --jobs 2 --json     # one labelled file per take
  dtm-label m41.npz archive/ --out labelled/ --dask tcp://scheduler:8786
output (--json): method, mode, frames, labels, accuracy, ghosts, ghost_rejection, swaps_per_min, search_errors,
  search_errors_held, search_error_kinds {ghost, left_out, relabelled}, search_error_rate, latency_ms {p50, p99, max, mean}, fps, per_label, inputs (one entry per input: source,
  frame_range, named, unlabelled_points, worker, out, error, and its own figures).
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dtm-label", formatter_class=HelpFormatter, epilog=EPILOG,
                                description="Label recordings (labels stripped, points shuffled per frame, their unlabelled "
                                            "points fed as ghosts) with a trained triangulated model; score against "
                                            "their own labels when they have names; write them labelled (--out).")
    p.add_argument("model", metavar="MODEL", nargs="?", default=None,
                   help="model file from dtm-train (.npz); omitted with --bank")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="recordings (.bvh .amc .c3d .csv .trc .tsv), named or not, or folders of them")
    p.add_argument("--frames", default="0:100%", help="frame range A:B of every input, integers or percentages")
    add_corruption_arguments(p)
    p.add_argument("--track-ids", action="store_true",
                   help="give the labeler the simulated mocap track ids instead of letting its tracker associate")
    p.add_argument("--bank", default=None, metavar="DIR",
                   help="label with a model bank (directory or single-file bank from dtm-train --action ... "
                        "--bank DIR): one model per action used at once; JSON adds active_action_accuracy "
                        "when the inputs' classes are bank actions")
    config.add_arguments(p, layers=("labeler", "bank"))
    p.add_argument("--out", default=None, metavar="FILE|DIR",
                   help="write the labelled capture: FILE.c3d, FILE.csv or FILE.trc (one input), or a folder for many "
                        "(one file per take, the archive's layout kept); channels named by the model's labels, "
                        "unlabelled points as *N, the input's rate, units and axes")
    p.add_argument("--out-format", choices=("c3d", "csv", "trc"), default=None,
                   help="file type in an --out folder (default: as the input; c3d for BVH/AMC and QTM's TSV)")
    p.add_argument("--out-points", default=None, metavar="FILE.csv",
                   help="write per-frame, per-point labels as CSV (true label, label, confidence, track id)")
    p.add_argument("--drop-unlabelled", action="store_true",
                   help="feed only the model's points (ignore * channels, unnamed columns and markers the model "
                        "does not know)")
    p.add_argument("--ignore-names", action="store_true",
                   help="label every point of the takes as an unnamed one (takes named in another convention); "
                        "nothing is scored")
    add_capture_options(p)
    a = p.add_argument_group("archives")
    a.add_argument("--jobs", type=int, default=1, metavar="N",
                   help="label N takes at once in local processes (0: one per CPU)")
    a.add_argument("--dask", default=None, metavar="ADDRESS",
                   help="run the takes on a dask.distributed cluster: a scheduler address (tcp://host:8786) or "
                        "'local' (a LocalCluster of --jobs workers started for this run)")
    p.add_argument("--calibrate", default="auto", metavar="auto|off|A:B",
                   help="subject calibration of a model whose body is generic (not yet calibrated to a person): "
                        "'auto' (default) self-calibrates it (not on the one capture a model was trained on: "
                        "that is its person; a model dtm-train calibrated to its takes' person keeps that on "
                        "their captures -- on their other takes measuring again the segments whose markers that "
                        "session placed elsewhere -- and has it set aside for anyone else's, keeping it where "
                        "that person's own does not hold up) on each take's first 5 s (a shorter take: its first "
                        "third or all of it, whichever the calibrated model reproduces better; the model's own "
                        "confirmed labels, the take's names unused) and keeps the calibration when the "
                        "calibrated model keeps the labels it was measured on (and stops, keeping the model as "
                        "it is, when the model needs a full search in over half of those frames), then labels "
                        "every frame (the JSON's 'calibration' says what was done); 'off': the model as it is; "
                        "A:B: calibrate on frames A:B (as dtm-calibrate) and label and score only the frames "
                        "after B")
    p.add_argument("--calibrate-labels", choices=("model", "capture"), default="model",
                   help="labels of the calibration frames: the model's own, confirmed by its votes (the take's "
                        "labels are not used), or the take's (an operator-labelled calibration)")
    p.add_argument("--take-votes", type=float, default=1.0, metavar="SECONDS",
                   help="offline votes (stream mode): each frame's labels voted over the frames SECONDS before "
                        "and after it, so a marker's later frames correct its first guess (0: the labels as the "
                        "live node publishes them, past frames only; the JSON's live_accuracy scores those)")
    p.add_argument("--no-take-pass", dest="take_pass", action="store_false",
                   help="skip the second pass over the take (with --take-votes > 0, single model): every frame "
                        "searched again at the facing the whole take gives it, from the voted labels, and voted "
                        "again; takes one to two times as long again as the first pass")
    p.add_argument("--restarts", type=float, default=RESTART_S, metavar="SECONDS",
                   help="offline (with --take-votes > 0, single model): the take is labelled again from a fresh "
                        "start every SECONDS of it, each kept from its restart point to the next where its labels "
                        "fit the model better summed over those frames (by over 20 nats per frame), so a labeling "
                        "lost for good (many markers hidden at once) is not carried to the end of the take; a fresh "
                        "start that agrees with the carried labels for 30 frames is stopped there (0: none; the "
                        "JSON's 'restarts' says what each did)")
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
            clip = load_clip(path, **capture_kwargs(args))
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


def _write_csv(path: str, runs: list, names: tuple[str, ...], multi: bool) -> None:
    name = lambda i: names[i] if i >= 0 else ""  # noqa: E731
    try:
        fh = open(path, "w", newline="", encoding="utf-8")
    except OSError as e:
        raise CliError(f"--out-points {path}: {e}") from None
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
    jobs = _jobs(args, settings, _out_paths(args))
    results = _run_takes(args, jobs, Path(args.model).read_bytes())
    failed = [r for r in results if r.error]
    runs = [r for r in results if not r.error]
    for r in failed:
        print(f"error: {r.error if r.source in r.error else r.source + ': ' + r.error}", file=sys.stderr)
    if not runs:
        raise CliError(failed[0].error if len(failed) == 1 else f"all {len(failed)} takes failed")
    for r in runs:
        if r.note and not args.json:
            print(f"note: {r.note}", file=sys.stderr)
    pooled = MetricsAccumulator.merge(r.accumulator for r in runs).metrics()
    if args.out_points:
        _write_csv(args.out_points, runs, model.labels, multi=len(runs) > 1)
    out = {"method": settings.method, "mode": settings.mode, "model": str(args.model)} | _metrics_json(pooled)
    out |= {"drop_unlabelled": args.drop_unlabelled, "jobs": args.jobs, "dask": args.dask,
            "take_votes_s": jobs[0].take_votes_s if jobs else 0.0,
            "take_pass": bool(jobs and jobs[0].take_pass and jobs[0].take_votes_s > 0 and not args.bank)}
    live = _live_accuracy(runs)
    if live is not None:
        out["live_accuracy"] = live
    voted = _live_accuracy(runs, "voted")
    if voted is not None:
        out["voted_accuracy"] = voted
    if failed:
        out["errors"] = len(failed)
    if _report(args, settings, out, results, []):
        _print_summary(args, settings, model, pooled, runs)
        if live is not None:
            print(f"live labels    {_pct(live)} right as published live (votes over past frames only); "
                  f"the figures above vote over +-{out['take_votes_s']:g} s (--take-votes)"
                  + (f", {_pct(voted)} before the take pass" if voted is not None else ""))
        for r in runs:
            if r.calibration is not None:
                print(f"calibration    {_calibration_line(r.calibration)}"
                      + (f" ({Path(r.source).name})" if len(runs) > 1 else ""))
    return 1 if failed else 0


def _calibration_line(c: dict) -> str:
    """One line on a take's subject calibration (``--calibrate``)."""
    if c.get("recognised"):
        who = f"recognised {c['recognised']}; "
        return who + (_calibration_line({k: v for k, v in c.items() if k not in ("recognised", "person")})
                      if c.get("applied", True) else "their calibration as it is")
    if c.get("applied", True) is False:
        return f"not applied: {c.get('reason', '')}"
    frames = c.get("frames")
    where = f"frames {frames[0]}:{frames[1]}" if isinstance(frames, list) else f"the first {frames} frames"
    kept = f", {100 * c['kept_share']:.0f} % of the model's confirmed labels kept" if "kept_share" in c else ""
    if "moved" in c:            # a session check of the person's calibration (training/calibrate.session_calibrate)
        moved = (f"{len(c['moved'])} segment length(s) placed elsewhere this session set on {where}: "
                 f"{', '.join(c['moved'])}" if c["moved"] else f"no marker placed elsewhere this session ({where})")
        broad = "; the broad motion weights from the same frames" if c.get("broad") else ""
        return f"the person's calibration, {moved}{broad}{kept}"
    return f"{c.get('segments', 0)} of {c.get('segments_total', 0)} segment lengths set on {where}{kept}"


def _live_accuracy(runs: list, stage: str = "causal") -> float | None:
    """Accuracy of the labels as published live, before the take votes (None without them);
    ``stage="voted"``: after the take votes, before the take pass (None without it)."""
    parts = [getattr(r, stage) for r in runs if getattr(r, stage, None) is not None]
    return MetricsAccumulator.merge(parts).metrics().accuracy if parts else None


def _out_paths(args) -> list[tuple[Path, str | None]]:
    """(take, labelled file to write or None) for every input."""
    takes = expand_inputs_rel(args.inputs)
    if not args.out:
        return [(f, None) for f, _ in takes]
    out = Path(args.out)
    if out.suffix.lower() in OUTPUT_SUFFIXES and not out.is_dir():
        if len(takes) != 1:
            raise CliError(f"--out {out}: {len(takes)} takes need a folder (--out DIR)")
        return [(takes[0][0], str(out))]
    if out.suffix and not out.is_dir():
        raise CliError(f"--out {out}: write a {', '.join(OUTPUT_SUFFIXES)} file, or give a folder")
    paths = []
    for f, rel in takes:
        kind = args.out_format or (f.suffix.lower().lstrip(".") if f.suffix.lower() in OUTPUT_SUFFIXES else "c3d")
        paths.append((f, str(out / rel.with_suffix("." + kind))))
    dup = {p for _, p in paths if [q for _, q in paths].count(p) > 1}
    if dup:
        raise CliError(f"--out {out}: several takes would write {sorted(dup)[0]}")
    return paths


def _jobs(args, settings, takes) -> list[LabelJob]:
    """One job per take: take ``i`` corrupted with ``seed + i`` (as a serial run)."""
    load = capture_kwargs(args)
    return [LabelJob(index=i, source=str(f), settings=settings, frames=args.frames, occlude=args.occlude,
                     clutter=args.clutter, noise_mm=args.noise_mm, gap_frames=args.gap_frames, seed=settings.seed + i,
                     use_ids=args.track_ids, keep_unlabelled=not args.drop_unlabelled,
                     ignore_names=args.ignore_names, out=out, keep_records=args.out_points is not None, load=load,
                     calibrate=args.calibrate, calibrate_labels=args.calibrate_labels,
                     take_votes_s=_take_votes(args, settings), take_pass=args.take_pass,
                     restart_s=_restarts(args))
            for i, (f, out) in enumerate(takes)]


def _take_votes(args, settings) -> float:
    if args.take_votes < 0:
        raise CliError("--take-votes must be >= 0 seconds")
    return args.take_votes if settings.mode == "stream" else 0.0


def _restarts(args) -> float:
    if args.restarts < 0:
        raise CliError("--restarts must be >= 0 seconds")
    return 0.0 if args.bank else args.restarts


def _run_takes(args, jobs: list[LabelJob], model_bytes: bytes) -> list[TakeResult]:
    """All takes, one progress bar (frames for one take here, takes otherwise)."""
    if args.jobs < 0:
        raise CliError("--jobs must be >= 0 (0: one per CPU)")
    workers = default_workers() if args.jobs == 0 else args.jobs
    quiet = True if args.quiet else None
    if len(jobs) == 1 and workers <= 1 and not args.dask:
        bar = tqdm(desc="labeling", unit="frame", file=sys.stderr, disable=quiet, leave=False)

        shown = ["labeling", 0]                           # the bar's stage and frames done

        def stage(name: str):
            def frames(done: int, total: int) -> None:
                if shown[0] != name or done < shown[1]:   # a new stage, or a new self-labelling round
                    bar.set_description(name, refresh=False)
                    bar.reset(total=total)
                    shown[:] = [name, 0]
                bar.update(done - shown[1])
                shown[1] = done
            return frames
        try:
            return [label_take(jobs[0], model_bytes, stage("labeling"), stage("self-calibrating"))]
        finally:
            bar.close()
    bar = tqdm(total=len(jobs), desc="labeling", unit="take", file=sys.stderr, disable=quiet, leave=False)

    def takes(done: int, total: int, r: TakeResult) -> None:
        bar.set_postfix_str(Path(r.source).name[:30])
        bar.update(done - bar.n)
    try:
        return run_jobs(label_take, jobs, model_bytes, workers=workers, dask=args.dask, progress=takes)
    except (OSError, RuntimeError, TimeoutError) as e:
        raise CliError(f"{'--dask ' + args.dask if args.dask else '--jobs'}: {e}") from None
    finally:
        bar.close()


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
                            keep_records=args.out_points is not None, done=done, total=total)
            run.settings.update(frame_offset=clip.meta["frame_range"][0], rate=clip.rate,
                                frame_range=clip.meta["frame_range"])
            runs.append(run)
            done += clip.n_frames
    except ValueError as e:
        raise CliError(str(e)) from None
    finally:
        bar.close()
    if args.out_points:
        _write_csv(args.out_points, runs, tuple(labels), multi=len(runs) > 1)
    return runs, MetricsAccumulator.merge(r.accumulator for r in runs).metrics()


def _report(args, settings, out: dict, runs: list, input_keys: list[str]) -> bool:
    """Complete the JSON object (corruption, settings, one entry per input with ``input_keys``
    of its run settings, or a take's own summary) and print it with ``--json``; True when a
    text summary is due."""
    out |= {"occlude": args.occlude, "clutter": args.clutter, "noise_mm": args.noise_mm,
            "gap_frames": args.gap_frames, "window": settings.window, "seed": settings.seed,
            "track_ids": args.track_ids,
            "inputs": [(r.summary() if isinstance(r, TakeResult) else
                        {"source": r.source, "frame_range": r.settings["frame_range"]}
                        | {k: r.settings[k] for k in input_keys})
                       | (_metrics_json(r.metrics) if getattr(r, "accumulator", None) is not None else {})
                       | ({"live_accuracy": r.causal.metrics().accuracy}
                          if getattr(r, "causal", None) is not None else {})
                       for r in runs]}
    for item in out["inputs"]:
        for k in ("per_label", "label_names", "labels"):
            item.pop(k, None)
    for key in ("out", "out_points"):
        if getattr(args, key, None):
            out[key] = str(getattr(args, key))
    if args.json:
        print(json.dumps(out, indent=1))
        return False
    return True


def _bank_main(args, settings, bank_settings) -> int:
    if args.out or args.jobs != 1 or args.dask or args.calibrate not in ("auto", "off"):
        raise CliError("--bank labels takes one after the other and writes no labelled capture "
                       "(--out, --jobs, --dask, --calibrate A:B are for a single model; a bank is not "
                       "calibrated: calibrate its models with dtm-calibrate)")
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


def _print_summary(args, settings, model, m: Metrics, runs: list) -> None:
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
    unl = sum(getattr(r, "unlabelled_points", 0) for r in runs)
    if unl:
        print(f"unlabelled     {unl} point{'s' if unl > 1 else ''} of the take{'s' if len(runs) > 1 else ''} "
              "(* channels, unnamed columns, markers not in the model) fed as ghosts")
    joined = sum(getattr(r, "fragments_joined", 0) for r in runs)
    if joined:
        print(f"fragments      {joined} samples of unlabelled channels continue named markers across their gaps: "
              "joined to them (labelled and scored as those markers)")
    unnamed = [r for r in runs if not getattr(r, "named", True)]
    if unnamed:
        print(f"not scored     {len(unnamed)} take{'s' if len(unnamed) > 1 else ''} without names")
    print(f"accuracy       {_pct(m.accuracy)} of {m.points} visible markers; all right in "
          f"{_pct(m.frame_accuracy)} of frames; search alone {_pct(m.search_accuracy)}")
    print("ghosts         " + (f"{_pct(m.ghost_rejection)} of {m.ghosts} left unlabelled" if m.ghosts else "none"))
    print(f"swaps          {m.swaps} ({_fmt(m.swaps_per_min)} per min)")
    kinds = ", ".join(f"{SEARCH_ERROR_KINDS[k]} in {v}" for k, v in m.search_error_kinds.items() if v)
    print(f"search errors  {m.search_errors} of {m.search_checked} frames ({_pct(m.search_error_rate)}); "
          f"{m.search_errors_held} of them held by the tracks' priors" + (f"; by kind: {kinds}" if kinds else ""))
    print(f"latency        p50 {_fmt(lat['p50'])} ms, p99 {_fmt(lat['p99'])} ms, max {_fmt(lat['max'])} ms; "
          f"{_fmt(m.fps)} frames/s; full searches in {_pct(m.full_search_rate)} of frames")
    worst = sorted(((v, k) for k, v in m.per_label.items() if v is not None))[:4]
    if worst and worst[0][0] < 1.0:
        print("weakest labels " + ", ".join(f"{k} {100 * v:.1f} %" for v, k in worst))
        pairs = m.confused_pairs(4)
        if pairs:
            print("confusions     " + ", ".join(f"{t}->{p} {c}" for t, p, c in pairs))
    for r in runs:
        if getattr(r, "out", None):
            print(f"wrote          {r.out}")
    if getattr(args, "out_points", None):
        print(f"wrote          {args.out_points}")


def main(argv=None) -> int:
    try:
        return run_main(_main, argv)
    except BrokenPipeError:          # e.g. piped into head
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
