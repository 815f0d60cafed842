"""The managed (lifecycle) variant of the dtm_labeler node.

Run::

    dtm-labeler-lifecycle-node --ros-args -p model_path:=/path/model.npz
    ros2 run dtm_labeler labeler_lifecycle_node --ros-args -p model_path:=/path/model.npz
    ros2 lifecycle set /dtm_labeler configure      # then activate / deactivate / cleanup

Same topics, parameters and services as :mod:`dtm_labeler.ros.node`, by state:

=================  ===========================================================================
unconfigured       parameters only (settable; nothing loaded, nothing published)
configure          loads the model (on the loader thread; the transition waits for it and fails,
                   with the reason logged, when the file is refused or model_path is empty);
                   creates the publishers (lifecycle ones), ``~/reset``, ``~/reload`` and the
                   ``/diagnostics`` timer
inactive           diagnostics say "inactive"; no subscription, nothing labelled
activate           publishers enabled, input subscription created: labelling
deactivate         input subscription destroyed (a frame still waiting is dropped as
                   ``inactive``), publishers disabled
cleanup            publishers, services and timer destroyed, the model freed
=================  ===========================================================================

A transition the current state does not have (deactivate while unconfigured) is refused with a
warning naming the ones it has; the node stays up.
"""
from __future__ import annotations

import sys
import time
from typing import Callable, List, Optional

from lifecycle_msgs.msg import Transition
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from . import params as P
from .core import CoreOwner, LabelerCore
from .node import run

__all__ = ["LabelerLifecycleNode", "main"]

#: a transition's name by id, for the message refusing one (``lifecycle_msgs/Transition``)
_TRANSITION_NAMES = {getattr(Transition, n): n[len("TRANSITION_"):].lower()
                     for n in dir(Transition) if n.startswith("TRANSITION_")}

#: the longest configure waits for the model (a 41-marker bank loads in about a second)
CONFIGURE_TIMEOUT_S = 30.0


class LabelerLifecycleNode(CoreOwner, LifecycleNode):
    """See the module doc; ``kwargs`` go to :class:`rclpy.lifecycle.LifecycleNode`."""

    def __init__(self, node_name: str = P.NODE_NAME, **kwargs):
        super().__init__(node_name, **kwargs)
        self.core = LabelerCore(self, lifecycle=True)
        srv = getattr(self, "_service_change_state", None)      # rclpy's own service (7.1)
        if srv is not None:
            srv.callback = self._refusing_unavailable(srv.callback)

    def _refusing_unavailable(self, change_state: Callable) -> Callable:
        """``~/change_state`` that refuses, with a message, a transition the current state does
        not have (``ros2 lifecycle set`` of deactivate while unconfigured): rclpy's own service
        raises there, and the exception would end the node's spin."""
        def checked(req, resp):
            sm = self._state_machine
            available = {label: tid for tid, label, *_ in sm.available_transitions}
            wanted = req.transition.label or next(
                (label for label, tid in available.items() if tid == req.transition.id),
                _TRANSITION_NAMES.get(req.transition.id, str(req.transition.id)))
            if wanted not in available:
                self.get_logger().warning(
                    f"transition '{wanted}' refused: the state '{sm.current_state[1]}' has "
                    f"{', '.join(sorted(available)) or 'none'}")
                resp.success = False
                return resp
            return change_state(req, resp)
        return checked

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        core = self.core
        if not core.load_model("configure") or not self._wait_loaded():
            self.get_logger().error(f"configure failed: {core.model['error'] or 'the model did not load'}")
            return TransitionCallbackReturn.FAILURE
        core.open_outputs()
        return super().on_configure(state)

    def _wait_loaded(self) -> bool:
        """Wait (off the labeling path: the executor is ours during a transition) until the
        worker runs the loaded model; False when it was refused or the process is stopping."""
        end = time.monotonic() + CONFIGURE_TIMEOUT_S
        while time.monotonic() < end and self.context.ok():
            status = self.core.model["status"]
            if status == "loaded" and self.core.worker.engine is not None:
                return True
            if status in ("no model", "reload failed") and self.core.loader.idle():
                return False
            time.sleep(0.01)
        return False

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        ret = super().on_activate(state)          # enables the lifecycle publishers first
        self.core.open_input()
        return ret

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.core.close_input()
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.core.close_outputs()
        self.core.unload("cleaned up (lifecycle): configure loads the model again")
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.core.close_input()
        self.core.close_outputs()
        self.core.unload("shut down (lifecycle)")
        return super().on_shutdown(state)


def main(args: Optional[List[str]] = None) -> int:
    """Entry point of ``dtm-labeler-lifecycle-node`` / ``ros2 run dtm_labeler labeler_lifecycle_node``."""
    return run(LabelerLifecycleNode, args)


if __name__ == "__main__":
    sys.exit(main())
