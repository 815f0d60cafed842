"""The node's side of the one parameter table (:mod:`dtm_labeler.labeling.config`).

The table -- every parameter's name, default, range or choices, description and layer --
and its validation live in :mod:`dtm_labeler.labeling.config` (pure Python, shared with
``dtm-label --params-file`` and ``dtm-bag label``). Here is only what needs ROS: the
``ParameterDescriptor`` of a table entry (:func:`descriptor`) and the QoS profiles
(:func:`qos_profile`). The node declares every entry of :data:`PARAMS` and its
on-set-parameters callback runs :func:`validate` + :func:`settings_from_params` on the
WHOLE resulting configuration: a value that is bad on its own, or bad together with the
others, is rejected with the reason and changes nothing.

What "a set" is follows rclpy (checked on rclpy 7.1): ``set_parameters`` (the
``~/set_parameters`` service, ``ros2 param set``, ``ros2 param load``) applies its parameters
ONE BY ONE -- the callback sees each alone, against the values already applied, so the good
ones of a list are applied and only the bad ones rejected (and a change that needs two values
at once, e.g. ``model_path`` with new ``expected_labels``, must be ordered or made atomic).
Only ``set_parameters_atomically`` (``~/set_parameters_atomically``) is all-or-nothing: one
callback with every value, and one bad value applies none.

``params/labeler.yaml`` holds every parameter with its default; it is generated from the table
(``python -m dtm_labeler.labeling.config --write-yaml params/labeler.yaml``) and a test checks it.
"""
from __future__ import annotations

from ..labeling.config import (DEFAULTS, LABELER_KEYS, NODE_NAME, PARAMS, QOS_CHOICES, SPECS, Param, check_labels,
                               format_value, load_params_file, render_yaml, settings_equal, settings_from_params,
                               validate)

ParamSpec = Param
INPUT_QOS_KEYS = frozenset({"input_qos", "input_depth"})
#: Parameters whose change recreates the input subscription.
INPUT_KEYS = INPUT_QOS_KEYS | {"input_type"}

__all__ = ["ParamSpec", "PARAMS", "SPECS", "DEFAULTS", "NODE_NAME", "QOS_CHOICES", "LABELER_KEYS",
           "INPUT_QOS_KEYS", "INPUT_KEYS", "validate", "settings_from_params", "check_labels", "descriptor",
           "qos_profile", "load_params_file", "format_value", "settings_equal", "render_yaml"]


def descriptor(spec: Param):
    """rcl_interfaces ParameterDescriptor of a table entry (description, type, range, read_only)."""
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


def incompatible_publishers(requested, offered) -> str:
    """Why publishers offering the QoS profiles ``offered`` cannot reach a subscription that
    requests ``requested`` ('' when they all can): a reliable subscription never hears a
    best-effort publisher. (The input subscription's QoS event handlers do not run -- the worker
    reads it, ros/inbox.py -- so /diagnostics names the mismatch.)"""
    from rclpy.qos import ReliabilityPolicy
    if requested.reliability != ReliabilityPolicy.RELIABLE:
        return ""
    bad = sum(1 for q in offered if q.reliability == ReliabilityPolicy.BEST_EFFORT)
    if not bad:
        return ""
    return (f"{bad} publisher(s) offer best-effort QoS to this reliable input: they are never heard "
            "(set input_qos:=sensor_data)")
