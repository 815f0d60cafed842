"""Imports go one way: motion -> model -> search -> labeling -> training -> evaluation -> ros -> cli.

Checked on the source text (every ``from``/``import`` statement, also inside functions), so a
backward import hidden in a function body to dodge a cycle fails too; and no module outside
``ros/`` and ``cli/`` imports rclpy or ROS message packages (the core stays free of ROS).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "dtm_labeler"
RANK = {"jsonable": 0, "motion": 0, "model": 1, "search": 2, "labeling": 3, "training": 4,
        "evaluation": 5, "ros": 6, "cli": 7}
ROS_MODULES = ("rclpy", "sensor_msgs", "std_msgs", "geometry_msgs", "visualization_msgs", "diagnostic_msgs",
               "rcl_interfaces", "dtm_labeler_msgs", "builtin_interfaces", "std_srvs", "lifecycle_msgs",
               "mocap4r2_msgs")


def _modules():
    return sorted(p for p in PKG.rglob("*.py") if "__pycache__" not in p.parts)


def _layer(path: Path) -> str:
    rel = path.relative_to(PKG).parts
    return rel[0] if len(rel) > 1 else Path(rel[0]).stem


def _imports(path: Path):
    """(absolute dotted module, line) of every import in the file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    pkg = ["dtm_labeler"] + list(path.relative_to(PKG).parts[:-1])
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg[:len(pkg) - node.level + 1]
                yield ".".join(base + ([node.module] if node.module else [])), node.lineno
            else:
                yield node.module or "", node.lineno
        elif isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PKG)))
def test_imports_only_go_down(path):
    own = _layer(path)
    if own not in RANK:
        return
    bad = []
    for mod, line in _imports(path):
        parts = mod.split(".")
        if parts[0] != "dtm_labeler" or len(parts) < 2 or parts[1] not in RANK:
            continue
        if RANK[parts[1]] > RANK[own]:
            bad.append(f"line {line}: {own} imports {mod}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("path", [p for p in _modules() if _layer(p) not in ("ros", "cli")],
                         ids=lambda p: str(p.relative_to(PKG)))
def test_core_is_free_of_ros(path):
    hits = [f"line {line}: {mod}" for mod, line in _imports(path) if mod.split(".")[0] in ROS_MODULES]
    assert not hits, "\n".join(hits)
