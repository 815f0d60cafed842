"""The managed node (``python -m dtm_labeler.ros.lifecycle``, real process, real DDS):
unconfigured (a transition it does not have is refused) -> configure (model loaded) -> activate
(labelling) -> deactivate (not labelling) -> cleanup (publishers gone, model freed) -> configure +
activate again; SIGTERM -> exit 0."""
from __future__ import annotations

import signal

import pytest

import node_helpers as H


@pytest.fixture(scope="module")
def managed():
    wm = H.walk_model()
    proc = H.NodeProcess("t_life", params={"model_path": wm.path, "diagnostics_period_s": 0.1},
                         module="dtm_labeler.ros.lifecycle")
    cl = H.NodeClient(proc)
    yield proc, cl, H.FrameFeed(wm, seed=6), wm
    cl.close()
    if proc.alive():
        proc.stop(signal.SIGKILL)


#: the state each transition of the test leads to when it succeeds
GOAL = {"configure": "inactive", "activate": "active", "deactivate": "inactive",
        "cleanup": "unconfigured"}


def transition(cl, label: str, attempts: int = 3) -> bool:
    """Ask for a transition; True when it succeeded. A transition is sent once per attempt: an
    answer lost to DDS matching (see ``NodeClient.call``) is told apart from a refusal by the
    state the node is in afterwards, and only a transition that did not happen is sent again."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    ids = {"configure": Transition.TRANSITION_CONFIGURE, "activate": Transition.TRANSITION_ACTIVATE,
           "deactivate": Transition.TRANSITION_DEACTIVATE, "cleanup": Transition.TRANSITION_CLEANUP}
    req = ChangeState.Request()
    req.transition.id = ids[label]
    for attempt in range(attempts):
        try:
            return cl.call(ChangeState, "change_state", req, timeout=30).success
        except AssertionError:
            if not cl.target.alive() or attempt == attempts - 1:
                raise
            if state(cl) == GOAL[label]:
                return True


def state(cl) -> str:
    from lifecycle_msgs.srv import GetState
    return cl.call(GetState, "get_state", resend_after=H.RESEND_S).current_state.label


def not_labelled(cl, feed) -> bool:
    """A frame published now gets no labelled output (checked after the diagnostics of the
    next period arrive, i.e. well after the node would have answered)."""
    xyz, truth, stamp = feed.next()
    cl.publish(xyz, stamp)
    n = len(cl.diags)
    cl.wait_for(lambda: len(cl.diags) >= n + 2 or cl.labeled_at(stamp), 5, "diagnostics")
    return cl.labeled_at(stamp) is None


def settles_ok(cl, feed, frames: int = 120) -> dict:
    """Keep labelling frame by frame until a diagnostics message of the active node says OK
    (at most ``frames``); that message, else the last one. A period holding the first frames
    after a (re)start may rightly say they were published unconfirmed while the first search
    ran in the background; a node that stays in WARN while it labels fails."""
    with cl.cond:
        start = len(cl.diags)
    for _ in range(frames):
        xyz, _truth, stamp = feed.next()
        cl.send(xyz, stamp)
        with cl.cond:
            for d in cl.diags[start:]:
                if d["active"] == "True" and d["labeling.level"] == "0":
                    return d
    with cl.cond:
        return cl.diags[-1]


def test_lifecycle_transitions(managed):
    proc, cl, feed, wm = managed
    assert state(cl) == "unconfigured"
    # a transition not available from the state is refused with a message; the node stays up
    assert not transition(cl, "deactivate") and state(cl) == "unconfigured"
    assert proc.wait_log("transition 'deactivate' refused")
    assert cl.sub_l.get_publisher_count() == 0 and cl.pub.get_subscription_count() == 0
    # configure: the model is loaded, publishers and diagnostics exist; no input yet
    assert transition(cl, "configure") and state(cl) == "inactive"
    assert proc.wait_log("model loaded")
    cl.wait_for(lambda: cl.sub_l.get_publisher_count() > 0, 10, "publishers after configure")
    d = cl.wait_diag(lambda d: d["model_status"] == "loaded")
    assert "inactive" in d["labeling.message"] and d["active"] == "False"
    assert cl.pub.get_subscription_count() == 0
    # activate: labelling
    assert transition(cl, "activate") and state(cl) == "active"
    cl.wait_for(lambda: cl.pub.get_subscription_count() > 0, 10, "input subscription")
    cl.probe()
    assert cl.run_frames(feed, 15) > 0.95
    # deactivate: no input, nothing labelled
    assert transition(cl, "deactivate") and state(cl) == "inactive"
    cl.wait_for(lambda: cl.pub.get_subscription_count() == 0, 10, "input subscription gone")
    assert not_labelled(cl, feed)
    # cleanup: publishers and model gone
    assert transition(cl, "cleanup") and state(cl) == "unconfigured"
    cl.wait_for(lambda: cl.sub_l.get_publisher_count() == 0, 10, "publishers gone")
    # configure + activate again: the model is loaded anew and labels
    assert transition(cl, "configure") and transition(cl, "activate")
    cl.wait_for(lambda: cl.pub.get_subscription_count() > 0, 10, "input subscription")
    cl.probe()
    assert cl.run_frames(feed, 10) > 0.95
    d = settles_ok(cl, feed)
    assert d["labeling.level"] == "0", d["labeling.message"]
    assert int(d["reloads_ok"]) == 2                                       # one load per configure


def test_configure_fails_without_a_model(managed):
    proc, cl, feed, wm = managed
    assert transition(cl, "deactivate") and transition(cl, "cleanup")
    assert cl.set(model_path="")[0].successful
    assert not transition(cl, "configure") and state(cl) == "unconfigured"
    assert proc.wait_log("configure failed: model_path is empty")
    assert cl.set(model_path=str(wm.path))[0].successful
    assert transition(cl, "configure") and state(cl) == "inactive"


def test_sigterm_exits_cleanly(managed):
    proc, cl, feed, wm = managed
    assert proc.stop(signal.SIGTERM) == 0
    assert "Traceback" not in proc.log()
