"""The dtm_labeler ROS 2 node: unlabeled marker clouds in, labelled markers out, in real time.

Run::

    dtm-labeler-node --ros-args -p model_path:=/path/model.npz [--params-file params/labeler.yaml]
    ros2 run dtm_labeler labeler_node --ros-args ...          (full ROS install)
    python -m dtm_labeler.ros.node --ros-args ...

The managed variant (configure / activate / deactivate / cleanup) is
:mod:`dtm_labeler.ros.lifecycle` (``dtm-labeler-lifecycle-node``, ``labeler_lifecycle_node``).

Topics (relative, remappable): in ``markers/unlabeled`` -- sensor_msgs/PointCloud2 (float32 x, y, z,
optional ``id``), mocap4r2_msgs/Markers or sensor_msgs/PointCloud by ``input_type``
(:mod:`.inputs`); out ``markers/labeled`` (dtm_labeler_msgs/LabeledMarkerArray),
``markers/labeled_cloud`` (PointCloud2 x, y, z, int32 label, float32 confidence),
``markers/labeled_mocap4r2`` (mocap4r2_msgs/Markers, marker_name = label),
``markers/visualization`` (visualization_msgs/MarkerArray) and ``/diagnostics``. Output headers
are the input's (same stamp; frame_id per ``frame_id`` / ``override_frame_id``). Services:
``~/reset`` (std_srvs/Trigger: forget window, tracks and votes) and ``~/reload`` (read the model
file again). Parameters: :mod:`dtm_labeler.ros.params` (all changeable at runtime except
output_qos/output_depth).

The node is wiring only (:class:`~.core.LabelerCore`): the labeler runs on a worker thread that
reads the input subscription itself (:mod:`.inbox`), labels the newest frame and never queues
(:mod:`.worker`), model files are read and widened on a
loader thread (:mod:`.loader`), stamps are checked and, when unusable, replaced by receive time
(:mod:`.stamps`), messages and diagnostics are built by pure modules (:mod:`.messages`,
:mod:`.diagnostics`). SIGINT and SIGTERM end the process with status 0 within a second in every
state, also during a model load or a long search.
"""
from __future__ import annotations

import ctypes
import os
import signal
import sys
import traceback
from typing import List, Optional

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from . import params as P
from .core import CoreOwner, LabelerCore
from .messages import NO_TRACK

__all__ = ["LabelerNode", "main", "run", "NO_TRACK", "GIL_SWITCH_S"]

#: the interpreter's thread switch interval in a node process (s; Python's default 0.005). The
#: labelling thread shares the GIL with the executor and the loader thread, which runs seconds of
#: Python when a model is loaded or calibrated (``auto_calibrate``: unpickling, the calibrated
#: model's terms); a thread that wants the GIL waits until the holder reaches this interval, so the
#: default let a frame wait 5 ms per hand-over. Measured (``bench_node_latency.py``, 120 Hz,
#: 2 flickering + 2 ghosts, 2026-12-04, before and after side by side in each run): with
#: ``auto_calibrate`` (14 points, a generic body) e2e p99 56.7 / 13.8 -> 11.5 / 9.4 ms (seconds
#: 5-9, where the loader works, maxima 10-31 -> 10-18 ms);
#: without it, where nothing but the labelling runs Python, within the runs' spread (14 points
#: 9.9 / 7.4 / 10.4 / 12.3 -> 8.1 / 7.6 / 9.2 / 15.6 ms, 41 markers 18.8 / 22.3 -> 16.4 / 20.6 ms).
GIL_SWITCH_S = 0.0005


class LabelerNode(CoreOwner, Node):
    """See the module doc. ``kwargs`` go to :class:`rclpy.node.Node` (e.g. ``context``,
    ``parameter_overrides``, ``namespace``); ``start_worker=False`` is for tests."""

    def __init__(self, node_name: str = P.NODE_NAME, *, start_worker: bool = True, **kwargs):
        super().__init__(node_name, **kwargs)
        self.core = LabelerCore(self, start_worker=start_worker)
        self.core.open_outputs()
        self.core.load_model("start-up")
        self.core.open_input()


def run(make_node, args: Optional[List[str]] = None) -> int:
    """Spin the node ``make_node()`` until SIGINT/SIGTERM (rclpy shuts the context down on
    both; the process's GIL switch interval set to :data:`GIL_SWITCH_S` first), stop its
    threads (a worker inside a long search is not waited for) and leave with status 0 -- at
    once, without interpreter finalization: tearing numba, llvmlite, scipy and rclpy down takes
    most of a second, and shutdown must stay under one. An exception that is not the shutdown
    itself is printed and exits 1."""
    # rclpy's handler shuts the context down and then calls Python's own SIGINT handler; the
    # default one raises KeyboardInterrupt wherever the main thread is, and inside a __del__
    # (rclpy's Future) that printed "Exception ignored ... Traceback" into the log of a clean
    # exit (CI, test_sigint_exits_cleanly, 1 run in many). The context's shutdown ends the spin.
    signal.signal(signal.SIGINT, lambda signum, frame: None)
    sys.setswitchinterval(GIL_SWITCH_S)
    rclpy.init(args=args)
    node, code = None, 0
    try:
        node = make_node()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():      # not the race of a signal arriving while the executor waits
            traceback.print_exc()
            code = 1
    finally:
        if node is not None:
            node.stop()
            try:
                node.destroy_node()
            except Exception:      # pragma: no cover - the context may already be gone
                pass
        rclpy.try_shutdown()
    _exit_now(code)
    return code                    # pragma: no cover - not reached


def _exit_now(code: int) -> None:
    """Flush Python's and C's stdio (rcutils logs through C), then end the process."""
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        ctypes.CDLL(None).fflush(None)
    except Exception:              # pragma: no cover - no libc symbol lookup here
        pass
    os._exit(code)


def main(args: Optional[List[str]] = None) -> int:
    """Entry point of ``dtm-labeler-node`` / ``ros2 run dtm_labeler labeler_node``."""
    return run(LabelerNode, args)


if __name__ == "__main__":
    sys.exit(main())
