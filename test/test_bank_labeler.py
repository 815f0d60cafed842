"""The bank labeler: migration rule (Ukita 4.3 read as a logistic of the fitness difference),
migration moving individuals toward the better-fitting model, and labeling a real switching
sequence (walk -> run, different subjects) with the active action following the true class."""
import numpy as np
import pytest

from dtm_labeler.evaluation.switching import join_clips, run_sequence, switch_metrics
from dtm_labeler.labeling.bank_labeler import (BankFrameResult, BankLabeler, BankSettings, Migration, allocate,
                                               migration_probability)
from dtm_labeler.search.evolve import Island
from dtm_labeler.search.problem import FrameProblem
from dtm_labeler.labeling.stream import LabelerSettings
from dtm_labeler.model.bank import ModelBank
from dtm_labeler.model.features import point_states
from dtm_labeler.training.train import TrainConfig, train_model
from dtm_labeler.motion import load_clip
from dtm_labeler.search import label_ops as ops

CFG = TrainConfig(mixture="fixed", k_fixed=2, structure="given")
WALK = "cmu_skeletal/bvh_from_fbx/cmu_07_01_walk_s07.bvh"
RUN = "cmu_skeletal/bvh_from_fbx/cmu_09_11_run_s09.bvh"


@pytest.fixture(scope="module")
def data(data_dir):
    walk = load_clip(data_dir / WALK, points="body14")
    run = load_clip(data_dir / RUN, points="body14")
    kw, kr = int(0.6 * walk.n_frames), int(0.6 * run.n_frames)
    bank = ModelBank({"walk": train_model([walk.slice(0, kw)], CFG)[0],
                      "run": train_model([run.slice(0, kr)], CFG)[0]})
    tw, tr = walk.slice(kw, None), run.slice(kr, None)
    tw.motion_class, tr.motion_class = "walk", "run"
    return bank, tw, tr


def test_migration_probability_rule():
    f = np.array([-100.0, -100.0, -90.0])
    p = migration_probability(f, np.array([-100.0, -90.0, -100.0]), np.array([10, 10, 10]), 1.0)
    assert p[0] == pytest.approx(0.5)
    assert p[1] == pytest.approx(1 / (1 + np.exp(-1.0)))       # 1 nat per labelled point better
    assert p[1] + p[2] == pytest.approx(1.0)                      # exp(-s_n)/(exp(-s_m)+exp(-s_n)) symmetry
    # Ukita's form with s^2 = -f / (tau k)
    sm, sn = 100.0 / 10, 90.0 / 10
    assert p[1] == pytest.approx(np.exp(-sn) / (np.exp(-sm) + np.exp(-sn)))
    hot = migration_probability(f[1:2], np.array([-90.0]), np.array([10]), 10.0)
    assert 0.5 < hot[0] < p[1]                                    # higher temperature: closer to a coin flip
    assert np.isfinite(migration_probability(np.array([-np.inf]), np.array([-5.0]), np.array([3]), 1.0)).all()
    assert allocate(24, np.array([0.5, 0.25, 0.25]), 4).tolist() == [10, 7, 7]
    assert allocate(8, np.array([1.0, 0.0, 0.0]), 4).sum() == 12


def test_migration_moves_individuals_toward_the_better_model(data):
    """Individuals near the true labeling of a walking frame, all starting in the run model,
    drift to the walk model; with a seed, averaged over repetitions."""
    bank, tw, _ = data
    lab = BankLabeler(bank, LabelerSettings(seed=3), BankSettings(min_share=2))
    states = point_states(tw.positions, tw.rate)[20]
    probs = [FrameProblem(m, states, lab.settings.background) for m in lab.models]
    n, M = probs[0].n, probs[0].M
    rng = np.random.default_rng(5)
    truth = np.arange(M)
    assert probs[0].fitness(truth[None])[0] > probs[1].fitness(truth[None])[0]   # walk fits a walking frame
    migrate = Migration(probs, lab.bank_settings, rng)

    def island(pop, m):
        return Island(pop.copy(), probs[m].fitness, None, probs[m].fitness(pop))
    moved_to_walk, moved_to_run = [], []
    for rep in range(20):
        base = np.repeat(truth[None], 16, 0)
        pop = ops.mutate(base, n, rng, 0.3)
        half = 8
        isl = [island(pop[:half], 0), island(pop[half:], 1)]
        migrate(isl, 1)
        moved_to_walk.append(len(isl[0].pop) - half)
    assert np.mean(moved_to_walk) > 3.0          # most movable run individuals (7 of 8 non-elite) went
    assert min(moved_to_walk) > 0
    # the reverse: individuals in the walk model rarely leave for the run model
    for rep in range(20):
        pop = ops.mutate(np.repeat(truth[None], 16, 0), n, rng, 0.3)
        isl = [island(pop, 0), island(truth[None], 1)]
        migrate(isl, 1)
        moved_to_run.append(16 - len(isl[0].pop))
    # (the broad part of each triangle's conditional makes far-off individuals cost alike in both
    # models, so some of them drift either way; the near-right ones stay)
    assert np.mean(moved_to_run) < 0.5 * np.mean(moved_to_walk)


def test_bank_labels_a_switching_sequence(data):
    bank, tw, tr = data
    seq = join_clips([tw, tr], min_part=30)
    assert len(seq.switches) == 1 and set(seq.classes) == {"walk", "run"}
    settings = LabelerSettings(seed=1)
    r = run_sequence(BankLabeler(bank, settings), seq, "bank", occlude=1, noise_mm=1.0, seed=2)
    m = switch_metrics(r, window=20)
    assert m["accuracy"] >= 0.90
    assert m["active_action_accuracy"] >= 0.80
    # the active action changes after the switch and settles on run
    s = seq.switches[0]
    assert r.active[s - 5] == "walk" and r.active[-1] == "run"


def test_hard_switching_and_bank_off(data):
    bank, tw, tr = data
    lab = BankLabeler(bank, LabelerSettings(seed=0), BankSettings(strategy="hard"))
    frames = tr.positions[:30]
    for k, f in enumerate(frames):
        res = lab.process(f[np.random.default_rng(k).permutation(14)], k / tr.rate)
    assert isinstance(res, BankFrameResult)
    assert res.active_action == "run" and set(res.action_scores) == {"walk", "run"}
    assert res.population["run"] > 0 and res.population["walk"] == 0
    off = BankLabeler(bank, LabelerSettings(seed=0), BankSettings(use_bank=False, default_action="walk"))
    res = off.process(tw.positions[0], 0.0)
    assert off.actions == ["walk"] and res.active_action == "walk" and (res.labels == np.arange(14)).sum() >= 12
    with pytest.raises(ValueError):
        BankSettings(strategy="nope")
    with pytest.raises(KeyError):
        BankLabeler(bank, LabelerSettings(), BankSettings(use_bank=False, default_action="swim"))


def test_node_uses_the_bank(tmp_path, data):
    """Node parameters use_bank / bank_path (in-process node, no DDS peers): the bank loads, the
    active action is published in LabeledMarkerArray.active_model and /diagnostics, a bad bank is
    rejected at runtime and the running one kept, use_bank=false goes back to model_path."""
    import time

    rclpy = pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter
    from std_msgs.msg import Header

    from dtm_labeler.model.bank import save_bank
    from dtm_labeler.model.io import save_model
    from dtm_labeler.ros.node import LabelerNode
    from dtm_labeler.ros.worker import Frame
    bank, tw, tr = data
    save_bank(bank, tmp_path / "bank")
    save_model(bank["walk"], tmp_path / "walk.npz")
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = LabelerNode(context=ctx, namespace="/t_bank", parameter_overrides=[    # lock step: searches inline
        Parameter("use_bank", value=True), Parameter("bank_path", value=str(tmp_path / "bank")),
        Parameter("model_path", value=str(tmp_path / "walk.npz")), Parameter("recovery", value="inline")])
    core = node.core
    published = []

    def capture(data):                 # markers/labeled goes out serialised (ros/messages.py)
        from rclpy.serialization import deserialize_message
        from dtm_labeler_msgs.msg import LabeledMarkerArray
        published.append(deserialize_message(data, LabeledMarkerArray) if isinstance(data, bytes) else data)
    core.outputs.labeled.publish = capture

    def diag():
        st = {s.name.rsplit(": ", 1)[1]: s for s in node.diagnostics()}
        return {kv.key: kv.value for kv in st["model"].values}

    def wait_engine(pred, what):       # models load on the node's loader thread
        end = time.monotonic() + 60
        while not (core.worker.engine is not None and pred(core.worker.engine)):
            assert time.monotonic() < end, what
            time.sleep(0.01)

    def feed(clip, n, t0):
        rng = np.random.default_rng(0)
        for k in range(n):
            xyz = clip.positions[k][rng.permutation(14)]
            t = t0 + k / clip.rate
            core.handler(Frame(xyz, None, Header(), t, t, time.perf_counter(), 0.0), core.worker.engine)

    try:
        wait_engine(lambda e: e.actions == ("walk", "run"), "the bank")
        d = diag()
        assert d["model_status"] == "loaded" and d["use_bank"] == "True" and d["bank_actions"] == "walk,run"
        feed(tr, 40, 0.0)
        assert published[-1].active_model == "run" and diag()["active_model"] == "run"
        assert sum(m.label != "" for m in published[-1].markers) >= 12
        # a damaged bank is rejected; the running bank stays
        (tmp_path / "bad").mkdir()
        (tmp_path / "bad" / "bank.json").write_text("{")
        r = node.set_parameters([Parameter("bank_path", value=str(tmp_path / "bad"))])[0]
        assert not r.successful and "corrupt" in r.reason
        assert core.worker.engine.actions == ("walk", "run")
        # bank off: back to the single model at model_path
        r = node.set_parameters([Parameter("use_bank", value=False)])[0]
        assert r.successful
        wait_engine(lambda e: e.actions == (), "the single model")
        assert core.worker.engine.labels == tuple(bank.labels)
        feed(tw, 3, 10.0)
        assert published[-1].active_model == "" and diag()["use_bank"] == "False"
        r = node.set_parameters([Parameter("use_bank", value=True), Parameter("bank_path", value="")])
        assert not all(x.successful for x in r)
    finally:
        node.destroy_node()
        ctx.try_shutdown()
