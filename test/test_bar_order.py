"""The marker bars' order (model/body.py ``BarOrder``): a labeling that shows a label nearer the
other end of a bar pays a fixed factor per row, a missing point drops it, the training learns the
rows from real takes (the wrist bars: the shoulder and upper-arm markers lie nearer the radial
end), they hold in another lab's takes of other motions, only calibrated bodies apply them, a
calibration keeps the rows the person's frames do not reverse, and model files keep them
(format 6; format 5 files load without), and the take pass's rows from the bar's side (format 9). On the same real bodies: the reach limits that run
between two limbs held still in the training stay on the DTM's edges (format 8)."""
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dtm_labeler.evaluation.generalisation import CASES, calibration_frames, case_clips, train_case_model, train_config
from dtm_labeler.evaluation.pipeline import label_clip_run, model_clip
from dtm_labeler.labeling.bar_flips import take_bar_orders
from dtm_labeler.labeling.config import LabelerSettings
from dtm_labeler.model.body import ORDER_NATS, BarOrder, BodyModel, CrossSegments, quads_off_ordered_bars
from dtm_labeler.model.features import point_states
from dtm_labeler.model.io import FORMAT_VERSION, load_model, save_model
from dtm_labeler.search.problem import Background, FrameProblem
from dtm_labeler.training.body_fit import bar_orders, bars, sided_reach
from dtm_labeler.training.calibrate import calibrated_body, kept_orders, self_calibrate
from model_files import as_older_format

# x at the origin; "near" 0.1 m away, "far" 0.2 m away, a fourth point elsewhere
LINE = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.5, 0.0]])


def _body(orders, n=4):
    return BodyModel(n_labels=n, pairs=np.zeros((0, 2)), kind=np.zeros(0), lo=np.zeros(0), hi=np.zeros(0),
                     within_sd=np.zeros(0), between_sd=np.zeros(0), orders=orders)


def test_factor_per_reversed_order_and_missing_points():
    order = BarOrder(_body([[0, 1, 2]]))
    swapped = LINE[[0, 2, 1, 3]]                          # the bar's ends exchanged
    hidden = LINE.copy()
    hidden[2] = np.nan
    got = order.labelled(np.stack([LINE, swapped, hidden]))
    assert got.tolist() == [0.0, -ORDER_NATS, 0.0]
    xyz = np.vstack([LINE, np.full((1, 3), np.nan)])      # row n: "missing"
    pop = np.array([[0, 1, 2, 3], [0, 2, 1, 3], [4, 2, 1, 3], [3, 1, 2, 0]])
    # the last row: x takes the fourth point, 0.51 m from near and 0.54 m from far: still as trained
    assert order(pop, xyz).tolist() == [0.0, -ORDER_NATS, 0.0, 0.0]
    with pytest.raises(ValueError, match="distinct"):
        _body([[0, 1, 1]])
    with pytest.raises(ValueError, match="distinct"):
        _body([[0, 1, 7]])


def test_kept_orders_drop_only_what_the_person_reverses():
    rng = np.random.default_rng(0)
    F = 100
    P = np.repeat(LINE[None], F, 0) + rng.normal(0, 0.001, (F, 4, 3))
    rows = np.array([[0, 1, 2], [3, 1, 2]])
    P[:20, [1, 2]] = P[:20, [2, 1]]                     # a fifth of the frames show the bar exchanged: kept
    assert kept_orders(rows[:1], P).tolist() == [[0, 1, 2]]
    P[:70, [1, 2]] = LINE[[2, 1]]                        # most frames the other way: dropped
    assert kept_orders(rows[:1], P).shape == (0, 3)
    P[:, 3] = np.nan                                     # never seen: kept
    assert kept_orders(rows[1:], P).tolist() == [[3, 1, 2]]
    # handedness quadruples holding both ends of an ordered bar are left to the order
    quads = np.array([[0, 1, 2, 3], [0, 1, 3, 5], [2, 3, 4, 5]])
    q, s, n = quads_off_ordered_bars(quads, np.array([1.0, -1.0, 1.0]), rows[:1])
    assert q.tolist() == [[0, 1, 3, 5], [2, 3, 4, 5]] and s.tolist() == [-1.0, 1.0] and n == 1
    # ... unless all four are of one segment cluster (the bar's own markers and a hand hanging from it)
    cluster = np.array([0, 0, 0, 0, 1, -1])
    q, s, n = quads_off_ordered_bars(quads, np.array([1.0, -1.0, 1.0]), rows[:1], cluster)
    assert q.tolist() == quads.tolist() and n == 0
    cluster[3] = 1                                       # the fourth label on another segment: left to the order
    q, s, n = quads_off_ordered_bars(quads, np.array([1.0, -1.0, 1.0]), rows[:1], cluster)
    assert q.tolist() == [[0, 1, 3, 5], [2, 3, 4, 5]] and n == 1
    cluster[:] = -1                                      # off every segment
    assert quads_off_ordered_bars(quads, np.ones(3), rows[:1], cluster)[2] == 1


def test_a_hand_marker_of_the_bars_cluster_orders_the_bar():
    """A wrist bar (radial end 0, ulnar end 1), a forearm marker 2 as far from both ends, and a
    finger marker 3 hanging from the ulnar end by a segment, 11 mm nearer the radial end, the
    hand flexing +-40 deg about the line through the two ends while the arm turns every way.
    The flexion leaves the finger's distance to each end as it was, so its order holds in every
    frame: a row (finger, radial, ulnar), though the finger is in the bar's own cluster; the
    forearm marker, as far from both, gives none."""
    rng = np.random.default_rng(3)
    a, b = np.zeros(3), np.array([0.0, 0.133, 0.0])
    forearm, finger = np.array([-0.15, 0.0665, 0.0]), np.array([0.13, 0.055, 0.0])
    frames = []
    for _ in range(300):
        flexed = Rotation.from_rotvec([0.0, rng.uniform(-0.7, 0.7), 0.0]).as_matrix() @ finger
        axis = rng.normal(size=3)
        turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(0, np.pi)).as_matrix()
        frames.append(np.stack([a, b, forearm, flexed]) @ turn.T + rng.normal(0, 0.5, 3))
    P = np.array(frames) + rng.normal(0, 0.001, (300, 4, 3))
    segments = np.array([[0, 1], [0, 2], [1, 2], [1, 3]])
    assert [tuple(r) for r in bars(P, segments)] == [(0, 1)]
    assert bar_orders([P], segments, np.array([[2, 0, 1], [3, 1, 0]])).tolist() == [[3, 0, 1]]


@pytest.fixture(scope="module")
def hdm_case(data_dir):
    """``dtm-eval``'s HDM05 -> CMU 85 cell: a body of HDM05's standing take (41 markers), and
    CMU 85's jump + twist (another lab, another person, another motion)."""
    case = next(c for c in CASES if c.key == "m_hdm05_to_85_02")
    train, test = case_clips(data_dir, case)
    model, _ = train_case_model(train, train_config(case, "body", 0))
    return model, train, test


def test_wrist_bars_learnt_from_a_real_take_hold_in_another_labs_motion(hdm_case):
    model, train, test = hdm_case
    L = list(model.labels)
    P = [model_clip(model, c).positions for c in train]
    found = {tuple(sorted((L[a], L[b]))) for a, b in bars(P[0], model.body.segments)}
    assert {("LWRA", "LWRB"), ("RWRA", "RWRB")} <= found
    rows = {tuple(L[i] for i in r) for r in model.body.orders}
    assert ("LSHO", "LWRA", "LWRB") in rows and ("RSHO", "RWRA", "RWRB") in rows      # nearer the radial end
    assert np.array_equal(bar_orders(P, model.body.segments, model.structure.array,
                                     reach=sided_reach(model.mirror_pairs, len(L))), model.body.orders)
    # CMU 85's true labels, every frame of the jump + twist: each row holds in at least 99 % of them
    X = model_clip(model, test).positions
    x, near, far = (X[:, model.body.orders[:, k]] for k in range(3))
    gap = np.linalg.norm(x - far, axis=-1) - np.linalg.norm(x - near, axis=-1)
    seen = np.isfinite(gap)
    assert seen.sum(0).min() >= 800 and ((gap > 0) | ~seen).mean(0).min() >= 0.99
    # a generic body keeps the rows without applying them
    assert model.body_order is None


def test_the_take_passs_rows_come_from_the_bars_side_and_hold_in_another_labs_motion(hdm_case, tmp_path):
    """``take_orders``: more rows for the offline pass's stretches (labeling/bar_flips.py), from
    the labels on the bar's side of the body wherever the triangles put them: the right wrist bar,
    which the frame factor orders by one label, gets more; they hold in CMU 85's jump + twist;
    a calibration keeps them; format 9 files keep them, format 8 files load without."""
    model, _, test = hdm_case
    L = list(model.labels)
    side = {L[a]: "L" for a, _ in model.mirror_pairs} | {L[b]: "R" for _, b in model.mirror_pairs}
    take = model.body.take_orders
    assert all(len({side.get(L[i]) for i in row}) == 1 and side.get(L[row[0]]) for row in take.tolist())
    right = {L[r[0]] for r in take if {L[r[1]], L[r[2]]} == {"RWRA", "RWRB"}}
    framed = {L[r[0]] for r in model.body.orders if {L[r[1]], L[r[2]]} == {"RWRA", "RWRB"}}
    assert len(right) >= 2 and len(right) > len(framed)
    X = model_clip(model, test).positions
    x, near, far = (X[:, take[:, k]] for k in range(3))
    gap = np.linalg.norm(x - far, axis=-1) - np.linalg.norm(x - near, axis=-1)
    seen = np.isfinite(gap)
    held = ((gap > 0) | ~seen).mean(0)
    assert seen.sum(0).min() >= 800 and np.median(held) >= 0.99 and held.min() >= 0.9   # measured: 0.91-1.0
    assert take_bar_orders(model).shape == (0, 3)          # a generic body: none, as the frame factor
    window = model_clip(model, test.slice(0, 270)).positions
    body, summary = calibrated_body(model.body, window, mirror_pairs=model.mirror_pairs,
                                    heading_pairs=model.heading_pairs)
    cal = model.replace(body=body)
    assert summary["take_bar_orders"] == body.take_orders.shape[0] == take.shape[0]
    rows = take_bar_orders(cal)
    assert {tuple(r) for r in np.vstack([body.orders, body.take_orders]).tolist()} == {tuple(r) for r in rows.tolist()}
    path = save_model(cal, tmp_path / "m.npz")
    assert np.array_equal(load_model(path).body.take_orders, body.take_orders)
    v8 = as_older_format(path, 8, lambda k: k.endswith("take_orders"))
    assert v8.provenance["format_version_read"] == 8 and v8.body.take_orders.shape == (0, 3)
    assert np.array_equal(take_bar_orders(v8), np.unique(body.orders, axis=0))


def test_calibrated_body_applies_the_order_to_a_real_exchange(hdm_case, tmp_path):
    model, _, test = hdm_case
    L = list(model.labels)
    window = model_clip(model, test.slice(0, 270)).positions
    body, summary = calibrated_body(model.body, window, mirror_pairs=model.mirror_pairs,
                                    heading_pairs=model.heading_pairs)
    cal = model.replace(body=body)
    assert summary["bar_orders"] == model.body.orders.shape[0] and summary["bar_orders_dropped"] == 0
    assert cal.body_order is not None
    a, b = L.index("RWRA"), L.index("RWRB")
    assert not any({a, b} <= set(q) for q in cal.body.quads.tolist())
    X = model_clip(model, test.slice(400, 402)).positions
    states = point_states(X, test.rate)[1]
    truth = np.arange(len(L))
    swap = truth.copy()
    swap[[a, b]] = swap[[b, a]]
    pop = np.stack([truth, swap])
    with_order = FrameProblem(cal, states, Background()).fitness(pop)
    reversed_rows = -cal.body_order.labelled(X[1][pop]) / ORDER_NATS
    assert reversed_rows.tolist()[0] == 0 and reversed_rows[1] >= 1
    cal.body_order, saved = None, cal.body_order
    try:
        without = FrameProblem(cal, states, Background()).fitness(pop)
    finally:
        cal.body_order = saved
    assert np.allclose(with_order - without, -ORDER_NATS * reversed_rows)
    # the labelled frame's likelihood has the same factor
    swapped = point_states(X[:, swap], test.rate)[1:]
    no_orders = cal.replace(body=replace(body, orders=np.zeros((0, 3))))
    assert np.isclose(cal.frame_log_likelihood(swapped)[0] - no_orders.frame_log_likelihood(swapped)[0],
                      -ORDER_NATS * reversed_rows[1])

    # format 6 keeps the rows; a format-5 file (no order array) loads as a body without them
    path = save_model(cal, tmp_path / "m.npz")
    back = load_model(path)
    assert FORMAT_VERSION >= 6 and np.array_equal(back.body.orders, cal.body.orders)
    assert np.array_equal(FrameProblem(back, states, Background()).fitness(pop), with_order)
    v5 = as_older_format(path, 5, lambda k: k == "body_orders")
    assert v5.provenance["format_version_read"] == 5 and v5.body.orders.shape == (0, 3) and v5.body_order is None
    assert np.allclose(FrameProblem(v5, states, Background()).fitness(pop), without)


def test_floor_moves_self_calibrated_keep_the_wrist_bars(case_cell):
    """``dtm-eval``'s floor-moves cell, self-calibrated on the first 225 frames: the labels of
    the next 120 frames (the wrist bars exchanged in 65 of 360 frames before the order)."""
    model, test = case_cell("m_floor")
    n_cal = calibration_frames(test, 5.0)
    window = model_clip(model, test.slice(0, n_cal))
    cal, _ = self_calibrate(model, window.positions, window.rate)
    assert cal.body_order is not None and cal.body.calibration["bar_orders"] >= 4
    run = label_clip_run(cal, test.slice(n_cal, n_cal + 120), LabelerSettings(seed=0), seed=0)
    assert run.accumulator.metrics().as_dict()["accuracy"] >= 0.99
    assert not [p for p in run.metrics.confused_pairs(8) if {p[0], p[1]} == {"RWRA", "RWRB"} and p[2] > 5]


def test_dtm_train_says_which_bars_it_ordered(data_dir, tmp_path, capsys):
    """dtm-train on HDM05's first 30 % (41 markers) names the rows it learnt, and says that a
    calibration applies them (--calibrate off); by default (one capture: the takes' person)
    and with --calibrate they apply."""
    from dtm_labeler.cli.train import main as train_main
    take = str(data_dir / "markers_c3d/hdm05_bd_05-01_01_120.c3d")
    out = tmp_path / "m.npz"
    assert train_main([take, "--points", "all", "--frames", "0:30%", "--k-max", "2", "--out", str(out),
                       "--quiet", "--calibrate", "off"]) == 0
    printed = capsys.readouterr().out
    model = load_model(out)
    line = next(s for s in printed.splitlines() if s.startswith("bars "))
    assert "LSHO" in line and "nearer LWRA than LWRB" in line and line.endswith("(applied once calibrated)")
    assert len(model.body.orders) == line.count(",") + line.count(" nearer ") and model.body_order is None
    take_line = printed.splitlines()[printed.splitlines().index(line) + 1]
    assert f"and {len(model.body.take_orders)} orders from the bars' side" in take_line and len(model.body.take_orders)
    # the actor stands on the left foot: its labels may rest that long before a rest reads as a reflection
    rests = dict(zip(model.labels, model.settings["longest_rest_s"]))
    line = next(s for s in printed.splitlines() if s.startswith("rests "))
    longest = max(rests, key=rests.get)
    assert longest.startswith("L") and rests[longest] > 5.0 and f"{longest} {rests[longest]:.1f} s" in line
    assert model.rest_limits(2.0)[model.labels.index(longest)] == 1.5 * rests[longest]
    assert train_main([take, "--points", "all", "--frames", "0:30%", "--k-max", "2", "--out", str(out),
                       "--quiet"]) == 0
    assert "(applied: calibrated)" in capsys.readouterr().out and load_model(out).body_order is not None


def test_reach_between_two_feet_held_still_stays_on_the_edges(hdm_case, tmp_path):
    """HDM05's standing take held the left ankle by the right forefoot, a link of its most rigid
    tree, and every pair of the two legs has its reach limit through it (the stance the training
    showed). A calibrated body holds those limits on the DTM's edges only: CMU 85's person, whose
    feet part up to 1.6 m, calibrated on the first frames of the jump + twist, pays a nat or two
    off the edges for the true labels of the frames after them (the legs' own chains); held off
    the edges as well (a format-7 file's reading), the same frames pay some 100 nats each."""
    model, _, test = hdm_case
    L = list(model.labels)
    off = model.body.matrix(model.body.reach_off_edges.astype(float), fill=1.0)
    legs = ("LANK", "LHEE", "LTOE", "LMT5"), ("RANK", "RHEE", "RTOE", "RMT5")
    assert all(off[L.index(a), L.index(b)] == 0 for a in legs[0] for b in legs[1])
    assert off[L.index("LANK"), L.index("LHEE")] == 1 and off[L.index("C7"), L.index("RTOE")] == 1
    window = model_clip(model, test.slice(0, 270)).positions
    body, _ = calibrated_body(model.body, window, mirror_pairs=model.mirror_pairs, heading_pairs=model.heading_pairs)
    cal = model.replace(body=body)
    X = model_clip(model, test.slice(270, 630)).positions
    now = cal.body_cross.labelled(X)
    every = CrossSegments(replace(body, reach_off_edges=None), cal.triangles, body.applied_kinds).labelled(X)
    assert np.median(now) > -3.0 and now.min() > -10.0 and np.median(every) < -50.0
    v7 = as_older_format(save_model(cal, tmp_path / "m.npz"), 7, lambda k: k.endswith("reach_off_edges"))
    assert v7.provenance["format_version_read"] == 7 and v7.body.reach_off_edges.all()
    assert np.allclose(v7.body_cross.labelled(X), every)


def test_a_bars_rows_come_from_its_side_of_the_body(hdm05_calibrated, hdm05_take):
    """training/body_fit.py sided_reach: the demo's kind of model (the take's first 2000 frames,
    mostly standing) orders each wrist bar by labels of its own side; from the triangles' reach
    alone the same frames give the left bar a row of the right forehead and the right bar rows of
    the midline and the other arm (orders a held pose kept), which the side leaves out."""
    model = hdm05_calibrated
    L = list(model.labels)
    side = {L[a]: "L" for a, _ in model.mirror_pairs} | {L[b]: "R" for _, b in model.mirror_pairs}
    rows = [tuple(L[i] for i in r) for r in model.body.orders]
    assert {near[0] for _, near, _ in rows} == {"L", "R"}                 # both wrist bars keep rows
    assert all(side.get(x) == side[near] == side[far] for x, near, far in rows)
    P = [model_clip(model, hdm05_take.slice(0, 2000)).positions]
    anywhere = [tuple(L[i] for i in r) for r in bar_orders(P, model.body.segments, model.structure.array)]
    assert any(side.get(x) != side[near] for x, near, _ in anywhere)
    sided = bar_orders(P, model.body.segments, model.structure.array,
                       reach=sided_reach(model.mirror_pairs, len(L)))
    assert np.array_equal(sided, model.body.orders)


def test_a_bar_without_a_known_side_is_ordered_from_anywhere():
    """A point set of one arm (no mirror partner for its labels): their side is unknown, and the
    reach leaves their bars' rows to the triangles; labels with a partner keep to their side."""
    pairs = np.array([[0, 1]])                      # e.g. LSHO / RSHO; 2-4 an arm's markers
    reach = sided_reach(pairs, 5)
    assert reach[2:].all() and reach[0, 0] and not reach[0, 1] and not reach[0, 2:].any()
