"""Generalisation beyond the training motions (issue 13): other takes, other motions, other people.

Every case trains models on some recordings and labels another one, exactly as ``dtm-label``
does (labels stripped, points shuffled, stream and single mode), in four variants:

* **today** -- the paper's model as before issue 13: per-triangle motion mixtures only
  (``TrainConfig(body_terms=False, broad_component=False)``: a format-1 model);
  structure: the hand-given one for the 14 body points, the one grown along the rigid tree
  (``--structure body``) at all markers, for every variant;
* **body** -- the same training with the body terms (:mod:`dtm_labeler.model.body`; the
  ``dtm-train`` default): a generic body, whose reach limits apply (its segment lengths wait
  for a calibration);
* **dtm-label default** -- what a user gets from ``dtm-train`` then ``dtm-label`` (both
  defaults; :func:`as_dtm_label`): ``dtm-train`` calibrates the model to its training takes'
  person when they are one person (one capture, or CMU takes of one subject:
  :func:`~dtm_labeler.motion.naming.one_subject`); ``dtm-label --calibrate auto`` labels one
  of the training captures with that calibration, no window of the test used
  (:func:`~dtm_labeler.evaluation.archive.keeps_training_calibration`); the same subject's
  other takes with it too, its segments whose markers sit elsewhere on the window measured
  again there and its broad weights fitted to the window's motion
  (:func:`~dtm_labeler.training.calibrate.session_calibrate`: markers are placed again each
  session); anyone else's with the generic body self-calibrated on the same window,
  its points shuffled as the labeler gets them, kept only when the calibrated model keeps >= 90
  % of the labels it was measured on (:func:`~dtm_labeler.training.calibrate.auto_calibrate`),
  else the training person's calibration (the generic model when the training takes are
  several people). Until 2026-12-06 the same subject's other takes kept the training
  calibration as it was;
* **body + calibration** -- that model calibrated on the first seconds of the test recording
  (at most ``calibration_s``, at most a third of it), the frames -- their points shuffled as
  the labeler gets them -- labelled by the model itself and confirmed by their vote confidence
  (:func:`~dtm_labeler.training.calibrate.self_calibrate`; no true label is used; segments whose
  confirmed length disagrees with their mirror's, or whose labels lie on the wrong side of the
  trunk, are not taken from those labels), then the rest labelled. Until 2026-11-29 the window's
  points came in label order: the order is a label too, and the searches read it (CMU 85 ->
  HDM05 calibrated 93.62 %, the right shank marker never taken and the left finger and wrist
  markers exchanged; 100 % shuffled).

The *generic model* group labels each person of the shared data with a model of every other
person in it: the other CMU subjects' skeletal clips and the 14 points derived from the markers of
the marker takes' people (MoCap Toolbox, Qualisys, CMU 85, HDM05), leaving out every recording of
the person labelled -- the issue's generic model, one person left out at a time.

All variants are scored on the same frames: those after the calibration window
(stream mode: the first ``stream_frames`` of them through one labeler; single mode:
``single_frames`` frames spread over them, each searched from scratch).

Where the errors come from (the diagnosis of each stream run): of the frames whose search
result is wrong, those where the true labeling scores *lower* than the chosen one are the
model's errors, the others the search's; for the model's errors the mean per-triangle
difference (truth minus chosen) of the fitness, and of its body part, says which triangles
prefer the wrong labeling.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..labeling.stream import LabelerSettings
from ..model.body import SEGMENT, slot_distances
from ..model.dtm import TriangulatedModel
from ..model.features import point_states
from ..motion.clip import MotionClip
from ..motion.load import load_clip
from ..motion.naming import one_subject
from ..search.problem import Background, FrameProblem
from ..training.calibrate import (CalibrationError, auto_calibrate, calibrate_on_takes, recognised_person,
                                  self_calibrate, session_calibrate)
from ..training.train import TrainConfig, train_model
from .archive import keeps_training_calibration, of_training_person
from .corruption import corrupt_clip
from .experiments import SUMMARY_KEYS, label_single, spread_frames
from .metrics import is_search_error
from .pipeline import label_clip_run, model_clip

# recordings in the shared data folder: key -> (relative path, subject, what)
RECORDINGS = {
    "W1": ("cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh", "CMU 7", "walk 07_01 (BVH)"),
    "R1": ("cmu_skeletal/bvh_from_fbx/cmu_09_11_run_s09.bvh", "CMU 9", "run 09_11 (BVH)"),
    "D1": ("cmu_skeletal/bvh_from_fbx/cmu_55_01_dance-whirl_s55.bvh", "CMU 55", "whirl 55_01 (BVH)"),
    "D2": ("cmu_skeletal/asf_amc/cmu_55_02_lambada-dance_s55.amc", "CMU 55", "lambada 55_02 (ASF)"),
    "D3": ("cmu_skeletal/asf_amc/cmu_s05_pirouette-dance.amc", "CMU 5", "pirouette (ASF)"),
    "mct_walk1": ("markers_csv/mct_walk1_28markers_60hz.csv", "MCT walker", "walk, 60 Hz"),
    "mct_dance1": ("markers_csv/mct_dance1_28markers_60hz.csv", "MCT dancer", "dance, 60 Hz"),
    "qualisys": ("markers_c3d/qualisys_walk_55markers.c3d", "Qualisys subject", "walk, 200 Hz"),
    "85_02": ("markers_c3d/cmu_85_02_jumptwist_s85_41markers.c3d", "CMU 85", "jump + twist 85_02"),
    "85_12": ("markers_c3d/cmu_85_12_breakdance_s85_41markers.c3d", "CMU 85", "breakdance 85_12"),
    "hdm05": ("markers_c3d/hdm05_bd_05-01_01_120.c3d", "HDM05 bd", "upper-body actions"),
}
SKELETAL = ("W1", "R1", "D1", "D2", "D3")
GROUPS = ("same person, other take", "same person, other motion", "other person",
          "other person, generic model of every other shared person", "41 markers",
          "other person, other motion, a model of one walk")
#: the marker takes' people (14 points derived from their markers): with the skeletal clips of
#: the other CMU subjects, every person of the shared data but the one labelled
MARKER_PEOPLE = ("mct_walk1", "mct_dance1", "qualisys", "85_02", "85_12", "hdm05")
#: of them, the takes that are not the MoCap Toolbox person(s)
MARKER_PEOPLE_NOT_MCT = tuple(k for k in MARKER_PEOPLE if not k.startswith("mct_"))
GENERIC_NOTE = "CMU skeletons of the other subjects + 14 points derived from the markers of the MoCap Toolbox, " \
               "Qualisys, CMU 85 and HDM05 people"
GENERIC_MCT_NOTE = "every CMU skeletal clip + the Qualisys, CMU 85 and HDM05 people's derived points; neither " \
                   "MoCap Toolbox take"
VARIANTS = ("today", "body", "body + calibration", "dtm-label default")
TODAY = {"body_terms": False, "broad_component": False}
MARKER_TRAINING = {"k_max": 4, "max_frames_per_triangle": 1500}


@dataclass(frozen=True)
class Case:
    """Train on ``train`` (recording keys, optionally ``KEY@A:B`` with fractions of the
    recording), label ``test`` (same syntax) at ``points`` (body14 or all)."""

    key: str
    group: str
    title: str
    train: tuple
    test: str
    points: str = "body14"
    note: str = ""


CASES = (
    Case("D1_halves", GROUPS[0], "whirl 55_01: first half -> second half", ("D1@0:0.5",), "D1@0.5:1"),
    Case("D2_halves", GROUPS[0], "lambada 55_02: first half -> second half", ("D2@0:0.5",), "D2@0.5:1"),
    Case("D2_to_D1", GROUPS[1], "subject 55: lambada -> whirl", ("D2",), "D1",
         note="ASF -> cgspeed skeleton: the neck, head and shoulders sit 11.6 cm lower relative to the pelvis"),
    Case("D1_to_D2", GROUPS[1], "subject 55: whirl -> lambada", ("D1",), "D2", note="cgspeed -> ASF skeleton"),
    Case("loso_5", GROUPS[2], "subject 5 pirouette; model: subjects 7, 9, 55", ("W1", "R1", "D1", "D2"), "D3"),
    Case("loso_7", GROUPS[2], "subject 7 walk; model: subjects 5, 9, 55", ("R1", "D1", "D2", "D3"), "W1"),
    Case("loso_9", GROUPS[2], "subject 9 run; model: subjects 5, 7, 55", ("W1", "D1", "D2", "D3"), "R1",
         note="no run in the training"),
    Case("loso_55", GROUPS[2], "subject 55 lambada; model: subjects 5, 7, 9", ("W1", "R1", "D3"), "D2"),
    Case("new_mct_dance", GROUPS[2], "MoCap Toolbox dancer; model: every CMU skeletal clip", SKELETAL, "mct_dance1",
         note="14 points derived from 28 surface markers"),
    Case("new_mct_walk", GROUPS[2], "MoCap Toolbox walker; model: every CMU skeletal clip", SKELETAL, "mct_walk1",
         note="14 points derived from 28 surface markers"),
    Case("generic_5", GROUPS[3], "subject 5 pirouette", ("W1", "R1", "D1", "D2") + MARKER_PEOPLE, "D3",
         note=GENERIC_NOTE),
    Case("generic_7", GROUPS[3], "subject 7 walk", ("R1", "D1", "D2", "D3") + MARKER_PEOPLE, "W1", note=GENERIC_NOTE),
    Case("generic_9", GROUPS[3], "subject 9 run", ("W1", "D1", "D2", "D3") + MARKER_PEOPLE, "R1",
         note=GENERIC_NOTE + "; no run in the training"),
    Case("generic_55", GROUPS[3], "subject 55 lambada", ("W1", "R1", "D3") + MARKER_PEOPLE, "D2", note=GENERIC_NOTE),
    Case("generic_mct_dance", GROUPS[3], "MoCap Toolbox dancer (14 points derived from 28 surface markers)",
         SKELETAL + MARKER_PEOPLE_NOT_MCT, "mct_dance1", note=GENERIC_MCT_NOTE),
    Case("generic_mct_walk", GROUPS[3], "MoCap Toolbox walker (14 points derived from 28 surface markers)",
         SKELETAL + MARKER_PEOPLE_NOT_MCT, "mct_walk1", note=GENERIC_MCT_NOTE),
    # a lab's first model is often one take of one motion: subject 7's walk alone, labelling other
    # people's dances and run (the arms in poses a walk never shows; ASF skeletons: other joint centres)
    Case("w7_to_D2", GROUPS[5], "subject 55 lambada; model: subject 7's walk", ("W1",), "D2",
         note="cgspeed -> ASF skeleton"),
    Case("w7_to_D1", GROUPS[5], "subject 55 whirl; model: subject 7's walk", ("W1",), "D1"),
    Case("w7_to_D3", GROUPS[5], "subject 5 pirouette; model: subject 7's walk", ("W1",), "D3",
         note="cgspeed -> ASF skeleton"),
    Case("w7_to_R1", GROUPS[5], "subject 9 run; model: subject 7's walk", ("W1",), "R1"),
    Case("m_85_02_to_85_12", GROUPS[4], "subject 85: jump + twist -> breakdance (standing part)",
         ("85_02",), "85_12@0.2:0.35", "all"),
    Case("m_85_12_to_85_02", GROUPS[4], "subject 85: breakdance -> jump + twist", ("85_12@0:0.5",), "85_02", "all"),
    Case("m_cmu_to_hdm05", GROUPS[4], "other person: CMU 85 (both takes) -> HDM05 bd", ("85_02", "85_12@0:0.5"),
         "hdm05@0:0.2", "all", note="another lab, another marker placement"),
    Case("m_hdm05_to_85_02", GROUPS[4], "other person: HDM05 bd -> CMU 85 jump + twist", ("hdm05@0:0.3",),
         "85_02", "all"),
    Case("m_floor", GROUPS[4], "floor moves: CMU 85 jump + twist, HDM05 -> breakdance on the floor",
         ("85_02", "hdm05@0:0.3"), "85_12@0.75:0.9", "all",
         note="the body leaning up to 50 deg; no upside-down pose in the shared data"),
)


@dataclass
class Plan:
    """Budgets of the section (recorded in results.json)."""

    cases: tuple = tuple(c.key for c in CASES)
    stream_frames: int = 480
    single_frames: int = 24
    marker_stream_frames: int = 360
    marker_single_frames: int = 8
    calibration_s: float = 5.0
    seed: int = 0
    extra: dict = field(default_factory=dict)


def quick_plan(seed: int = 0) -> Plan:
    return Plan(cases=("D2_to_D1", "loso_5"), stream_frames=60, single_frames=3, marker_stream_frames=30,
                marker_single_frames=2, seed=seed)


# -- data -----------------------------------------------------------------------------------------------
def parse_source(spec: str) -> tuple[str, float, float]:
    """``KEY`` or ``KEY@A:B`` (fractions of the recording) -> (key, a, b)."""
    key, _, rng = spec.partition("@")
    if key not in RECORDINGS:
        raise ValueError(f"unknown recording {key!r}; have {', '.join(RECORDINGS)}")
    if not rng:
        return key, 0.0, 1.0
    a, b = (float(x) for x in rng.split(":"))
    return key, a, b


def load_source(data_dir: Path, spec: str, points: str) -> MotionClip:
    key, a, b = parse_source(spec)
    clip = load_clip(Path(data_dir) / RECORDINGS[key][0], points=points)
    i, j = int(round(a * clip.n_frames)), int(round(b * clip.n_frames))
    out = clip.slice(i, j)
    out.meta["source_spec"] = spec
    return out


def case_clips(data_dir: Path, case: Case) -> tuple[list[MotionClip], MotionClip]:
    """Training clips (at the model's points) and the test clip of a case."""
    train = [load_source(data_dir, s, case.points) for s in case.train]
    test = load_source(data_dir, case.test, case.points)
    if case.points == "all":                 # one marker set: the first training clip's names, in its order
        names = train[0].names
        train = [c.select(names) for c in train]
        test = test.select(names)
    return train, test


def model_key(case: Case, variant: str) -> tuple:
    return (tuple(case.train), case.points, "today" if variant == "today" else "body")


def train_config(case: Case, variant: str, seed: int) -> TrainConfig:
    """MDL mixtures; the hand-given structure for the 14 body points, the structure grown along
    the rigid tree (``--structure body``) for marker sets -- the same for both variants."""
    kw = dict(seed=seed, structure="given")
    if case.points != "body14":
        kw.update(MARKER_TRAINING, structure="body")
    if variant == "today":
        kw.update(TODAY)
    return TrainConfig(**kw)


def train_case_model(clips: list[MotionClip], config: TrainConfig) -> tuple[TriangulatedModel, dict]:
    t0 = time.perf_counter()
    model, summary = train_model(clips, config)
    return model, {"seconds": time.perf_counter() - t0, "frames": summary.frames_total,
                   "components": summary.components, "structure": summary.structure,
                   "segments": 0 if model.body is None else int((model.body.kind == SEGMENT).sum()),
                   "segment_edges": segment_edges(model)}


def segment_edges(model: TriangulatedModel) -> int:
    """How many of the edges the structure introduces carry a segment term."""
    if model.body is None:
        return 0
    idx = model.body.pair_index()
    seg = np.append(model.body.kind == SEGMENT, False)          # row -1 (no pair): not a segment
    tri = model.triangles
    n = int(seg[idx[tri[0, 1], tri[0, 2]]])
    for i, j in ((0, 1), (0, 2)):
        n += int(seg[idx[tri[:, i], tri[:, j]]].sum())
    return n


# -- one labeling cell --------------------------------------------------------------------------------
def calibration_frames(clip: MotionClip, seconds: float) -> int:
    """Frames of the calibration window: ``seconds`` of the recording, at most a third of it."""
    return int(min(round(seconds * clip.rate), clip.n_frames // 3))


def as_dtm_label(model: TriangulatedModel, train: list[MotionClip], window: MotionClip,
                 seed: int) -> tuple[TriangulatedModel, dict]:
    """The model ``dtm-train`` makes of ``train`` (``model``: its generic body) as ``dtm-label
    --calibrate auto`` labels a capture whose first frames are ``window`` (the module doc's
    *dtm-label default*), and a summary of what was done (``person`` says whose body labels)."""
    why = one_subject([c.source for c in train])
    person = None
    if why is not None and model.body is not None:
        try:
            person = calibrate_on_takes(model, train)
        except CalibrationError:
            person = None
        else:
            person.provenance["calibration"]["why"] = why
    if person is not None and keeps_training_calibration(person, window.source) is not None:
        return person, {"applied": False, "person": "training takes' (one of its captures; the same person: " + why + ")"}
    stream = corrupt_clip(model_clip(model, window), seed=seed)
    if person is not None and of_training_person(person, window.source) is not None:
        out, summary = session_calibrate(person, [f.xyz for f in stream], stream.rate)
        return out, summary | {"person": "training takes' (the same person: " + why + "), session check"}
    out, summary = auto_calibrate(model, [f.xyz for f in stream], stream.rate)
    found = recognised_person(out, person, [f.xyz for f in stream], stream.rate) if summary.get("applied") else None
    if found is not None:
        return found[0], found[1] | {"person": "training takes' (recognised by their lengths), session check"}
    if summary.get("applied"):
        return out, summary | {"person": "self-calibrated on the window"}
    if person is not None:
        return person, summary | {"person": "training takes' (self-calibration refused)"}
    return out, summary | {"person": "generic body"}


def run_variant(model: TriangulatedModel, test: MotionClip, variant: str, plan: Plan, markers: bool,
                train: list[MotionClip] | None = None) -> dict:
    """Stream and single-mode scores of one variant on the frames after the calibration window
    (``train``: the training clips, for the *dtm-label default*'s person; :func:`as_dtm_label`)."""
    t0 = time.perf_counter()
    n_cal = calibration_frames(test, plan.calibration_s)
    rest = test.slice(n_cal, None)
    out: dict = {"calibration_frames": n_cal}
    if variant == "dtm-label default":         # dtm-train's model, as dtm-label --calibrate auto runs it
        model, out["calibration"] = as_dtm_label(model, train or [], test.slice(0, n_cal), plan.seed)
    if variant == "body + calibration":         # the window as the labeler gets it (module doc)
        cal = corrupt_clip(model_clip(model, test.slice(0, n_cal)), seed=plan.seed)
        try:
            model, confirmed = self_calibrate(model, [f.xyz for f in cal], cal.rate)
        except CalibrationError as e:
            out["subject_calibration_error"] = str(e)
            return out
        info = model.provenance["calibration"]
        out["calibration"] = {k: info[k] for k in ("frames", "segments", "segments_total", "scale",
                                                   "median_change_m", "segments_from_mirror",
                                                   "asymmetric_dropped", "wrong_side_labels")}
        out["calibration"]["confirmed_fraction"] = float(np.isfinite(confirmed[..., 0]).mean())
    n_stream = plan.marker_stream_frames if markers else plan.stream_frames
    n_single = plan.marker_single_frames if markers else plan.single_frames
    settings = LabelerSettings(seed=plan.seed)
    run = label_clip_run(model, rest.slice(0, n_stream), settings, seed=plan.seed, keep_records=True)
    d = run.accumulator.metrics().as_dict()
    out["stream"] = {k: d[k] for k in SUMMARY_KEYS}
    out["stream"]["confusions"] = run.metrics.confused_pairs(4)
    out["diagnosis"] = diagnose(model, rest.slice(0, n_stream), run.records)
    out["single"] = label_single(model, rest, spread_frames(rest.n_frames, n_single), "cbga", seed=plan.seed)
    out["wall_s"] = time.perf_counter() - t0
    return out


def diagnose(model: TriangulatedModel, clip: MotionClip, records, max_frames: int = 30) -> dict:
    """Model's vs search's errors of a stream run and, for the model's errors, the mean
    per-triangle fitness difference truth minus chosen (total and its body part)."""
    mc = model_clip(model, clip)
    states = point_states(mc.positions, mc.rate)
    M, T = model.n_labels, model.structure.n_triangles
    wrong = model_err = search_err = 0
    diff, body_diff = [], []
    for r in records:
        if r.index == 0:
            continue
        chosen = np.full(M, M)
        vis = (r.search_labels >= 0) & (r.truth >= 0)
        chosen[r.search_labels[vis]] = r.truth[vis]
        true = np.where(np.isfinite(mc.positions[r.index]).all(1), np.arange(M), M)
        if np.array_equal(chosen, true):
            continue
        wrong += 1
        if is_search_error(r.truth_fitness, r.log_likelihood):
            search_err += 1
            continue
        model_err += 1
        if len(diff) >= max_frames:
            continue
        problem = FrameProblem(model, states[r.index], Background())
        pop = np.stack([true, chosen])
        _, bins = problem.fitness(pop, return_bins=True)
        diff.append(np.diff(problem.triangle_table(pop, bins)[::-1], axis=0)[0])
        pos = np.where(pop[..., None] < M, mc.positions[r.index][np.minimum(pop, M - 1)], np.nan)
        d, ok = slot_distances(pos, model.triangles)
        body = [model.edge_terms(np.arange(T), d[k], ok[k]) for k in range(2)]
        body_diff.append(body[0] - body[1])
    names = model.structure.names(model.labels)
    mean = np.mean(diff, 0) if diff else np.zeros(T)
    bmean = np.mean(body_diff, 0) if body_diff else np.zeros(T)
    worst = np.argsort(mean)[:3]
    return {"frames": len(records), "wrong": wrong, "model_errors": model_err, "search_errors": search_err,
            "worst_triangles": [{"triangle": names[t], "truth_minus_chosen": float(mean[t]),
                                 "body_part": float(bmean[t])} for t in worst if mean[t] < 0],
            "truth_minus_chosen": mean.tolist(), "body_part": bmean.tolist()}


# -- the section ----------------------------------------------------------------------------------------
def selected_cases(plan: Plan) -> list[Case]:
    unknown = set(plan.cases) - {c.key for c in CASES}
    if unknown:
        raise ValueError(f"unknown generalisation case(s) {', '.join(sorted(unknown))}")
    return [c for c in CASES if c.key in plan.cases]


def model_tasks(data_dir: Path, plan: Plan) -> dict[tuple, dict]:
    """One training task per distinct (training recordings, points, today/body)."""
    tasks = {}
    for case in selected_cases(plan):
        train, _ = case_clips(data_dir, case)
        for variant in ("today", "body"):
            key = model_key(case, variant)
            if key not in tasks:
                tasks[key] = dict(clips=train, config=train_config(case, variant, plan.seed))
    return tasks


def cell_tasks(data_dir: Path, plan: Plan, models: dict[tuple, TriangulatedModel]) -> list[tuple]:
    """(case key, variant, kwargs of :func:`run_variant`) for every case and variant."""
    out = []
    for case in selected_cases(plan):
        train, test = case_clips(data_dir, case)
        for variant in VARIANTS:
            kw = dict(train=train) if variant == "dtm-label default" else {}
            out.append((case.key, variant, dict(model=models[model_key(case, variant)], test=test, variant=variant,
                                                plan=plan, markers=case.points != "body14", **kw)))
    return out


def case_info(data_dir: Path, plan: Plan, model_summaries: dict[tuple, dict]) -> dict:
    """What each case trained on and tested (for the report)."""
    out = {}
    for case in selected_cases(plan):
        train, test = case_clips(data_dir, case)
        out[case.key] = {
            "group": case.group, "title": case.title, "note": case.note, "points": case.points,
            "train": [{"spec": s, "recording": RECORDINGS[parse_source(s)[0]][2],
                       "subject": RECORDINGS[parse_source(s)[0]][1], "frames": c.n_frames}
                      for s, c in zip(case.train, train)],
            "test": {"spec": case.test, "recording": RECORDINGS[parse_source(case.test)[0]][2],
                     "subject": RECORDINGS[parse_source(case.test)[0]][1], "frames": test.n_frames,
                     "rate": test.rate},
            "models": {v: model_summaries.get(model_key(case, v)) for v in ("today", "body")},
        }
    return out


def plan_dict(plan: Plan) -> dict:
    return dataclasses.asdict(plan)


__all__ = ["CASES", "Case", "Plan", "quick_plan", "VARIANTS", "GROUPS", "RECORDINGS", "model_tasks", "cell_tasks",
           "case_info", "run_variant", "as_dtm_label", "diagnose", "train_case_model", "calibration_frames", "load_source"]
