"""The input subscription, read by the node's worker thread itself instead of the executor.

Why (measured, ``results/node_latency_compare.md``): with the executor calling the input
callback, every cloud cost the executor thread ~0.9 ms of Python (rclpy rebuilds its wait set
over every entity of the node per wake-up, takes the message through its task machinery, then
the callback decodes) -- while the worker thread was labelling the previous cloud. The two
threads share the GIL, so that work was paid inside the labelling (and the handoff of each
frame from one thread to the other waited for the GIL and a wake-up): the node's own latency
(receive -> published) was ~1.3x the labeler's, with p99 tails well above it.

How: the subscription is an ordinary one of the node (in the graph, remappable, counting its
publishers) but in a callback group whose subscriptions no executor takes (:class:`NotExecuted`;
its QoS event handlers do not run either: a publisher whose QoS cannot reach it is named in
``/diagnostics`` instead, :func:`~.params.incompatible_publishers`). The worker waits on a wait set of its own -- the
subscription and a guard condition (:meth:`Inbox.wake`: a model installed, settings, a reset,
stop) -- as ``rclpy.wait_for_message`` does, and when it looks takes every message there
(:meth:`Inbox.poll`): the newest is searched, the older ones carried (ros/worker.py). The
subscription's history is the queue that executor callbacks used to fill in the node, so its
depth is at least :data:`~.worker.OBSERVED_SKIPS` + 1 (:func:`history_depth`); a message's
arrival is its DDS reception time (``received_timestamp``), not the moment it is taken.
"""
from __future__ import annotations

import threading
import time
from typing import Any, List, Optional, Tuple

from rclpy.callback_groups import CallbackGroup
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.subscription import Subscription

__all__ = ["Inbox", "NotExecuted", "history_depth", "arrival_age_s"]


class NotExecuted(CallbackGroup):
    """A callback group no executor runs: the input subscription is read by the :class:`Inbox`.
    Its QoS event handlers are in it too -- in the executor's wait set, rmw wakes them on every
    message the subscription holds, and the executor rebuilt its wait set in a loop until the
    worker took the message (measured: ~40 % of a core, and the GIL)."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


def history_depth(input_depth: int, carried: int) -> int:
    """The subscription's keep-last depth: the user's, but at least the frames the worker
    carries plus the one it searches (they wait in DDS now, not in the node)."""
    return max(int(input_depth), int(carried) + 1)


def arrival_age_s(info: Optional[dict]) -> float:
    """How long ago (s) DDS received the message of ``info`` (0 without a reception stamp)."""
    ns = info.get("received_timestamp") if info else None
    if not ns:
        return 0.0
    return max(0.0, (time.time_ns() - int(ns)) * 1e-9)


class Inbox:
    """The worker's wait set over the input subscription (:meth:`attach`, from any thread) and
    a wake-up guard condition (:meth:`wake`). ``poll`` runs in the worker thread only."""

    def __init__(self, context):
        self._context = context
        self._gc = GuardCondition(None, None, context=context)    # no node's: no executor sees it
        self._ws = _rclpy.WaitSet(1, 1, 0, 0, 0, 0, context.handle)
        self._cond = threading.Condition()
        self._sub: Optional[Subscription] = None
        self._depth = 1
        self._waiting_on: Optional[Subscription] = None     # the subscription poll() holds

    def attach(self, sub: Optional[Subscription], depth: int = 1) -> None:
        """Read ``sub`` from now on (None: no input). Returns when the worker no longer waits on
        the previous one: detach before destroying a subscription, so that it is gone from DDS
        when it returns (a new one of another type on the topic is refused while it lives)."""
        with self._cond:
            self._sub, self._depth = sub, int(depth)
        self.wake()
        with self._cond:
            self._cond.wait_for(lambda: self._waiting_on is None or self._waiting_on is sub, timeout=1.0)

    def wake(self) -> None:
        """Make the current or next :meth:`poll` return."""
        try:
            self._gc.trigger()
        except Exception:            # pragma: no cover - destroyed at shutdown
            pass

    def poll(self, timeout_s: Optional[float]) -> Tuple[Optional[Subscription], List[Tuple[Any, dict]], bool]:
        """Wait up to ``timeout_s`` (None: until a message or :meth:`wake`; 0: just look), then
        take every message there. Returns (the subscription they came from, [(msg, info)],
        whether the history was full -- older messages may have been pushed out of it)."""
        with self._cond:
            sub, depth = self._sub, self._depth
            self._waiting_on = sub
        try:
            with self._gc.handle:
                self._ws.clear_entities()
                self._ws.add_guard_condition(self._gc.handle)
                if sub is None:
                    self._ws.wait(-1 if timeout_s is None else int(timeout_s * 1e9))
                    return None, [], False
                with sub.handle:        # a destroy requested meanwhile waits for this block
                    self._ws.add_subscription(sub.handle)
                    self._ws.wait(-1 if timeout_s is None else int(timeout_s * 1e9))
                    taken = []
                    while len(taken) < depth:
                        m = sub.handle.take_message(sub.msg_type, sub.raw)
                        if m is None:
                            break
                        taken.append(m)
                    return sub, taken, len(taken) >= depth
        except Exception:
            if self._context.ok():
                raise
            time.sleep(0.01)            # the context is shutting down: the worker is stopped next
            return None, [], False
        finally:
            with self._cond:
                self._waiting_on = None
                self._cond.notify_all()

    def close(self) -> None:
        self.attach(None)
        try:
            self._gc.destroy()
        except Exception:            # pragma: no cover
            pass
