"""Shared pytest set-up.

Rule one (../shared/ros2.md): DDS stays on loopback. This runs before any test module
imports rclpy, and every test session gets its own ROS_DOMAIN_ID unless one is set; under
``pytest -n N`` every worker moves to a domain of its own.
"""
import os
from pathlib import Path

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):   # small matrices: threads only add latency
    os.environ.setdefault(_var, "1")
os.environ.setdefault("ROS_DOMAIN_ID", str(40 + os.getpid() % 50))
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")       # gw0, gw1 ... under pytest -n N
if _WORKER.startswith("gw"):                               # parallel workers: a domain each
    os.environ["ROS_DOMAIN_ID"] = str((int(os.environ["ROS_DOMAIN_ID"]) + 1 + int(_WORKER[2:])) % 100)

import pytest  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get("DTM_DATA_DIR", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The real recordings in ../shared/data; tests that need them skip (with a reason) without."""
    if not (DATA_DIR / "index.csv").is_file():
        pytest.skip(f"real mocap data not found at {DATA_DIR} (set DTM_DATA_DIR or place ../shared/data)")
    return DATA_DIR


@pytest.fixture(scope="session", autouse=True)
def _no_node_left_behind():
    """A fixture that failed before yielding leaves its node process running (and talking on
    this test session's DDS domain): kill them all at the end of the session."""
    yield
    import sys
    helpers = sys.modules.get("node_helpers")
    if helpers is not None:
        helpers.kill_leftovers()
