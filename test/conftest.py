"""Shared pytest set-up.

Rule one (../shared/ros2.md): DDS stays on loopback. This runs before any test module
imports rclpy, and every test session gets its own ROS_DOMAIN_ID unless one is set; under
``pytest -n N`` every worker moves to a domain of its own.
"""
import os
from pathlib import Path

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):   # small matrices: threads only add latency
    os.environ.setdefault(_var, "1")
os.environ.setdefault("ROS_DOMAIN_ID", str(40 + os.getpid() % 50))
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")       # gw0, gw1 ... under pytest -n N
if _WORKER.startswith("gw"):                               # parallel workers: a domain each
    os.environ["ROS_DOMAIN_ID"] = str((int(os.environ["ROS_DOMAIN_ID"]) + 1 + int(_WORKER[2:])) % 100)

import pytest  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get("DTM_DATA_DIR", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The real recordings in ../shared/data; tests that need them skip (with a reason) without."""
    if not (DATA_DIR / "index.csv").is_file():
        pytest.skip(f"real mocap data not found at {DATA_DIR} (set DTM_DATA_DIR or place ../shared/data)")
    return DATA_DIR


@pytest.fixture(scope="session", autouse=True)
def _no_node_left_behind():
    """A fixture that failed before yielding leaves its node process running (and talking on
    this test session's DDS domain): kill them all at the end of the session."""
    yield
    import sys
    helpers = sys.modules.get("node_helpers")
    if helpers is not None:
        helpers.kill_leftovers()


def _node_processes(value, depth: int = 0):
    """The NodeProcess objects in a fixture value (itself, a NodeClient's target, or one level
    of tuple/list/dict)."""
    helpers = __import__("sys").modules.get("node_helpers")
    if helpers is None or depth > 1:
        return
    if isinstance(value, helpers.NodeProcess):
        yield value
    elif isinstance(value, helpers.NodeClient):
        yield value.target
    elif isinstance(value, (tuple, list)):
        for v in value:
            yield from _node_processes(v, depth + 1)
    elif isinstance(value, dict):
        for v in value.values():
            yield from _node_processes(v, depth + 1)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A failed test that talked to node processes shows each one's state and the end of its
    log (a node that stopped answering says why, or shows that it said nothing)."""
    outcome = yield
    report = outcome.get_result()
    if not report.failed:
        return
    seen = set()
    for value in getattr(item, "funcargs", {}).values():
        for proc in _node_processes(value):
            if id(proc) in seen:
                continue
            seen.add(id(proc))
            rc = proc.proc.poll()
            state = "running" if rc is None else f"exited with {rc}"
            try:
                tail = "\n".join(proc.log().splitlines()[-40:])
            except OSError as e:
                tail = f"(log unreadable: {e})"
            report.sections.append((f"node {proc.fqn} ({state}, log {proc.log_path})", tail))


#: Modules whose tests take longest (6-44 s each, measured with ``--durations=0`` on 2026-12-05), run first
#: so that under ``pytest -n 2`` the workers end together instead of one finishing a long test
#: alone. pytest.ini's ``--no-loadscope-reorder`` makes xdist keep this order: by default it hands
#: out the files with the most tests first, which put the single 30-s colcon test last.
#: test_release_moves.py is left to the alphabetical rest: it reads a run test_young_checks.py
#: makes (``dance_pooled``), which the other worker loads once it is done, not makes again.
LONG_FIRST = ("test_calibrate_cli.py", "test_upright.py", "test_background_join.py", "test_bar_order.py",
              "test_archive.py", "test_published_confidence.py", "test_accuracy_floors.py",
              "test_background_sweeps.py", "test_node_colcon.py", "test_label_cli.py", "test_e2e_replay.py",
              "test_node_reload.py", "test_cluster_turns.py", "test_training_augment.py", "test_recovery.py",
              "test_young_checks.py", "test_settings_honoured.py",
              "test_node_bad_input.py", "test_node_params.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FIRST)))


HDM05 = "markers_c3d/hdm05_bd_05-01_01_120.c3d"


def made_once(tmp_path_factory, worker_id: str, filename: str, build, save, load):
    """What ``build()`` makes, shared by the workers of one ``pytest -n N`` run: a worker that
    asks after another has made it loads that worker's file (``load(path)``, written by
    ``save(value, path)``); the first makes it and saves it; one that asks while another is
    making it makes its own (waiting would cost as much). Alone (``worker_id`` "master") it is
    made here."""
    import fcntl
    if worker_id == "master":
        return build()
    root = tmp_path_factory.getbasetemp().parent              # this run's, shared by its workers
    path = root / filename
    with open(root / f"{filename}.lock", "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:                                # another worker is making it now
            return build()
        if path.is_file():
            return load(path)
        value = build()
        save(value, path)
        return value


def trained_once(tmp_path_factory, worker_id: str, name: str, build):
    """A model ``build()`` trains, shared by the workers of one ``pytest -n N`` run
    (:func:`made_once`, the file written by ``save_model``). Saving and loading keep the model
    exactly (fitness equal to the last bit on the floor cell's and HDM05's frames, the same
    labels over 60 frames of a stream), so a test does not depend on which worker trained it."""
    from dtm_labeler.model.io import load_model, save_model
    return made_once(tmp_path_factory, worker_id, f"trained_{name}.npz", build, save_model, load_model)


def computed_once(tmp_path_factory, worker_id: str, name: str, build):
    """A result ``build()`` computes (JSON's kinds: numbers, strings, lists and dicts, numpy
    scalars as numbers), shared by the workers of one ``pytest -n N`` run (:func:`made_once`):
    a deterministic computation another worker has already done is loaded, not done again. The
    result is returned as the file gives it back, also to the worker that computed it, so every
    worker reads the same (tuples as lists). No pickles, here as in model files."""
    import json

    def save(value, path):
        path.write_text(json.dumps(value, default=lambda o: o.item()))

    def load(path):
        return json.loads(path.read_text())
    return made_once(tmp_path_factory, worker_id, f"computed_{name}.json",
                     lambda: json.loads(json.dumps(build(), default=lambda o: o.item())), save, load)


@pytest.fixture(scope="session")
def case_cell(data_dir, tmp_path_factory, worker_id):
    """``case_cell(key)``: (the generic body ``dtm-eval``'s cell ``key`` trains -- ``train_case_model``
    on its training takes, seed 0, trained once per test run --, the cell's test clip)."""
    from dtm_labeler.evaluation.generalisation import CASES, case_clips, train_case_model, train_config
    cells = {}

    def get(key: str):
        if key not in cells:
            case = next(c for c in CASES if c.key == key)
            train, test = case_clips(data_dir, case)
            model = trained_once(tmp_path_factory, worker_id, f"case_{key}",
                                 lambda: train_case_model(train, train_config(case, "body", 0))[0])
            cells[key] = (model, test)
        return cells[key]
    return get


@pytest.fixture(scope="session")
def hdm05_take(data_dir):
    """HDM05's 41-marker take (its unlabelled copies as loaded with ``points="all"``)."""
    from dtm_labeler.motion.load import load_clip
    return load_clip(data_dir / HDM05, points="all")


@pytest.fixture(scope="session")
def hdm05_calibrated(hdm05_take, tmp_path_factory, worker_id):
    """A model of the take's first 2000 frames (CBGA, K <= 2) calibrated to its person -- the
    demo's kind of model (trained once per test run)."""
    from dtm_labeler.training.calibrate import calibrate_on_takes
    from dtm_labeler.training.train import TrainConfig, train_model
    train = hdm05_take.slice(0, 2000)

    def build():
        m, _ = train_model([train], TrainConfig(seed=0, k_max=2, structure="cbga"))
        return calibrate_on_takes(m, [train])
    return trained_once(tmp_path_factory, worker_id, "hdm05_calibrated", build)


@pytest.fixture(scope="session")
def hdm05_half_hidden(hdm05_calibrated, hdm05_take):
    """240 frames (2 s) after :func:`hdm05_calibrated`'s training part with half of the samples
    hidden as a capture's occlusions hide them (gaps of ~0.25 s), 1 mm of noise: the frames
    the labeler gets. A half-hidden cold start is chaotic: nine such draws (frames 2400, 3000,
    3600 + 240, gap draws 1-3) ended 3-72 % right, and one changed row of the model moves a
    draw by 30 points either way; this one (frames 3600-3840, draw 3) is recovered by the join
    with the model's bar orders from the triangles' reach (67.5 %, the filled join only 42.4 %)
    and from the bar's side (67.5 %, 35.3 %). Until 2026-12-06: frames 2400-2640, draw 1
    (62.9 % and 23.5 %; 29.7 % and 28.3 % with the side's rows)."""
    from background_runs import half_hidden_frames
    return half_hidden_frames(hdm05_calibrated, hdm05_take, 3600, draw=3)


@pytest.fixture(scope="session")
def hdm05_markers(data_dir, tmp_path_factory, worker_id):
    """HDM05's 41 markers (``to_point_set(..., "all")``) and a model of the take's first 600
    frames (one component per triangle), trained once per test run: (model, the take)."""
    from dtm_labeler.motion import load_clip, to_point_set
    from dtm_labeler.training.train import TrainConfig, train_model
    clip = to_point_set(load_clip(data_dir / HDM05), "all")
    model = trained_once(tmp_path_factory, worker_id, "hdm05_markers",
                         lambda: train_model([clip.slice(0, 600)], TrainConfig(mixture="fixed", k_fixed=1, seed=0))[0])
    return model, clip


@pytest.fixture(scope="session")
def gappy_upper(data_dir, tmp_path_factory, worker_id):
    """12 upper-body HDM05 markers, half of the samples hidden in real-looking gaps; a model
    of another part of the take (the labeler is often lost on the frames after it), trained
    once per test run: (model, the gapped clip)."""
    from dtm_labeler.motion.load import load_clip
    from dtm_labeler.training.train import TrainConfig, train_model
    from test_gappy_training import HDM as TAKE, UPPER, _gapped
    clip = _gapped(load_clip(data_dir / TAKE).select(UPPER), 0.5)
    model = trained_once(tmp_path_factory, worker_id, "gappy_upper",
                         lambda: train_model([clip.slice(1200, 2400)], TrainConfig(seed=0, k_max=2, structure="greedy"))[0])
    return model, clip


@pytest.fixture(scope="session")
def half_hidden_background(hdm05_calibrated, hdm05_half_hidden, tmp_path_factory, worker_id):
    """``background_runs.background_run`` on :func:`hdm05_half_hidden`, audits off -- what
    test_background_join reads of its joins and test_background_sweeps of the searches asked
    for; run once per test run (the run is deterministic)."""
    from background_runs import background_run
    return computed_once(tmp_path_factory, worker_id, "half_hidden_background",
                         lambda: background_run(hdm05_calibrated, hdm05_half_hidden))


@pytest.fixture(scope="session")
def dance_pooled(data_dir, tmp_path_factory, worker_id):
    """``dance_pooled(**settings)``: ``dance_streams.pooled`` on ``dance_streams.dance_case``
    with these labeler settings -- (accuracy, search errors) over the four corruption seeds'
    streams. The model is trained and each distinct ``LabelerSettings`` run once per test run
    (the runs are deterministic: test_young_checks' young checks on and test_release_moves'
    release moves on are both the defaults, one run)."""
    import hashlib
    from dance_streams import dance_case, pooled
    from dtm_labeler.labeling.config import LabelerSettings
    model, test = dance_case(data_dir, lambda name, build: trained_once(tmp_path_factory, worker_id, name, build))
    done = {}

    def get(**settings):
        key = hashlib.sha1(repr(LabelerSettings(recovery="inline", **settings)).encode()).hexdigest()[:16]
        if key not in done:
            done[key] = computed_once(tmp_path_factory, worker_id, f"dance_pooled_{key}",
                                      lambda: pooled(model, test, **settings))
        return done[key]
    return get
