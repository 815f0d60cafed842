"""``dtm-train``: learn a triangulated model (structure + per-triangle mixtures) from recordings."""
from __future__ import annotations

import argparse
import json
import sys

from tqdm import tqdm

from ..model.io import save_model
from ..model.training import MIXTURE_KINDS, STRUCTURE_METHODS, TrainConfig, train_model
from .common import CliError, HelpFormatter, load_inputs, point_spec, run_main

EPILOG = """examples:
  dtm-train ../shared/data/cmu_skeletal/bvh_from_fbx --out walk_run_dance.npz
  dtm-train walk.bvh --frames 0:90% --structure greedy --mixture fixed --k-fixed 3 --out m.npz
  dtm-train capture.c3d --points all --out markers41.npz
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dtm-train", formatter_class=HelpFormatter, epilog=EPILOG,
                                description="Train a decomposable triangulated model (Hu & Wong): "
                                            "structure search + one Gaussian mixture per triangle.")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="recordings (.bvh .amc .c3d .csv) or folders of them")
    p.add_argument("--out", required=True, help="model file to write (.npz)")
    p.add_argument("--points", default="body14",
                   help="body14 (the paper's 14 points), all (every labelled marker), or NAME,NAME,...")
    p.add_argument("--frames", default=None, help="frame range A:B, integers or percentages (0:90%%)")
    p.add_argument("--mixture", choices=MIXTURE_KINDS, default="mdl",
                   help="mdl: EM with the MDL rule choosing K (eq. 8-11); fixed: K = --k-fixed; single: one Gaussian")
    p.add_argument("--k-min", type=int, default=1)
    p.add_argument("--k-max", type=int, default=8)
    p.add_argument("--k-fixed", type=int, default=3)
    p.add_argument("--structure", choices=STRUCTURE_METHODS, default="cbga",
                   help="cbga (constraint-based GA), greedy (Song et al.), sga (simple GA), given (hand-made, body14)")
    p.add_argument("--position-floor", type=float, default=0.02, metavar="M",
                   help="covariance floor for relative positions (std, metres)")
    p.add_argument("--velocity-floor", type=float, default=0.2, metavar="MPS",
                   help="covariance floor for velocities (std, m/s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    config = TrainConfig(mixture=args.mixture, k_min=args.k_min, k_max=args.k_max, k_fixed=args.k_fixed,
                         structure=args.structure, seed=args.seed, position_floor_m=args.position_floor,
                         velocity_floor_mps=args.velocity_floor)
    try:
        config.check()
    except ValueError as e:
        raise CliError(str(e)) from None
    clips = load_inputs(args.inputs, point_spec(args.points), args.frames)
    bar = None if args.quiet or args.json else tqdm(total=1, desc="training", unit="step", file=sys.stderr)

    def progress(stage: str, i: int, k: int) -> None:
        if bar is not None:
            bar.set_description(stage)
            bar.total = k
            bar.n = i
            bar.refresh()

    try:
        model, summary = train_model(clips, config, progress)
    except ValueError as e:
        raise CliError(str(e)) from None
    finally:
        if bar is not None:
            bar.close()
    save_model(model, args.out)
    s = summary.as_dict() | {"out": str(args.out)}
    if args.json:
        print(json.dumps(s, indent=1))
        return 0
    print(f"model     {args.out}")
    print(f"clips     {len(clips)}: " + ", ".join(c.source.split('/')[-1] for c in clips))
    print(f"frames    {s['frames_total']} ({s['frames_complete']} with every point seen)")
    print(f"labels    {len(s['labels'])}: {' '.join(s['labels'])}")
    print(f"structure {s['structure_method']}: " + "  ".join("(" + ",".join(t) + ")" for t in s["structure"]))
    print(f"K         {s['components']}  (mixture: {args.mixture})")
    print(f"loglik    {s['loglik_per_frame']:.2f} per frame (model); structure score "
          f"{s['structure_loglik_per_frame']:.2f} per frame (Gaussian)")
    print(f"msg len   {sum(s['message_length']):.0f} nats total over triangles")
    print(f"time      {s['seconds']:.1f} s")
    return 0


def main(argv=None) -> int:
    return run_main(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
