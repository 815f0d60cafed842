"""A stream labelled with background recovery made deterministic (``DeferredRecovery``: a GA's
result 25 frames after the request, its first interim result after 2, a sweep's after 2), with
what test_background_join and test_background_sweeps read of it: the readings each join offered,
the searches asked for, the kind of search each joined frame took, every frame's labels."""
from __future__ import annotations

from dtm_labeler.evaluation.corruption import corrupt_clip
from dtm_labeler.evaluation.pipeline import model_clip
from dtm_labeler.labeling.recovery import DeferredRecovery
from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler


def half_hidden_frames(model, take, start: int, draw: int) -> list:
    """240 frames (2 s) of ``take`` from ``start`` with half of the samples hidden as a
    capture's occlusions hide them (gaps of ~0.25 s, gap draw ``draw``), 1 mm of noise: the
    frames the labeler gets."""
    from test_gappy_training import _gapped
    clip = _gapped(take, 0.5, seed=draw, gap_s=0.25).slice(start, start + 240)
    return list(corrupt_clip(model_clip(model, clip), noise_mm=1.0, seed=1))


def background_run(model, frames, audit_period_s: float = 0.0) -> dict:
    """``accuracy``: share of the visible markers labelled right; ``offered``: (number of
    readings, whether a search had vouched for a frame of the stream by then) of each join;
    ``asked``: (kind, stamp) of every request; ``joined``: kind of the request whose result
    each joined frame took; ``labels``: every frame's labels."""
    lab = StreamLabeler(model, LabelerSettings(recovery="background", audit_period_s=audit_period_s))
    lab.recovery.close()
    lab.recovery = DeferredRecovery(lab, delay_frames=25, interim_frames=2, sweep_frames=2)
    join, offered = lab._join, []

    def counted(inp):
        out = join(inp)
        if out is not None:
            offered.append((len(out[0]), lab._vouched))
        return out
    lab._join = counted
    asked, submit = [], lab.recovery.submit
    lab.recovery.submit = lambda req: (asked.append((req.kind, lab.last_stamp)), submit(req))
    joined, labels, right, seen = [], [], 0, 0
    for fr in frames:
        r = lab.process(fr.xyz, fr.stamp)
        labels.append(r.labels.tolist())
        if r.recovered:
            joined.append(asked[-1][0] if not lab.recovery.busy else asked[-2][0])
        v = fr.truth >= 0
        right += int((r.labels[v] == fr.truth[v]).sum())
        seen += int(v.sum())
    lab.close()
    return dict(accuracy=right / seen, offered=offered, asked=asked, joined=joined, labels=labels)
