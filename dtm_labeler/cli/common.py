"""Argument parsing and input helpers shared by the console scripts."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from ..motion.clip import MotionClip, frame_range
from ..motion.load import load_clip
from ..motion.pointsets import AllBut, to_point_set
from ..motion.qtm_tsv import holds_markers

RECORDING_SUFFIXES = (".bvh", ".amc", ".c3d", ".csv", ".trc", ".tsv")


class CliError(Exception):
    """A user-facing error: printed without a traceback, exit status 2."""


def parse_frames(spec: str | None, n_frames: int) -> tuple[int, int]:
    """``A:B`` with integers or percentages (``0:90%``, ``90%:``); Python slice semantics."""
    try:
        return frame_range(spec, n_frames)
    except ValueError as e:
        raise CliError(str(e)) from None


def expand_inputs(inputs: Sequence[str]) -> list[Path]:
    """Files as given; folders searched recursively for recordings (FBX and ASF skipped:
    the BVH and AMC files carry the same motion; of QTM's ``.tsv`` exports only the 3D ones)."""
    out: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            found = sorted(q for q in p.rglob("*") if q.suffix.lower() in RECORDING_SUFFIXES
                           and "positions_csv" not in q.parts
                           and (q.suffix.lower() != ".tsv" or holds_markers(q)))
            if not found:
                raise CliError(f"{p}: no recordings ({' '.join(RECORDING_SUFFIXES)}) found")
            out.extend(found)
        elif p.is_file():
            out.append(p)
        else:
            raise CliError(f"{p}: no such file or folder")
    return out


def expand_inputs_rel(inputs: Sequence[str]) -> list[tuple[Path, Path]]:
    """:func:`expand_inputs` with each file's path relative to the folder it was found in
    (a file given directly: its name), for mirroring an archive's layout in an output folder."""
    out = []
    for item in inputs:
        p = Path(item)
        for f in expand_inputs([item]):
            out.append((f, f.relative_to(p) if p.is_dir() else Path(f.name)))
    return out


def add_capture_options(p: argparse.ArgumentParser) -> None:
    """``--up-axis``, ``--units``, ``--asf``: how to read captures whose files do not say."""
    g = p.add_argument_group("reading captures")
    g.add_argument("--up-axis", default="auto", type=str.upper, choices=("AUTO", "X", "Y", "Z"), metavar="AXIS",
                   help="vertical axis of the marker files: auto (C3D POINT:Y_SCREEN or the CSV comments, checked "
                        "against the body; else the body's long axis), or X, Y, Z to force it")
    g.add_argument("--units", default=None, choices=("mm", "cm", "m", "inch"),
                   help="length unit of the files' numbers when their own statement is wrong or missing "
                        "(default: C3D POINT:UNITS, CSV comments, else mm)")
    g.add_argument("--subject", default=None, metavar="NAME",
                   help="in a capture of several subjects (the same marker names under prefixes NAME:...), the "
                        "one whose markers are the points; the others' are unlabelled points")
    g.add_argument("--asf", default=None, metavar="PATH",
                   help="skeleton for .amc takes (default: same name, the CMU subject's NN.asf for NN_MM.amc, "
                        "or the only .asf in the folder)")


def capture_kwargs(args) -> dict:
    """``load_clip`` keywords from :func:`add_capture_options` arguments."""
    kw = {"up_axis": args.up_axis}
    if args.units:
        kw["units"] = args.units
    if getattr(args, "subject", None):
        kw["subject"] = args.subject
    if args.asf:
        if not Path(args.asf).is_file():
            raise CliError(f"--asf {args.asf}: no such file")
        kw["asf_path"] = args.asf
    return kw


def point_spec(spec: str) -> str | list[str] | AllBut:
    """``--points``: body14, all, all,-NAME,... (every point but these), or NAME,NAME,..."""
    if spec in ("body14", "all"):
        return spec
    names = [s.strip() for s in spec.split(",") if s.strip()]
    if names and names[0] == "all":
        left_out = [n[1:].strip() if n.startswith("-") else "" for n in names[1:]]
        if not left_out or not all(left_out):
            raise CliError("--points all,-NAME,...: every name after 'all' starts with '-' (the points left out)")
        return AllBut(tuple(left_out))
    if len(names) < 3:
        raise CliError("--points needs body14, all, or at least 3 comma-separated names")
    return names


def load_inputs(inputs: Sequence[str], points: str | list[str], frames: str | None = None,
                load: dict | None = None) -> list[MotionClip]:
    clips = []
    for path in expand_inputs(inputs):
        try:
            clip = load_clip(path, **(load or {}))
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
