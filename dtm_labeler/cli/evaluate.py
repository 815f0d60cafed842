"""``dtm-eval``: reproduce the paper's tables and figures (Hu & Wong, section V) on given data.

Writes ``DIR/report.md`` (Markdown, with the paper's numbers beside ours), PNG figures and
``DIR/results.json`` (every number in the report). Sections (``--only``):

  tables12     Tables 1-2 / Figs. 8-9: tests of the per-triangle probability models
  structure    structures found by CBGA / simple GA / greedy vs the given one (Fig. 12)
  table3       Table 3 / Fig. 11: labeling accuracy per method, single and stream mode
  occlusion    Fig. 13: accuracy vs occluded points per frame
  noise        Fig. 14: accuracy vs Gaussian position noise
  voting       Fig. 15: accuracy vs number of voting frames (stream mode)
  generations  Fig. 10: best fitness per generation, CBGA vs SGA label search
  cross        train on some subjects, test on another subject
  markers      41-marker C3D and 28-marker CSV recordings at all markers
  generalisation  other takes, other motions, other people: today's model vs body terms vs
               body terms + calibration (dtm_labeler.evaluation.generalisation)
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

from ..evaluation.plans import SECTIONS, PlanError, Runner, make_plan, run_sections
from ..evaluation.report import write_report
from ..evaluation.switching import ExperimentSettings, run_experiment
from .common import CliError, HelpFormatter, run_main

REPO = Path(__file__).resolve().parents[2]

EPILOG = """examples:
  dtm-eval --quick --out /tmp/eval          smoke test (about 1-2 minutes)
  dtm-eval                                  full run into results/eval (about 15-25 minutes on 2 cores)
  dtm-eval --only tables12,structure        just the model tests
  dtm-eval --frames-per-test 30 --jobs 2    more test frames per cell
  dtm-eval --only bank                      action-model bank on switching sequences (results/eval/bank)
  dtm-eval --only generalisation            other takes / motions / people, with and without calibration
"""

def _default_data_dir() -> Path:
    env = os.environ.get("DTM_DATA_DIR")
    return Path(env) if env else REPO.parent / "shared" / "data"


# -- main -------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dtm-eval", formatter_class=HelpFormatter, epilog=EPILOG,
                                description="Reproduce Hu & Wong's tables and figures (section V) on the "
                                            "recordings in --data; writes report.md, PNG figures and results.json.")
    p.add_argument("--data", default=None, metavar="DIR",
                   help="data folder with index.csv (default: $DTM_DATA_DIR or ../shared/data next to the repo)")
    p.add_argument("--out", default=None, metavar="DIR", help="output folder (default: results/eval in the repo)")
    p.add_argument("--only", default=None, metavar="LIST", help=f"comma-separated sections of: {','.join(SECTIONS)}")
    p.add_argument("--quick", action="store_true", help="tiny budgets (about 1-2 minutes), for smoke tests")
    p.add_argument("--seed", type=int, default=0, help="seed of training, corruption and search")
    p.add_argument("--frames-per-test", type=int, default=None, metavar="N",
                   help="test frames per single-mode cell (default 12, quick 3); stream cells use 8N frames "
                        "(greedy stream cells N)")
    p.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), metavar="J",
                   help="worker processes (with --dask local: the LocalCluster's workers)")
    p.add_argument("--dask", default=None, metavar="ADDRESS",
                   help="run the training and labeling tasks on a dask.distributed cluster: a scheduler address "
                        "(tcp://host:8786) or 'local' (a LocalCluster started for the run)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--bank", action="store_true",
                   help="also run the action-model bank comparison (Ukita 4.1-4.4: pooled model, hard switching, "
                        "bank without / with synthesized transitions on switching sequences) into OUT/bank/; "
                        "--only bank runs just that")
    p.add_argument("--merge", action="store_true",
                   help="keep the sections of the results.json already in --out that this run does not redo "
                        "(e.g. --only generalisation --merge adds that section to a full report)")
    p.add_argument("--rebuild", action="store_true",
                   help="only rewrite report.md and the figures from the results.json already in --out")
    return p


def _sections(spec: str | None) -> list[str]:
    if not spec:
        return list(SECTIONS)
    out = [s.strip() for s in spec.split(",") if s.strip()]
    bad = [s for s in out if s not in SECTIONS]
    if bad or not out:
        raise CliError(f"--only: unknown section(s) {', '.join(bad) or spec!r}; choose from {', '.join(SECTIONS)}")
    return [s for s in SECTIONS if s in out]


def _main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    args.only, bank_only = _split_bank(args)
    sections = [] if bank_only else _sections(args.only)
    if args.frames_per_test is not None and args.frames_per_test < 1:
        raise CliError("--frames-per-test must be >= 1")
    if args.jobs < 1:
        raise CliError("--jobs must be >= 1")
    data_dir = Path(args.data) if args.data else _default_data_dir()
    if not (data_dir / "index.csv").is_file():
        raise CliError(f"{data_dir}: no index.csv (give the data folder with --data or $DTM_DATA_DIR)")
    out_dir = Path(args.out) if args.out else REPO / "results" / "eval"
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CliError(f"--out {out_dir}: {e}") from None
    if args.rebuild:
        try:
            saved = json.loads((out_dir / "results.json").read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise CliError(f"--rebuild: cannot read {out_dir / 'results.json'}: {e}") from None
        paths = write_report(out_dir, saved["results"], saved["meta"])
        print(f"rewrote {paths['report']} ({len(paths['figures'])} figures) from results.json")
        return 0
    if args.bank:
        _bank_section(args, data_dir, out_dir)
        if bank_only:
            return 0
    plan = make_plan(args.quick, args.seed, args.frames_per_test)
    t_start = time.perf_counter()
    runner = Runner(args.jobs, args.quiet, args.dask)
    try:
        results = run_sections(sections, plan, data_dir, runner, args.quiet)
    except PlanError as e:
        raise CliError(str(e)) from None
    finally:
        runner.close()
    wall = time.perf_counter() - t_start
    argv_txt = " ".join(["dtm-eval"] + (list(argv) if argv is not None else sys.argv[1:]))
    if args.merge:
        results, merged = _merge_saved(out_dir, results, sections)
        sections = merged
    meta = {"command": argv_txt, "sections": sections, "data_dir": str(data_dir), "wall_s": wall,
            "plan": {k: v for k, v in vars(plan).items()}, "jobs": args.jobs, "dask": args.dask,
            "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
            "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    paths = write_report(out_dir, results, meta)
    print(f"wrote {paths['report']} ({len(paths['figures'])} figures, results.json) in {wall / 60:.1f} min")
    return 0


def _merge_saved(out_dir: Path, results: dict, sections: list) -> tuple[dict, list]:
    """``results`` over the saved results.json of ``out_dir`` (its other sections kept)."""
    try:
        saved = json.loads((out_dir / "results.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise CliError(f"--merge: cannot read {out_dir / 'results.json'}: {e}") from None
    old = saved.get("results", {})
    merged = dict(old)
    merged.update(results)
    for key in ("sequences", "models"):
        if key in old and key in results:
            merged[key] = {**old[key], **results[key]}
    kept = [s for s in saved.get("meta", {}).get("sections", []) if s not in sections]
    return merged, [s for s in SECTIONS if s in set(kept) | set(sections)]


# -- action-model bank (dtm_labeler.evaluation.switching; separate report in OUT/bank) ----------------------
def _split_bank(args) -> tuple:
    """``--only`` without the pseudo-section ``bank`` (which turns on ``--bank``); True when
    only the bank section was asked for."""
    if not args.only:
        return args.only, False
    parts = [s.strip() for s in args.only.split(",") if s.strip()]
    if "bank" in parts:
        args.bank = True
        parts = [s for s in parts if s != "bank"]
        return (",".join(parts) or None), not parts
    return args.only, False


def _bank_section(args, data_dir: Path, out_dir: Path) -> None:
    es = ExperimentSettings(seeds=(args.seed + 1,), incremental=False, max_dance_frames=120,
                            train=dict(mixture="fixed", k_fixed=2, structure="given")) if args.quick else \
        ExperimentSettings(seeds=(args.seed + 1, args.seed + 2))
    t0 = time.perf_counter()
    run_experiment(data_dir, out_dir / "bank", es, progress=(lambda m: None) if args.quiet else
                   (lambda m: print(m, file=sys.stderr, flush=True)))
    print(f"wrote {out_dir / 'bank' / 'report.md'} in {(time.perf_counter() - t0) / 60:.1f} min")


def main(argv=None) -> int:
    try:
        return run_main(_main, argv)
    except BrokenPipeError:
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
