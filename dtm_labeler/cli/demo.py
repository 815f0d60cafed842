"""``dtm-demo``: the whole system in one command -- train, make a stream, run the node, replay, score.

With no arguments (the embedded default, no files needed):

1. trains a model on a synthetic BODY14 walker (cached under ``$XDG_CACHE_HOME/dtm_labeler`` or
   ``~/.cache/dtm_labeler``; a temp dir if that is not writable);
2. makes a test stream from a *different* synthetic walker (other seed, speed, heading and
   style), with noise, occlusion gaps and ghost points, and writes it as a bag;
3. starts the node (``dtm-labeler-node``, its own process) and the player (``dtm-bag play
   --restamp``, another process), both with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and the
   demo's ``ROS_DOMAIN_ID`` in their environment;
4. subscribes to ``markers/labeled``, ``markers/ground_truth`` and ``/diagnostics`` and prints a
   line a second (frames, accuracy, end-to-end latency) and a final summary, then stops both
   processes (SIGINT, then SIGTERM/SIGKILL if needed). Exit status 1 if the node failed.

End-to-end latency = DDS reception of the labelled frame in this process (the message info's
time: this process's own pauses do not count) - the header stamp the player put on the cloud
(its wall-clock send schedule); it includes DDS both ways, decoding, labeling and publishing.

``--data PATH`` replays a real recording instead: the model is trained on its first 70 %
(``--train-frames``; cached too) and the rest (``--test-frames``) is replayed, so the labelled
frames were never seen in training. The recording is one person, so the model is calibrated to
them as ``dtm-train --calibrate`` does (the training frames' own labels set the body terms: what a
lab does with a subject's range-of-motion take before capturing them); ``--no-calibrate`` keeps
the generic model. ``--model`` skips training.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .common import CliError, HelpFormatter, add_corruption_arguments, run_main

EPILOG = """examples:
  dtm-demo
  dtm-demo --occlude 2 --gap-frames 1 --clutter 2       flicker: a new 2 of the 14 points hidden every frame, 2 ghosts
  dtm-demo --data ../shared/data/markers_c3d/hdm05_bd_05-01_01_120.c3d --points all --train-frames 0:70% \\
           --occlude 3 --gap-frames 1 --clutter 2       41 markers, 3 flickering + 2 ghosts
  dtm-demo --duration 20 --rate-hz 360 --occlude 2 --clutter 3
  dtm-demo --data ../shared/data/cmu_skeletal/bvh_from_fbx/cmu_55_01_dance-whirl_s55.bvh
  dtm-demo --data capture.c3d --points all --train-frames 0:80% --json
"""

#: the embedded default: training walker and (different) test walker
TRAIN_WALKER = dict(duration=8.0, rate=120.0, speed=1.3, heading=0.0, gait="walk", seed=0)
TEST_WALKER = dict(speed=1.15, heading=0.9, gait="walk", seed=7, height=1.70, start_xy=(0.5, -1.0))


# ------------------------------------------------------------------------ processes (shared)

def ros_env(domain_id: int | None = None, base: dict | None = None) -> dict:
    """Environment for a child that runs rclpy: rule one (LOCALHOST) and a ROS_DOMAIN_ID
    (given, else the current one, else one derived from this process id)."""
    env = dict(os.environ if base is None else base)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(int(domain_id))
    else:
        env.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def _script(name: str, module: str) -> list[str]:
    """``[venv/bin/name]`` when installed next to this Python, else ``[python, -m, module]``."""
    exe = Path(sys.executable).parent / name
    if exe.is_file() and os.access(exe, os.X_OK):
        return [str(exe)]
    return [sys.executable, "-m", module]


def start_node(model_path: str | Path, env: dict, log_path: str | Path | None = None,
               params: dict | None = None, params_file: str | Path | None = None) -> subprocess.Popen:
    """Start ``dtm-labeler-node`` with ``model_path`` (+ ``-p`` params) in its own process."""
    cmd = _script("dtm-labeler-node", "dtm_labeler.ros.node") + ["--ros-args"]
    if params_file:
        cmd += ["--params-file", str(params_file)]
    for k, v in {"model_path": str(model_path), **(params or {})}.items():
        v = str(v).lower() if isinstance(v, bool) else v
        cmd += ["-p", f"{k}:={v}"]
    out = open(log_path, "wb") if log_path else subprocess.DEVNULL
    return subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)


def start_player(bag: str | Path, env: dict, extra: list[str] | None = None) -> subprocess.Popen:
    """Start ``dtm-bag play BAG --json ...`` in its own process (summary JSON on stdout)."""
    cmd = _script("dtm-bag", "dtm_labeler.cli.bag") + ["play", str(bag), "--json"] + list(extra or [])
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)


def stop_process(proc: subprocess.Popen, timeout: float = 5.0) -> int:
    """SIGINT (clean shutdown), then SIGTERM, then SIGKILL; returns the exit status."""
    if proc.poll() is not None:
        return proc.returncode
    for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
        try:
            proc.send_signal(sig)
        except ProcessLookupError:
            break
        try:
            return proc.wait(wait)
        except subprocess.TimeoutExpired:
            continue
    return proc.wait()


def tail(path: str | Path, n: int = 15) -> str:
    try:
        return "\n".join(Path(path).read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


# ------------------------------------------------------------------------------ data + model

def cache_dir() -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "dtm_labeler"
    try:
        base.mkdir(parents=True, exist_ok=True)
        probe = base / ".write_test"
        probe.write_text("")
        probe.unlink()
        return base
    except OSError:
        d = Path(tempfile.gettempdir()) / "dtm_labeler_cache"
        d.mkdir(parents=True, exist_ok=True)
        return d


def resample(clip, rate: float):
    """The clip at ``rate`` Hz by linear interpolation in time (NaN where a neighbour is missing)."""
    if abs(rate - clip.rate) < 1e-9:
        return clip
    t_old = clip.times
    n = max(int(np.floor(t_old[-1] * rate + 1e-9)) + 1, 1)
    t = np.arange(n) / rate
    i = np.clip(np.searchsorted(t_old, t, side="right") - 1, 0, clip.n_frames - 1)
    j = np.minimum(i + 1, clip.n_frames - 1)
    w = np.where(j > i, (t - t_old[i]) * clip.rate, 0.0)[:, None, None]
    pos = (1 - w) * clip.positions[i] + w * clip.positions[j]
    out = clip._replace(positions=pos, rate=float(rate))
    out.meta["resampled_from_hz"] = clip.rate
    return out


#: the demo's structure search: it trains on the first part of the take it then plays, and within
#: one take the CBGA's triangles, free to relate any points the take moves together, label best
#: (HDM05, 41 markers, 3 flickering + 2 ghosts, 12 s live, two runs each: 97.1-97.5 % right,
#: 95.6-96.8 % of ghosts rejected; grown along the rigid tree, dtm-train's default for marker
#: sets because it holds for other motions: 95.4 %, 91.2-91.6 %)
DEMO_STRUCTURE = "cbga"


#: the packages whose code decides what a trained model holds (:func:`training_revision`)
TRAINING_PACKAGES = ("motion", "model", "search", "training")


def training_revision() -> str:
    """A hash of the source of :data:`TRAINING_PACKAGES`: code that trains differently (a body
    term's rule, a structure's growth) gives another revision, with the file format unchanged."""
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha1()
    for pkg in TRAINING_PACKAGES:
        for f in sorted((root / pkg).glob("*.py")):
            h.update(f"{pkg}/{f.name}".encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:12]


def cached_model_path(key: dict) -> Path:
    """Where the demo keeps the model trained for ``key``: named by a hash of the key, the
    model file format and the training code's revision, so a newer format (new model terms) or
    training that has changed trains again instead of reusing the older model."""
    from ..model import io as model_io

    key = dict(key, format_version=model_io.FORMAT_VERSION, structure=DEMO_STRUCTURE,
               training=training_revision())
    h = hashlib.sha1(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:12]
    return cache_dir() / f"demo_model_{h}.npz"


def _train_cached(key: dict, make_clips, quiet: bool, log, calibrate: bool = False) -> Path:
    """Train (or reuse) a model for ``key`` (structure :data:`DEMO_STRUCTURE`), calibrated to
    the clips' one person when asked (:func:`~dtm_labeler.training.calibrate.calibrate_on_takes`);
    returns the model path."""
    from ..model.io import save_model
    from ..training.calibrate import calibrate_on_takes
    from ..training.train import TrainConfig, train_model

    path = cached_model_path(key)
    if path.is_file():
        log(f"model     {path} (cached)")
        return path
    t = time.perf_counter()
    clips = make_clips()
    model, summary = train_model(clips, TrainConfig(seed=0, structure=DEMO_STRUCTURE))
    if calibrate:
        model = calibrate_on_takes(model, clips)
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    save_model(model, tmp)
    os.replace(tmp, path)
    log(f"model     {path} (trained{' and calibrated to the person' if calibrate else ''} in "
        f"{time.perf_counter() - t:.1f} s on {sum(c.n_frames for c in clips)} frames)")
    return path


def prepare(args, work: Path, log) -> tuple[Path, Path, dict]:
    """(model path, bag path, description) for the demo arguments."""
    from ..evaluation.corruption import corrupt_clip
    from ..model.io import load_model
    from ..motion import synthesize
    from ..ros.bag import write_bag
    from ..motion.pointsets import model_points
    from .common import load_inputs, parse_frames, point_spec

    rate = args.rate_hz
    if args.data is None:
        train = dict(TRAIN_WALKER)
        model_path = Path(args.model) if args.model else _train_cached(
            {"synthetic": train, "v": 1}, lambda: [synthesize(**train)], args.quiet, log)
        model = load_model(model_path)
        clip = synthesize(duration=args.duration, rate=rate or 120.0, noise_mm=0.0, **TEST_WALKER)
        what = (f"synthetic walker (seed {TEST_WALKER['seed']}, {TEST_WALKER['speed']} m/s, heading "
                f"{TEST_WALKER['heading']} rad) -- trained on another (seed {train['seed']}, {train['speed']} m/s, "
                f"heading {train['heading']})")
    else:
        data = Path(args.data)
        if not data.is_file():
            raise CliError(f"--data {data}: no such file")
        points = point_spec(args.points)
        full = load_inputs([str(data)], points)[0]
        a, b = parse_frames(args.train_frames, full.n_frames)
        if args.model:
            model_path = Path(args.model)
        else:
            calibrate = not args.no_calibrate
            model_path = _train_cached({"data": str(data.resolve()), "mtime": data.stat().st_mtime,
                                        "points": args.points, "frames": [a, b], "v": 1,
                                        **({"calibrated": True} if calibrate else {})},
                                       lambda: [full.slice(a, b)], args.quiet, log, calibrate=calibrate)
        model = load_model(model_path)
        test_spec = args.test_frames or (f"{b}:" if b < full.n_frames else None)
        if test_spec is None:
            raise CliError("--train-frames covers the whole recording; give --test-frames")
        c, d = parse_frames(test_spec, full.n_frames)
        clip = full.slice(c, d)
        if rate:
            clip = resample(clip, rate)
        max_frames = int(round(args.duration * clip.rate))
        clip = clip.slice(0, max_frames)
        what = f"{data.name} frames {c}:{min(d, c + max_frames)} (model trained on frames {a}:{b})"
        if args.model:
            what = f"{data.name} frames {c}:{min(d, c + max_frames)} (model {args.model})"
    try:
        clip = model_points(clip, model.labels)
    except ValueError as e:
        raise CliError(f"the model's labels are not in the test data: {e}") from None
    stream = corrupt_clip(clip, occlude=args.occlude, clutter=args.clutter, noise_mm=args.noise_mm, seed=args.seed,
                          gap_frames=args.gap_frames)
    bag = work / "demo_bag"
    s = write_bag(stream, bag, storage="mcap", force=True)
    desc = dict(stream=what, frames=s["frames"], rate_hz=s["rate_hz"], duration_s=s["duration_s"],
                labels=len(model.labels), occlude=args.occlude, clutter=args.clutter, noise_mm=args.noise_mm,
                gap_frames=args.gap_frames, model=str(model_path))
    return model_path, bag, desc


# ------------------------------------------------------------------------------------- main

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dtm-demo", formatter_class=HelpFormatter, epilog=EPILOG,
                                description="Train a model, start the labeler node and a bag player in their own "
                                            "processes, replay a test stream in real time and report live "
                                            "accuracy and end-to-end latency. No arguments: embedded synthetic "
                                            "default (no files needed).")
    p.add_argument("--data", default=None, metavar="PATH",
                   help="a real labelled recording to replay instead of the synthetic walker")
    p.add_argument("--points", default="body14", help="with --data: body14, all, all,-NAME,... (all but these), or NAME,NAME,...")
    p.add_argument("--train-frames", default="0:70%", metavar="A:B", help="with --data: frames to train on")
    p.add_argument("--test-frames", default=None, metavar="A:B",
                   help="with --data: frames to replay (default: the rest after --train-frames)")
    p.add_argument("--no-calibrate", action="store_true",
                   help="with --data: keep the trained model generic (default: calibrated to the recording's "
                        "person on the training frames' labels, as dtm-train --calibrate)")
    p.add_argument("--model", default=None, help="use this model file instead of training one")
    p.add_argument("--duration", type=float, default=10.0, metavar="S", help="seconds of stream to replay (at most)")
    p.add_argument("--rate-hz", type=float, default=None, metavar="HZ",
                   help="stream rate (synthetic: generated at it; --data: resampled to it); default 120 / the "
                        "recording's")
    add_corruption_arguments(p, occlude=1, gap_frames=24.0, clutter=2, noise_mm=1.0)
    p.add_argument("--seed", type=int, default=1, help="seed of the corruption")
    p.add_argument("--param", action="append", default=[], metavar="NAME:=VALUE",
                   help="extra node parameter (repeatable), e.g. --param method:=greedy")
    p.add_argument("--domain-id", type=int, default=None,
                   help="ROS_DOMAIN_ID for the demo's processes (default: $ROS_DOMAIN_ID, else from the pid)")
    p.add_argument("--keep", action="store_true", help="keep the work directory (bag, node log)")
    p.add_argument("--json", action="store_true", help="print the final summary as one JSON object")
    p.add_argument("--quiet", action="store_true", help="no live lines")
    return p


def _frames_with_errors(per_frame: list) -> dict:
    """How many scored frames had a wrong or missing label, how many of them came before the
    stream's first fully right frame (the start-up, before any labeling was known), and the
    accuracy from that frame on (steady state; None when no frame was right)."""
    wrong = [c < t for _, c, t in per_frame]
    first_right = wrong.index(False) if False in wrong else len(wrong)
    rest = per_frame[first_right:]
    seen = sum(t for _, _, t in rest)
    return dict(total=int(sum(wrong)), before_first_right_frame=first_right,
                accuracy_from_first_right_frame=sum(c for _, c, _ in rest) / seen if seen else None)


def _fmt_ms(d: dict, k: str) -> str:
    v = d.get(k, float("nan"))
    return "  n/a" if v != v else f"{v:5.1f}"


def _main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.duration <= 0 or (args.rate_hz is not None and args.rate_hz <= 0):
        raise CliError("--duration and --rate-hz must be positive")
    if args.occlude < 0 or args.clutter < 0 or args.noise_mm < 0 or args.gap_frames < 1:
        raise CliError("--occlude, --clutter, --noise-mm must be >= 0 and --gap-frames >= 1")
    params = {}
    for item in args.param:
        if ":=" not in item:
            raise CliError(f"--param {item!r}: expected NAME:=VALUE")
        k, v = item.split(":=", 1)
        params[k.strip()] = v.strip()
    env = ros_env(args.domain_id)
    # this process runs rclpy too (the monitor): rule one here as well
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = env["ROS_DOMAIN_ID"]
    say = (lambda s: None) if args.json else (lambda s: print(s, flush=True))
    live = (lambda s: None) if (args.json or args.quiet) else say

    work = Path(tempfile.mkdtemp(prefix="dtm_demo_"))
    node = player = None
    t_start = time.perf_counter()
    try:
        model_path, bag, desc = prepare(args, work, say)
        say(f"stream    {desc['stream']}")
        say(f"          {desc['frames']} frames at {desc['rate_hz']:g} Hz ({desc['duration_s']:.1f} s), "
            f"{desc['labels']} labels; occlude {args.occlude} (gaps ~{args.gap_frames:g} frames), "
            f"{args.clutter} ghosts, noise {args.noise_mm:g} mm")
        say(f"ROS       ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']}, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST")

        from ..model.io import load_model
        from ..ros.player import ReplayMonitor
        labels = load_model(model_path).labels
        log_path = work / "node.log"
        node = start_node(model_path, env, log_path, params)
        with ReplayMonitor(known_labels=labels) as mon:
            if not mon.wait_ready(timeout=30.0, alive=lambda: node.poll() is None,
                                  topics=("markers/labeled", "/diagnostics")):
                raise CliError(f"the node did not come up (exit status {node.poll()}):\n{tail(log_path)}")
            # wait until the node says its model is loaded (a fresh install compiles its kernels
            # on the first load): frames sent before that would be dropped as "no_model"
            if not mon.wait_model_loaded(timeout=60.0, alive=lambda: node.poll() is None):
                raise CliError(f"the node did not load its model within 60 s (exit status {node.poll()}):\n"
                               f"{tail(log_path)}")
            say(f"node      up after {time.perf_counter() - t_start:.1f} s (pid {node.pid}); playing")
            player = start_player(bag, env, ["--restamp", "--wait-for", "markers/unlabeled", "markers/ground_truth",
                                             "--start-delay", "0.3", "--wait-timeout", "20"])
            last = t_play = time.monotonic()
            prev = mon.snapshot()
            while player.poll() is None:
                time.sleep(0.1)
                if node.poll() is not None:
                    break
                if time.monotonic() - last >= 1.0:
                    s = mon.snapshot(score=not args.quiet)      # quiet: score at the end (no load here)
                    with mon.lock:
                        recent = np.asarray(mon.latency_ms[prev["labeled"]:])
                    lat = dict(p50=np.percentile(recent, 50), p99=np.percentile(recent, 99)) if recent.size \
                        else {}
                    acc = s["accuracy"]
                    live(f"  t={time.monotonic() - t_play:5.1f} s  "
                         f"sent {s['truth']:5d}  labelled {s['labeled']:5d}  skipped {s['node_skipped']:4d}  "
                         f"accuracy {'  n/a ' if acc != acc else f'{100 * acc:6.2f}'} %  "
                         f"latency p50 {_fmt_ms(lat, 'p50')} ms  p99 {_fmt_ms(lat, 'p99')} ms")
                    prev = s
                    last = time.monotonic()
            node_failed = node.poll() is not None
            try:
                out, err = player.communicate(timeout=30.0)
            except subprocess.TimeoutExpired:
                stop_process(player)
                out, err = player.communicate()
            if player.returncode != 0:
                raise CliError(f"the player failed (exit status {player.returncode}): "
                               f"{err.decode(errors='replace').strip()[-800:]}")
            play = json.loads(out.decode())
            sent = int(play["sent"].get("/markers/unlabeled", 0))
            # let the last frames and a diagnostics message arrive
            final = mon.wait_diag(lambda d: int(d.get("frames_received", 0)) >= sent and
                                  int(d.get("frames_published", 0)) + mon.skipped(d) >= int(d["frames_received"])
                                  and mon.n_labeled >= int(d.get("frames_published", 0)), timeout=4.0)
            time.sleep(0.1)
            s = mon.snapshot()
            with mon.lock:
                per_frame = sorted(mon.scorer.per_frame)
        node_rc = stop_process(node)
        node_failed = node_failed or node_rc not in (0, -signal.SIGINT)
        node_log = tail(log_path, 20) if node_failed else ""
    finally:
        for p in (player, node):
            if p is not None and p.poll() is None:
                stop_process(p)
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)

    received = s["node_received"]
    summary = dict(desc, frames_sent=sent, frames_received_by_node=received, frames_labelled=s["labeled"],
                   frames_carried=s["node_carried"], frames_skipped=s["node_skipped"],
                   skipped_detail=s["node_skipped_detail"],
                   frames_lost=max(sent - received, 0), accuracy=s["accuracy"], true_markers=s["true_markers"],
                   ghost_rejection=s["ghost_rejection"], frames_with_errors=_frames_with_errors(per_frame),
                   latency_ms=s["latency_ms"],
                   node_latency_ms=s["node_latency_ms"], player_lateness_ms=play.get("lateness_ms", {}),
                   player_start_held_ms=play.get("start_held_ms", 0.0),
                   node_resets=int(final.get("resets_gap", 0) or 0) + int(final.get("resets_time_backwards", 0) or 0),
                   node_exit_status=node_rc, node_ok=not node_failed, node_log_tail=node_log or None, domain_id=int(env["ROS_DOMAIN_ID"]),
                   seconds=time.perf_counter() - t_start, work_dir=str(work) if args.keep else None)
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        lat, nl = s["latency_ms"], s["node_latency_ms"]
        acc, errs = s["accuracy"], summary["frames_with_errors"]
        print("summary")
        print(f"  frames      sent {sent}, received by the node {received}, labelled {s['labeled']} "
              f"({s['node_carried']} carried by the tracks while a search ran), "
              f"skipped {s['node_skipped']} " + (f"({', '.join(f'{k} {v}' for k, v in s['node_skipped_detail'].items() if v)})"
                                                 if s["node_skipped"] else "")
              + (f", lost in transport {sent - received}" if sent > received else ""))
        print(f"  accuracy    {'n/a' if acc != acc else f'{100 * acc:.2f} %'} of {s['true_markers']} visible true "
              f"markers in labelled frames" + (f"; ghosts left unlabeled {100 * s['ghost_rejection']:.1f} %"
                                               if s["ghosts"] else "")
              + f"; {errs['total']} frames with an error ({errs['before_first_right_frame']} of them at the start"
              + (f"; from the first right frame on {100 * errs['accuracy_from_first_right_frame']:.2f} %)"
                 if errs["accuracy_from_first_right_frame"] is not None else ")"))
        print(f"  latency     end-to-end (stamp -> labelled frame here) p50 {lat['p50']:.1f} ms, "
              f"p99 {lat['p99']:.1f} ms, max {lat['max']:.1f} ms; in the node p50 {nl['p50']:.1f} ms, "
              f"p99 {nl['p99']:.1f} ms")
        print(f"  node        {'ok' if not node_failed else 'FAILED'} (exit status {node_rc}), "
              f"{summary['node_resets']} window resets; "
              f"total {summary['seconds']:.1f} s")
        if node_failed:
            print(f"  node log    (last lines)\n{node_log}")
    return 1 if node_failed else 0


def main(argv=None) -> int:
    return run_main(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
