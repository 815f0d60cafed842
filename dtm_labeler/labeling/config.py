"""The one parameter table: every tunable setting of the labeler, the bank and the node.

Each :class:`Param` states once its name, default, range or choices, description and the
layer that reads it (``labeler``: :class:`LabelerSettings`; ``bank``:
:class:`~.bank_labeler.BankSettings`; ``node``: the ROS node only). From this table come

* the defaults and the validation of :class:`LabelerSettings` (``__post_init__``) and of the
  bank settings,
* the node's declared parameters with their descriptors (:mod:`dtm_labeler.ros.params`) and
  ``params/labeler.yaml`` (:func:`render_yaml`),
* the labeler flags of ``dtm-label`` and ``dtm-bag label`` (:func:`add_arguments`), and
* ``--params-file`` for both (:func:`load_params_file`): a YAML tuned on the live node
  replays offline exactly.

Pure Python (no ROS), so it is tested without a node. ``settings_from_params`` maps a flat
parameter set onto the nested settings (the full and the warm GA, the clutter model, the
tracker).
"""
from __future__ import annotations

import argparse
import json
import math
import textwrap
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Dict, Iterable, Mapping, Optional, Sequence, Tuple

import numpy as np

from ..search.label_search import GASettings
from ..search.problem import Background
from .tracker import TrackerSettings

NODE_NAME = "dtm_labeler"
METHODS = ("cbga", "sga", "greedy", "exhaustive", "tracker")
RECOVERY = ("auto", "inline", "background")
MODES = ("stream", "single")
STRATEGIES = ("spread", "hard")
QOS_CHOICES = ("sensor_data", "reliable")
INPUT_TYPES = ("pointcloud2", "mocap4r2_markers", "pointcloud")      # dtm_labeler.ros.inputs
MOCAP4R2_IDS = ("auto", "name", "index", "none")
STAMP_SOURCES = ("auto", "header", "receive")                       # dtm_labeler.ros.stamps
LAYERS = ("labeler", "bank", "node")
INT_MAX = 2 ** 31 - 1


@dataclass(frozen=True)
class Param:
    """One setting. ``range`` is inclusive ``(lo, hi)`` for numbers; ``choices`` for strings;
    ``read_only`` ones are start-up only on the node; ``flag`` is the command-line flag of
    ``dtm-label`` / ``dtm-bag label`` (None: not a flag there)."""

    name: str
    default: Any
    description: str
    layer: str = "labeler"
    range: Optional[Tuple[float, float]] = None
    choices: Optional[Tuple[str, ...]] = None
    read_only: bool = False
    flag: Optional[str] = None

    @property
    def kind(self) -> str:
        d = self.default
        if isinstance(d, bool):
            return "bool"
        if isinstance(d, int):
            return "int"
        if isinstance(d, float):
            return "double"
        if isinstance(d, str):
            return "string"
        if isinstance(d, (list, tuple)):
            return "string_array"
        raise TypeError(f"unsupported default for {self.name}: {d!r}")

    def check(self, value: Any) -> Any:
        """Type/range/choice check of one value; returns it normalised (int -> float for
        doubles, None -> [] for a string array). ValueError naming the parameter."""
        kind, name = self.kind, self.name
        if kind == "bool":
            if not isinstance(value, (bool, np.bool_)):
                raise ValueError(f"{name} must be a bool, got {value!r}")
            value = bool(value)
        elif kind == "int":
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"{name} must be an integer, got {value!r}")
            value = int(value)
        elif kind == "double":
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise ValueError(f"{name} must be a number, got {value!r}")
            value = float(value)
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value!r}")
        elif kind == "string":
            if not isinstance(value, str):
                raise ValueError(f"{name} must be a string, got {value!r}")
        else:
            if value is None:
                value = []
            if isinstance(value, str) or not all(isinstance(v, str) for v in value):
                raise ValueError(f"{name} must be a list of strings, got {value!r}")
            value = list(value)
        if self.range is not None and not self.range[0] <= value <= self.range[1]:
            raise ValueError(f"{name} = {value!r} is out of range [{self.range[0]}, {self.range[1]}]")
        if self.choices is not None and value not in self.choices:
            raise ValueError(f"{name} must be one of {', '.join(self.choices)}, got {value!r}")
        return value


_FULL = GASettings(population=64, max_generations=80, stagnation=10, wide_sweeps=1, mirror_sweeps=3, fresh_starts=3)
_WARM = GASettings(population=24, max_generations=10, stagnation=3, polish=True, polish_rounds=1, p_recreate=0.15,
                   fresh_fraction=0.0, region_sweeps=0)

PARAMS: Tuple[Param, ...] = (
    # -- model (node) -------------------------------------------------------------------------
    Param("model_path", "", "Model file (.npz from dtm-train). Setting it at runtime hot-reloads "
          "the model; a file that cannot be loaded (or whose labels differ from expected_labels) "
          "is rejected and the running model is kept. Empty = no model (nothing is labelled).", "node"),
    Param("expected_labels", [], "Label names the model must have, in order; empty = accept any "
          "model. A model whose labels differ is rejected.", "node"),
    Param("model_name", "", "Name published as LabeledMarkerArray.active_model (e.g. 'walk'); "
          "empty for a single-model labeler.", "node"),
    Param("bank_path", "", "Model bank (directory with bank.json, or single-file bank .npz, from "
          "dtm-train --action NAME --bank DIR): one model per action, all used at once (Ukita). "
          "Loaded when use_bank is true; setting it at runtime hot-reloads the bank.", "node"),
    Param("use_bank", False, "Label with the model bank at bank_path instead of model_path; the "
          "active action is published as LabeledMarkerArray.active_model and in /diagnostics.", "node"),
    # -- search --------------------------------------------------------------------------------
    Param("method", "cbga", "Label search: cbga (constraint-based GA, the paper's), sga "
          "(simple GA), greedy (DP over the DTM), exhaustive (tiny models only), tracker "
          "(carry labels along tracks, search only when lost).", choices=METHODS, flag="--method"),
    Param("mode", "stream", "stream: warm-started search + per-track votes over the window; "
          "single: every frame labelled from scratch.", choices=MODES, flag="--mode"),
    Param("window", 10, "Frames in the sliding vote window (eq. 32).", range=(1, 10000), flag="--window"),
    Param("population", _FULL.population, "Population of the full (cold) GA search.", range=(4, 4096),
          flag="--population"),
    Param("max_generations", _FULL.max_generations, "Generation cap of the full GA search.",
          range=(0, 100000), flag="--generations"),
    Param("stagnation", _FULL.stagnation, "Full GA stops after this many generations without "
          "improvement.", range=(1, 100000)),
    Param("time_budget_ms", 0.0, "Time budget per GA search in ms (full and warm); 0 = none.",
          range=(0.0, 60000.0)),
    Param("warm_population", _WARM.population, "Population of the warm-started GA (stream "
          "mode, labels carried over from the last frame).", range=(4, 4096)),
    Param("warm_generations", _WARM.max_generations, "Generation cap of the warm GA.", range=(0, 100000)),
    Param("warm_stagnation", _WARM.stagnation, "Warm GA stops after this many generations "
          "without improvement.", range=(1, 100000)),
    Param("fresh_fraction", _FULL.fresh_fraction, "Share of a seeded full search's population "
          "drawn fresh (model-guided sampling) instead of mutants of the carried labeling.",
          range=(0.0, 1.0)),
    Param("region_sweeps", _FULL.region_sweeps, "Exact region sweeps over every label at the end "
          "of a full search (0 = none).", range=(0, 16)),
    Param("wide_sweeps", _FULL.wide_sweeps, "Then sweeps over every label's body neighbourhood (it and "
          "its 6 nearest labels on the mean body), each relabelled exactly as a whole over the points "
          "it holds and the nearest free ones: a limb's labels permuted along it, which the label-and-"
          "partner regions do not hold, are put right (0 = none). Measured on 41 HDM05 markers, 3 gaps + 2 "
          "ghosts, corruption seed 3, cold searches from 12 random seeds: right at the end 10 -> 12, "
          "median time to the first right labeling 0.9 -> 0.43 s; single-frame mode 85.3 -> 87.6 % "
          "(~13 % more time).", range=(0, 16)),
    Param("mirror_sweeps", _FULL.mirror_sweeps, "Marker sets: then at most this many sweeps over every label's body "
          "neighbourhood joined with its mirror image (both hands', both feet's markers), each relabelled exactly "
          "as a whole over 20 shared points, a point the DP gives to two labels branched on (mirror_branches): "
          "a crouched body's two arm chains interleaved, which the one-sided regions do not hold, are put right. "
          "dtm-eval's 41-marker single-frame cells (cold searches from scratch): CMU 85 breakdance 79.3 -> 97.6 %, "
          "HDM05 96.8 -> 98.4 %. Single-frame mode only: a stream's full searches (cold starts, recoveries) "
          "search as without them (0 = none).", range=(0, 16)),
    Param("mirror_branches", _FULL.mirror_branches, "Extra DP solves each mirrored neighbourhood of mirror_sweeps may "
          "spend where its best relabelling gives one point to two labels (each claimant keeps it in turn, then "
          "none).", range=(0, 64)),
    Param("fresh_starts", _FULL.fresh_starts, "A search from scratch also finishes (polish, sweeps, the "
          "labels read through the turned-round body) the bests of this many fresh model-guided "
          "populations, beside the GA's: a refined start is right or not by the luck of its population, "
          "the GA from a bad one took 1.5-5 s at 41 markers and could end wrong. In a background worker "
          "they run right after the first generation and join the stream at once; in single-frame mode "
          "after the first GA. Measured on 41 HDM05 markers, 3 gaps + 2 ghosts: the stream labeler's "
          "first worker seed right at 0.71 s instead of never (5 s, 11 labels wrong); single-frame mode "
          "87.6 -> 92.2 % (search errors 14 -> 3 of 40 frames; ~60 % more time). Not in an inline stream's "
          "cold searches: on 12 upper-body HDM05 markers half hidden, live / voted 78.0 / 86.7 -> 61.4 / "
          "74.2 %.", range=(0, 64)),
    Param("refit_drop", 60.0, "A warm result this many nats below the running fitness "
          "level triggers a full search.", range=(0.001, 1e9)),
    Param("restarts", 2, "Full GA searches repeated from fresh populations (at most "
          "this many more) while the best still falls refit_drop short of the level.", range=(0, 16)),
    Param("accept_drop", 30.0, "The carried-over labeling is accepted without a GA "
          "when within this many nats of the running level.", range=(0.001, 1e9)),
    Param("fast_rounds", 4, "Hill-climbing rounds of the fast path (moves of the carried labeling "
          "per frame).", range=(0, 1000)),
    Param("release_moves", True, "The fast path also tries leaving missing each label on a track begun "
          "in the last 2 s (a ghost that took over a hidden marker's label); on a marker set, whose "
          "labels pay hold_nats to be left on no point, only once leaving the label out has fitted "
          "better by 30 nats over the frames in a row it did (then without that price), while at "
          "most a quarter of the labels are missing."),
    Param("swap_radius_m", 0.15, "The fast path also tries swapping the labels of points closer "
          "than this (m): where the tracker may have swapped two markers.", range=(0.0, 10.0)),
    Param("mirror_switch_nats", 0.5, "Nats per label the fast path's whole mirror image of the "
          "carried labeling must gain besides its fitness (a track keeps its side unless the frame's "
          "evidence outweighs this prior; eq. 32 read as a hidden Markov chain). 0 = off: in a symmetric "
          "gait the mirror fits about as well as the truth and a few nats turned whole streams round.",
          range=(0.0, 1000.0)),
    Param("chain_moves", 0, "The fast path also tries moving a hole (a missing label whose track is "
          "not coasting) along chains of up to this many neighbouring markers (limb chains from the "
          "model's mean body): each label takes the next one's point, as when tracking carried a limb's "
          "labels one marker along, and the last one the carried labeling's free points. Taken when it gains "
          "10 nats. 0 or 1 = off, the default: with 3 (corruption seeds 1-3, inline) search errors fall (41 "
          "HDM05 markers with 3 gaps + 2 ghosts 367 -> 246, with flicker 101 -> 87, 14 points with gaps 228 "
          "-> 192) for about the same accuracy (+0.2, 0.0, +0.3 points), but the 41-marker p99 rises 1-2 ms "
          "and gapped captures move both ways (HDM05 halves, 50 % hidden: mean 97.6 -> 96.9 %; Qualisys "
          "95.8 -> 96.7 %).", range=(0, 6)),
    Param("cluster_turns", True, "On region-check frames the fast path also tries every other "
          "arrangement of each small rigid cluster's labels over its points (3-4 markers on one segment: a "
          "head, a wrist bar and its forearm marker), taken when it gains more than the moves' priors: a "
          "head read turned by 90 degrees is four labels each one along, which no single swap undoes "
          "without passing worse labelings (CMU 85's floor moves under dtm-label's default: the head "
          "turned in 221 of 360 frames, 94.0 -> 99.9 %)."),
    Param("hold_nats", 15.0, "Nats the fast path's move must gain besides its fitness to take a label "
          "off the track that has carried it for hold_s (seen this frame) and give it to a point no label "
          "holds, whose track has carried that label for hold_s less, or to no point; or to take the label a coasting "
          "track (its marker hidden) has carried for hold_s and give it to a point whose track never "
          "carried it; or to give a label to a point whose track has been left unlabelled for hold_s while "
          "that label was on another track (a trajectory keeps its label, or its lack of one; eq. 32 read "
          "as a hidden Markov chain). Stops a ghost riding beside a marker from "
          "taking its label (41 HDM05 markers, 3 flickering + 2 ghosts, four seeds: wrong labels after the "
          "first right frame 0.47-0.98 -> 0.36-0.58 %), and a ghost beside a hidden marker (14 points with "
          "gaps + ghosts, three seeds: search errors 242 -> 208). Offline, the take pass's searches keep it "
          "for a label a track carries in hold_s of the take (a walk model on a whirl: 94.2 -> 100 %). "
          "On a marker set every label on a seen point pays it to be left on no point, held or not, while at "
          "most a quarter of the labels are missing (41 "
          "HDM05 markers with gaps + ghosts, inline, three seeds: search errors 209 -> 149 of 2970). "
          "0 = off.", range=(0.0, 1000.0)),
    Param("hold_s", 1.0, "Stream time (s) a track must have carried a label before hold_nats protects "
          "it, and by which it must out-hold the point it would go to. Shorter also protects a wrong point "
          "that took a hidden marker's label during its gap (0.2 s: 41 markers with gaps -0.3 points).",
          range=(0.0, 3600.0)),
    Param("cluster_memory_s", 4.0, "Memory (s) of the arrangement prior: a move of the fast path that "
          "puts a small rigid cluster's labels (a wrist bar with its forearm and finger markers, a head) on "
          "the same tracks in another arrangement pays the log-likelihood by which the frames since those "
          "tracks began, discounted over this time, prefer the arrangement they carry (eq. 32 read as a "
          "hidden Markov chain over the cluster's arrangement). Keeps a wrist bar's ends from following a "
          "motion mixture that prefers them exchanged for a phase of each movement. 0 = off.",
          range=(0.0, 3600.0)),
    Param("bar_order_gain", 15.0, "Evidence (nats, ORDER_NATS per frame clipped per partner) by which a "
          "marker bar's order must say its two tracked ends are the other way round before the labeler "
          "exchanges them and holds them so: a wrist bar's ends (radial / ulnar) lie nearer or farther the "
          "shoulder, upper arm and finger whatever the motion, where the motion mixtures of a pose not in the "
          "training may prefer them exchanged. A body calibrated to a person only (its bar rows), stream mode only. 0 = off.",
          range=(0.0, 1000.0)),
    Param("turn_check", True, "A search from scratch also tries the body turned round: the model's "
          "exact whole-body max-product at the facing opposite to the search's result, kept when it fits "
          "better (a cold start under a model of another lab settled on the body seen from behind: CMU 85 "
          "model on HDM05, 2.4 % right). About 1 s per such search at 41 markers, ~10 ms at 14 points."),
    Param("upright_deg", 15.0, "A search from scratch also runs on the frame's points turned upright "
          "(their long axis onto the vertical) when that axis leans more than this many degrees, and keeps "
          "what it finds there when it fits the frame as it is better (a body on the floor under a model of "
          "standing motions: CMU 85 breakdance, 27 -> 97 % right). One more search per leaning frame. "
          "0 = off.", range=(0.0, 90.0)),
    Param("bend_starts", 4, "A search from scratch under a marker set's model that still fits below 60 % "
          "of the level after its other starts (on a frame showing at least half the labels' points) also "
          "runs on the frame pitched back 60 deg about this many horizontal axes, spread round the "
          "vertical, and keeps what it finds there when it fits the frame as it is better (a body bent "
          "at the hips under a model that never saw it: trunk read upside down; CMU 85 stand-up, single "
          "frames 94.5 -> 97.6 %); when it still fits poorly, again at 120 deg (a body upside down in a flip: CMU 85 "
          "jump + twist, single frames 92.6 -> 96.7 %). One more search per axis and pitch, only on such frames. "
          "0 = off.", range=(0, 12)),
    Param("region_checks", 1, "Body regions relabelled exactly (max-product DP "
          "given the rest of the body) per frame while checks are due (one pass over the "
          "regions after a GA search, then every region_every frames); repairs a wrong "
          "labeling that tracking carries on. 0 = off.", range=(0, 64)),
    Param("young_checks", 1, "Regions relabelled exactly per frame, besides region_checks, around "
          "labels on points whose track began less than half a second ago -- a point back from a gap, "
          "or a ghost that took a hidden point's label -- one such label after another. Joint centres "
          "only (the 14 body points): on a marker set the exact relabelling of a hand's or a foot's "
          "region follows the model's own errors. 0 = off.", range=(0, 16)),
    Param("young_candidates", 3, "Points each label of a young check's region may take: its own and the "
          "nearest others no label outside the region holds (a missing label: the nearest its distance "
          "bounds allow). The other region checks, and the searches' final sweeps, take 6. A young check "
          "runs in nearly every frame of a stream with gaps or ghosts, and its DP's rows grow with the cube "
          "of this per triangle: 6 -> 3 on bench_stream_latency's 14 points with 3 gaps + 2 ghosts (seeds "
          "1-3, inline) kept the labels (98.78 -> 98.81 %, search errors 26 -> 25) and cut the steady p99 "
          "2.46-2.56 -> 2.21-2.30 ms.", range=(1, 64)),
    Param("region_every", 240, "Background region check every this many frames "
          "in steady state (0 = only after GA searches).", range=(0, 1000000)),
    Param("region_size", 6, "Labels per region of the region checks and of the "
          "full search's final region sweep (more = larger repairs, more work per frame).", range=(2, 16)),
    Param("region_branches", 0, "Extra DP solves each region check of the fast path may spend where the "
          "region's best relabelling gives one point to two labels (each claimant keeps it in turn, then "
          "none). 0 = resolve the conflict after the DP, the default: measured with 6 on the 41-marker "
          "HDM05 streams (seeds 1-5), gaps 92.5 -> 92.4 %, flicker 96.0 -> 95.6 % (seed 5: 96.0 -> "
          "93.9 %); 12 upper-body markers half hidden 51.1 -> 64.4 % as published live.", range=(0, 64)),
    Param("sweep_branches", 0, "The same for the region sweep that ends every GA search. 6 undoes a label "
          "moved onto its neighbour's point, which resolving after the DP cannot: CMU 85 model, "
          "self-calibrated, on HDM05 94.1 -> 97.6 % (search errors 252 -> 0 of 360), the 41-marker HDM05 "
          "streams unchanged (seeds 1-5); but in dtm-eval's generalisation cells 85_02 -> 85_12 99.1 -> "
          "91.4 % (dtm-label's self-calibration check then rejects the calibration), floor moves 93.6 -> "
          "57.0 %, pooled ECE 4.2 -> 5.4 %. 0 = resolve after, the default.", range=(0, 64)),
    Param("recovery", "auto", "Where recovery searches run when the fast path cannot vouch for a "
          "frame: inline (in that frame: deterministic), background (a worker process; frames go on "
          "with the best labeling known, flagged doubtful, and the result joins a later frame: what a "
          "live stream needs) or auto (background in the node, inline offline).", choices=RECOVERY,
          flag="--recovery"),
    Param("misfit_nats", 0.0, "A label whose triangles fall more than this many nats below what the "
          "model expects of a right labeling (floors drawn from the model itself) gets an exact region "
          "check at once; three such frames in a row ask for an audit (inline: a full search then). "
          "0 = off, the default: measured, 15 cut the search errors of a 14-point stream with gaps "
          "(33 -> 21 of 300 frames) but led a clean 41-marker stream into a wrong labeling it kept "
          "(HDM05, 1000 frames: 97.5 -> 91.6 %).",
          range=(0.0, 1e6)),
    Param("audit_period_s", 1.0, "Background recovery: while the labeling looks fine, the worker "
          "checks it four times per this many stream seconds -- exact region sweeps, the fourth a full "
          "search from scratch -- and a better labeling replaces it. Catches a wrong labeling the "
          "running level has adapted to. A doubted frame asks for a warm search (then a full one) at most "
          "once per this, and for an exact region sweep from the carried labeling between them (half of "
          "41 markers hidden: 57 -> 70 % right). Inline (offline), with a bank: a labeling that stays lost (a frame "
          "10 nats per label below the model's fit reference for 3 frames) gets a full search from scratch, at "
          "most once per this, the wait doubling up to 8x while such searches find nothing better. "
          "0 = off.", range=(0.0, 3600.0)),
    Param("confidence_temperature", 3.0, "Temperature (nats) of the local label posterior behind "
          "the published confidences (see labeling/confidence.py); the calibrated constant.",
          range=(0.01, 1000.0)),
    Param("seed", 0, "Random seed of the searches (reproducible runs).", range=(0, INT_MAX), flag="--seed"),
    # -- tracker -------------------------------------------------------------------------------
    Param("gate_m", TrackerSettings.gate_m, "Tracker association radius in metres of a track seen "
          "only once (no velocity yet: the point may have moved several centimetres).",
          range=(0.0001, 100.0)),
    Param("known_gate_m", TrackerSettings.known_gate_m, "Tracker association radius in metres of a "
          "track whose velocity is known (grows with the track's speed); smaller, so a neighbour in a "
          "dense marker cluster does not take over a track while its marker is hidden.",
          range=(0.0001, 100.0)),
    Param("gate_speed_factor", TrackerSettings.gate_speed_factor, "Gate growth per metre of "
          "predicted travel between frames.", range=(0.0, 100.0)),
    Param("max_misses", TrackerSettings.max_misses, "Frames a lost track coasts (and is predicted) "
          "before it is deleted.", range=(0, 100000)),
    Param("accel_mps2", TrackerSettings.accel_mps2, "Largest marker acceleration (m/s^2) the tracker "
          "allows off its constant-velocity prediction: the gate grows by accel dt^2 / 2, so tracks "
          "survive frames a slow consumer skipped.", range=(0.0, 10000.0)),
    Param("new_track_speed_mps", TrackerSettings.new_track_speed_mps, "Speed (m/s) a track seen only "
          "once may have moved at (its velocity is not known yet).", range=(0.0, 100.0)),
    # -- clutter model ---------------------------------------------------------------------------
    Param("clutter_volume_m3", Background.volume_m3, "Capture volume (m^3) of the uniform "
          "clutter/ghost position density.", range=(1e-6, 1e9)),
    Param("clutter_max_speed_mps", Background.max_speed_mps, "Clutter velocities are uniform "
          "within +-this (m/s) per axis.", range=(1e-6, 1e6)),
    Param("detection_probability", Background.detection_probability, "Probability that a "
          "body marker is seen in a frame (missing-marker prior); in (0, 1).", range=(0.001, 0.999)),
    Param("clutter_fixed_share", Background.fixed_share, "Share of the clutter velocity density "
          "that is fixed reflections (floor tape, a prop): a Gaussian about 0 of clutter_fixed_speed_mps, "
          "so a point that has stayed put longer than its label ever did in training (and than "
          "clutter_fixed_after_s) is not taken for a marker whose neighbours are hidden (0.002: a "
          "perfectly still point's gain -9 nats). 0 = uniform clutter (the paper's).",
          range=(0.0, 0.999)),
    Param("clutter_fixed_speed_mps", Background.fixed_speed_mps, "Measured speed spread (m/s per "
          "axis) of a fixed reflection; raise it for noisy systems (1 mm at 120 Hz: 0.17).",
          range=(1e-6, 100.0)),
    Param("clutter_fixed_after_s", Background.fixed_after_s, "A point is scored as possibly a fixed "
          "reflection only once it has stayed within 1 cm this long (s) and 1.5 x its label's "
          "longest rest in the training takes (a foot in stance: under a second in a walk). "
          "0 with a model without training rests = every still point.", range=(0.0, 3600.0)),
    # -- input bounds ------------------------------------------------------------------------------
    Param("max_points", 0, "At most this many points (nearest the body) enter the "
          "search; the rest are published unlabelled. 0 = 2 x labels + 8.", range=(0, 1000000)),
    Param("noise_mm", 0.0, "Measurement noise of the capture system (sd per coordinate, "
          "mm). The model is widened by it (relative positions and velocities); 0 = the model's "
          "own floor only. Set it for noisy systems: 10 mm undeclared makes true labelings look "
          "impossible.", range=(0.0, 500.0), flag="--assume-noise-mm"),
    Param("heading_snap_deg", 4.0, "Candidate labelings whose facing is within "
          "this (degrees) of the carried labeling's are scored at its facing: a one-marker move "
          "then costs only its own triangles. 0 = every candidate at its own facing.", range=(0.0, 30.0)),
    Param("max_gap_s", 0.5, "An input gap (header stamps) longer than this resets the "
          "window and tracks.", range=(0.001, 1e6)),
    # -- bank (Ukita) --------------------------------------------------------------------------
    Param("bank_strategy", "spread", "spread: the population over all action models with migration; "
          "hard: one model at a time, switched to the best after every frame.", "bank", choices=STRATEGIES,
          flag="--bank-strategy"),
    Param("migration_temperature", 1.0, "Migration temperature tau (nats per labelled point) of "
          "Ukita's rule between action models.", "bank", range=(1e-6, 1e6)),
    Param("min_share", 4, "GA individuals every action model keeps.", "bank", range=(1, 4096)),
    Param("score_temperature", 4.0, "Tempering of the action evidence (nats per labelled point).", "bank",
          range=(1e-6, 1e6)),
    Param("switch_rate_hz", 1.0, "Prior rate of action changes (stickiness of the active action).", "bank",
          range=(1e-6, 1e6)),
    Param("default_action", "", "Action active at the start (and the only one when use_bank is false "
          "on a bank); empty = the first.", "bank"),
    Param("search_on_switch", True, "Full search in the frame after the active action changes.", "bank"),
    # -- I/O (node) ----------------------------------------------------------------------------
    Param("input_type", "pointcloud2", "Message type of markers/unlabeled: pointcloud2 "
          "(sensor_msgs/PointCloud2: IMRCLab motion_capture_tracking, bags), mocap4r2_markers "
          "(mocap4r2_msgs/Markers: mocap4r2 OptiTrack/Qualisys/Vicon drivers), pointcloud "
          "(sensor_msgs/PointCloud: natnet_ros2). Changing it recreates the subscription.", "node",
          choices=INPUT_TYPES),
    Param("mocap4r2_ids", "auto", "Track ids from mocap4r2 markers: auto (marker names when "
          "every marker has a unique one -- Vicon; list indices are ignored: OptiTrack and "
          "Qualisys number markers by list position), name, index (marker_index, for drivers "
          "whose indices persist), none (the node tracks by position).", "node", choices=MOCAP4R2_IDS),
    Param("stamp_source", "auto", "Time the labeler runs on: auto (header stamps; after "
          "stamp faults -- zero, repeated, backwards, jumping -- receive time at the frame "
          "rate, back to stamps once they are clean), header, receive.", "node", choices=STAMP_SOURCES),
    Param("frame_id", "", "frame_id of the outputs when the input's is empty (or always, "
          "with override_frame_id); empty = the input's.", "node"),
    Param("override_frame_id", False, "Use frame_id for every output, whatever the input says.", "node"),
    Param("input_qos", "sensor_data", "QoS of markers/unlabeled: sensor_data (best effort) or "
          "reliable. Changing it (or input_depth) recreates the subscription.", "node", choices=QOS_CHOICES),
    Param("input_depth", 5, "History depth (keep-last) of the input subscription; the node "
          "itself keeps only the newest cloud.", "node", range=(1, 1000)),
    Param("output_qos", "reliable", "QoS of the published topics: reliable or sensor_data "
          "(best effort). Start-up only.", "node", choices=QOS_CHOICES, read_only=True),
    Param("output_depth", 10, "History depth of the published topics. Start-up only.", "node",
          range=(1, 1000), read_only=True),
    Param("publish_cloud", True, "Publish markers/labeled_cloud (PointCloud2 x,y,z,label,"
          "confidence) -- built only while it has subscribers.", "node"),
    Param("publish_visualization", True, "Publish markers/visualization (RViz MarkerArray) -- "
          "built only while it has subscribers.", "node"),
    Param("visualization_period_s", 0.033, "Minimum header-stamp interval between visualization "
          "messages (0 = every frame; the default gives RViz about 30 Hz and saves the "
          "MarkerArray cost on most frames of a 120 Hz stream).", "node", range=(0.0, 3600.0)),
    Param("marker_scale", 0.05, "Sphere diameter of the RViz markers in metres.", "node", range=(0.001, 10.0)),
    Param("viz_marker_lifetime_s", 1.0, "Lifetime of the RViz markers (s): RViz drops them this "
          "long after the last update, so a stopped node leaves no stale markers. 0 = for ever.", "node",
          range=(0.0, 3600.0)),
    Param("viz_namespace", "dtm_labeler", "Namespace prefix of the RViz markers (<ns>/labelled, "
          "<ns>/skeleton, ...).", "node"),
    Param("publish_mocap4r2", True, "Publish markers/labeled_mocap4r2 (mocap4r2_msgs/Markers, "
          "marker_name = label) -- built only while it has subscribers and mocap4r2_msgs is "
          "installed.", "node"),
    Param("carry_max_ms", 30.0, "A cloud that arrived while a search ran is published afterwards, "
          "with the labels its tracks carry, if it is at most this old then (ms); older ones are "
          "only followed by the tracker and counted stale. Bounds the lateness of carried frames "
          "when labeling cannot keep up (0 = never carry: newest cloud only).", "node",
          range=(0.0, 10000.0)),
    Param("publish_occluded", True, "Add an occluded=true, predicted=true LabeledMarker for "
          "every model label missing this frame whose track can still be predicted.", "node"),
    Param("diagnostics_period_s", 1.0, "Period of the /diagnostics status (steady clock).", "node",
          range=(0.01, 3600.0)),
    Param("calibration_s", 5.0, "Seconds of stream the ~/calibrate service collects: the labels "
          "confirmed in that time (confidence >= 0.5 with the release counted in full) set the "
          "subject's body terms (segment lengths, reach scale; training/calibrate.py), then the calibrated model replaces the "
          "running one without a reset. Any motion; the model must have body terms.", "node",
          range=(0.5, 120.0)),
    Param("auto_calibrate", False, "Self-calibrate a generic body (not yet calibrated to a person; a body "
          "dtm-train calibrated to its training takes' person counts as generic again: the streaming "
          "person is not known) on the first calibration_s seconds of stream after each model load, as "
          "dtm-label does by default: "
          "the model's own confirmed labels set the segment lengths (in a process of its own, at idle "
          "priority), and the calibrated model replaces the running one without a reset only when it keeps "
          ">= 90 % of those labels on the same frames (training/calibrate.py auto_calibrate); /diagnostics "
          "'calibration' says what was done.", "node"),
    Param("latency_window", 500, "Frames over which the latency percentiles in /diagnostics are "
          "computed.", "node", range=(1, 1000000)),
)

SPECS: Dict[str, Param] = {p.name: p for p in PARAMS}
DEFAULTS: Dict[str, Any] = {p.name: (list(p.default) if isinstance(p.default, (list, tuple)) else p.default)
                            for p in PARAMS}
LABELER_KEYS = frozenset(p.name for p in PARAMS if p.layer == "labeler")
BANK_KEYS = frozenset(p.name for p in PARAMS if p.layer == "bank")


def check_fields(obj, names: Mapping[str, str] | None = None) -> None:
    """Validate (and normalise) the fields of a settings dataclass that are table parameters:
    a field named like a parameter, or mapped to one by ``names`` (field -> parameter)."""
    names = names or {}
    for f in fields(obj):
        name = names.get(f.name, f.name)
        if name in SPECS:
            setattr(obj, f.name, SPECS[name].check(getattr(obj, f.name)))


@dataclass
class LabelerSettings:
    """Everything the labeler reads (defaults and ranges from :data:`PARAMS`)."""

    method: str = DEFAULTS["method"]
    mode: str = DEFAULTS["mode"]
    window: int = DEFAULTS["window"]
    full: GASettings = field(default_factory=lambda: replace(_FULL))
    warm: GASettings = field(default_factory=lambda: replace(_WARM))
    background: Background = field(default_factory=Background)
    tracker: TrackerSettings = field(default_factory=TrackerSettings)
    max_points: int = DEFAULTS["max_points"]
    refit_drop: float = DEFAULTS["refit_drop"]
    restarts: int = DEFAULTS["restarts"]
    accept_drop: float = DEFAULTS["accept_drop"]
    fast_rounds: int = DEFAULTS["fast_rounds"]
    swap_radius_m: float = DEFAULTS["swap_radius_m"]
    release_moves: bool = DEFAULTS["release_moves"]
    chain_moves: int = DEFAULTS["chain_moves"]
    mirror_switch_nats: float = DEFAULTS["mirror_switch_nats"]
    cluster_turns: bool = DEFAULTS["cluster_turns"]
    hold_nats: float = DEFAULTS["hold_nats"]
    hold_s: float = DEFAULTS["hold_s"]
    cluster_memory_s: float = DEFAULTS["cluster_memory_s"]
    bar_order_gain: float = DEFAULTS["bar_order_gain"]
    turn_check: bool = DEFAULTS["turn_check"]
    upright_deg: float = DEFAULTS["upright_deg"]
    bend_starts: int = DEFAULTS["bend_starts"]
    region_checks: int = DEFAULTS["region_checks"]
    region_size: int = DEFAULTS["region_size"]
    region_every: int = DEFAULTS["region_every"]
    young_checks: int = DEFAULTS["young_checks"]
    young_candidates: int = DEFAULTS["young_candidates"]
    region_branches: int = DEFAULTS["region_branches"]
    max_gap_s: float = DEFAULTS["max_gap_s"]
    noise_mm: float = DEFAULTS["noise_mm"]
    heading_snap_deg: float = DEFAULTS["heading_snap_deg"]
    recovery: str = DEFAULTS["recovery"]
    misfit_nats: float = DEFAULTS["misfit_nats"]
    audit_period_s: float = DEFAULTS["audit_period_s"]
    confidence_temperature: float = DEFAULTS["confidence_temperature"]
    seed: int = DEFAULTS["seed"]

    def __post_init__(self) -> None:
        check_fields(self)


def validate(values: Mapping[str, Any]) -> Dict[str, Any]:
    """Check a full parameter set (missing keys take their defaults; unknown keys are errors).
    Returns the normalised values; ValueError names the parameter."""
    unknown = sorted(set(values) - set(SPECS))
    if unknown:
        raise ValueError(f"unknown parameter(s): {', '.join(unknown)}")
    out = dict(DEFAULTS)
    for name, value in values.items():
        out[name] = SPECS[name].check(value)
    if len(set(out["expected_labels"])) != len(out["expected_labels"]):
        raise ValueError("expected_labels contains duplicate names")
    return out


def settings_from_params(values: Mapping[str, Any]) -> LabelerSettings:
    """The :class:`LabelerSettings` of a parameter set (validated first; missing keys take
    their defaults). ValueError from the table or the settings classes' own checks."""
    v = validate(values)
    budget = v["time_budget_ms"] / 1e3 if v["time_budget_ms"] > 0 else None
    full = replace(_FULL, population=v["population"], max_generations=v["max_generations"],
                   stagnation=v["stagnation"], n_elite=min(_FULL.n_elite, v["population"] - 1),
                   time_budget_s=budget, region_size=v["region_size"], fresh_fraction=v["fresh_fraction"],
                   region_sweeps=v["region_sweeps"], region_branches=v["sweep_branches"],
                   wide_sweeps=v["wide_sweeps"], mirror_sweeps=v["mirror_sweeps"],
                   mirror_branches=v["mirror_branches"], fresh_starts=v["fresh_starts"])
    warm = replace(_WARM, population=v["warm_population"], max_generations=v["warm_generations"],
                   stagnation=v["warm_stagnation"], n_elite=min(_WARM.n_elite, v["warm_population"] - 1),
                   time_budget_s=budget)
    direct = {f.name: v[f.name] for f in fields(LabelerSettings) if f.name in SPECS}
    return LabelerSettings(
        full=full, warm=warm,
        background=Background(volume_m3=v["clutter_volume_m3"], max_speed_mps=v["clutter_max_speed_mps"],
                              detection_probability=v["detection_probability"],
                              fixed_share=v["clutter_fixed_share"], fixed_speed_mps=v["clutter_fixed_speed_mps"],
                              fixed_after_s=v["clutter_fixed_after_s"]),
        tracker=TrackerSettings(gate_m=v["gate_m"], known_gate_m=v["known_gate_m"],
                                gate_speed_factor=v["gate_speed_factor"],
                                max_misses=v["max_misses"], accel_mps2=v["accel_mps2"],
                                new_track_speed_mps=v["new_track_speed_mps"]), **direct)


def params_from_settings(settings: LabelerSettings) -> Dict[str, Any]:
    """The flat labeler parameters of ``settings`` (inverse of :func:`settings_from_params`)."""
    s = settings
    out = {f.name: getattr(s, f.name) for f in fields(LabelerSettings) if f.name in SPECS}
    out.update(population=s.full.population, max_generations=s.full.max_generations, stagnation=s.full.stagnation,
               time_budget_ms=(s.full.time_budget_s or 0.0) * 1e3, warm_population=s.warm.population,
               warm_generations=s.warm.max_generations, warm_stagnation=s.warm.stagnation,
               fresh_fraction=s.full.fresh_fraction, region_sweeps=s.full.region_sweeps,
               wide_sweeps=s.full.wide_sweeps, mirror_sweeps=s.full.mirror_sweeps,
               mirror_branches=s.full.mirror_branches, sweep_branches=s.full.region_branches,
               fresh_starts=s.full.fresh_starts,
               gate_m=s.tracker.gate_m, known_gate_m=s.tracker.known_gate_m,
               gate_speed_factor=s.tracker.gate_speed_factor,
               max_misses=s.tracker.max_misses, accel_mps2=s.tracker.accel_mps2,
               new_track_speed_mps=s.tracker.new_track_speed_mps, clutter_volume_m3=s.background.volume_m3,
               clutter_max_speed_mps=s.background.max_speed_mps,
               detection_probability=s.background.detection_probability,
               clutter_fixed_share=s.background.fixed_share, clutter_fixed_speed_mps=s.background.fixed_speed_mps,
               clutter_fixed_after_s=s.background.fixed_after_s)
    return out


def settings_equal(a: Any, b: Any) -> bool:
    """Equality of (nested) settings dataclasses that may hold numpy arrays."""
    if is_dataclass(a) and is_dataclass(b):
        return type(a) is type(b) and all(settings_equal(getattr(a, f.name), getattr(b, f.name))
                                          for f in fields(a))
    if hasattr(a, "shape") or hasattr(b, "shape"):
        return bool(np.array_equal(np.asarray(a), np.asarray(b)))
    return a == b


def check_labels(model_labels: Sequence[str], expected: Iterable[str], where: str = "model") -> None:
    """Raise ValueError when ``expected`` is non-empty and differs from the model's labels."""
    expected = list(expected or [])
    labels = list(model_labels)
    if expected and labels != expected:
        missing = [x for x in expected if x not in labels]
        extra = [x for x in labels if x not in expected]
        detail = []
        if missing:
            detail.append(f"missing {', '.join(missing)}")
        if extra:
            detail.append(f"unexpected {', '.join(extra)}")
        if not detail:
            detail.append("same names in a different order")
        raise ValueError(f"{where} has labels [{', '.join(labels)}], expected_labels are "
                         f"[{', '.join(expected)}] ({'; '.join(detail)})")


# -- files and flags ---------------------------------------------------------------------------
def load_params_file(path: str | Path, node_name: str = NODE_NAME) -> Dict[str, Any]:
    """The ``ros__parameters`` a ROS 2 params file gives node ``node_name`` (``/**`` wildcard
    entries first, then ``name`` / ``/name`` ones override), as a plain dict. A plain
    mapping of parameter names (no node key) is accepted too."""
    import yaml
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError) as e:
        raise ValueError(f"params file {path}: {e}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"params file {path}: expected a mapping")
    out: Dict[str, Any] = {}
    bare = node_name.lstrip("/")
    for key in ("/**", "**", bare, "/" + bare):
        block = doc.get(key)
        if isinstance(block, dict) and isinstance(block.get("ros__parameters"), dict):
            out.update(block["ros__parameters"])
    if not out and all(k in SPECS for k in doc):
        out = dict(doc)
    return out


def add_arguments(parser: argparse.ArgumentParser, layers: Sequence[str] = ("labeler",)) -> None:
    """The table's command-line flags for ``layers`` plus ``--params-file``. Flag defaults
    are left unset, so a params file is overridden only by flags actually given."""
    parser.add_argument("--params-file", default=None, metavar="YAML",
                        help="node parameters file (params/labeler.yaml format, e.g. tuned on the live node); "
                             "flags given on the command line override it")
    for p in PARAMS:
        if p.flag is None or p.layer not in layers:
            continue
        kind = {"int": int, "double": float, "string": str}[p.kind]
        parser.add_argument(p.flag, dest=f"param_{p.name}", type=kind, default=argparse.SUPPRESS, choices=p.choices,
                            metavar=None if p.choices else p.name.upper(),
                            help=f"{p.description} (default {format_value(p.default)})")


def params_from_args(args: argparse.Namespace, layers: Sequence[str] = ("labeler",)) -> Dict[str, Any]:
    """The parameters of ``--params-file`` (those of ``layers``) overridden by the flags given."""
    values = {}
    if getattr(args, "params_file", None):
        values = {k: v for k, v in load_params_file(args.params_file).items()
                  if k in SPECS and SPECS[k].layer in layers}
    for p in PARAMS:
        given = getattr(args, f"param_{p.name}", None)
        if given is not None and p.layer in layers:
            values[p.name] = given
    return values


def format_value(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(str(v) for v in value) + "]"
    return str(value)


def _yaml_scalar(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(json.dumps(x) for x in v) + "]"
    return repr(v) if isinstance(v, float) else str(v)


def render_yaml(key: str = "/**") -> str:
    """The text of params/labeler.yaml: every parameter, its description and default."""
    lines = [
        "# dtm_labeler parameters: every parameter with its default (node, dtm-label --params-file,",
        "# dtm-bag label --params-file). Generated by",
        "# `python -m dtm_labeler.labeling.config --write-yaml params/labeler.yaml`; edit the table in",
        "# dtm_labeler/labeling/config.py, not this file.",
        "# Use:  dtm-labeler-node --ros-args --params-file params/labeler.yaml -p model_path:=/path/model.npz",
        "# The block is keyed /** (every node of the process, so also a node started in a namespace or",
        "# under another name: a key 'dtm_labeler' would not match /ns/dtm_labeler). To target one node",
        "# of a shared file, key it by the node's full name (/ns/dtm_labeler). Every parameter can be",
        "# changed at runtime through the parameter services except the read-only ones; ranges are",
        "# inclusive. set_parameters applies values one by one; set_parameters_atomically all or none.",
        f"{key}:", "  ros__parameters:"]
    for p in PARAMS:
        extra = [f"layer {p.layer}"]
        if p.range:
            extra.append(f"range [{p.range[0]}, {p.range[1]}]")
        if p.choices:
            extra.append("one of " + "|".join(p.choices))
        if p.read_only:
            extra.append("read-only: start-up only")
        text = p.description + " (" + "; ".join(extra) + ")"
        lines += ["    # " + line for line in textwrap.wrap(text, 92)]
        lines.append(f"    {p.name}: {_yaml_scalar(p.default)}")
    return "\n".join(lines) + "\n"


__all__ = ["Param", "PARAMS", "SPECS", "DEFAULTS", "LABELER_KEYS", "BANK_KEYS", "NODE_NAME", "METHODS", "MODES", "RECOVERY",
           "STRATEGIES", "QOS_CHOICES", "LabelerSettings", "check_fields", "validate", "settings_from_params", "params_from_settings",
           "settings_equal", "check_labels", "load_params_file", "add_arguments", "params_from_args",
           "format_value", "render_yaml"]


if __name__ == "__main__":  # pragma: no cover - maintenance entry point
    import sys
    if len(sys.argv) == 3 and sys.argv[1] == "--write-yaml":
        Path(sys.argv[2]).write_text(render_yaml(), encoding="utf-8")
        print(f"wrote {sys.argv[2]}")
    else:
        sys.stdout.write(render_yaml())
