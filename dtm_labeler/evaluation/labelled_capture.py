"""A labeler's output as a labelled capture: one channel per model label, unlabelled points as ``*N``.

What ``dtm-label ... --out labelled.c3d|.csv|.trc`` and ``dtm-bag label ... --out labelled.c3d``
write. Per frame, the point published with label ``m`` goes into channel ``m`` (a gap where
no point carries it); the points left unlabelled go into ``*N`` channels by their labeler
track: a track keeps its channel while it is seen, a channel is reused only after its track
ended, so a ghost or an unknown marker reads as one trajectory as long as the tracker held
it. Positions are the input's own (no smoothing, no filling).

The file keeps the input's rate, units, vertical axis, first frame number and C3D screen
axes (:class:`CaptureFormat`, taken from the input clip's ``meta``). A TRC states no vertical:
one written from another format is Y up, the convention of OpenSim and of TRC readers (a TRC
input keeps its own).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..motion.c3d_write import write_c3d
from ..motion.clip import MotionClip
from ..motion.markers_csv import write_markers_csv
from ..motion.trc import write_trc

OUTPUT_SUFFIXES = (".c3d", ".csv", ".trc")


@dataclass
class CaptureFormat:
    """How to write a capture so it matches its input."""

    rate: float
    units: str = "mm"
    up_axis: str = "Z"
    first_frame: int = 0
    screen: tuple[str, str] | None = None
    frame_numbers: np.ndarray | None = None
    source_format: str = ""                    # the input's ``meta['format']``

    @classmethod
    def of(cls, clip: MotionClip, start: int = 0) -> "CaptureFormat":
        """The format of ``clip`` (a slice starting at frame ``start`` of its file)."""
        m = clip.meta
        fn = m.get("frame_numbers")
        fn = np.asarray(fn) if isinstance(fn, np.ndarray) and len(fn) == clip.n_frames else None
        units = m.get("units") or "mm"
        return cls(rate=float(clip.rate), units=units if units in ("mm", "cm", "m") else "mm",
                   up_axis=m.get("up_axis", "Z"), first_frame=int(m.get("first_frame", 0)) + int(start),
                   screen=tuple(m["screen"]) if m.get("screen") else None, frame_numbers=fn,
                   source_format=str(m.get("format", "")))


@dataclass
class LabelledCapture:
    positions: np.ndarray                      # (F, M + K, 3) metres, Z up, NaN = gap
    names: tuple[str, ...]                     # model labels, then *0 .. *K-1
    n_labels: int
    fmt: CaptureFormat
    track_channels: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    def write(self, path: str | Path) -> Path:
        """``.c3d``, ``.csv`` or ``.trc`` by suffix, in the input's units, axes and rate."""
        path = Path(path)
        suffix = path.suffix.lower()
        f = self.fmt
        if suffix == ".c3d":
            return write_c3d(path, self.positions, self.names, f.rate, f.units, f.up_axis, f.first_frame, f.screen)
        if suffix == ".csv":
            frames = f.frame_numbers if f.frame_numbers is not None else f.first_frame + np.arange(self.n_frames)
            return write_markers_csv(path, self.positions, self.names, f.rate, frames, f.units, f.up_axis,
                                     comments=("labelled by dtm-label: channels named by the model's labels, "
                                               "unlabelled points as *N",))
        if suffix == ".trc":
            frames = f.frame_numbers if f.frame_numbers is not None else f.first_frame + 1 + np.arange(self.n_frames)
            up = f.up_axis if f.source_format == "trc" else "Y"
            return write_trc(path, self.positions, self.names, f.rate, frames, f.units, up)
        raise ValueError(f"{path}: labelled captures are written as {', '.join(OUTPUT_SUFFIXES)}")


def assemble(frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], labels: Sequence[str], n_frames: int,
             fmt: CaptureFormat) -> LabelledCapture:
    """Channels from per-frame ``(xyz (n, 3), published labels (n,), track ids (n,))``."""
    M = len(labels)
    lab = np.full((n_frames, M, 3), np.nan)
    unl_rows: list[tuple[int, int, np.ndarray]] = []      # (frame, channel, xyz)
    owner: list[int] = []                                 # track holding each *N channel (-1 free)
    channel_of: dict[int, int] = {}
    for t, (xyz, labs, tids) in enumerate(frames):
        xyz = np.asarray(xyz, dtype=np.float64)
        labs = np.asarray(labs, dtype=np.int64)
        on = labs >= 0
        lab[t, labs[on]] = xyz[on]
        free_tracks = set(int(x) for x in np.asarray(tids)[~on])
        for c, tr in enumerate(owner):                    # channels of tracks not unlabelled now are free
            if tr not in free_tracks:
                owner[c] = -1
        used: set[int] = set()
        for i in np.flatnonzero(~on):
            tr = int(tids[i])
            c = channel_of.get(tr, -1) if tr >= 0 else -1
            if c < 0 or c in used or owner[c] not in (-1, tr):
                c = next((k for k, o in enumerate(owner) if o == -1 and k not in used), len(owner))
                if c == len(owner):
                    owner.append(-1)
            owner[c] = tr
            used.add(c)
            if tr >= 0:
                channel_of[tr] = c
            unl_rows.append((t, c, xyz[i]))
    K = len(owner)
    unl = np.full((n_frames, K, 3), np.nan)
    for t, c, p in unl_rows:
        unl[t, c] = p
    return LabelledCapture(np.concatenate([lab, unl], axis=1), tuple(labels) + tuple(f"*{k}" for k in range(K)),
                           M, fmt, channel_of)


def from_records(records, labels: Sequence[str], n_frames: int, fmt: CaptureFormat) -> LabelledCapture:
    """:func:`assemble` from :class:`~dtm_labeler.evaluation.pipeline.FrameRecord` s."""
    return assemble(((r.xyz, r.labels, r.track_ids) for r in records), labels, n_frames, fmt)


def from_stamped(frames: Sequence[tuple[int, np.ndarray, np.ndarray, np.ndarray]], labels: Sequence[str],
                 units: str = "mm") -> LabelledCapture:
    """:func:`assemble` from ``(stamp_ns, xyz, labels, track ids)`` per cloud (a bag): the rate
    is the median stamp step, each cloud goes to the frame its stamp falls on (clouds missing
    from the bag leave gaps), the first frame is 0, Z up."""
    if not frames:
        raise ValueError("no clouds to write")
    stamps = np.array([f[0] for f in frames], dtype=np.float64) * 1e-9
    steps = np.diff(stamps)
    steps = steps[steps > 0]
    rate = 1.0 / float(np.median(steps)) if steps.size else 1.0
    index = np.round((stamps - stamps[0]) * rate).astype(np.int64)
    n = int(index.max()) + 1
    empty = (np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64))
    by_frame: list = [empty] * n
    for i, (_, xyz, labs, tids) in zip(index, frames):
        by_frame[i] = (xyz, labs, tids)
    return assemble(by_frame, labels, n, CaptureFormat(rate=round(rate, 3), units=units))
