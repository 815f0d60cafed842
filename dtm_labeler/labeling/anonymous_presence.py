"""Whether a take shows a model's anonymous points at all: a session whose extra markers were
taken off is labelled without them.

Why. ``dtm-train`` learns a capture's unnamed markers that ride on the body as anonymous points
(:mod:`dtm_labeler.training.anonymous`), so that such a marker is not given the label of a hidden
marker beside it. A model is one session's marker placement; another session of the same set may
not carry those markers. Then an anonymous point has nothing of its own to explain, and every
point it is given is a named marker (HDM05's gapped halves with the six `*` markers left out,
live: ``*byLWRB`` on LWRB's point, ``*byLMT5`` on LMT5's), and the take pass starts from those
frames: draws 1-4 98.70 / 99.09 / 98.45 / 99.66 % under the model without anonymous points,
97.92 / 98.51 / 94.05 / 98.63 % under the model with them (``results/captures.md``).

The reading. Eq. 31 gives each model point a detection probability: a point a take shows is
labelled in about the share of frames its marker was seen in training (``settings["seen_share"]``,
:func:`~dtm_labeler.training.train.train_model`), scaled by how much more or less this take shows
of the named markers than the training did (its occlusions). Where the anonymous points together
are held in well under that -- under :data:`ABSENT_BELOW` of it -- their detection probability in
this take is read as 0: the take does not carry those markers, and it is labelled by the model
without them (:meth:`~dtm_labeler.model.dtm.TriangulatedModel.named_only`). The points are judged
together: markers are put on or taken off for a session, and one point's count over a take is
too noisy to judge alone (HDM05's gapped halves, live: one point held in 224 of 600 frames with
its marker absent, another in 135 with it present).

Measured (``benchmarks/bench_captures.py --only gapghosts``: the live pass's counts, the model of
the gapped first half with its anonymous points; held / expected): HDM05's draws 1-4 with the
markers 0.82-1.03, without them 0.18-0.29; the Qualisys walk's draws 2-4 0.88-1.53 and 0.10-0.55.
Without them every take is then labelled as by ``dtm-train --ignore-unlabelled``'s model (the
same structure, mixtures, body and levels: :meth:`~dtm_labeler.model.dtm.TriangulatedModel.named_only`).
The node (:meth:`~dtm_labeler.labeling.tracked.TrackedLabeler.anonymous_presence`) makes the same
judgement over the frames it searched and warns in its diagnostics; it labels on with the model
it loaded.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..model.dtm import TriangulatedModel

__all__ = ["ABSENT_BELOW", "MIN_EXPECTED_FRAMES", "AnonymousPresence", "anonymous_presence"]

#: held / expected under which the take is read as not carrying the anonymous points' markers
#: (module doc: between the highest ratio without the markers, 0.55, and the lowest with them, 0.82)
ABSENT_BELOW = 0.65
#: no judgement on fewer expected frames of the anonymous points (all of them together)
MIN_EXPECTED_FRAMES = 30.0


@dataclass(frozen=True)
class AnonymousPresence:
    """What a take showed of a model's anonymous points (module doc)."""

    points: tuple[str, ...]       # the anonymous points
    held_frames: int              # frames x points in which the live pass gave them a point
    expected_frames: float        # ... what their training's seen shares predict for this take
    absent: bool                  # the take is read as not carrying their markers

    @property
    def ratio(self) -> float:
        return self.held_frames / self.expected_frames if self.expected_frames > 0 else float("nan")

    def as_dict(self) -> dict:
        return asdict(self) | {"ratio": round(self.ratio, 3), "expected_frames": round(self.expected_frames, 1),
                               "points": list(self.points)}

    @classmethod
    def from_dict(cls, d: dict) -> "AnonymousPresence":
        """From :meth:`as_dict` (a run's settings, a JSON summary)."""
        return cls(tuple(d["points"]), int(d["held_frames"]), float(d["expected_frames"]), bool(d["absent"]))

    def note(self, live: bool = False) -> str:
        """What a user reads of an absent judgement ('' otherwise); ``live``: for the node, which
        labels with the model it loaded."""
        if not self.absent:
            return ""
        seen = (f"does not show the model's {len(self.points)} anonymous points ({', '.join(self.points)}: "
                f"held in {self.held_frames} of the {self.expected_frames:.0f} frames their training predicts)")
        if live:
            return (f"the stream {seen}: their markers taken off? they take named markers' points; "
                    "a model trained with --ignore-unlabelled labels such a session")
        return f"the take {seen}: labelled without them"


def anonymous_presence(model: TriangulatedModel, label_frames: np.ndarray, n_frames: int
                       ) -> AnonymousPresence | None:
    """The judgement of the module doc from ``label_frames`` (per label, the frames of the take's
    ``n_frames`` in which it held a point: ``TrackedLabeler.label_frames``); None for a model
    without anonymous points."""
    anon = np.asarray(model.anonymous, dtype=bool)
    if not anon.any() or n_frames <= 0:
        return None
    held = np.asarray(label_frames, dtype=np.float64).reshape(-1)[:anon.size]
    seen = np.asarray(model.settings.get("seen_share") or np.ones(anon.size), dtype=np.float64)
    if seen.size != anon.size:
        seen = np.ones(anon.size)
    named = ~anon
    train_named = float(seen[named].mean()) if named.any() else 1.0
    take_named = float(held[named].mean()) / n_frames if named.any() else 1.0
    scale = take_named / train_named if train_named > 0 else 1.0
    expected = float(seen[anon].sum() * scale * n_frames)
    got = int(held[anon].sum())
    absent = expected >= MIN_EXPECTED_FRAMES and got < ABSENT_BELOW * expected
    return AnonymousPresence(tuple(model.labels[i] for i in np.flatnonzero(anon)), got, expected, bool(absent))
