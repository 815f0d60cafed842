"""Unlabelled fragments of named markers (issue 14): a '*' run that continues a named marker
across its gap is that marker -- joined to it at load, scored and written as it; ghosts beside a
hidden marker, partial copies and other markers stay unlabelled."""
import json

import numpy as np
import pytest

from dtm_labeler.cli.label import main as label_main
from dtm_labeler.model.io import save_model
from dtm_labeler.motion.c3d_write import write_c3d
from dtm_labeler.motion.fragments import find_fragments
from dtm_labeler.motion.load import load_clip
from dtm_labeler.motion.markers_csv import write_markers_csv
from dtm_labeler.training.train import TrainConfig, train_model

HDM = "markers_c3d/hdm05_bd_05-01_01_120.c3d"
UPPER = ["LFHD", "RFHD", "C7", "CLAV", "LSHO", "RSHO", "LELB", "RELB", "LWRA", "RWRA", "LFWT", "RFWT"]
KNEES = ["LKNE", "RKNE"]                         # real markers the model does not know: '*' channels


@pytest.fixture(scope="module")
def hdm(data_dir):
    return load_clip(data_dir / HDM)


@pytest.fixture(scope="module")
def take(hdm):
    """HDM05 frames 2000-2600 as a system whose auto-labelling broke trajectories would write
    them: each UPPER marker loses two stretches to '*' channels (0-3 frames unseen between the
    named part and the fragment), beside the knees as '*' channels, a ghost that starts 4 cm off
    where a marker vanished, and a partial copy of a seen marker. Returns the clip of the true
    positions, the channels (F, C, 3), their names and the fragments' (marker, first, last)."""
    clip = hdm.select(UPPER).slice(2000, 2600)
    knees = hdm.select(KNEES).slice(2000, 2600).positions
    P = clip.positions.copy()
    F, N, _ = P.shape
    rng = np.random.default_rng(3)
    stars, runs = [], []
    for j in range(N):
        for part in range(2):
            a = int(rng.integers(20 + 290 * part, 200 + 290 * part))
            b = a + int(rng.integers(8, 80))
            gap = int(rng.integers(0, 4))
            ch = np.full((F, 3), np.nan)
            ch[a:b] = P[a:b, j]
            P[a - gap:b + gap, j] = np.nan
            stars.append(ch)
            runs.append((UPPER[j], a, b - 1))
    ghost = np.full((F, 3), np.nan)                  # where RWRA vanished, a frame later, 4 cm off
    w = UPPER.index("RWRA")                          # (frames 285-304 hold no fragment)
    P[285:305, w] = np.nan
    ghost[286:306] = clip.positions[286:306, w] + [0.04, 0, 0]
    copy = np.full((F, 3), np.nan)                   # a partial copy of C7 where C7 is seen
    seen_c7 = np.flatnonzero(np.isfinite(P[:, UPPER.index("C7"), 0]))[:40]
    copy[seen_c7] = P[seen_c7, UPPER.index("C7")]
    channels = np.concatenate([P, knees, np.stack(stars + [ghost, copy], 1)], 1)
    names = UPPER + [f"*{i}" for i in range(channels.shape[1] - N)]
    return clip, channels, names, runs


def test_fragments_join_their_markers_and_nothing_else(take, tmp_path):
    clip, channels, names, runs = take
    path = tmp_path / "broken.c3d"
    write_c3d(path, channels, names, clip.rate)
    got = load_clip(path)
    # every fragment's samples are back in its marker, as the system measured them
    for marker, a, b in runs:
        j = got.index(marker)
        assert np.abs(got.positions[a:b + 1, j] - clip.positions[a:b + 1, clip.index(marker)]).max() < 1e-4, marker
    frags = got.meta["unlabelled_fragments"]
    assert sorted((f["marker"], f["first"], f["last"]) for f in frags) == sorted(runs)
    assert f"{len(runs)} unlabelled fragments" in got.meta["fragments_note"]
    # the knees, the ghost beside the vanished wrist and the copy stay unlabelled, untouched
    left = got.meta["unlabelled"]
    kept = np.isfinite(left[..., 0]).sum(0)
    assert (kept[:2] == np.isfinite(channels[:, len(UPPER):len(UPPER) + 2, 0]).sum(0)).all()
    assert kept[-2] == 20 and kept[-1] == 40 and kept[2:-2].sum() == 0
    # the same channels in a marker CSV; and the loader's switch keeps them apart
    csv = tmp_path / "broken.csv"
    write_markers_csv(csv, channels, names, clip.rate)
    assert len(load_clip(csv).meta["unlabelled_fragments"]) == len(runs)
    apart = load_clip(path, join_fragments=False)
    assert "unlabelled_fragments" not in apart.meta
    assert np.isfinite(apart.meta["unlabelled"][..., 0]).sum() == np.isfinite(channels[:, len(UPPER):, 0]).sum()


def test_fragment_rules_on_a_whole_take(hdm):
    """Every marker of the 41, stretches moved to '*' channels: joined where one end meets the
    marker's trajectory within 3 unseen frames at 120 Hz (MAX_GAP_S), not at 4; where both ends
    do, across up to 30 (MAX_BRIDGE_S), not 31; a run 2-4 cm off the marker's path not; never
    to the wrong marker."""
    P0 = hdm.positions[:3000]
    F, N, _ = P0.shape
    names = list(hdm.names)

    def draw(gap, off=0.0, resumes=True):
        rng = np.random.default_rng(1)
        P, extra, truth = P0.copy(), [], []
        for _ in range(5 if resumes else 1):         # a marker that never resumes: one stretch
            for j in range(N):
                a = int(rng.integers(40, F - 200))
                b = a + int(rng.integers(5, 120))
                if not np.isfinite(P[a - gap - 2:b + gap + 2, j]).all():
                    continue
                ch = np.full((F, 3), np.nan)
                ch[a:b] = P[a:b, j] + [off, 0.0, 0.0]
                P[a - gap:b + gap if resumes else F, j] = np.nan
                extra.append(ch)
                truth.append(names[j])
        found = find_fragments(P, names, np.stack(extra, 1), [f"*{i}" for i in range(len(extra))], hdm.rate)
        assert all(truth[int(f.channel[1:])] == f.marker for f in found)       # never the wrong marker
        return len(found) / len(extra)
    assert draw(0) == 1.0 and draw(3) == 1.0 and draw(10) > 0.85 and draw(30) > 0.5 and draw(31) == 0.0
    assert draw(3, resumes=False) > 0.4 and draw(4, resumes=False) == 0.0
    assert draw(0, 0.02) == 0.0 and draw(10, 0.04) == 0.0 and draw(3, 0.02) < 0.05


def test_dtm_label_scores_fragments_as_their_markers(take, hdm, tmp_path, capsys):
    clip, channels, names, runs = take
    model, _ = train_model([hdm.select(UPPER).slice(1200, 1900)], TrainConfig(seed=0, k_max=2, structure="greedy"))
    mpath = save_model(model, tmp_path / "upper12.npz")
    path, out = tmp_path / "broken.c3d", tmp_path / "labelled.c3d"
    write_c3d(path, channels, names, clip.rate)
    assert label_main([str(mpath), str(path), "--json", "--quiet", "--out", str(out), "--calibrate", "off"]) == 0
    d = json.loads(capsys.readouterr().out)
    samples = sum(b - a + 1 for _, a, b in runs)
    assert d["inputs"][0]["fragments_joined"] == samples and "unlabelled fragments" in d["inputs"][0]["note"]
    knees = int(np.isfinite(channels[:, len(UPPER):len(UPPER) + 2, 0]).sum())
    assert d["ghosts"] == knees + 20 + 40                    # the knees, the ghost, the copy: no fragment
    assert d["accuracy"] > 0.92 and d["ghost_rejection"] > 0.9   # the take unbroken: 94.8 %, rejection 100 %
    back = load_clip(out)
    right = sum(int((np.abs(back.positions[a:b + 1, back.index(m)]
                            - clip.positions[a:b + 1, clip.index(m)]).max(-1) < 1e-4).sum()) for m, a, b in runs)
    assert right / samples > 0.9                             # the labelled C3D carries them by name


def test_systems_names_for_unlabelled_trajectories(hdm, tmp_path):
    """QTM's 'Unidentified N', Motive's 'Unlabeled N' and a stray part kept as 'NAME-1' are
    unlabelled channels: joined where they continue their marker, left unlabelled elsewhere; a
    'NAME-1' seen beside NAME is a marker of its own."""
    clip = hdm.select(UPPER).slice(2000, 2300)
    P = clip.positions.copy()
    F = clip.n_frames
    parts = {}
    for name, (a, b) in (("RWRA", (50, 90)), ("LELB", (120, 160))):
        j = UPPER.index(name)
        ch = np.full((F, 3), np.nan)
        ch[a:b] = P[a:b, j]
        P[a:b, j] = np.nan
        parts[name] = ch
    ghost = np.full((F, 3), np.nan)
    ghost[10:40] = P[10:40, UPPER.index("C7")] + [0.0, 0.0, 0.3]
    own = hdm.select(["LKNE"]).slice(2000, 2300).positions[:, 0]          # a marker named CLAV-1, always seen
    names = UPPER + ["RWRA-1", "Subj:Unidentified 7", "Unlabeled 1001", "CLAV-1"]
    path = tmp_path / "systems.c3d"
    write_c3d(path, np.concatenate([P, np.stack([parts["RWRA"], parts["LELB"], ghost, own], 1)], 1), names, clip.rate)
    got = load_clip(path)
    assert got.names == tuple(UPPER + ["CLAV-1"])
    assert {(f["channel"], f["marker"]) for f in got.meta["unlabelled_fragments"]} == {
        ("RWRA-1", "RWRA"), ("Subj:Unidentified 7", "LELB")}
    assert np.abs(got.positions[:, :len(UPPER)] - clip.positions).max() < 1e-4      # both joined back
    left = got.meta["unlabelled"]
    assert np.isfinite(left[..., 0]).sum() == 30                              # the ghost, as it was
