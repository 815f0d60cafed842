"""``dtm-train``: learn a triangulated model (structure + per-triangle mixtures) from recordings."""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from tqdm import tqdm

from ..model.dtm import REST_MARGIN
from ..model.io import save_model
from ..motion.naming import one_subject
from ..search.problem import Background
from ..training.anonymous import with_riding_markers
from ..training.calibrate import one_person_by_lengths
from ..training.train import BODY_AUGMENTATION, MIXTURE_KINDS, STRUCTURE_METHODS, TrainConfig, train_model
from .common import (CliError, HelpFormatter, add_capture_options, capture_kwargs, load_inputs, point_spec,
                     run_main)

_DEFAULTS = TrainConfig()


def _jitter(text: str) -> float | None:
    """A relative sd, or ``auto`` (None: the measured default for the 14 body points, 0 otherwise)."""
    if text.strip().lower() == "auto":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number or 'auto'") from None


EPILOG = """examples:
  dtm-train ../shared/data/cmu_skeletal/bvh_from_fbx --out walk_run_dance.npz
  dtm-train walk.bvh --frames 0:90% --structure greedy --mixture fixed --k-fixed 3 --out m.npz
  dtm-train capture.c3d --points all --out markers41.npz
  dtm-train walk.bvh --scale-jitter 0 --proportion-jitter 0 --tempo-jitter 0 --out m.npz   # no body augmentation
  dtm-train ../shared/data/markers_c3d/cmu_85_0*.c3d --points all --out generic41.npz   # grown along the body
  dtm-train capture.c3d --points all --frames 0:70% --structure cbga --out take41.npz   # only for this take's motion
model bank (one model per action, Ukita L1-L3; the other actions' files are not touched):
  dtm-train walk.bvh --action walk --bank bank/
  dtm-train run.bvh --action run --bank bank/            # + synthesized walk<->run paths
  dtm-train dance.bvh --action dance --bank bank/ --no-transitions
  dtm-train dance.bvh --action dance --bank bank/ --retrain-neighbours   # paths into every model
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dtm-train", formatter_class=HelpFormatter, epilog=EPILOG,
                                description="Train a decomposable triangulated model (Hu & Wong): "
                                            "structure search + one Gaussian mixture per triangle.")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="recordings (.bvh .amc .c3d .csv .trc .tsv) or folders of them")
    p.add_argument("--out", default=None, help="model file to write (.npz); required unless --bank is given")
    p.add_argument("--points", default="body14",
                   help="body14 (the paper's 14 points), all (every labelled marker), all,-NAME,... (every "
                        "labelled marker but these), or NAME,NAME,...")
    p.add_argument("--frames", default=None, help="frame range A:B, integers or percentages (0:90%%)")
    p.add_argument("--ignore-unlabelled", action="store_true",
                   help="learn nothing of the capture's unlabelled (*) trajectories. Default: of one capture, "
                        "those seen often that ride on the body (a marker the set does not name: a back marker, "
                        "a toe, a prop) are learnt as anonymous points, which dtm-label and the node publish "
                        "unlabelled -- so that such a marker does not take the label of a hidden marker beside it")
    p.add_argument("--mixture", choices=MIXTURE_KINDS, default="mdl",
                   help="mdl: EM with the MDL rule choosing K (eq. 8-11); fixed: K = --k-fixed; single: one Gaussian")
    p.add_argument("--k-min", type=int, default=1)
    p.add_argument("--k-max", type=int, default=8)
    p.add_argument("--k-fixed", type=int, default=3)
    p.add_argument("--structure", choices=STRUCTURE_METHODS, default="auto",
                   help="auto (cbga for the 14 body points, body for marker sets), cbga (constraint-based GA), "
                        "greedy (Song et al.), sga (simple GA), given (hand-made, body14), body (greedy along the "
                        "most rigid tree: every point joins the segment it hangs from, so every bone carries its "
                        "body term and the model holds for motions the takes never showed)")
    p.add_argument("--position-floor", type=float, default=0.02, metavar="M",
                   help="covariance floor for relative positions (std, metres)")
    p.add_argument("--velocity-floor", type=float, default=0.2, metavar="MPS",
                   help="covariance floor for velocities (std, m/s)")
    a = p.add_argument_group("augmentation (copies of the training frames performed by other bodies, so the model "
                             "labels people of other sizes, proportions and speeds than the recorded ones; 'auto' = "
                             + ", ".join(f"{k.split('_')[0]} {v:g}" for k, v in BODY_AUGMENTATION.items())
                             + " for the 14 body points, 0 for other point sets such as --points all)")
    a.add_argument("--augment-copies", type=int, default=_DEFAULTS.augment_copies, metavar="N",
                   help="augmented copies of every training frame (each with its own random body and tempo); "
                        "0 = the recorded frames only")
    a.add_argument("--scale-jitter", type=_jitter, default="auto", metavar="SD",
                   help="relative sd of a random isotropic body scale per copied frame (0.05 = people about 5 %% "
                        "taller or shorter); positions and velocities scale together")
    a.add_argument("--proportion-jitter", type=_jitter, default="auto", metavar="SD",
                   help="relative sd of a random length factor per body segment (the most rigid links between "
                        "points: bones, the trunk) per copied frame: other limb proportions and marker placements")
    a.add_argument("--tempo-jitter", type=_jitter, default="auto", metavar="SD",
                   help="relative sd of a random tempo per copied frame: the same poses performed faster or "
                        "slower (every velocity times the factor, positions kept)")
    a.add_argument("--yaw-jitter", type=float, default=_DEFAULTS.yaw_jitter_deg, metavar="DEG",
                   help="uniform heading error in +-DEG per copied frame (tolerance to heading noise)")
    g = p.add_argument_group("body model (motions the training never showed; --calibrate / dtm-calibrate set a person's body)")
    g.add_argument("--body-terms", action=argparse.BooleanOptionalAction, default=True,
                   help="motion-independent terms on the structure's edges: segment lengths (bones, marker "
                        "clusters; applied once calibrated to a person: --calibrate, dtm-calibrate) and reach limits")
    g.add_argument("--broad-component", action=argparse.BooleanOptionalAction, default=True,
                   help="one broad component per triangle mixture, its weight fitted on held-out frames, so a "
                        "pose the training never showed is not vetoed; applied once the body is calibrated "
                        "(--calibrate, dtm-calibrate, dtm-label --calibrate, ~/calibrate): with a generic body it would make "
                        "ghosts near the body cheap to label")
    g.add_argument("--calibrate", nargs="?", const="on", default="auto", choices=("auto", "on", "off"),
                   help="calibrate the body terms to the takes' person (their segment lengths from the takes' own "
                        "labels, as dtm-calibrate on a labelled capture), so the model is that person's from the "
                        "start: 'auto' (default) when the takes are known to be one person (one capture, or CMU "
                        "takes of one subject), 'on' (or the bare flag): the takes are one person, 'off': a "
                        "generic body. dtm-label sets the calibration aside for a capture of someone else and "
                        "self-calibrates there (its --calibrate auto)")
    p.add_argument("--seed", type=int, default=0)
    b = p.add_argument_group("model bank (one model per action, Ukita sections 4.1-4.4)")
    b.add_argument("--action", default=None, metavar="NAME",
                   help="train the model of action NAME into --bank (added, or replaced if present)")
    b.add_argument("--bank", default=None, metavar="DIR", help="bank directory (bank.json + one model per action)")
    b.add_argument("--transitions", action=argparse.BooleanOptionalAction, default=True,
                   help="train with paths synthesized between this action and every action already in the bank "
                        "(L2: only the new model gets them unless --retrain-neighbours)")
    b.add_argument("--retrain-neighbours", action="store_true",
                   help="also retrain every other action with its recorded sources plus the paths to all actions "
                        "(their files change)")
    b.add_argument("--transition-distance", type=float, default=0.10, metavar="M",
                   help="end points of transition paths: RMS pose distance per body point below M (or below "
                        "1.25 x the pair's closest distance when larger)")
    add_capture_options(p)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if (args.action is None) != (args.bank is None):
        raise CliError("--action and --bank go together")
    if args.out is None and args.bank is None:
        raise CliError("--out is required (or --action NAME --bank DIR)")
    config = TrainConfig(mixture=args.mixture, k_min=args.k_min, k_max=args.k_max, k_fixed=args.k_fixed,
                         structure=args.structure, seed=args.seed, position_floor_m=args.position_floor,
                         velocity_floor_mps=args.velocity_floor, augment_copies=args.augment_copies,
                         scale_jitter=args.scale_jitter, proportion_jitter=args.proportion_jitter,
                         tempo_jitter=args.tempo_jitter, yaw_jitter_deg=args.yaw_jitter,
                         body_terms=args.body_terms, broad_component=args.broad_component)
    try:
        config.check()
    except ValueError as e:
        raise CliError(str(e)) from None
    if args.bank is not None:
        return _bank_main(args, config)
    clips = load_inputs(args.inputs, point_spec(args.points), args.frames, capture_kwargs(args))
    for c in clips:
        for key in ("up_axis_note", "fragments_note"):
            if c.meta.get(key) and not args.json:
                print(f"note: {c.source}: {c.meta[key]}" if key == "fragments_note" else f"note: {c.meta[key]}",
                      file=sys.stderr)
    bar = None if args.quiet or args.json else tqdm(total=1, desc="training", unit="step", file=sys.stderr)

    def progress(stage: str, i: int, k: int) -> None:
        if bar is not None:
            bar.set_description(stage)
            bar.total = k
            bar.n = i
            bar.refresh()

    plain, dropped = clips, []
    clips, riding = (plain, []) if args.ignore_unlabelled else with_riding_markers(plain)
    try:
        while True:
            try:
                model, summary = train_model(clips, config, progress)
                break
            except ValueError as e:      # anonymous points the training cannot hold: without them
                out = [r.name for r in riding if r.name in str(e)]
                if not out:
                    raise
                print(f"note: {', '.join(out)} left out ({e})", file=sys.stderr)
                dropped += out
                clips, riding = with_riding_markers(plain, dropped)
    except ValueError as e:
        raise CliError(str(e)) from None
    finally:
        if bar is not None:
            bar.close()
    calibration = None
    why = one_subject([c.source for c in clips]) if args.calibrate == "auto" else \
        ("asked" if args.calibrate == "on" else None)
    if why is None and args.calibrate == "auto" and model.body is not None:
        why = one_person_by_lengths(model, clips)     # several captures no name ties: their bodies may
    if why is not None and (model.body is not None or args.calibrate == "on"):
        model, calibration = _calibrated(model, clips, strict=args.calibrate == "on")
        if calibration is not None:     # kept in the file: dtm-label reads whose the calibration is
            calibration["why"] = model.provenance["calibration"]["why"] = why
    save_model(model, args.out)
    s = summary.as_dict() | {"out": str(args.out)} | ({"calibration": calibration} if calibration else {})
    if model.body is not None:
        s["body"] = {"segments": int(len(model.body.segments)), "rigid_pairs": int(model.body.rigid_pairs.shape[0]),
                     "bar_orders": [[model.labels[i] for i in row] for row in model.body.orders.tolist()],
                     "take_bar_orders": [[model.labels[i] for i in row] for row in model.body.take_orders.tolist()]}
    rests = model.settings.get("longest_rest_s")
    if rests:
        s["longest_rest_s"] = dict(zip(model.labels, rests))
    if riding:
        s["anonymous"] = [dict(name=r.name, channel=r.channel, rides_with=r.partner, distance_m=round(r.distance_m, 4),
                               spread_m=round(r.spread_m, 4), seen=round(r.coverage, 3)) for r in riding]
    if args.json:
        print(json.dumps(s, indent=1))
        return 0
    for note in s.get("notes", []):
        print(f"note: {note}", file=sys.stderr)
    print(f"model     {args.out}")
    print(f"clips     {len(clips)}: " + ", ".join(c.source.split('/')[-1] for c in clips))
    print(f"frames    {s['frames_total']} ({s['frames_complete']} with every point seen)")
    named = [n for n, a in zip(model.labels, model.anonymous) if not a]
    print(f"labels    {len(named)}: {' '.join(named)}" + (f" (+ {len(riding)} anonymous)" if riding else ""))
    if riding:
        print(f"unlabelled {len(riding)} {'trajectory rides' if len(riding) == 1 else 'trajectories ride'} on the "
              "body, learnt as anonymous points (published "
              "unlabelled; --ignore-unlabelled: not learnt): "
              + ", ".join(f"{r.name} ({r.channel}, {100 * r.distance_m:.0f} cm from {r.partner}, seen "
                          f"{100 * r.coverage:.0f} %)" for r in riding))
    cov = sorted(s["coverage"].items(), key=lambda kv: kv[1])
    if cov and cov[0][1] < 0.999:
        print(f"coverage  seen in {100 * float(np.median([v for _, v in cov])):.0f} % of frames (median); least: "
              + ", ".join(f"{k} {100 * v:.0f} %" for k, v in cov[:5])
              + f"; structure scored on {s['structure_scored_on']}")
    why = (f" (auto: {'the 14 body points' if s['structure_method'] == 'cbga' else 'a marker set'})"
           if args.structure == "auto" else "")
    print(f"structure {s['structure_method']}{why}: " + "  ".join("(" + ",".join(t) + ")" for t in s["structure"]))
    print(f"K         {s['components']}  (mixture: {args.mixture})")
    print(f"loglik    {s['loglik_per_frame']:.2f} per frame (model); structure score "
          f"{s['structure_loglik_per_frame']:.2f} per frame (Gaussian)")
    print(f"msg len   {sum(s['message_length']):.0f} nats total over triangles")
    aug = model.settings["augmentation"]
    print(f"augment   {aug['copies']} cop{'y' if aug['copies'] == 1 else 'ies'}" + (
        f": scale sd {aug['scale_sd']:g}, proportion sd {aug['proportion_sd']:g}, tempo sd {aug['tempo_sd']:g}, "
        f"yaw +-{aug['yaw_jitter_deg']:g} deg" if aug["copies"] else ""))
    if "body" in s and s["body"]["rigid_pairs"]:
        print(f"body      {s['body']['segments']} segments; {s['body']['rigid_pairs']} rigid marker pairs of the "
              "person in their clusters (what dtm-label's pass over a take measures it by)")
    if "body" in s and s["body"]["bar_orders"]:
        nearer: dict = {}
        for x, near, far in s["body"]["bar_orders"]:
            nearer.setdefault((near, far), []).append(x)
        print("bars      " + "; ".join(f"{', '.join(xs)} nearer {near} than {far}" for (near, far), xs in nearer.items())
              + (" (applied: calibrated)" if model.body.calibration else " (applied once calibrated)"))
    if "body" in s and s["body"]["take_bar_orders"]:
        print(f"          and {len(s['body']['take_bar_orders'])} orders from the bars' side of the body, which "
              "dtm-label's pass over a take reads over whole stretches (exchanged bars turned back)")
    if rests:
        floor = Background().fixed_after_s
        still = sorted(((r, lab) for lab, r in zip(model.labels, rests) if REST_MARGIN * r > floor), reverse=True)
        print("rests     " + (f"{len(still)} labels stood still for over {floor / REST_MARGIN:.1f} s in training "
                              "(longest: " + ", ".join(f"{lab} {r:.1f} s" for r, lab in still[:6])
                              + (", ..." if len(still) > 6 else "") + ")"
                              if still else f"no label stood still for {floor / REST_MARGIN:.1f} s in training")
              + f"; a point still for longer than {REST_MARGIN:g} x its label's longest rest and {floor:g} s "
              "is scored as possibly a fixed reflection")
    if calibration:
        other = ("every other capture" if calibration["why"] == "asked" else
                 "other CMU takes of the same subject and captures whose self-calibration measures this person's "
                 "lengths")
        kept = (f"dtm-label keeps it on these captures and on {other} (measuring again there the segments "
                "whose markers that session placed elsewhere)"
                + ("" if calibration["why"] == "asked" else ", and self-calibrates anyone else's capture (keeping "
                   "this calibration where that does not hold up)"))
        print(f"person    calibrated to the takes' person ({calibration['why']}): {calibration['segments']} of "
              f"{calibration['segments_total']} segment lengths from {calibration['frames']} frames (scale "
              f"{calibration['scale']:.3f}); {kept}; --calibrate off: generic")
    print(f"time      {s['seconds']:.1f} s")
    return 0


def _calibrated(model, clips, strict: bool = True):
    """``model`` calibrated to the training takes' person and the JSON-ready summary; a
    calibration that cannot be made is an error when asked for (``strict``), else a note and
    the generic model (summary None)."""
    from ..training.calibrate import CalibrationError, calibrate_on_takes
    try:
        out = calibrate_on_takes(model, clips)
    except CalibrationError as e:
        if not strict:
            print(f"note: the body stays generic: {e}", file=sys.stderr)
            return model, None
        raise CliError(f"--calibrate: {e}") from None
    summary = out.provenance["calibration"]
    return out, {k: v for k, v in summary.items() if not isinstance(v, (dict, list))}


def _bank_sources(args):
    """Training recordings as TransitionSources (body14 + local rotations when skeletal)."""
    from ..training.transitions import TransitionSource
    from .common import expand_inputs, parse_frames
    out = []
    for path in expand_inputs(args.inputs):
        try:
            if args.points == "body14":
                src = TransitionSource.load(path)
            else:
                src = TransitionSource(load_inputs([str(path)], point_spec(args.points))[0], None)
        except (ValueError, KeyError, OSError) as e:
            raise CliError(f"{path}: {e}") from None
        a, b = parse_frames(args.frames, src.clip.n_frames)
        if (a, b) != (0, src.clip.n_frames):
            src = TransitionSource(src.clip.slice(a, b), src.skeletal.slice(a, b) if src.skeletal else None)
        src.clip.meta["frame_range"] = [a, b]
        out.append(src)
    return out


def _bank_main(args, config) -> int:
    from ..model.bank import BankFileError, add_to_bank, check_action_name, load_bank
    from ..training.bank_training import load_sources, train_action
    from ..model.bank import BANK_JSON
    from ..training.transitions import TransitionSettings
    from pathlib import Path
    try:
        check_action_name(args.action)
    except BankFileError as e:
        raise CliError(str(e)) from None
    bank_dir = Path(args.bank)
    if bank_dir.suffix.lower() == ".npz":
        raise CliError("--bank must be a directory (single-file banks are written with dtm_labeler.model.bank.save_bank)")
    try:
        bank = load_bank(bank_dir) if (bank_dir / BANK_JSON).is_file() else None
    except BankFileError as e:
        raise CliError(str(e)) from None
    if args.transitions and args.points != "body14":
        raise CliError("--transitions synthesizes body14 poses; use --points body14 or --no-transitions")
    try:
        tset = TransitionSettings(max_distance_m=args.transition_distance) if args.transitions else None
    except ValueError as e:
        raise CliError(str(e)) from None
    sources = _bank_sources(args)
    others = {}
    if bank is not None:
        for a in bank.actions:
            if a != args.action and (tset is not None):
                others[a] = load_sources(bank.records.get(a, {}))
                if not others[a]:
                    print(f"warning: no training recording of action {a!r} found; no paths to it", file=sys.stderr)
    results = []
    try:
        model, record, summary = train_action(args.action, sources, others, config, tset)
        record["transition_mode"] = "L2" if tset is not None else "none"
        bank = add_to_bank(bank_dir, args.action, model, record)
        results.append((args.action, record, summary))
        if args.out:
            save_model(model, args.out)
        if args.retrain_neighbours and tset is not None:
            all_src = {a: (sources if a == args.action else load_sources(bank.records.get(a, {})))
                       for a in bank.actions}
            for a in bank.actions:
                if a == args.action or not all_src[a]:
                    continue
                m2, r2, s2 = train_action(a, all_src[a], {b: v for b, v in all_src.items() if b != a}, config, tset)
                r2["transition_mode"] = "retrained with all"
                bank = add_to_bank(bank_dir, a, m2, r2)
                results.append((a, r2, s2))
    except (ValueError, BankFileError) as e:
        raise CliError(str(e)) from None
    out = {"bank": str(bank_dir), "actions": bank.actions,
           "trained": [{"action": a, "synthesized_frames": r["synthesized_frames"],
                        "transitions": [{k: v for k, v in t.items() if k != "paths_detail"} for t in r["transitions"]],
                        "frames": r["frames"], "seconds": s.seconds, "components": s.components} for a, r, s in results]}
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    print(f"bank      {bank_dir} ({len(bank.actions)} actions: {', '.join(bank.actions)})")
    for a, r, s in results:
        tr = ", ".join(f"{t['with']}: {t['paths']} paths / {t['frames']} frames" for t in r["transitions"]) or "none"
        print(f"{a:9s} {r['frames']} recorded + {r['synthesized_frames']} synthesized frames; transitions {tr}; "
              f"{s.seconds:.1f} s")
    return 0


def main(argv=None) -> int:
    return run_main(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
