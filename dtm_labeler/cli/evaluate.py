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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..evaluation.archive import JobRunner, call_task
from .common import CliError, HelpFormatter, run_main

SECTIONS = ("tables12", "structure", "table3", "occlusion", "noise", "voting", "generations", "cross", "markers",
            "generalisation")
REPO = Path(__file__).resolve().parents[2]

EPILOG = """examples:
  dtm-eval --quick --out /tmp/eval          smoke test (about 1-2 minutes)
  dtm-eval                                  full run into results/eval (about 15-25 minutes on 2 cores)
  dtm-eval --only tables12,structure        just the model tests
  dtm-eval --frames-per-test 30 --jobs 2    more test frames per cell
  dtm-eval --only bank                      action-model bank on switching sequences (results/eval/bank)
  dtm-eval --only generalisation            other takes / motions / people, with and without calibration
"""

MARKER_FILES = (
    ("cmu85_02", "markers_c3d/cmu_85_02_jumptwist_s85_41markers.c3d", "CMU 85_02 jump+twist (41 markers, 120 Hz)"),
    ("cmu85_12", "markers_c3d/cmu_85_12_breakdance_s85_41markers.c3d", "CMU 85_12 breakdance (41 markers, 120 Hz)"),
    ("hdm05", "markers_c3d/hdm05_bd_05-01_01_120.c3d", "HDM05 bd 05-01 upper-body actions (41 markers, 120 Hz)"),
    ("mct_walk1", "markers_csv/mct_walk1_28markers_60hz.csv", "MoCap Toolbox walk1 (28 markers, 60 Hz, real gaps)"),
    ("mct_dance1", "markers_csv/mct_dance1_28markers_60hz.csv", "MoCap Toolbox dance1 (28 markers, 60 Hz)"),
)
CROSS_FOLDS = (("7", ("W1",)), ("9", ("R1",)), ("55", ("D1", "D2")), ("5", ("D3",)))
# people outside the CMU skeletal clips (body14 derived from their markers): key, file, title
CROSS_NEW = (
    ("qualisys_walk", "markers_c3d/qualisys_walk_55markers.c3d", "Qualisys walk (unknown subject, 200 Hz)"),
    ("mct_walk1", "markers_csv/mct_walk1_28markers_60hz.csv", "MoCap Toolbox walk1 (60 Hz)"),
    ("mct_dance1", "markers_csv/mct_dance1_28markers_60hz.csv", "MoCap Toolbox dance1 (60 Hz)"),
)
# the training without the body augmentation (sizes, proportions, tempos), for comparison
NO_BODY_AUG = {"scale_jitter": 0.0, "proportion_jitter": 0.0, "tempo_jitter": 0.0}


@dataclass
class Plan:
    """Every budget knob of a run (recorded in results.json)."""

    quick: bool
    seed: int
    frames_per_test: int
    stream_frames: int
    greedy_stream_frames: int
    seq_model: tuple = ("W1", "R1", "D1", "D2", "D3")       # tables12, structure
    seq_label: tuple = ("W1", "R1", "D1")                   # table3, occlusion, voting, generations
    occlusion_levels: tuple = (0, 1, 2, 3, 4, 5)
    occlusion_greedy_seq: tuple = ()
    noise_levels_mm: tuple = (0, 5, 10, 20, 40)
    noise_seq: str = "W1"
    windows: tuple = (1, 2, 3, 5, 8, 10, 15)
    voting_occlude: int = 2
    generation_frames: int = 6
    generations: int = 300
    structure_generations: int = 200
    cross_folds: tuple = CROSS_FOLDS
    cross_new: tuple = tuple(c[0] for c in CROSS_NEW)
    marker_files: tuple = tuple(m[0] for m in MARKER_FILES)
    marker_k_max: int = 4
    marker_train_frames: int = 1500
    marker_gap_frames: float = 12.0
    marker_occlude: int = 3
    marker_clutter: int = 3
    extra: dict = field(default_factory=dict)


def make_plan(args) -> Plan:
    n = args.frames_per_test
    if args.quick:
        n = n or 3
        return Plan(quick=True, seed=args.seed, frames_per_test=n, stream_frames=6 * n, greedy_stream_frames=n,
                    seq_model=("W1", "R1"), seq_label=("W1",), occlusion_levels=(0, 2, 4), occlusion_greedy_seq=(),
                    noise_levels_mm=(0, 10, 40), windows=(1, 5), generation_frames=2, generations=60,
                    structure_generations=40, cross_folds=(("5", ("D3",)),), cross_new=("mct_walk1",),
                    marker_files=("mct_walk1",),
                    marker_k_max=3, marker_train_frames=600)
    n = n or 12
    return Plan(quick=False, seed=args.seed, frames_per_test=n, stream_frames=8 * n, greedy_stream_frames=n)


# -- the pool ------------------------------------------------------------------------------------
class Runner:
    """Runs (function, kwargs) tasks in worker processes or on dask with one progress bar."""

    def __init__(self, jobs: int, quiet: bool, dask: str | None = None):
        self.jobs = max(1, jobs)
        self.quiet = quiet
        self.where = f"dask {dask}" if dask else f"{self.jobs} worker(s)"
        self.runner = JobRunner(self.jobs, dask)

    def map(self, tasks: list[tuple], desc: str) -> list:
        """``tasks`` = [(label, fn, kwargs)]; results in order."""
        if not self.quiet and not sys.stderr.isatty():      # no live bar in logs: one line per stage
            print(f"dtm-eval: {desc}: {len(tasks)} tasks on {self.where}", file=sys.stderr, flush=True)
        bar = tqdm(total=len(tasks), desc=desc, unit="task", file=sys.stderr, disable=True if self.quiet else None,
                   dynamic_ncols=True)
        labels = [label for label, _, _ in tasks]
        serial = not self.runner.parallel

        def progress(done: int, total: int, _result) -> None:
            bar.update(done - bar.n)
            if serial and done < total:                    # serial: name the task that runs next
                bar.set_postfix_str(labels[done][:40])

        if serial and labels:
            bar.set_postfix_str(labels[0][:40])
        try:
            return self.runner.map(call_task, [(fn, kw) for _, fn, kw in tasks], None, progress)
        finally:
            bar.close()

    def close(self) -> None:
        self.runner.close()


# -- task functions (module level: picklable) -----------------------------------------------------
def _train_task(clips, kind, structure, seed, overrides=None):
    from ..evaluation.model_tests import train_kind
    t0 = time.perf_counter()
    model, summary = train_kind(clips, kind, structure=structure, seed=seed, **(overrides or {}))
    summary["seconds"] = time.perf_counter() - t0
    return model, summary


def _structure_task(**kw):
    from ..evaluation.model_tests import structure_comparison
    return structure_comparison(**kw)


def _cell_task(**kw):
    from ..evaluation.experiments import run_cell
    return run_cell(dict(kw))


def _gen_train_task(clips, config):
    from ..evaluation.generalisation import train_case_model
    return train_case_model(clips, config)


def _gen_cell_task(**kw):
    from ..evaluation.generalisation import run_variant
    return run_variant(**kw)


def _generalisation(plan: Plan, data_dir: Path, runner: Runner) -> dict:
    """The generalisation section: train every case's models, then label (see the module)."""
    from ..evaluation import generalisation as gen
    gplan = gen.quick_plan(plan.seed) if plan.quick else gen.Plan(seed=plan.seed)
    try:
        tasks = gen.model_tasks(data_dir, gplan)
    except (OSError, ValueError, KeyError) as e:
        raise CliError(f"generalisation: {e}") from None
    keys = list(tasks)
    trained = runner.map([(" ".join(map(str, k[0])) + f" {k[2]}", _gen_train_task, tasks[k]) for k in keys],
                         "generalisation: training")
    models = {k: t[0] for k, t in zip(keys, trained)}
    cells = gen.cell_tasks(data_dir, gplan, models)
    order = sorted(range(len(cells)), key=lambda i: not cells[i][2]["markers"])      # 41-marker cells first
    outs = runner.map([(f"{cells[i][0]} {cells[i][1]}", _gen_cell_task, cells[i][2]) for i in order],
                      "generalisation: labeling")
    res: dict = {}
    for i, o in zip(order, outs):
        res.setdefault(cells[i][0], {})[cells[i][1]] = o
    return {"plan": gen.plan_dict(gplan), "cases": gen.case_info(data_dir, gplan, {k: t[1] for k, t in zip(keys, trained)}),
            "results": res}


# -- data -------------------------------------------------------------------------------------------
def _default_data_dir() -> Path:
    env = os.environ.get("DTM_DATA_DIR")
    return Path(env) if env else REPO.parent / "shared" / "data"


def _load_sequences(data_dir: Path, keys) -> dict:
    from ..evaluation.model_tests import SEQUENCES, split_clip
    from ..motion.load import load_clip
    out = {}
    for s in SEQUENCES:
        if s.key not in keys:
            continue
        path = data_dir / s.path
        try:
            clip = load_clip(path, points="body14")
        except (OSError, ValueError, KeyError) as e:
            raise CliError(f"{path}: {e}") from None
        train, test, cut = split_clip(clip)
        out[s.key] = dict(spec=s, clip=clip, train=train, test=test, cut=cut)
    return out


def _load_marker_clip(data_dir: Path, rel: str, points: str = "all"):
    from ..motion.load import load_clip
    path = data_dir / rel
    try:
        return load_clip(path, points=points)
    except (OSError, ValueError, KeyError) as e:
        raise CliError(f"{path}: {e}") from None


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
        from ..evaluation.report import write_report
        paths = write_report(out_dir, saved["results"], saved["meta"])
        print(f"rewrote {paths['report']} ({len(paths['figures'])} figures) from results.json")
        return 0
    if args.bank:
        _bank_section(args, data_dir, out_dir)
        if bank_only:
            return 0
    plan = make_plan(args)
    t_start = time.perf_counter()
    runner = Runner(args.jobs, args.quiet, args.dask)
    try:
        results = run_sections(sections, plan, data_dir, runner, args.quiet)
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
    from ..evaluation.report import write_report
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


def _tables12(seqs, models, plan, quiet) -> dict:
    from ..evaluation.model_tests import MIXTURE_KINDS, held_out_states, triangle_tests
    out = {}
    bar = tqdm(total=len(seqs) * 3 * 12, desc="tables 1-2", unit="triangle", file=sys.stderr,
               disable=True if quiet else None, dynamic_ncols=True)
    try:
        for key, s in seqs.items():
            ms = {k: models[(key, k, "given")][0] for k in MIXTURE_KINDS}
            states = held_out_states(s["clip"], ms["mdl"].labels, np.arange(s["cut"], s["clip"].n_frames))
            r = triangle_tests(ms, states, progress=lambda: bar.update(1))
            r["triangles"] = ms["mdl"].structure.names(ms["mdl"].labels)
            out[key] = r
    finally:
        bar.close()
    return out


def run_sections(sections, plan: Plan, data_dir: Path, runner: Runner, quiet: bool) -> dict:
    from ..evaluation.experiments import TABLE3_ROWS, spread_frames
    from ..training.train import TrainConfig
    from ..motion.pointsets import BODY14
    need_model_seqs = set()
    if "tables12" in sections or "structure" in sections:
        need_model_seqs |= set(plan.seq_model)
    label_secs = {"table3", "occlusion", "noise", "voting", "generations"} & set(sections)
    if label_secs:
        need_model_seqs |= set(plan.seq_label)
    if "noise" in sections:
        need_model_seqs.add(plan.noise_seq)
    if "cross" in sections:
        need_model_seqs |= {k for _, ks in plan.cross_folds for k in ks}
        need_model_seqs |= {"W1", "R1", "D1", "D2", "D3"} if not plan.quick else {"W1", "R1"}
    seqs = _load_sequences(data_dir, need_model_seqs)
    results: dict = {"sequences": {k: {"title": s["spec"].title, "path": s["spec"].path, "frames": s["clip"].n_frames,
                                       "train_frames": s["cut"], "test_frames": s["clip"].n_frames - s["cut"],
                                       "rate": s["clip"].rate, "subject": s["spec"].subject}
                                   for k, s in seqs.items()}}
    seed = plan.seed

    # ---- models ---------------------------------------------------------------------------------------
    wanted: dict[tuple, tuple] = {}
    if "tables12" in sections or "structure" in sections:
        for k in plan.seq_model:
            for kind in ("single", "fixed", "mdl"):
                wanted[(k, kind, "given")] = (seqs[k]["train"], kind, "given")
    t3 = "table3" in sections
    for k in plan.seq_label:
        if t3:
            for kind in ("single", "fixed", "mdl"):
                wanted[(k, kind, "given")] = (seqs[k]["train"], kind, "given")
            wanted[(k, "mdl", "cbga")] = (seqs[k]["train"], "mdl", "cbga")
        if label_secs - {"table3"}:
            wanted[(k, "mdl", "given")] = (seqs[k]["train"], "mdl", "given")
    if "occlusion" in sections:
        for k in plan.occlusion_greedy_seq:
            wanted[(k, "mdl", "given")] = (seqs[k]["train"], "mdl", "given")
    if "noise" in sections:
        for kind in ("single", "mdl"):
            wanted[(plan.noise_seq, kind, "given")] = (seqs[plan.noise_seq]["train"], kind, "given")
    cross_train, cross_new = {}, {}
    if "cross" in sections:
        for subj, test_keys in plan.cross_folds:
            train_keys = [k for k, s in seqs.items() if s["spec"].subject != subj]
            cross_train[subj] = train_keys
            wanted[("cross" + subj, "mdl", "given")] = ([seqs[k]["clip"] for k in train_keys], "mdl", "given")
            wanted[("cross" + subj, "mdl", "given", "noaug")] = ([seqs[k]["clip"] for k in train_keys], "mdl",
                                                                 "given", NO_BODY_AUG)
        for key, rel, title in CROSS_NEW:
            if key in plan.cross_new:
                cross_new[key] = dict(clip=_load_marker_clip(data_dir, rel, "body14"), title=title, rel=rel)
        if cross_new:
            every = [s["clip"] for s in seqs.values()]
            wanted[("crossnew", "mdl", "given")] = (every, "mdl", "given")
            wanted[("crossnew", "mdl", "given", "noaug")] = (every, "mdl", "given", NO_BODY_AUG)
    marker_clips = {}
    if "markers" in sections:
        for key, rel, title in MARKER_FILES:
            if key not in plan.marker_files:
                continue
            clip = _load_marker_clip(data_dir, rel)
            from ..evaluation.model_tests import split_clip
            train, test, cut = split_clip(clip)
            # long recordings: train on the last ``marker_train_frames`` frames before the cut
            tr = train.slice(max(0, cut - plan.marker_train_frames), None)
            marker_clips[key] = dict(clip=clip, train=tr, test=test, cut=cut, title=title, rel=rel)
            wanted[("marker_" + key, "mdl", "cbga")] = (tr, "mdl", "cbga",
                                                       dict(k_max=plan.marker_k_max, max_frames_per_triangle=1500))
    keys = list(wanted)
    tasks = []
    for key in keys:
        spec = wanted[key]
        tasks.append((" ".join(key), _train_task,
                      dict(clips=spec[0], kind=spec[1], structure=spec[2], seed=seed,
                           overrides=spec[3] if len(spec) > 3 else None)))
    # structure comparisons run with the training tasks (independent)
    struct_keys = list(plan.seq_model) if "structure" in sections else []
    for k in struct_keys:
        s = seqs[k]
        tasks.append((f"structure {k}", _structure_task,
                      dict(train=s["train"], test=s["clip"], test_frames=np.arange(s["cut"], s["clip"].n_frames),
                           labels=s["clip"].names, seed=seed, generations=plan.structure_generations)))
    done = runner.map(tasks, "training")
    models = dict(zip(keys, done[:len(keys)]))
    results["models"] = {" ".join(k): {"components": m[1]["components"], "structure": m[1]["structure"],
                                       "structure_method": m[1]["structure_method"], "seconds": m[1]["seconds"],
                                       "frames": m[1]["frames_total"], "loglik_per_frame": m[1]["loglik_per_frame"]}
                         for k, m in models.items()}
    if struct_keys:
        results["structure"] = dict(zip(struct_keys, done[len(keys):]))

    if "tables12" in sections:
        results["tables12"] = _tables12({k: seqs[k] for k in plan.seq_model}, models, plan, quiet)

    # ---- labeling cells ---------------------------------------------------------------------------------
    N = plan.frames_per_test
    cells: list[tuple] = []          # (result path tuple, label, kwargs)

    def single(path, mkey, clip, frames, method, **kw):
        cells.append((path, " ".join(map(str, path)),
                      dict(kind="single", model=models[mkey][0], clip=clip, frames=frames, method=method, seed=seed,
                           **kw)))

    def stream(path, mkey, clip, method, **kw):
        cells.append((path, " ".join(map(str, path)),
                      dict(kind="stream", model=models[mkey][0], clip=clip, method=method, seed=seed, **kw)))

    def block(s, n):
        return s["test"].slice(0, min(n, s["test"].n_frames))

    for k in (plan.seq_label if label_secs else ()):        # --only cross / markers load no W1 ...
        s = seqs[k]
        frames = spread_frames(s["test"].n_frames, N)
        if t3:
            for name, kind, struct, method in TABLE3_ROWS:
                single(("table3", "single", name, k), (k, kind, struct), s["test"], frames, method)
                nst = plan.greedy_stream_frames if method == "greedy" else plan.stream_frames
                stream(("table3", "stream", name, k), (k, kind, struct), block(s, nst), method)
        if "occlusion" in sections:
            for occ in plan.occlusion_levels:
                single(("occlusion", "MixGM+CBGA", k, occ), (k, "mdl", "given"), s["test"], frames, "cbga",
                       occlude=occ)
                if k in plan.occlusion_greedy_seq:
                    single(("occlusion", "MixGM+Greedy", k, occ), (k, "mdl", "given"), s["test"], frames, "greedy",
                           occlude=occ)
        if "voting" in sections:
            for w in plan.windows:
                stream(("voting", k, w), (k, "mdl", "given"), block(s, plan.stream_frames), "cbga", window=w,
                       occlude=plan.voting_occlude)
        if "generations" in sections:
            gframes = spread_frames(s["test"].n_frames, plan.generation_frames)
            cells.append((("generations", k), f"generations {k}",
                          dict(kind="generations", model=models[(k, "mdl", "given")][0], clip=s["test"],
                               frames=gframes, generations=plan.generations, seed=seed)))
    if "noise" in sections:
        k = plan.noise_seq
        s = seqs[k]
        frames = spread_frames(s["test"].n_frames, N)
        for mm in plan.noise_levels_mm:
            for name, kind, method in (("MixGM+CBGA", "mdl", "cbga"), ("MixGM+Greedy", "mdl", "greedy"),
                                       ("Gaussian+Greedy", "single", "greedy")):
                single(("noise", name, mm), (k, kind, "given"), s["test"], frames, method, noise_mm=float(mm))
    if "cross" in sections:
        for subj, test_keys in plan.cross_folds:
            for tk in test_keys:
                clip = seqs[tk]["clip"]
                frames = spread_frames(clip.n_frames, N)
                mk = ("cross" + subj, "mdl", "given")
                single(("cross", subj, tk, "MixGM+CBGA single"), mk, clip, frames, "cbga")
                single(("cross", subj, tk, "MixGM+Greedy single"), mk, clip, frames, "greedy")
                stream(("cross", subj, tk, "MixGM+CBGA stream"), mk, clip.slice(0, plan.stream_frames), "cbga")
                single(("cross", subj, tk, "no body aug. single"), mk + ("noaug",), clip, frames, "cbga")
                stream(("cross", subj, tk, "no body aug. stream"), mk + ("noaug",),
                       clip.slice(0, plan.stream_frames), "cbga")
        for key, c in cross_new.items():
            clip = c["clip"]
            frames = spread_frames(clip.n_frames, N)
            for tag, mk in (("", ("crossnew", "mdl", "given")),
                            ("no body aug. ", ("crossnew", "mdl", "given", "noaug"))):
                single(("cross", "new", key, tag + "single"), mk, clip, frames, "cbga")
                stream(("cross", "new", key, tag + "stream"), mk, clip.slice(0, plan.stream_frames), "cbga")
    if "markers" in sections:
        for key, mc in marker_clips.items():
            mk = ("marker_" + key, "mdl", "cbga")
            blk = mc["test"].slice(0, min(plan.stream_frames, mc["test"].n_frames))
            stream(("markers", key, "clean"), mk, blk, "cbga")
            stream(("markers", key, "gaps"), mk, blk, "cbga", occlude=plan.marker_occlude,
                   gap_frames=plan.marker_gap_frames)
            stream(("markers", key, "clutter"), mk, blk, "cbga", clutter=plan.marker_clutter)
            single(("markers", key, "single"), mk, mc["test"], spread_frames(mc["test"].n_frames, max(2, N // 2)),
                   "cbga")
    if cells:
        # longest first keeps both workers busy to the end
        def cost(c):
            kw = c[2]
            n = len(kw.get("frames", [])) if kw["kind"] != "stream" else kw["clip"].n_frames / 10
            return n * (8 if kw.get("method") == "greedy" else 1) + (200 if kw["kind"] == "generations" else 0)
        order = sorted(range(len(cells)), key=lambda i: -cost(cells[i]))
        outs = runner.map([(cells[i][1], _cell_task, cells[i][2]) for i in order], "labeling")
        for i, o in zip(order, outs):
            cur = results
            path = cells[i][0]
            for p in path[:-1]:
                cur = cur.setdefault(str(p), {})
            cur[str(path[-1])] = o
    if "table3" in sections:
        results.setdefault("table3", {})["frames"] = {
            "single": {k: len(spread_frames(seqs[k]["test"].n_frames, N)) for k in plan.seq_label},
            "stream": {k: min(plan.stream_frames, seqs[k]["test"].n_frames) for k in plan.seq_label},
            "stream_greedy": {k: min(plan.greedy_stream_frames, seqs[k]["test"].n_frames) for k in plan.seq_label}}
    if "cross" in sections:
        results.setdefault("cross", {})["folds"] = {subj: {"test": list(tk), "train": cross_train[subj]}
                                                    for subj, tk in plan.cross_folds}
        results["cross"]["new_subjects"] = {
            k: {"title": c["title"], "path": c["rel"], "frames": c["clip"].n_frames, "rate": c["clip"].rate,
                "train": list(seqs), "train_subjects": sorted({s["spec"].subject for s in seqs.values()}, key=int)}
            for k, c in cross_new.items()}
        body14 = TrainConfig().resolved(BODY14)
        results["cross"]["augmentation"] = {"default": {k: getattr(body14, k) for k in (
            "augment_copies", "scale_jitter", "proportion_jitter", "tempo_jitter", "yaw_jitter_deg")},
            "without": NO_BODY_AUG}
    if "generalisation" in sections:
        results["generalisation"] = _generalisation(plan, data_dir, runner)
    if "markers" in sections:
        results.setdefault("markers", {})["files"] = {
            k: {"title": m["title"], "path": m["rel"], "points": m["clip"].n_points, "rate": m["clip"].rate,
                "frames": m["clip"].n_frames, "train_frames": m["train"].n_frames,
                "missing_fraction": float(np.isnan(m["clip"].positions[..., 0]).mean()),
                "test_missing_fraction": float(np.isnan(m["test"].positions[..., 0]).mean())}
            for k, m in marker_clips.items()}
    return results


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
    from ..evaluation.switching import ExperimentSettings, run_experiment
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
