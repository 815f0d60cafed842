"""The experiment plans of ``dtm-eval``: which models to train and which cells to label for
each section of the report, with every budget in one :class:`Plan` (recorded in results.json).

:func:`run_sections` is the whole run: load the recordings a section needs, train every model
once (:func:`wanted_models`, in parallel through a :class:`Runner`), build the labeling cells
(:func:`label_cells`), run them longest first and file each result under its path in the
results dict, then add what the report says about the inputs (:func:`section_info`). The
sections themselves live in :mod:`.model_tests` (Tables 1-2, structure), :mod:`.experiments`
(Table 3, Figs. 10-15, cross-subject, markers) and :mod:`.generalisation`; the report in
:mod:`.report`. Errors in the data raise :class:`PlanError` (the CLI prints them).
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..motion.load import load_clip
from ..motion.pointsets import BODY14
from ..training.train import TrainConfig
from . import generalisation as gen
from .archive import JobRunner, call_task
from .experiments import TABLE3_ROWS, run_cell, spread_frames
from .model_tests import (MIXTURE_KINDS, SEQUENCES, held_out_states, split_clip, structure_comparison,
                          train_kind, triangle_tests)

SECTIONS = ("tables12", "structure", "table3", "occlusion", "noise", "voting", "generations", "cross", "markers",
            "generalisation")
LABEL_SECTIONS = {"table3", "occlusion", "noise", "voting", "generations"}


class PlanError(ValueError):
    """A recording a section needs cannot be read."""


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


def make_plan(quick: bool, seed: int = 0, frames_per_test: int | None = None) -> Plan:
    """The full plan, or tiny budgets with ``quick`` (smoke tests)."""
    n = frames_per_test
    if quick:
        n = n or 3
        return Plan(quick=True, seed=seed, frames_per_test=n, stream_frames=6 * n, greedy_stream_frames=n,
                    seq_model=("W1", "R1"), seq_label=("W1",), occlusion_levels=(0, 2, 4), occlusion_greedy_seq=(),
                    noise_levels_mm=(0, 10, 40), windows=(1, 5), generation_frames=2, generations=60,
                    structure_generations=40, cross_folds=(("5", ("D3",)),), cross_new=("mct_walk1",),
                    marker_files=("mct_walk1",),
                    marker_k_max=3, marker_train_frames=600)
    n = n or 12
    return Plan(quick=False, seed=seed, frames_per_test=n, stream_frames=8 * n, greedy_stream_frames=n)


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
    t0 = time.perf_counter()
    model, summary = train_kind(clips, kind, structure=structure, seed=seed, **(overrides or {}))
    summary["seconds"] = time.perf_counter() - t0
    return model, summary


def _structure_task(**kw):
    return structure_comparison(**kw)


def _cell_task(**kw):
    return run_cell(dict(kw))


def _gen_train_task(clips, config):
    return gen.train_case_model(clips, config)


def _gen_cell_task(**kw):
    return gen.run_variant(**kw)


def generalisation(plan: Plan, data_dir: Path, runner: Runner) -> dict:
    """The generalisation section: train every case's models, then label (see the module)."""
    gplan = gen.quick_plan(plan.seed) if plan.quick else gen.Plan(seed=plan.seed)
    try:
        tasks = gen.model_tasks(data_dir, gplan)
    except (OSError, ValueError, KeyError) as e:
        raise PlanError(f"generalisation: {e}") from None
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
def load_sequences(data_dir: Path, keys) -> dict:
    out = {}
    for s in SEQUENCES:
        if s.key not in keys:
            continue
        path = data_dir / s.path
        try:
            clip = load_clip(path, points="body14")
        except (OSError, ValueError, KeyError) as e:
            raise PlanError(f"{path}: {e}") from None
        train, test, cut = split_clip(clip)
        out[s.key] = dict(spec=s, clip=clip, train=train, test=test, cut=cut)
    return out


def load_marker_clip(data_dir: Path, rel: str, points: str = "all"):
    path = data_dir / rel
    try:
        return load_clip(path, points=points)
    except (OSError, ValueError, KeyError) as e:
        raise PlanError(f"{path}: {e}") from None


# -- the run -----------------------------------------------------------------------------------------
def tables12(seqs, models, quiet) -> dict:
    """Tables 1-2: the per-triangle model tests on each sequence's held-out frames."""
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


def model_sequences(sections, plan: Plan) -> set:
    """The skeletal sequences (keys of :data:`~.model_tests.SEQUENCES`) the sections need."""
    need = set()
    if "tables12" in sections or "structure" in sections:
        need |= set(plan.seq_model)
    if LABEL_SECTIONS & set(sections):
        need |= set(plan.seq_label)
    if "noise" in sections:
        need.add(plan.noise_seq)
    if "cross" in sections:
        need |= {k for _, ks in plan.cross_folds for k in ks}
        need |= {"W1", "R1", "D1", "D2", "D3"} if not plan.quick else {"W1", "R1"}
    return need


def marker_inputs(sections, plan: Plan, data_dir: Path) -> tuple[dict, dict]:
    """(marker takes of the markers section, new people of the cross section)."""
    marker_clips, cross_new = {}, {}
    if "markers" in sections:
        for key, rel, title in MARKER_FILES:
            if key not in plan.marker_files:
                continue
            clip = load_marker_clip(data_dir, rel)
            train, test, cut = split_clip(clip)
            # long recordings: train on the last ``marker_train_frames`` frames before the cut
            tr = train.slice(max(0, cut - plan.marker_train_frames), None)
            marker_clips[key] = dict(clip=clip, train=tr, test=test, cut=cut, title=title, rel=rel)
    if "cross" in sections:
        for key, rel, title in CROSS_NEW:
            if key in plan.cross_new:
                cross_new[key] = dict(clip=load_marker_clip(data_dir, rel, "body14"), title=title, rel=rel)
    return marker_clips, cross_new


def wanted_models(sections, plan: Plan, seqs: dict, marker_clips: dict, cross_new: dict) -> dict[tuple, tuple]:
    """Every model the sections label with: key -> (clips, mixture kind, structure[, overrides])."""
    wanted: dict[tuple, tuple] = {}
    if "tables12" in sections or "structure" in sections:
        for k in plan.seq_model:
            for kind in ("single", "fixed", "mdl"):
                wanted[(k, kind, "given")] = (seqs[k]["train"], kind, "given")
    label_secs = LABEL_SECTIONS & set(sections)
    for k in plan.seq_label:
        if "table3" in sections:
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
    if "cross" in sections:
        for subj, _ in plan.cross_folds:
            clips = [s["clip"] for s in seqs.values() if s["spec"].subject != subj]
            wanted[("cross" + subj, "mdl", "given")] = (clips, "mdl", "given")
            wanted[("cross" + subj, "mdl", "given", "noaug")] = (clips, "mdl", "given", NO_BODY_AUG)
        if cross_new:
            every = [s["clip"] for s in seqs.values()]
            wanted[("crossnew", "mdl", "given")] = (every, "mdl", "given")
            wanted[("crossnew", "mdl", "given", "noaug")] = (every, "mdl", "given", NO_BODY_AUG)
    for key, mc in marker_clips.items():
        wanted[("marker_" + key, "mdl", "cbga")] = (mc["train"], "mdl", "cbga",
                                                   dict(k_max=plan.marker_k_max, max_frames_per_triangle=1500))
    return wanted


class Cells:
    """The labeling cells of a run: (result path, progress label, :func:`~.experiments.run_cell` kwargs)."""

    def __init__(self, models: dict, seed: int):
        self.models, self.seed, self.items = models, seed, []

    def single(self, path, mkey, clip, frames, method, **kw) -> None:
        self.items.append((path, " ".join(map(str, path)),
                           dict(kind="single", model=self.models[mkey][0], clip=clip, frames=frames, method=method,
                                seed=self.seed, **kw)))

    def stream(self, path, mkey, clip, method, **kw) -> None:
        self.items.append((path, " ".join(map(str, path)),
                           dict(kind="stream", model=self.models[mkey][0], clip=clip, method=method, seed=self.seed,
                                **kw)))

    def generations(self, key, clip, frames, generations) -> None:
        self.items.append((("generations", key), f"generations {key}",
                           dict(kind="generations", model=self.models[(key, "mdl", "given")][0], clip=clip,
                                frames=frames, generations=generations, seed=self.seed)))

    def longest_first(self) -> list[int]:
        """Cell order that keeps every worker busy to the end."""
        def cost(kw):
            n = len(kw.get("frames", [])) if kw["kind"] != "stream" else kw["clip"].n_frames / 10
            return n * (8 if kw.get("method") == "greedy" else 1) + (200 if kw["kind"] == "generations" else 0)
        return sorted(range(len(self.items)), key=lambda i: -cost(self.items[i][2]))


def _block(s: dict, n: int):
    return s["test"].slice(0, min(n, s["test"].n_frames))


def skeletal_cells(cells: Cells, sections, plan: Plan, seqs: dict) -> None:
    """Table 3, occlusion, voting, generations and noise cells (the paper's section V)."""
    N = plan.frames_per_test
    for k in (plan.seq_label if LABEL_SECTIONS & set(sections) else ()):     # --only cross / markers load no W1
        s = seqs[k]
        frames = spread_frames(s["test"].n_frames, N)
        if "table3" in sections:
            for name, kind, struct, method in TABLE3_ROWS:
                cells.single(("table3", "single", name, k), (k, kind, struct), s["test"], frames, method)
                nst = plan.greedy_stream_frames if method == "greedy" else plan.stream_frames
                cells.stream(("table3", "stream", name, k), (k, kind, struct), _block(s, nst), method)
        if "occlusion" in sections:
            for occ in plan.occlusion_levels:
                cells.single(("occlusion", "MixGM+CBGA", k, occ), (k, "mdl", "given"), s["test"], frames, "cbga",
                             occlude=occ)
                if k in plan.occlusion_greedy_seq:
                    cells.single(("occlusion", "MixGM+Greedy", k, occ), (k, "mdl", "given"), s["test"], frames,
                                 "greedy", occlude=occ)
        if "voting" in sections:
            for w in plan.windows:
                cells.stream(("voting", k, w), (k, "mdl", "given"), _block(s, plan.stream_frames), "cbga", window=w,
                             occlude=plan.voting_occlude)
        if "generations" in sections:
            cells.generations(k, s["test"], spread_frames(s["test"].n_frames, plan.generation_frames),
                              plan.generations)
    if "noise" in sections:
        s = seqs[plan.noise_seq]
        frames = spread_frames(s["test"].n_frames, N)
        for mm in plan.noise_levels_mm:
            for name, kind, method in (("MixGM+CBGA", "mdl", "cbga"), ("MixGM+Greedy", "mdl", "greedy"),
                                       ("Gaussian+Greedy", "single", "greedy")):
                cells.single(("noise", name, mm), (plan.noise_seq, kind, "given"), s["test"], frames, method,
                             noise_mm=float(mm))


def other_cells(cells: Cells, sections, plan: Plan, seqs: dict, marker_clips: dict, cross_new: dict) -> None:
    """Cross-subject and marker-take cells."""
    N = plan.frames_per_test
    if "cross" in sections:
        for subj, test_keys in plan.cross_folds:
            for tk in test_keys:
                clip = seqs[tk]["clip"]
                frames = spread_frames(clip.n_frames, N)
                mk = ("cross" + subj, "mdl", "given")
                cells.single(("cross", subj, tk, "MixGM+CBGA single"), mk, clip, frames, "cbga")
                cells.single(("cross", subj, tk, "MixGM+Greedy single"), mk, clip, frames, "greedy")
                cells.stream(("cross", subj, tk, "MixGM+CBGA stream"), mk, clip.slice(0, plan.stream_frames), "cbga")
                cells.single(("cross", subj, tk, "no body aug. single"), mk + ("noaug",), clip, frames, "cbga")
                cells.stream(("cross", subj, tk, "no body aug. stream"), mk + ("noaug",),
                             clip.slice(0, plan.stream_frames), "cbga")
        for key, c in cross_new.items():
            clip = c["clip"]
            frames = spread_frames(clip.n_frames, N)
            for tag, mk in (("", ("crossnew", "mdl", "given")),
                            ("no body aug. ", ("crossnew", "mdl", "given", "noaug"))):
                cells.single(("cross", "new", key, tag + "single"), mk, clip, frames, "cbga")
                cells.stream(("cross", "new", key, tag + "stream"), mk, clip.slice(0, plan.stream_frames), "cbga")
    for key, mc in marker_clips.items():
        mk = ("marker_" + key, "mdl", "cbga")
        blk = mc["test"].slice(0, min(plan.stream_frames, mc["test"].n_frames))
        cells.stream(("markers", key, "clean"), mk, blk, "cbga")
        cells.stream(("markers", key, "gaps"), mk, blk, "cbga", occlude=plan.marker_occlude,
                     gap_frames=plan.marker_gap_frames)
        cells.stream(("markers", key, "clutter"), mk, blk, "cbga", clutter=plan.marker_clutter)
        cells.single(("markers", key, "single"), mk, mc["test"], spread_frames(mc["test"].n_frames, max(2, N // 2)),
                     "cbga")


def section_info(results: dict, sections, plan: Plan, seqs: dict, marker_clips: dict, cross_new: dict) -> None:
    """What the report says about the inputs of each section (frames, folds, files)."""
    N = plan.frames_per_test
    if "table3" in sections:
        results.setdefault("table3", {})["frames"] = {
            "single": {k: len(spread_frames(seqs[k]["test"].n_frames, N)) for k in plan.seq_label},
            "stream": {k: min(plan.stream_frames, seqs[k]["test"].n_frames) for k in plan.seq_label},
            "stream_greedy": {k: min(plan.greedy_stream_frames, seqs[k]["test"].n_frames) for k in plan.seq_label}}
    if "cross" in sections:
        results.setdefault("cross", {})["folds"] = {
            subj: {"test": list(tk), "train": [k for k, s in seqs.items() if s["spec"].subject != subj]}
            for subj, tk in plan.cross_folds}
        results["cross"]["new_subjects"] = {
            k: {"title": c["title"], "path": c["rel"], "frames": c["clip"].n_frames, "rate": c["clip"].rate,
                "train": list(seqs), "train_subjects": sorted({s["spec"].subject for s in seqs.values()}, key=int)}
            for k, c in cross_new.items()}
        body14 = TrainConfig().resolved(BODY14)
        results["cross"]["augmentation"] = {"default": {k: getattr(body14, k) for k in (
            "augment_copies", "scale_jitter", "proportion_jitter", "tempo_jitter", "yaw_jitter_deg")},
            "without": NO_BODY_AUG}
    if "markers" in sections:
        results.setdefault("markers", {})["files"] = {
            k: {"title": m["title"], "path": m["rel"], "points": m["clip"].n_points, "rate": m["clip"].rate,
                "frames": m["clip"].n_frames, "train_frames": m["train"].n_frames,
                "missing_fraction": float(np.isnan(m["clip"].positions[..., 0]).mean()),
                "test_missing_fraction": float(np.isnan(m["test"].positions[..., 0]).mean())}
            for k, m in marker_clips.items()}


def run_sections(sections, plan: Plan, data_dir: Path, runner: Runner, quiet: bool) -> dict:
    """Every section of ``sections`` (module doc); the results dict of results.json."""
    seqs = load_sequences(data_dir, model_sequences(sections, plan))
    marker_clips, cross_new = marker_inputs(sections, plan, data_dir)
    results: dict = {"sequences": {k: {"title": s["spec"].title, "path": s["spec"].path, "frames": s["clip"].n_frames,
                                       "train_frames": s["cut"], "test_frames": s["clip"].n_frames - s["cut"],
                                       "rate": s["clip"].rate, "subject": s["spec"].subject}
                                   for k, s in seqs.items()}}
    seed = plan.seed
    wanted = wanted_models(sections, plan, seqs, marker_clips, cross_new)
    keys = list(wanted)
    tasks = [(" ".join(key), _train_task, dict(clips=spec[0], kind=spec[1], structure=spec[2], seed=seed,
                                               overrides=spec[3] if len(spec) > 3 else None))
             for key, spec in wanted.items()]
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
        results["tables12"] = tables12({k: seqs[k] for k in plan.seq_model}, models, quiet)

    cells = Cells(models, seed)
    skeletal_cells(cells, sections, plan, seqs)
    other_cells(cells, sections, plan, seqs, marker_clips, cross_new)
    if cells.items:
        order = cells.longest_first()
        outs = runner.map([(cells.items[i][1], _cell_task, cells.items[i][2]) for i in order], "labeling")
        for i, o in zip(order, outs):
            cur = results
            path = cells.items[i][0]
            for p in path[:-1]:
                cur = cur.setdefault(str(p), {})
            cur[str(path[-1])] = o
    section_info(results, sections, plan, seqs, marker_clips, cross_new)
    if "generalisation" in sections:
        results["generalisation"] = generalisation(plan, data_dir, runner)
    return results
