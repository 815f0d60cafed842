"""``dtm-bag make|play|label|info``: recordings as rosbag2 bags, real-time replay, offline labeling.

``make``  a labelled recording -> bag with ``/markers/unlabeled`` (PointCloud2, points shuffled
          per frame, optional uint32 ``id`` track ids) and ``/markers/ground_truth``
          (LabeledMarkerArray), optionally with simulated occlusions, ghosts and noise.
``play``  replays a bag over DDS on its recorded timeline (``ros2 bag play`` substitute).
``label`` labels a bag offline with the node's engine into a new bag (+ ``/markers/labeled``,
          ``/markers/labeled_cloud``) and scores it against the ground truth.
``info``  topics, counts and duration of a bag.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading

from tqdm import tqdm

from ..labeling import config
from .common import (CliError, HelpFormatter, add_capture_options, add_corruption_arguments, amount_arg,
                     capture_kwargs, expand_inputs, parse_frames, point_spec, run_main)

EPILOG = """examples:
  dtm-bag make walk.bvh --out walk_bag --frames 90%: --occlude 1 --clutter 2 --noise-mm 1
  dtm-bag make capture.c3d --points all --storage sqlite3 --no-ids --out capture_bag
  dtm-bag play walk_bag --rate 0.5 --loop
  dtm-bag play walk_bag --restamp --clock --wait-for markers/unlabeled markers/ground_truth
  dtm-bag label walk.npz walk_bag --out walk_labeled --json
  dtm-bag info walk_labeled
"""


def _pos_float(text: str) -> float:
    v = float(text)
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError("must be > 0")
    return v




def build_parser() -> argparse.ArgumentParser:
    from ..ros.bag import STORAGES

    p = argparse.ArgumentParser(prog="dtm-bag", formatter_class=HelpFormatter, epilog=EPILOG,
                                description="rosbag2 tools: make bags from recordings, replay them over DDS, "
                                            "label them offline.")
    sub = p.add_subparsers(dest="command", required=True, metavar="{make,play,label,info}")

    m = sub.add_parser("make", formatter_class=HelpFormatter, help="recording -> bag (unlabeled cloud + truth)",
                       description="Write a labelled recording as a rosbag2 bag: /markers/unlabeled (PointCloud2, "
                                   "points shuffled per frame) and /markers/ground_truth (LabeledMarkerArray).")
    m.add_argument("input", metavar="INPUT", help="a recording (.bvh .amc .c3d .csv .trc .tsv)")
    m.add_argument("--out", required=True, metavar="BAG", help="bag directory to write")
    m.add_argument("--storage", choices=STORAGES, default="mcap")
    m.add_argument("--points", default="body14", help="body14, all, all,-NAME,... (all but these), or NAME,NAME,... (the labels in the bag)")
    m.add_argument("--frames", default=None, help="frame range A:B, integers or percentages (90%%:)")
    add_corruption_arguments(m)
    m.add_argument("--ids", action=argparse.BooleanOptionalAction, default=True,
                   help="add a uint32 'id' field with mocap-like track ids to the cloud")
    m.add_argument("--frame-id", default="mocap", help="header.frame_id")
    m.add_argument("--seed", type=int, default=0, help="seed of shuffling, occlusions, ghosts and noise")
    m.add_argument("--rate-hz", type=_pos_float, default=None, metavar="HZ",
                   help="re-time the frames at this rate (default: the recording's rate)")
    m.add_argument("--start-time", type=amount_arg, default=1.0, metavar="S",
                   help="stamp of the first frame, seconds since the epoch")
    m.add_argument("--no-ground-truth", action="store_true", help="write only /markers/unlabeled")
    m.add_argument("--drop-unlabelled", action="store_true",
                   help="leave out the recording's unlabelled points (C3D * channels, unnamed CSV columns, markers "
                        "not in --points); by default they are in the cloud as ghosts")
    add_capture_options(m)
    m.add_argument("--force", action="store_true", help="replace BAG if it exists")
    m.add_argument("--json", action="store_true", help="print the summary as JSON")

    y = sub.add_parser("play", formatter_class=HelpFormatter, help="replay a bag over DDS in real time",
                       description="Publish a bag's messages over DDS on their recorded timeline (recorded CDR "
                                   "bytes, one rclpy publisher per topic, reliable QoS). DDS discovery follows "
                                   "the environment (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE); --localhost "
                                   "keeps it on this machine.")
    y.add_argument("bag", metavar="BAG")
    y.add_argument("--rate", type=_pos_float, default=1.0, help="playback speed factor")
    y.add_argument("--loop", action="store_true", help="play again and again until interrupted")
    y.add_argument("--topics", nargs="+", default=None, metavar="TOPIC", help="play only these topics")
    y.add_argument("--start-delay", type=amount_arg, default=0.0, metavar="S",
                   help="pause after the subscribers are there, before the first message")
    y.add_argument("--wait-for", nargs="*", default=None, metavar="TOPIC",
                   help="wait until each of these topics has a subscriber (default: markers/unlabeled; "
                        "give no topic to start at once)")
    y.add_argument("--wait-timeout", type=amount_arg, default=30.0, metavar="S",
                   help="play anyway after waiting this long for subscribers")
    y.add_argument("--clock", action="store_true", help="publish /clock (for use_sim_time)")
    y.add_argument("--restamp", action="store_true",
                   help="set header stamps to the wall-clock send schedule (end-to-end latency = "
                        "reception - stamp); default: recorded stamps as they are")
    y.add_argument("--localhost", action="store_true",
                   help="set ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST for this process")
    y.add_argument("--quiet", action="store_true", help="print nothing but errors")
    y.add_argument("--json", action="store_true", help="print the playback summary as JSON")

    la = sub.add_parser("label", formatter_class=HelpFormatter, help="label a bag offline into a new bag",
                        description="Label every cloud of a bag with the node's engine (StreamLabeler, header "
                                    "stamps as time); write the input topics plus /markers/labeled and "
                                    "/markers/labeled_cloud; score against /markers/ground_truth when present.")
    la.add_argument("model", metavar="MODEL", help="model file from dtm-train (.npz)")
    la.add_argument("bag", metavar="BAG")
    la.add_argument("--out", default=None, metavar="OUT_BAG|FILE",
                    help="bag to write (input topics + labels), or a labelled capture FILE.c3d / FILE.csv (one "
                         "channel per model label, unlabelled points as *N, mm, rate from the stamps); "
                         "default: only score")
    la.add_argument("--storage", choices=STORAGES, default=None, help="storage of OUT_BAG (default: as BAG)")
    la.add_argument("--topic", default="markers/unlabeled", help="cloud topic to label")
    config.add_arguments(la)
    la.add_argument("--force", action="store_true", help="replace OUT_BAG if it exists")
    la.add_argument("--json", action="store_true", help="print one JSON object")
    la.add_argument("--quiet", action="store_true", help="no progress bar")

    i = sub.add_parser("info", formatter_class=HelpFormatter, help="topics, counts and duration of a bag")
    i.add_argument("bag", metavar="BAG")
    i.add_argument("--json", action="store_true")
    return p


# ------------------------------------------------------------------------------------- make

def _make(args) -> int:
    from ..evaluation.corruption import corrupt_clip
    from ..motion.load import load_clip
    from ..motion.pointsets import BODY14
    from ..motion.unlabelled import model_input
    from ..ros.bag import BagError, write_bag

    if args.gap_frames < 1:
        raise CliError("--gap-frames must be >= 1")
    paths = expand_inputs([args.input])
    if len(paths) != 1:
        raise CliError(f"{args.input}: give one recording, not a folder of {len(paths)}")
    points = point_spec(args.points)
    try:
        full = load_clip(paths[0], **capture_kwargs(args))
        labels = full.names if points == "all" else BODY14 if points == "body14" else points
        a, b = parse_frames(args.frames, full.n_frames)
        mi = model_input(full.slice(a, b), labels, keep_unlabelled=not args.drop_unlabelled)
    except (ValueError, KeyError, OSError) as e:
        raise CliError(f"{paths[0]}: {e}") from None
    if not mi.named:
        raise CliError(f"{paths[0]}: names none of the points {', '.join(list(labels)[:6])}...; "
                       "a bag needs the true labels (give --points the take's names)")
    clip = mi.clip
    stream = corrupt_clip(clip, occlude=args.occlude, clutter=args.clutter, noise_mm=args.noise_mm, seed=args.seed,
                          gap_frames=args.gap_frames, extra=mi.extra)
    try:
        s = write_bag(stream, args.out, storage=args.storage, frame_id=args.frame_id, ids=args.ids,
                      start_time=args.start_time, rate_hz=args.rate_hz, ground_truth=not args.no_ground_truth,
                      force=args.force)
    except BagError as e:
        raise CliError(str(e)) from None
    if args.json:
        print(json.dumps(s, indent=1))
        return 0
    print(f"bag       {s['out']} ({s['storage']})")
    print(f"source    {clip.source}")
    print(f"frames    {s['frames']} at {s['rate_hz']:g} Hz = {s['duration_s']:.2f} s, first stamp "
          f"{s['start_time_s']:g} s")
    print(f"labels    {len(s['labels'])}: {' '.join(s['labels'])}")
    print(f"points    {s['points_per_frame']:.1f} per frame ({s['occluded_per_frame']:.1f} hidden, "
          f"{s['ghosts_per_frame']:.1f} ghosts, noise {args.noise_mm:g} mm), ids {'yes' if s['ids'] else 'no'}")
    if mi.n_extra:
        print(f"unlabelled {mi.n_extra} point{'s' if mi.n_extra > 1 else ''} of the recording in the cloud as ghosts "
              f"({', '.join(mi.extra_names[:6])}{' ...' if mi.n_extra > 6 else ''})")
    print(f"topics    {', '.join(s['topics'])}")
    return 0


# ------------------------------------------------------------------------------------- play

def _play(args) -> int:
    if args.localhost:
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    from ..ros.bag import BagError, bag_info
    from ..ros.player import play

    stop = threading.Event()

    def on_term(signum, frame):
        stop.set()

    signal.signal(signal.SIGTERM, on_term)
    say = (lambda s: None) if args.quiet or args.json else (lambda s: print(s, file=sys.stderr, flush=True))
    try:
        info = bag_info(args.bag)
        say(f"playing {args.bag}: {info['messages']} messages, {info['duration_s']:.2f} s at rate {args.rate:g}"
            + (" (loop)" if args.loop else ""))
        wait_for = args.wait_for
        stats = play(args.bag, rate=args.rate, loop=args.loop, topics=args.topics, start_delay=args.start_delay,
                     clock=args.clock, restamp=args.restamp, wait_for=wait_for, wait_timeout=args.wait_timeout,
                     stop=stop, log=say)
    except BagError as e:
        raise CliError(str(e)) from None
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(stats.as_dict(), indent=1))
        return 0
    lat = stats.lateness_ms
    say(f"sent {sum(stats.sent.values())} messages (" + ", ".join(f"{t} {n}" for t, n in stats.sent.items())
        + f") in {stats.duration_s:.2f} s; lateness p50 {lat.get('p50', float('nan')):.2f} ms, "
          f"p99 {lat.get('p99', float('nan')):.2f} ms, max {lat.get('max', float('nan')):.2f} ms"
        + (f"; the first send was held {stats.start_held_ms:.0f} ms, the timeline starts after it"
           if stats.start_held_ms else "")
        + (" (stopped)" if stats.stopped else ""))
    return 0


# ------------------------------------------------------------------------------------ label

def _label(args) -> int:
    from pathlib import Path

    import numpy as np

    from ..evaluation.labelled_capture import OUTPUT_SUFFIXES, from_stamped
    from ..model.io import load_model
    from ..labeling.anonymous_presence import AnonymousPresence
    from ..ros.bag import BagError, label_bag

    try:
        model = load_model(args.model)
    except (OSError, ValueError, KeyError) as e:
        raise CliError(f"{args.model}: cannot read model: {e}") from None
    try:
        settings = config.settings_from_params(config.params_from_args(args))
    except (ValueError, KeyError, OSError) as e:
        raise CliError(str(e)) from None
    bar = tqdm(desc="labeling", unit="frame", file=sys.stderr, disable=True if (args.quiet or args.json) else None,
               leave=False)

    def progress(i: int, n: int) -> None:
        bar.total = n
        bar.update(i - bar.n)

    capture = args.out is not None and Path(args.out).suffix.lower() in OUTPUT_SUFFIXES
    if capture and Path(args.out).exists() and not args.force:
        raise CliError(f"{args.out} exists (use --force to replace it)")
    clouds: list = []

    def keep(xyz, res, stamp_ns: int) -> None:
        clouds.append((stamp_ns, np.asarray(xyz, dtype=np.float64), np.asarray(res.labels), np.asarray(res.track_ids)))

    try:
        s = label_bag(model, args.bag, None if capture else args.out, settings, storage=args.storage, topic=args.topic,
                      force=args.force, progress=progress, on_frame=keep if capture else None)
        presence = s.get("anonymous_points")
        if presence and presence["absent"]:      # the bag lacks those markers: labelled without them
            clouds.clear()
            model = model.named_only()
            s = label_bag(model, args.bag, None if capture else args.out, settings, storage=args.storage,
                          topic=args.topic, force=True, progress=progress, on_frame=keep if capture else None)
            s["anonymous_points"], s["note"] = presence, AnonymousPresence.from_dict(presence).note()
        if capture:
            written = from_stamped(clouds, model.labels).write(args.out)
            s["out"] = str(written)
    except (BagError, ValueError) as e:
        raise CliError(str(e)) from None
    finally:
        bar.close()
    s["model"] = str(args.model)
    if args.json:
        print(json.dumps(s, indent=1))
        return 0
    lat = s["latency_ms"]
    print(f"model      {args.model} ({s['labels']} labels), {s['method']}, {s['mode']} mode")
    print(f"bag        {args.bag}: {s['frames']} frames" + (f" -> {s['out']}" if s["out"] else ""))
    if s["true_markers"]:
        print(f"accuracy   {100 * s['accuracy']:.2f} % of {s['true_markers']} visible true markers "
              f"({s['scored_frames']} frames with ground truth)")
        if s["ghosts"]:
            print(f"ghosts     {100 * s['ghost_rejection']:.2f} % of {s['ghosts']} left unlabeled")
    else:
        print("accuracy   n/a (no /markers/ground_truth in the bag)")
    print(f"latency    p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms, max {lat['max']:.2f} ms per frame; "
          f"{s['fps']:.0f} frames/s")
    if s.get("note"):
        print(f"note       {s['note']}")
    return 0


def _info(args) -> int:
    from ..ros.bag import BagError, bag_info
    try:
        s = bag_info(args.bag)
    except BagError as e:
        raise CliError(str(e)) from None
    if args.json:
        print(json.dumps(s, indent=1))
        return 0
    print(f"bag       {s['path']} ({s['storage']})")
    print(f"messages  {s['messages']}, {s['duration_s']:.3f} s from {s['start_s']:.3f} s")
    for t, d in s["topics"].items():
        print(f"  {t:28s} {d['type']:42s} {d['count']}")
    return 0


def _main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    return {"make": _make, "play": _play, "label": _label, "info": _info}[args.command](args)


def main(argv=None) -> int:
    return run_main(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
