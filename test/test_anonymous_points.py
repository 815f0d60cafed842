"""Anonymous model points: a capture's unlabelled trajectories that ride on the body are learnt
and published unlabelled, so that such a marker does not take a hidden marker's label (issue 14:
real ghosts in gapped captures; training/anonymous.py)."""
import json

import numpy as np
import pytest

from dtm_labeler.cli.label import main as label_main
from dtm_labeler.cli.train import main as train_main
from dtm_labeler.model.io import load_model
from dtm_labeler.motion.c3d_write import write_c3d
from dtm_labeler.motion.load import load_clip
from dtm_labeler.motion.unlabelled import model_input
from dtm_labeler.training.anonymous import riding_markers, with_riding_markers

HDM = "markers_c3d/hdm05_bd_05-01_01_120.c3d"
NAMED = ["LFHD", "RFHD", "C7", "CLAV", "STRN", "LSHO", "RSHO", "LUPA", "RUPA", "LELB", "RELB", "LFWT", "RFWT"]
EXTRA = ["RBAC", "T10"]                 # real markers on the back the set does not name


@pytest.fixture(scope="module")
def hdm(data_dir):
    return load_clip(data_dir / HDM)


def _capture(hdm, path, a, b, hide=(), fragment=None, reflection=False, extra=True):
    """Frames a:b of NAMED as named channels and EXTRA as '*' channels (``extra`` False: none,
    the markers taken off); ``hide``: named markers hidden throughout; ``fragment``: (name, every
    k-th frame) moved from the named channel into a '*' channel of its own (what auto-labelling
    leaves at a gap); a fixed reflection as one more '*' channel."""
    clip = hdm.select(NAMED + EXTRA).slice(a, b)
    P = clip.positions.copy()
    for n in hide:
        P[:, NAMED.index(n)] = np.nan
    stars = [P[:, len(NAMED) + k] for k in range(len(EXTRA))] if extra else []
    if fragment is not None:
        name, every = fragment
        j = NAMED.index(name)
        frag = np.full_like(P[:, j], np.nan)
        frag[::every] = P[::every, j]
        P[::every, j] = np.nan
        stars.append(frag)
    if reflection:
        stars.append(np.tile(np.nanmean(P[:, NAMED.index("LFWT")], 0) + [0.8, 0.0, -0.5], (len(P), 1)))
    pos = np.concatenate([P[:, :len(NAMED)]] + ([np.stack(stars, 1)] if stars else []), axis=1)
    write_c3d(path, pos, NAMED + [f"*{k}" for k in range(len(stars))], clip.rate)
    return path


def test_riding_trajectories_are_taken_fragments_and_reflections_are_not(hdm, tmp_path):
    path = _capture(hdm, tmp_path / "train.c3d", 1200, 1900, fragment=("RSHO", 3), reflection=True)
    # the loaders join a fragment that continues its marker (test_fragments); kept apart here, the
    # training's own rule must still leave it out
    joined = load_clip(path)
    assert {f["marker"] for f in joined.meta["unlabelled_fragments"]} == {"RSHO"}
    assert np.isfinite(joined.positions[:, NAMED.index("RSHO")]).all()
    clip = load_clip(path, join_fragments=False)
    riding = riding_markers(clip)
    # *0 RBAC and *1 T10 ride on the trunk; *2 (RSHO's fragment: never seen with RSHO) and *3
    # (a fixed point while the body walks) do not
    assert sorted(r.channel for r in riding) == ["*0", "*1"]
    assert all(r.name.startswith("*by") and r.partner in NAMED and r.spread_m < 0.015 for r in riding)
    (out,), taken = with_riding_markers([clip])
    assert out.names[:len(NAMED)] == tuple(NAMED) and out.names[len(NAMED):] == tuple(r.name for r in taken)
    assert np.array_equal(out.positions[:, len(NAMED)], clip.meta["unlabelled"][:, 0], equal_nan=True)
    assert out.meta["unlabelled_names"] == ("*2", "*3")          # the rest stay unlabelled channels
    assert with_riding_markers([clip, clip])[1] == []            # several captures: none taken


@pytest.fixture(scope="module")
def models(hdm, tmp_path_factory):
    d = tmp_path_factory.mktemp("anon")
    train = _capture(hdm, d / "train.c3d", 1200, 1900)
    out = {}
    for tag, extra in (("anonymous", []), ("ignored", ["--ignore-unlabelled"])):
        out[tag] = d / f"{tag}.npz"
        assert train_main([str(train), "--points", "all", "--out", str(out[tag]), "--quiet", "--json",
                           "--structure", "greedy", "--k-max", "2", *extra]) == 0
    return d, out


def test_train_learns_them_and_label_publishes_them_unlabelled(hdm, models, tmp_path, capsys):
    d, paths = models
    capsys.readouterr()
    anon, ignored = load_model(paths["anonymous"]), load_model(paths["ignored"])
    assert ignored.labels == tuple(NAMED) and not ignored.anonymous.any()
    assert anon.labels[:len(NAMED)] == tuple(NAMED) and anon.anonymous.sum() == 2
    assert (anon.published(np.array([0, len(NAMED), len(NAMED) + 1, -1])) == [0, -1, -1, -1]).all()
    # leaves of the structure: never a parent; the named points' triangles those of the model without them
    tri = anon.structure.array
    assert set(tri[-2:, 0].tolist()) == {len(NAMED), len(NAMED) + 1} and (tri[:, 1:] < len(NAMED)).all()
    assert anon.structure.names(anon.labels)[:-2] == ignored.structure.names(ignored.labels)
    # ... and of the rigid tree: the named pairs' body terms (segments, reach limits) are theirs without
    # them (lengths within 0.5 mm: the calibration's overall scale reads every point)
    def named_terms(m):
        b = m.body
        return {(m.labels[i], m.labels[j]): (k, r, lo, hi) for (i, j), k, lo, hi, r in
                zip(b.pairs.tolist(), b.kind.tolist(), b.lo.tolist(), b.hi.tolist(), b.reach_off_edges.tolist())
                if not (m.anonymous[i] or m.anonymous[j])}
    a, b = named_terms(anon), named_terms(ignored)
    assert a.keys() == b.keys() and all(a[k][:2] == b[k][:2] for k in a)
    assert max(abs(np.subtract(a[k][2:], b[k][2:])).max() for k in a) < 5e-4
    # a later stretch with RSHO hidden throughout: the back marker beside it is a real marker
    # the model without anonymous points can only call RSHO or clutter
    test = _capture(hdm, tmp_path / "test.c3d", 2000, 2360, hide=("RSHO",))
    mi = model_input(load_clip(test), anon.labels)
    assert mi.named and mi.n_extra == 2 and np.isnan(mi.clip.positions[:, anon.anonymous]).all()
    res = {}
    for tag in ("anonymous", "ignored"):
        out = tmp_path / f"{tag}.c3d"
        assert label_main([str(paths[tag]), str(test), "--json", "--quiet", "--out", str(out)]) == 0
        res[tag] = json.loads(capsys.readouterr().out)
        written = load_clip(out)
        assert not any(n.startswith("*by") for n in written.names)     # never a published label
    assert res["anonymous"]["ghosts"] == res["ignored"]["ghosts"] > 0
    assert res["anonymous"]["ghost_rejection"] > 0.97
    assert res["anonymous"]["ghost_rejection"] > res["ignored"]["ghost_rejection"] + 0.1
    assert res["anonymous"]["accuracy"] > 0.99
    # the take carries the markers: labelled with its anonymous points
    presence = res["anonymous"]["inputs"][0]["anonymous_points"]
    assert presence["absent"] is False and presence["ratio"] > 0.7


def test_stream_and_carried_frames_never_publish_an_anonymous_label(hdm, models, tmp_path):
    """The node's path: every searched frame and every frame the tracks only follow
    (``observe``: the worker busy) publish the anonymous points unlabelled."""
    from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler
    _, paths = models
    model = load_model(paths["anonymous"])
    mi = model_input(load_clip(_capture(hdm, tmp_path / "t.c3d", 2000, 2120, hide=("RSHO",))), model.labels)
    lab = StreamLabeler(model, LabelerSettings())
    named, seen_anon = len(NAMED), 0
    for f in range(mi.clip.n_frames):
        xyz = np.concatenate([mi.clip.positions[f], mi.extra[f]])
        xyz = xyz[np.isfinite(xyz).all(1)]
        res = lab.process(xyz, f / mi.clip.rate) if f % 3 else lab.observe(xyz, f / mi.clip.rate)
        assert res.labels.max() < named
        if f % 3:
            seen_anon += int((res.assignment[named:] >= 0).sum())      # the search did use them
    lab.close()
    assert seen_anon > 50


def test_a_stream_without_those_markers_is_noticed_live(hdm, models, tmp_path):
    """The node's labeler judges the same from the frames it searched (the node's diagnostics warn,
    labeling/anonymous_presence.py): a session without the markers is noticed, one with them not."""
    from dtm_labeler.labeling.bank_labeler import BankSettings
    from dtm_labeler.labeling.stream import LabelerSettings
    from dtm_labeler.ros.engine import NodeLabeler, NodeSettings, Source, load, prepare
    _, paths = models
    source = Source(str(paths["anonymous"]))
    prepared = prepare(source, load(source), 0.0, BankSettings(), spare=False)
    model = prepared.base
    notes = {}
    for extra in (True, False):
        mi = model_input(load_clip(_capture(hdm, tmp_path / f"s{extra}.c3d", 2000, 2240, extra=extra)), model.labels)
        node = NodeLabeler(prepared, NodeSettings(LabelerSettings(recovery="inline"), BankSettings()))
        assert node.anonymous_absent == ""              # nothing searched yet: no judgement
        for f in range(mi.clip.n_frames):
            xyz = np.concatenate([mi.clip.positions[f], mi.extra[f]])
            node.process(xyz[np.isfinite(xyz).all(1)], f / mi.clip.rate)
        found = node._lab.anonymous_presence()
        assert node._lab.frames_searched == mi.clip.n_frames
        notes[extra] = (found, node.anonymous_absent)
        node.close()
    assert not notes[True][0].absent and notes[True][0].ratio > 0.7 and notes[True][1] == ""
    assert notes[False][0].absent and notes[False][0].ratio < 0.5
    assert "anonymous points" in notes[False][1] and "--ignore-unlabelled" in notes[False][1]


def test_named_structure_is_the_same_on_a_gappy_capture(hdm, tmp_path):
    """With gaps the structure is scored on pairs of points (a covariance made positive
    semi-definite as a whole) or on complete frames: both would depend on the anonymous points
    if they were scored together; the named points' structure is scored on their own states."""
    from dtm_labeler.training.train import TrainConfig, train_model
    rng = np.random.default_rng(3)
    clip = load_clip(_capture(hdm, tmp_path / "g.c3d", 1200, 1900))
    P, U = clip.positions.copy(), clip.meta["unlabelled"].copy()
    for arr in (P, U):                                   # 30 % of the samples hidden in 12-frame gaps
        for j in range(arr.shape[1]):
            for s in rng.choice(arr.shape[0] - 12, 18, replace=False):
                arr[s:s + 12, j] = np.nan
    clip = clip._replace(positions=P, meta=clip.meta | {"unlabelled": U})
    (with_anon,), riding = with_riding_markers([clip])
    assert len(riding) == 2
    cfg = TrainConfig(seed=0, k_max=1, structure="greedy", mixture="single")
    plain, summary = train_model([clip], cfg)
    anon, _ = train_model([with_anon], cfg)
    assert summary.structure_scored_on == "pairs of points"
    assert anon.structure.names(anon.labels)[:-2] == plain.structure.names(plain.labels)


def test_a_take_without_those_markers_is_labelled_by_the_model_without_them(hdm, models, tmp_path, capsys):
    """Another session of the set with the extra markers taken off: the anonymous points have
    nothing of their own to explain, the live pass holds them in few frames, and the take is
    labelled by the model without them (labeling/anonymous_presence.py) -- the model
    ``--ignore-unlabelled`` makes, as far as the named points go."""
    from dtm_labeler.labeling.anonymous_presence import anonymous_presence
    d, paths = models
    anon, ignored = load_model(paths["anonymous"]), load_model(paths["ignored"])
    named = anon.named_only()
    assert named.labels == ignored.labels and not named.anonymous.any() and named.named_only() is named
    assert named.structure.names(named.labels) == ignored.structure.names(ignored.labels)
    assert all(np.allclose(a.means, b.means) and np.allclose(a.covariances, b.covariances)
               for a, b in zip(named.mixtures, ignored.mixtures))
    for key in ("pairs", "kind", "rigid_pairs", "orders", "take_orders", "quads"):   # the person's, without them
        assert getattr(named.body, key).tolist() == getattr(ignored.body, key).tolist(), key
    for key in ("lo", "hi", "within_sd", "rigid_length"):
        assert np.allclose(getattr(named.body, key), getattr(ignored.body, key), atol=1e-9), key
    assert named.settings["loglik_per_label"] == pytest.approx(ignored.settings["loglik_per_label"])
    assert len(anon.settings["seen_share"]) == anon.n_labels and len(named.settings["seen_share"]) == len(NAMED)
    # the judgement: held in under half of the frames the training's shares predict
    frames = np.round(np.array(anon.settings["seen_share"]) * 400).astype(int)
    assert not anonymous_presence(anon, frames, 400).absent
    frames[anon.anonymous] //= 4
    assert anonymous_presence(anon, frames, 400).absent
    assert anonymous_presence(ignored, frames[:len(NAMED)], 400) is None

    test = _capture(hdm, tmp_path / "off.c3d", 2000, 2360, hide=("RSHO",), extra=False)
    res = {}
    for tag in ("anonymous", "ignored"):
        assert label_main([str(paths[tag]), str(test), "--json", "--quiet"]) == 0
        res[tag] = json.loads(capsys.readouterr().out)
    take = res["anonymous"]["inputs"][0]
    assert take["anonymous_points"]["absent"] is True and take["anonymous_points"]["ratio"] < 0.5
    assert "labelled without them" in take["note"]
    assert "anonymous_points" not in res["ignored"]["inputs"][0]
    assert res["anonymous"]["accuracy"] == pytest.approx(res["ignored"]["accuracy"], abs=0.003)


def test_bag_label_without_those_markers_labels_again_without_them(hdm, models, tmp_path, capsys):
    """``dtm-bag label``: the same judgement over a bag's clouds, and the bag labelled again by
    the model without the anonymous points (the labelled C3D written once, from that pass)."""
    from dtm_labeler.cli.bag import main as bag_main
    d, paths = models
    test = _capture(hdm, tmp_path / "off.c3d", 2000, 2240, hide=("RSHO",), extra=False)
    assert bag_main(["make", str(test), "--points", "all", "--out", str(tmp_path / "bag"), "--json"]) == 0
    capsys.readouterr()
    res = {}
    for tag in ("anonymous", "ignored"):
        out = tmp_path / f"{tag}.c3d"
        assert bag_main(["label", str(paths[tag]), str(tmp_path / "bag"), "--out", str(out), "--json",
                         "--quiet"]) == 0
        res[tag] = json.loads(capsys.readouterr().out)
        back = load_clip(out)
        assert back.n_frames == 240 and not any(n.startswith("*by") for n in back.names)
    assert res["anonymous"]["anonymous_points"]["absent"] is True
    assert "labelled without them" in res["anonymous"]["note"] and res["anonymous"]["labels"] == len(NAMED)
    assert "anonymous_points" not in res["ignored"]
    assert res["anonymous"]["accuracy"] == pytest.approx(res["ignored"]["accuracy"], abs=0.003)
