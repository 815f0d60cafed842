"""The node's parameters: one table, the mapping to :class:`LabelerSettings`, validation.

Pure Python (no rclpy at import time), so the mapping is unit-testable without a node. The
node (:mod:`dtm_labeler.ros.node`) declares every entry of :data:`PARAMS` with a
``ParameterDescriptor`` built by :func:`descriptor` (description, range, read_only), and its
on-set-parameters callback runs :func:`validate` + :func:`settings_from_params` on the WHOLE
resulting configuration: a value that is bad on its own, or bad together with the others, is
rejected with the reason and changes nothing.

What "a set" is follows rclpy (checked on rclpy 7.1): ``set_parameters`` (the
``~/set_parameters`` service, ``ros2 param set``, ``ros2 param load``) applies its parameters
ONE BY ONE -- the callback sees each alone, against the values already applied, so the good
ones of a list are applied and only the bad ones rejected (and a change that needs two values
at once, e.g. ``model_path`` with new ``expected_labels``, must be ordered or made atomic).
Only ``set_parameters_atomically`` (``~/set_parameters_atomically``) is all-or-nothing: one
callback with every value, and one bad value applies none.

``params/labeler.yaml`` holds every parameter with its default; it is generated from the table
(``python -m dtm_labeler.ros.params --write-yaml params/labeler.yaml``) and a test checks it
matches :data:`DEFAULTS` -- the search/tracker defaults follow :class:`LabelerSettings`, so
regenerate the file when those change.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Dict, Iterable, Mapping, Optional, Sequence, Tuple

from ..search.problem import Background
from ..labeling.stream import METHODS, MODES, LabelerSettings
from ..labeling.tracker import TrackerSettings
from .inputs import INPUT_TYPES, MOCAP4R2_IDS
from .stamps import STAMP_SOURCES

__all__ = ["ParamSpec", "PARAMS", "SPECS", "DEFAULTS", "NODE_NAME", "QOS_CHOICES", "LABELER_KEYS",
           "INPUT_QOS_KEYS", "INPUT_KEYS", "validate", "settings_from_params", "check_labels", "descriptor",
           "qos_profile", "load_params_file", "format_value", "settings_equal", "render_yaml"]

NODE_NAME = "dtm_labeler"
QOS_CHOICES = ("sensor_data", "reliable")
INT_MAX = 2 ** 31 - 1


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter. ``range`` is inclusive ``(lo, hi)`` for numbers; ``choices`` for
    strings; ``read_only`` ones can only be given at start-up (params file / ``-p``)."""

    name: str
    default: Any
    description: str
    range: Optional[Tuple[float, float]] = None
    choices: Optional[Tuple[str, ...]] = None
    read_only: bool = False

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


_D = LabelerSettings()   # the library defaults; the table below repeats them (a test checks)

PARAMS: Tuple[ParamSpec, ...] = (
    # -- model ------------------------------------------------------------------------------
    ParamSpec("model_path", "", "Model file (.npz from dtm-train). Setting it at runtime hot-reloads "
              "the model; a file that cannot be loaded (or whose labels differ from expected_labels) "
              "is rejected and the running model is kept. Empty = no model (nothing is labelled)."),
    ParamSpec("expected_labels", [], "Label names the model must have, in order; empty = accept any "
              "model. A model whose labels differ is rejected."),
    ParamSpec("model_name", "", "Name published as LabeledMarkerArray.active_model (e.g. 'walk'); "
              "empty for a single-model labeler."),
    ParamSpec("bank_path", "", "Model bank (directory with bank.json, or single-file bank .npz, from "
              "dtm-train --action NAME --bank DIR): one model per action, all used at once (Ukita). "
              "Loaded when use_bank is true; setting it at runtime hot-reloads the bank."),
    ParamSpec("use_bank", False, "Label with the model bank at bank_path instead of model_path; the "
              "active action is published as LabeledMarkerArray.active_model and in /diagnostics."),
    # -- search ------------------------------------------------------------------------------
    ParamSpec("method", _D.method, "Label search: cbga (constraint-based GA, the paper's), sga "
              "(simple GA), greedy (DP over the DTM), exhaustive (tiny models only), tracker "
              "(carry labels along tracks, search only when lost).", choices=METHODS),
    ParamSpec("mode", _D.mode, "stream: warm-started search + per-track votes over the window; "
              "single: every frame labelled from scratch.", choices=MODES),
    ParamSpec("window", _D.window, "Frames in the sliding vote window (eq. 32).", range=(1, 10000)),
    ParamSpec("population", _D.full.population, "Population of the full (cold) GA search.",
              range=(4, 4096)),
    ParamSpec("max_generations", _D.full.max_generations, "Generation cap of the full GA search.",
              range=(0, 100000)),
    ParamSpec("stagnation", _D.full.stagnation, "Full GA stops after this many generations without "
              "improvement.", range=(1, 100000)),
    ParamSpec("time_budget_ms", 0.0, "Time budget per GA search in ms (full and warm); 0 = none.",
              range=(0.0, 60000.0)),
    ParamSpec("warm_population", _D.warm.population, "Population of the warm-started GA (stream "
              "mode, labels carried over from the last frame).", range=(4, 4096)),
    ParamSpec("warm_generations", _D.warm.max_generations, "Generation cap of the warm GA.",
              range=(0, 100000)),
    ParamSpec("warm_stagnation", _D.warm.stagnation, "Warm GA stops after this many generations "
              "without improvement.", range=(1, 100000)),
    ParamSpec("refit_drop", _D.refit_drop, "A warm result this many nats below the running fitness "
              "level triggers a full search.", range=(0.001, 1e9)),
    ParamSpec("restarts", _D.restarts, "Full GA searches repeated from fresh populations (at most "
              "this many more) while the best still falls refit_drop short of the level.",
              range=(0, 16)),
    ParamSpec("accept_drop", _D.accept_drop, "The carried-over labeling is accepted without a GA "
              "when within this many nats of the running level.", range=(0.001, 1e9)),
    ParamSpec("region_checks", _D.region_checks, "Body regions relabelled exactly (max-product DP "
              "given the rest of the body) per frame while checks are due (one pass over the "
              "regions after a GA search, then every region_every frames); repairs a wrong "
              "labeling that tracking carries on. 0 = off.", range=(0, 64)),
    ParamSpec("region_every", _D.region_every, "Background region check every this many frames "
              "in steady state (0 = only after GA searches).", range=(0, 1000000)),
    ParamSpec("region_size", _D.region_size, "Labels per region of the region checks and of the "
              "full search's final region sweep (more = "
              "larger repairs, more work per frame).", range=(2, 16)),
    ParamSpec("seed", _D.seed, "Random seed of the searches (reproducible runs).", range=(0, INT_MAX)),
    # -- tracker ------------------------------------------------------------------------------
    ParamSpec("gate_m", _D.tracker.gate_m, "Tracker association radius in metres (grows with the "
              "track's speed).", range=(0.0001, 100.0)),
    ParamSpec("gate_speed_factor", _D.tracker.gate_speed_factor, "Gate growth per metre of "
              "predicted travel between frames.", range=(0.0, 100.0)),
    ParamSpec("max_misses", _D.tracker.max_misses, "Frames a lost track coasts (and is predicted) "
              "before it is deleted.", range=(0, 100000)),
    # -- clutter model ---------------------------------------------------------------------------
    ParamSpec("clutter_volume_m3", _D.background.volume_m3, "Capture volume (m^3) of the uniform "
              "clutter/ghost position density.", range=(1e-6, 1e9)),
    ParamSpec("clutter_max_speed_mps", _D.background.max_speed_mps, "Clutter velocities are uniform "
              "within +-this (m/s) per axis.", range=(1e-6, 1e6)),
    ParamSpec("detection_probability", _D.background.detection_probability, "Probability that a "
              "body marker is seen in a frame (missing-marker prior); in (0, 1).",
              range=(0.001, 0.999)),
    # -- input bounds ------------------------------------------------------------------------------
    ParamSpec("max_points", _D.max_points, "At most this many points (nearest the body) enter the "
              "search; the rest are published unlabelled. 0 = 2 x labels + 8.", range=(0, 1000000)),
    ParamSpec("noise_mm", _D.noise_mm, "Measurement noise of the capture system (sd per coordinate, "
              "mm). The model is widened by it (relative positions and velocities); 0 = the model's "
              "own floor only. Set it for noisy systems: 10 mm undeclared makes true labelings look "
              "impossible.", range=(0.0, 500.0)),
    ParamSpec("heading_snap_deg", _D.heading_snap_deg, "Candidate labelings whose facing is within "
              "this (degrees) of the carried labeling's are scored at its facing: a one-marker move "
              "then costs only its own triangles. 0 = every candidate at its own facing.",
              range=(0.0, 30.0)),
    ParamSpec("max_gap_s", _D.max_gap_s, "An input gap (header stamps) longer than this resets the "
              "window and tracks.", range=(0.001, 1e6)),
    # -- I/O --------------------------------------------------------------------------------
    ParamSpec("input_type", "pointcloud2", "Message type of markers/unlabeled: pointcloud2 "
              "(sensor_msgs/PointCloud2: IMRCLab motion_capture_tracking, bags), mocap4r2_markers "
              "(mocap4r2_msgs/Markers: mocap4r2 OptiTrack/Qualisys/Vicon drivers), pointcloud "
              "(sensor_msgs/PointCloud: natnet_ros2). Changing it recreates the subscription.",
              choices=INPUT_TYPES),
    ParamSpec("mocap4r2_ids", "auto", "Track ids from mocap4r2 markers: auto (marker names when "
              "every marker has a unique one -- Vicon; list indices are ignored: OptiTrack and "
              "Qualisys number markers by list position), name, index (marker_index, for drivers "
              "whose indices persist), none (the node tracks by position).", choices=MOCAP4R2_IDS),
    ParamSpec("stamp_source", "auto", "Time the labeler runs on: auto (header stamps; after "
              "stamp faults -- zero, repeated, backwards, jumping -- receive time at the frame "
              "rate, back to stamps once they are clean), header, receive.", choices=STAMP_SOURCES),
    ParamSpec("frame_id", "", "frame_id of the outputs when the input's is empty (or always, "
              "with override_frame_id); empty = the input's."),
    ParamSpec("override_frame_id", False, "Use frame_id for every output, whatever the input "
              "says."),
    ParamSpec("input_qos", "sensor_data", "QoS of markers/unlabeled: sensor_data (best effort) or "
              "reliable. Changing it (or input_depth) recreates the subscription.", choices=QOS_CHOICES),
    ParamSpec("input_depth", 5, "History depth (keep-last) of the input subscription; the node "
              "itself keeps only the newest cloud.", range=(1, 1000)),
    ParamSpec("output_qos", "reliable", "QoS of the published topics: reliable or sensor_data "
              "(best effort). Start-up only.", choices=QOS_CHOICES, read_only=True),
    ParamSpec("output_depth", 10, "History depth of the published topics. Start-up only.",
              range=(1, 1000), read_only=True),
    ParamSpec("publish_cloud", True, "Publish markers/labeled_cloud (PointCloud2 x,y,z,label,"
              "confidence) -- built only while it has subscribers."),
    ParamSpec("publish_visualization", True, "Publish markers/visualization (RViz MarkerArray) -- "
              "built only while it has subscribers."),
    ParamSpec("visualization_period_s", 0.033, "Minimum header-stamp interval between visualization "
              "messages (0 = every frame; the default gives RViz about 30 Hz and saves the "
              "MarkerArray cost on most frames of a 120 Hz stream).", range=(0.0, 3600.0)),
    ParamSpec("marker_scale", 0.05, "Sphere diameter of the RViz markers in metres.",
              range=(0.001, 10.0)),
    ParamSpec("viz_marker_lifetime_s", 1.0, "Lifetime of the RViz markers (s): RViz drops them "
              "this long after the last update, so a stopped node leaves no stale markers. 0 = "
              "for ever.", range=(0.0, 3600.0)),
    ParamSpec("viz_namespace", "dtm_labeler", "Namespace prefix of the RViz markers "
              "(<ns>/labelled, <ns>/skeleton, ...)."),
    ParamSpec("publish_mocap4r2", True, "Publish markers/labeled_mocap4r2 (mocap4r2_msgs/Markers, "
              "marker_name = label) -- built only while it has subscribers and mocap4r2_msgs is "
              "installed."),
    ParamSpec("publish_occluded", True, "Add an occluded=true, predicted=true LabeledMarker for "
              "every model label missing this frame whose track can still be predicted."),
    ParamSpec("diagnostics_period_s", 1.0, "Period of the /diagnostics status (steady clock).",
              range=(0.01, 3600.0)),
    ParamSpec("latency_window", 500, "Frames over which the latency percentiles in /diagnostics are "
              "computed.", range=(1, 1000000)),
)

SPECS: Dict[str, ParamSpec] = {p.name: p for p in PARAMS}
DEFAULTS: Dict[str, Any] = {p.name: (list(p.default) if isinstance(p.default, (list, tuple))
                                     else p.default) for p in PARAMS}
#: Parameters that change LabelerSettings (the rest are node-only).
LABELER_KEYS = frozenset({
    "method", "mode", "window", "population", "max_generations", "stagnation", "time_budget_ms",
    "warm_population", "warm_generations", "warm_stagnation", "refit_drop", "restarts", "accept_drop", "seed",
    "region_checks", "region_size", "region_every",
    "gate_m", "gate_speed_factor", "max_misses", "clutter_volume_m3", "clutter_max_speed_mps",
    "detection_probability", "max_points", "max_gap_s", "noise_mm", "heading_snap_deg"})
INPUT_QOS_KEYS = frozenset({"input_qos", "input_depth"})
#: Parameters whose change recreates the input subscription.
INPUT_KEYS = INPUT_QOS_KEYS | {"input_type"}


def _check_one(spec: ParamSpec, value: Any) -> Any:
    """Type/range/choice check of one value; returns it normalised (int->float for doubles,
    None->[] for an unset string array)."""
    kind = spec.kind
    name = spec.name
    if kind == "bool":
        if not isinstance(value, bool):
            raise ValueError(f"{name} must be a bool, got {value!r}")
    elif kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{name} must be an integer, got {value!r}")
    elif kind == "double":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{name} must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value!r}")
    elif kind == "string":
        if not isinstance(value, str):
            raise ValueError(f"{name} must be a string, got {value!r}")
    elif kind == "string_array":
        if value is None:
            value = []
        if isinstance(value, str) or not all(isinstance(v, str) for v in value):
            raise ValueError(f"{name} must be a list of strings, got {value!r}")
        value = list(value)
    if spec.range is not None and not spec.range[0] <= value <= spec.range[1]:
        raise ValueError(f"{name} = {value!r} is out of range [{spec.range[0]}, {spec.range[1]}]")
    if spec.choices is not None and value not in spec.choices:
        raise ValueError(f"{name} must be one of {', '.join(spec.choices)}, got {value!r}")
    return value


def validate(values: Mapping[str, Any]) -> Dict[str, Any]:
    """Check a full parameter set (missing keys take their defaults; unknown keys are errors).

    Returns the normalised values. Raises ValueError with a message naming the parameter.
    """
    unknown = sorted(set(values) - set(SPECS))
    if unknown:
        raise ValueError(f"unknown parameter(s): {', '.join(unknown)}")
    out = dict(DEFAULTS)
    for name, value in values.items():
        out[name] = _check_one(SPECS[name], value)
    if len(set(out["expected_labels"])) != len(out["expected_labels"]):
        raise ValueError("expected_labels contains duplicate names")
    return out


def settings_from_params(values: Mapping[str, Any]) -> LabelerSettings:
    """The :class:`LabelerSettings` of a parameter set (validated first; missing keys take
    their defaults). Raises ValueError (the settings classes' own checks included)."""
    v = validate(values)
    budget = v["time_budget_ms"] / 1e3 if v["time_budget_ms"] > 0 else None
    d = LabelerSettings()
    # replace() keeps every other GA setting at the library default (whatever fields exist)
    full = replace(d.full, population=v["population"], max_generations=v["max_generations"],
                   stagnation=v["stagnation"], n_elite=min(d.full.n_elite, v["population"] - 1),
                   time_budget_s=budget, region_size=v["region_size"])
    warm = replace(d.warm, population=v["warm_population"], max_generations=v["warm_generations"],
                   stagnation=v["warm_stagnation"], n_elite=min(d.warm.n_elite, v["warm_population"] - 1),
                   time_budget_s=budget)
    return LabelerSettings(
        method=v["method"], mode=v["mode"], window=v["window"], full=full, warm=warm,
        background=Background(volume_m3=v["clutter_volume_m3"], max_speed_mps=v["clutter_max_speed_mps"],
                              detection_probability=v["detection_probability"]),
        tracker=TrackerSettings(gate_m=v["gate_m"], gate_speed_factor=v["gate_speed_factor"],
                                max_misses=v["max_misses"]),
        max_points=v["max_points"], refit_drop=v["refit_drop"], restarts=v["restarts"],
        accept_drop=v["accept_drop"],
        max_gap_s=v["max_gap_s"], noise_mm=v["noise_mm"], heading_snap_deg=v["heading_snap_deg"], seed=v["seed"],
        region_checks=v["region_checks"], region_size=v["region_size"], region_every=v["region_every"])


def settings_equal(a: Any, b: Any) -> bool:
    """Equality of (nested) settings dataclasses that may hold numpy arrays."""
    if is_dataclass(a) and is_dataclass(b):
        return type(a) is type(b) and all(settings_equal(getattr(a, f.name), getattr(b, f.name))
                                          for f in fields(a))
    if hasattr(a, "shape") or hasattr(b, "shape"):
        import numpy as np
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


def format_value(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(str(v) for v in value) + "]"
    return str(value)


def descriptor(spec: ParamSpec):
    """rcl_interfaces ParameterDescriptor of a spec (description, type, range, read_only)."""
    from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                    ParameterType)
    types = {"bool": ParameterType.PARAMETER_BOOL, "int": ParameterType.PARAMETER_INTEGER,
             "double": ParameterType.PARAMETER_DOUBLE, "string": ParameterType.PARAMETER_STRING,
             "string_array": ParameterType.PARAMETER_STRING_ARRAY}
    d = ParameterDescriptor(name=spec.name, type=types[spec.kind], description=spec.description,
                            read_only=spec.read_only)
    if spec.choices:
        d.additional_constraints = "one of: " + ", ".join(spec.choices)
    if spec.range is not None:
        lo, hi = spec.range
        if spec.kind == "int":
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                         step=0.0)]
    return d


def qos_profile(kind: str, depth: int):
    """rclpy QoSProfile: 'sensor_data' = best effort, volatile; 'reliable' = reliable, volatile;
    both keep-last ``depth`` (never an unbounded queue)."""
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
    if kind not in QOS_CHOICES:
        raise ValueError(f"QoS must be one of {', '.join(QOS_CHOICES)}, got {kind!r}")
    rel = ReliabilityPolicy.BEST_EFFORT if kind == "sensor_data" else ReliabilityPolicy.RELIABLE
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth), reliability=rel,
                      durability=DurabilityPolicy.VOLATILE)


def load_params_file(path: str | Path, node_name: str = NODE_NAME) -> Dict[str, Any]:
    """The ``ros__parameters`` a ROS 2 params file gives node ``node_name`` (``/**`` wildcard
    entries first, then ``name`` / ``/name`` ones override), as a plain dict."""
    import yaml
    doc = yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {}
    out: Dict[str, Any] = {}
    bare = node_name.lstrip("/")
    for key in ("/**", "**", bare, "/" + bare):
        block = doc.get(key)
        if isinstance(block, dict) and isinstance(block.get("ros__parameters"), dict):
            out.update(block["ros__parameters"])
    return out


def _yaml_scalar(v: Any) -> str:
    import json
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(json.dumps(x) for x in v) + "]"
    return repr(v) if isinstance(v, float) else str(v)


def render_yaml(key: str = "/**") -> str:
    """The text of params/labeler.yaml: every parameter, its description and default."""
    import textwrap
    lines = [
        "# dtm_labeler node parameters: every parameter with its default.",
        "# Generated by `python -m dtm_labeler.ros.params --write-yaml params/labeler.yaml`; edit the",
        "# table in dtm_labeler/ros/params.py, not this file.",
        "# Use:  dtm-labeler-node --ros-args --params-file params/labeler.yaml -p model_path:=/path/model.npz",
        "# The block is keyed /** (every node of the process, so also a node started in a namespace or",
        "# under another name: a key 'dtm_labeler' would not match /ns/dtm_labeler). To target one node",
        "# of a shared file, key it by the node's full name (/ns/dtm_labeler). Every parameter can be",
        "# changed at runtime through the parameter services except the read-only ones; ranges are",
        "# inclusive. set_parameters applies values one by one; set_parameters_atomically all or none.",
        f"{key}:", "  ros__parameters:"]
    for p in PARAMS:
        extra = []
        if p.range:
            extra.append(f"range [{p.range[0]}, {p.range[1]}]")
        if p.choices:
            extra.append("one of " + "|".join(p.choices))
        if p.read_only:
            extra.append("read-only: start-up only")
        text = p.description + (" (" + "; ".join(extra) + ")" if extra else "")
        lines += ["    # " + line for line in textwrap.wrap(text, 92)]
        lines.append(f"    {p.name}: {_yaml_scalar(p.default)}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":  # pragma: no cover - maintenance entry point
    import sys
    if len(sys.argv) == 3 and sys.argv[1] == "--write-yaml":
        Path(sys.argv[2]).write_text(render_yaml(), encoding="utf-8")
        print(f"wrote {sys.argv[2]}")
    else:
        sys.stdout.write(render_yaml())
