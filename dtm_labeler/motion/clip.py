"""The one motion-clip type every loader produces and every consumer reads."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np


PER_FRAME_META = ("unlabelled", "frame_numbers")   # meta entries with one row per frame


@dataclass
class MotionClip:
    """A labelled recording: ``positions[frame, point] = (x, y, z)``.

    Conventions (fixed for the whole library):

    * metres, right-handed, **Z up** (loaders rotate Y-up data by +90 deg about X:
      ``(x, y, z) -> (x, -z, y)``, which keeps handedness);
    * ``NaN`` marks a missing sample (occlusion, gap); loaders map other gap
      codes such as ``(0, 0, 0)`` to NaN;
    * ``rate`` in Hz; frame ``i`` is at time ``i / rate``;
    * ``names[p]`` is the label of point column ``p``.
    """

    positions: np.ndarray
    rate: float
    names: tuple[str, ...]
    source: str = ""
    motion_class: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, dtype=np.float64)
        self.names = tuple(str(n) for n in self.names)
        if self.positions.ndim != 3 or self.positions.shape[2] != 3:
            raise ValueError(f"positions must be frames x points x 3, got {self.positions.shape}")
        if self.positions.shape[1] != len(self.names):
            raise ValueError(f"{self.positions.shape[1]} point columns but {len(self.names)} names")
        if len(set(self.names)) != len(self.names):
            raise ValueError("point names must be unique")
        if not np.isfinite(self.rate) or self.rate <= 0:
            raise ValueError(f"frame rate must be positive, got {self.rate}")
        bad = ~np.isfinite(self.positions)
        if bad.any():  # a point is missing as a whole: one NaN coordinate hides all three
            self.positions[bad.any(axis=2)] = np.nan

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def n_points(self) -> int:
        return self.positions.shape[1]

    @property
    def duration(self) -> float:
        return self.n_frames / self.rate

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.rate

    @property
    def missing(self) -> np.ndarray:
        """Boolean (frames, points): True where the sample is missing."""
        return np.isnan(self.positions[..., 0])

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no point named {name!r}; have {', '.join(self.names)}") from None

    def select(self, names: Sequence[str]) -> "MotionClip":
        """The clip restricted to (and reordered as) ``names``."""
        idx = [self.index(n) for n in names]
        return self._replace(positions=self.positions[:, idx], names=tuple(names))

    def slice(self, start: int | None = None, stop: int | None = None) -> "MotionClip":
        """Frames ``start:stop`` (Python slice semantics); per-frame ``meta`` arrays
        (:data:`PER_FRAME_META`) are sliced with them."""
        meta = dict(self.meta)
        for key in PER_FRAME_META:
            v = meta.get(key)
            if isinstance(v, np.ndarray) and v.ndim and v.shape[0] == self.n_frames:
                meta[key] = v[start:stop]
        return self._replace(positions=self.positions[start:stop], meta=meta)

    def velocities(self) -> np.ndarray:
        """Backward-difference velocities in m/s, shape like ``positions``.

        ``v[t] = (x[t] - x[t-1]) * rate``; frame 0 and any sample whose predecessor
        is missing get NaN (no velocity can be measured there).
        """
        v = np.full_like(self.positions, np.nan)
        v[1:] = (self.positions[1:] - self.positions[:-1]) * self.rate
        return v

    def _replace(self, **changes) -> "MotionClip":
        kw = dict(positions=self.positions, rate=self.rate, names=self.names, source=self.source,
                  motion_class=self.motion_class, meta=dict(self.meta))
        kw.update(changes)
        return MotionClip(**kw)


def frame_range(spec: str | None, n_frames: int) -> tuple[int, int]:
    """``A:B`` with integers or percentages (``0:90%``, ``90%:``) -> ``(a, b)``, Python slice
    semantics clipped to ``n_frames``; ValueError for a malformed or empty range."""
    if not spec:
        return 0, n_frames
    if ":" not in spec:
        raise ValueError(f"--frames {spec!r}: expected A:B (integers or percentages, e.g. 0:90%)")
    parts = spec.split(":", 1)

    def one(text: str, default: int) -> int:
        text = text.strip()
        if not text:
            return default
        try:
            if text.endswith("%"):
                return int(round(float(text[:-1]) / 100.0 * n_frames))
            v = int(text)
        except ValueError:
            raise ValueError(f"--frames {spec!r}: {text!r} is not an integer or percentage") from None
        return v if v >= 0 else n_frames + v

    a, b = one(parts[0], 0), one(parts[1], n_frames)
    a, b = max(0, min(a, n_frames)), max(0, min(b, n_frames))
    if b <= a:
        raise ValueError(f"--frames {spec!r} selects no frames of {n_frames}")
    return a, b

