"""Argument parsing and input helpers shared by the console scripts."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from ..motion.clip import MotionClip
from ..motion.load import load_clip
from ..motion.pointsets import to_point_set

RECORDING_SUFFIXES = (".bvh", ".amc", ".c3d", ".csv")


class CliError(Exception):
    """A user-facing error: printed without a traceback, exit status 2."""


def parse_frames(spec: str | None, n_frames: int) -> tuple[int, int]:
    """``A:B`` with integers or percentages (``0:90%``, ``90%:``); Python slice semantics."""
    if not spec:
        return 0, n_frames
    if ":" not in spec:
        raise CliError(f"--frames {spec!r}: expected A:B (integers or percentages, e.g. 0:90%)")
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
            raise CliError(f"--frames {spec!r}: {text!r} is not an integer or percentage") from None
        return v if v >= 0 else n_frames + v

    a, b = one(parts[0], 0), one(parts[1], n_frames)
    a, b = max(0, min(a, n_frames)), max(0, min(b, n_frames))
    if b <= a:
        raise CliError(f"--frames {spec!r} selects no frames of {n_frames}")
    return a, b


def expand_inputs(inputs: Sequence[str]) -> list[Path]:
    """Files as given; folders searched recursively for recordings (FBX and ASF skipped:
    the BVH and AMC files carry the same motion)."""
    out: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            found = sorted(q for q in p.rglob("*") if q.suffix.lower() in RECORDING_SUFFIXES
                           and "positions_csv" not in q.parts)
            if not found:
                raise CliError(f"{p}: no recordings (.bvh .amc .c3d .csv) found")
            out.extend(found)
        elif p.is_file():
            out.append(p)
        else:
            raise CliError(f"{p}: no such file or folder")
    return out


def point_spec(spec: str) -> str | list[str]:
    if spec in ("body14", "all"):
        return spec
    names = [s.strip() for s in spec.split(",") if s.strip()]
    if len(names) < 3:
        raise CliError("--points needs body14, all, or at least 3 comma-separated names")
    return names


def load_inputs(inputs: Sequence[str], points: str | list[str], frames: str | None = None) -> list[MotionClip]:
    clips = []
    for path in expand_inputs(inputs):
        try:
            clip = load_clip(path)
            clip = to_point_set(clip, points)
        except (ValueError, KeyError, OSError) as e:
            raise CliError(f"{path}: {e}") from None
        a, b = parse_frames(frames, clip.n_frames)
        clips.append(clip.slice(a, b))
    return clips


def count_arg(text: str) -> int:
    v = int(text)
    if v < 0:
        raise argparse.ArgumentTypeError("must be >= 0")
    return v


def amount_arg(text: str) -> float:
    v = float(text)
    if not v >= 0 or v == float("inf"):
        raise argparse.ArgumentTypeError("must be a finite number >= 0")
    return v


def _frames(text: str) -> float:
    v = float(text)
    if not v >= 1 or v == float("inf"):
        raise argparse.ArgumentTypeError("must be >= 1")
    return v


def add_corruption_arguments(parser: argparse.ArgumentParser, occlude: int = 0, gap_frames: float = 1.0,
                             clutter: int = 0, noise_mm: float = 0.0) -> None:
    """The simulated capture faults of a labelled recording turned into a stream (hidden points,
    their gap lengths, ghost points, noise; :func:`dtm_labeler.evaluation.corruption.corrupt_clip`),
    declared once for every console script that makes streams."""
    parser.add_argument("--occlude", type=count_arg, default=occlude, metavar="K", help="hide K true points per frame")
    parser.add_argument("--gap-frames", type=_frames, default=gap_frames, metavar="G",
                        help="mean length of a simulated occlusion in frames (1: new hidden set every frame)")
    parser.add_argument("--clutter", type=count_arg, default=clutter, metavar="K",
                        help="K ghost points per frame (short-lived tracks near the body)")
    parser.add_argument("--noise-mm", type=amount_arg, default=noise_mm, metavar="S",
                        help="Gaussian noise, std per coordinate (mm)")


def run_main(main_body, argv=None) -> int:
    try:
        return main_body(argv)
    except CliError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help with every default shown and the examples epilog kept as written."""
