"""``dtm-calibrate``: set a model's body terms to one person from a few seconds of them."""
from __future__ import annotations

import argparse
import json
import sys

from ..model.io import load_model, save_model
from ..motion.load import load_clip
from ..training.calibrate import LABEL_SOURCES, CalibrationError, calibrate_from_clip
from .common import CliError, HelpFormatter, add_capture_options, capture_kwargs, parse_frames, run_main

EPILOG = """examples:
  dtm-calibrate models/generic.npz rom_trial.c3d --frames 0:600 --out models/alice.npz
  dtm-calibrate models/generic.npz take01.c3d --frames 0:5% --labels model --out models/take01.npz
  dtm-label models/alice.npz take02.c3d --json            # every take of the person with her body
Any motion does: the body terms use the distances between points on one segment (bones,
marker clusters), which every pose shows. 'capture' uses the capture's own labels (an
operator-labelled trial); 'model' labels the frames with the model and keeps the labels the
votes confirm, twice (the second time with the calibrated model); 'auto' takes the capture's
labels when it has the model's points.
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dtm-calibrate", formatter_class=HelpFormatter, epilog=EPILOG,
                                description="Calibrate a model's body terms (segment lengths, reach) to the "
                                            "person in a capture, the way Vicon / OptiTrack subject calibration "
                                            "works; the motion model is kept.")
    p.add_argument("model", metavar="MODEL", help="model file from dtm-train (.npz, format 2)")
    p.add_argument("capture", metavar="CAPTURE", help="recording of the person (.bvh .amc .c3d .csv .trc .tsv)")
    p.add_argument("--frames", default="0:600", help="calibration frames A:B, integers or percentages")
    p.add_argument("--labels", choices=LABEL_SOURCES, default="auto",
                   help="where the calibration frames' labels come from")
    p.add_argument("--out", required=True, metavar="MODEL2", help="calibrated model to write (.npz)")
    p.add_argument("--json", action="store_true", help="print the calibration summary as JSON")
    add_capture_options(p)
    return p


def _main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        model = load_model(args.model)
    except (OSError, ValueError) as e:
        raise CliError(str(e)) from None
    try:
        clip = load_clip(args.capture, **capture_kwargs(args))
    except (OSError, ValueError, KeyError) as e:
        raise CliError(f"{args.capture}: {e}") from None
    a, b = parse_frames(args.frames, clip.n_frames)
    try:
        out, summary = calibrate_from_clip(model, clip.slice(a, b), args.labels)
    except CalibrationError as e:
        raise CliError(f"{args.capture}: {e}") from None
    save_model(out, args.out)
    summary = dict(summary, out=str(args.out), frame_range=[a, b])
    if args.json:
        print(json.dumps(summary, indent=1))
        return 0
    print(f"calibrated  {args.out} from {args.capture} frames {a}:{b} ({summary['source']})")
    print(f"segments    {summary['segments']} of {summary['segments_total']} measured; body scale "
          f"{summary['scale']:.3f} x the generic one; median length change {1000 * summary['median_change_m']:.1f} mm")
    if "confirmed_fraction" in summary:
        print(f"labels      {100 * summary['confirmed_fraction']:.1f} % of label-frames confirmed by the votes")
    return 0


def main(argv=None) -> int:
    return run_main(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
