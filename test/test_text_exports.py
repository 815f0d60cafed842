"""The marker text exports labs work with -- TRC (Cortex, OpenSim), QTM's 3D TSV, OptiTrack Motive's
CSV -- read as their C3D twins are, and ``dtm-label`` from each of them to a labelled TRC.

The files are real recordings (the shared C3D takes) written in each vendor's layout, with the
quirks of their exporters: QTM's header lines, events, zeros for gaps and ``Unidentified N``
trajectories; Motive's header rows, constraint columns of rigid bodies and bones, blank cells and
``Unlabeled N`` markers; TRC's per-marker header, short rows and ``NaN`` cells."""
import json

import numpy as np
import pytest

from dtm_labeler.cli.common import CliError, expand_inputs
from dtm_labeler.cli.label import main as label_main
from dtm_labeler.model.io import save_model
from dtm_labeler.motion.axes import from_z_up
from dtm_labeler.motion.load import load_clip
from dtm_labeler.motion.qtm_tsv import holds_markers
from dtm_labeler.motion.trc import write_trc
from dtm_labeler.training.train import TrainConfig, train_model

HDM = "markers_c3d/hdm05_bd_05-01_01_120.c3d"
QUALISYS = "markers_c3d/qualisys_walk_55markers.c3d"
CMU = "markers_c3d/cmu_85_02_jumptwist_s85_41markers.c3d"
UPPER = ["LFHD", "RFHD", "C7", "CLAV", "LSHO", "RSHO", "LELB", "RELB", "LWRA", "RWRA", "LFWT", "RFWT"]
GHOSTS = ["LKNE", "RKNE"]


def _holed(clip, seed=0, share=0.1):
    """``clip``'s positions with ``share`` of the samples hidden (NaN)."""
    P = clip.positions.copy()
    P[np.random.default_rng(seed).random(P.shape[:2]) < share] = np.nan
    return P


def write_qtm_tsv(path, positions, names, rate, up="Z", zeros_for_gaps=True, columns=True, frequency=None,
                  types=False):
    """``positions`` (metres, Z up) as QTM writes a 3D TSV export: mm, header lines, an event,
    a ``Frame Time <M> X ...`` column line (``columns``), gaps as 0 0 0 (older QTM) or empty;
    ``types``: a text column of each trajectory's per-frame type after its Z."""
    P = from_z_up(np.asarray(positions, dtype=float), up) * 1000.0
    F, N, _ = P.shape
    lines = ["FILE_VERSION\t2.0.0", f"NO_OF_FRAMES\t{F}", "NO_OF_CAMERAS\t12", f"NO_OF_MARKERS\t{N}",
             f"FREQUENCY\t{frequency or f'{rate:g}'}", "NO_OF_ANALOG\t0", "ANALOG_FREQUENCY\t0", "DESCRIPTION\t--",
             "TIME_STAMP\t2026-12-08, 09:41:17.220\t5721.38", "DATA_INCLUDED\t3D", "EVENT\tstart\t3\t0.015",
             "MARKER_NAMES\t" + "\t".join(names), "TRAJECTORY_TYPES\t" + "\t".join(["Measured"] * N)]
    per = [*"XYZ", "Type"] if types else [*"XYZ"]
    if columns:
        lines.append("Frame\tTime\t" + "\t".join(f"{n} {a}" for n in names for a in per) + "\t")
    for i in range(F):
        gap = "0.000" if zeros_for_gaps else ""
        cells = []
        for k in range(N):
            cells += [gap if not np.isfinite(v) else f"{v:.3f}" for v in P[i, k]]
            if types:
                cells.append("Measured" if np.isfinite(P[i, k]).all() else "Gap")
        lead = [str(i + 1), f"{i / rate:.5f}"] if columns else []
        lines.append("\t".join(lead + cells))
    path.write_text("\n".join(lines) + "\n")
    return path


def write_motive_csv(path, positions, names, rate, constraints=True):
    """``positions`` (metres, Z up) as Motive exports them: Y up, metres, the header rows, a rigid
    body and a skeleton's bone-marker constraints beside the measured markers, blank cells."""
    P = from_z_up(np.asarray(positions, dtype=float), "Y")
    F, N, _ = P.shape
    types, labels, ids, kinds, axes = [], [], [], [], []
    if constraints:                                  # a rigid body (rotation + position) and its marker
        types += ["Rigid Body"] * 7 + ["Rigid Body Marker"] * 3
        labels += ["wand"] * 7 + ["wand:Marker1"] * 3
        ids += ["1"] * 7 + ["1-1"] * 3
        kinds += ["Rotation"] * 4 + ["Position"] * 3 + ["Position"] * 3
        axes += list("XYZW") + list("XYZ") * 2
    for k, n in enumerate(names):
        types += ["Marker"] * 3
        labels += [n] * 3
        ids += [f"{k + 10:X}"] * 3
        kinds += ["Position"] * 3
        axes += list("XYZ")
        if constraints and k == 0:                   # a bone's constraint of the first marker
            types += ["Bone Marker"] * 3
            labels += [n] * 3
            ids += ["Skel:1"] * 3
            kinds += ["Position"] * 3
            axes += list("XYZ")
    out = [f"Format Version,1.23,Take Name,take,Take Notes,,Capture Frame Rate,{rate:f},Export Frame Rate,{rate:f},"
           "Capture Start Time,2026-12-08 09.41.17.220 AM,Capture Start Frame,0,Total Frames in Take,"
           f"{F},Total Exported Frames,{F},Rotation Type,Quaternion,Length Units,Meters,Coordinate Space,Global",
           "", ",Type," + ",".join(types), ",Name," + ",".join(labels), ",ID," + ",".join(ids),
           ",," + ",".join(kinds), "Frame,Time (Seconds)," + ",".join(axes)]
    rng = np.random.default_rng(1)
    for i in range(F):
        cells = []
        for k in range(N):
            if constraints and k == 0 and not cells:
                cells += [f"{v:.6f}" for v in rng.normal(size=4)] + [f"{v:.6f}" for v in rng.normal(size=6)]
            xyz = ["" if not np.isfinite(v) else f"{v:.6f}" for v in P[i, k]]
            cells += xyz
            if constraints and k == 0:               # the constraint is filled in where the marker is not seen
                cells += [f"{v + 0.001:.6f}" for v in np.nan_to_num(P[i, k], nan=0.5)]
        out.append(f"{i},{i / rate:.6f}," + ",".join(cells))
    path.write_text("\n".join(out) + "\n")
    return path


# -- loaders ------------------------------------------------------------------------------------------
def test_trc_round_trip_finds_the_vertical_and_keeps_gaps_names_and_frames(data_dir, tmp_path):
    clip = load_clip(data_dir / HDM).slice(300, 420)
    P = _holed(clip)
    ghosts = load_clip(data_dir / HDM).select(GHOSTS).slice(300, 420).positions
    f = write_trc(tmp_path / "t.trc", np.concatenate([P, ghosts], 1), list(clip.names) + ["*0", ""], clip.rate,
                  frame_numbers=np.arange(301, 421), units="m", up_axis="Y")
    back = load_clip(f)
    assert back.names == clip.names and back.meta["format"] == "trc"
    assert (back.meta["units"], back.meta["up_axis"], back.meta["up_axis_source"], back.rate) == ("m", "Y", "body", 120)
    np.testing.assert_allclose(back.positions, P, atol=1e-6)
    assert np.array_equal(np.isnan(back.positions), np.isnan(P))
    assert back.meta["frame_numbers"][0] == 301 and back.meta["frame_numbers"][-1] == 420
    assert len(back.meta["unlabelled_names"]) == 2                     # '*0' and the nameless one
    np.testing.assert_allclose(back.meta["unlabelled"], ghosts, atol=1e-6)
    forced = load_clip(f, up_axis="Z")                               # --up-axis: the file's axes taken as they are
    assert forced.meta["up_axis_source"] == "--up-axis"
    np.testing.assert_allclose(forced.positions, from_z_up(P, "Y"), atol=1e-6)


def test_trc_variants_other_writers_produce(data_dir, tmp_path):
    """Space-separated, a missing marker written as NaN, 0 0 0 or a row cut short, mm by default."""
    clip = load_clip(data_dir / HDM).slice(500, 530)
    n = clip.n_points
    P = from_z_up(clip.positions, "Y") * 1000.0
    lines = ["PathFileType 4 (X/Y/Z) t.trc",
             "DataRate CameraRate NumFrames NumMarkers Units OrigDataRate OrigDataStartFrame OrigNumFrames",
             f"120 120 30 {n} mm 120 1 30", "Frame# Time " + " ".join(clip.names),
             " ".join(f"X{k} Y{k} Z{k}" for k in range(1, n + 1)), ""]
    for i in range(30):
        v = [f"{x:.4f}" for x in P[i].reshape(-1)]
        if i == 3:
            v[0:3] = ["NaN"] * 3                     # LFHD hidden
        if i == 4:
            v[3:6] = ["0", "0", "0"]                 # RFHD hidden, C3D style
        if i == 5:
            v = v[:-3]                               # the last marker hidden: the row cut short
        lines.append(f"{i + 1} {i / 120:.5f} " + " ".join(v))
    (tmp_path / "s.trc").write_text("\n".join(lines) + "\n")
    back = load_clip(tmp_path / "s.trc")
    want = clip.positions.copy()
    want[3, 0] = want[4, 1] = want[5, -1] = np.nan
    assert back.names == clip.names and (back.meta["units"], back.meta["up_axis"]) == ("mm", "Y")
    np.testing.assert_allclose(back.positions, want, atol=1e-6)
    assert np.array_equal(np.isnan(back.positions), np.isnan(want))


def test_bad_trc_files_say_what_is_wrong(tmp_path):
    (tmp_path / "a.trc").write_text("hello\n")
    with pytest.raises(ValueError, match="PathFileType"):
        load_clip(tmp_path / "a.trc")
    (tmp_path / "b.trc").write_text("PathFileType\t4\nDataRate\tNumFrames\n120\t2\nFrame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n")
    with pytest.raises(ValueError, match="NumMarkers"):
        load_clip(tmp_path / "b.trc")
    (tmp_path / "c.trc").write_text("PathFileType\t4\nDataRate\tNumMarkers\tUnits\n120\t1\tfurlongs\n"
                                    "Frame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n1\t0\t1\t2\t3\n2\t0.5\t1\t2\t3\n"
                                    "3\t1.0\t1\t2\t3\n")
    with pytest.raises(ValueError, match="DataRate is 120 Hz but the time stamps"):
        load_clip(tmp_path / "c.trc")


def test_qtm_tsv_reads_like_the_qualisys_c3d(data_dir, tmp_path):
    """The shared Qualisys walk (a QTM capture, Z up) as QTM's TSV: the same points, gaps (QTM's
    zeros), rate, and its unidentified trajectory as an unlabelled point; without the column line
    too, and with empty cells for gaps; an external timebase (``FREQUENCY EXT``) timed by its Time column;
    a text column of trajectory types beside the numbers."""
    c3d = load_clip(data_dir / QUALISYS).slice(0, 120)
    P = _holed(c3d, seed=2)
    stray = P[:, :1] + np.array([0.0, 0.0, 0.3])             # a trajectory QTM did not identify
    names = list(c3d.meta["raw_labels"]) + ["Unidentified 1"]
    for kw in (dict(), dict(columns=False, zeros_for_gaps=False), dict(frequency="EXT"), dict(types=True)):
        f = write_qtm_tsv(tmp_path / "walk.tsv", np.concatenate([P, stray], 1), names, c3d.rate, **kw)
        back = load_clip(f)
        assert back.names == c3d.names and back.rate == 200.0 and back.meta["format"] == "qtm_tsv"
        assert (back.meta["units"], back.meta["up_axis"]) == ("mm", "Z")
        np.testing.assert_allclose(back.positions, P, atol=1e-6)
        assert np.array_equal(np.isnan(back.positions), np.isnan(P))
        assert back.meta["unlabelled_names"] == ("Unidentified 1",)
        assert back.meta["qtm_events"] == [["start", "3", "0.015"]]
    assert holds_markers(f)


def test_qtm_exports_without_markers_are_refused_and_skipped_in_folders(data_dir, tmp_path):
    c3d = load_clip(data_dir / QUALISYS).slice(0, 20)
    write_qtm_tsv(tmp_path / "walk.tsv", c3d.positions, list(c3d.names), c3d.rate)
    six = tmp_path / "walk_6d.tsv"
    six.write_text("NO_OF_FRAMES\t20\nNO_OF_CAMERAS\t12\nNO_OF_BODIES\t1\nFREQUENCY\t200\nDATA_INCLUDED\t6D\n"
                   "BODY_NAMES\twand\nFrame\tTime\tX\tY\tZ\n1\t0\t1\t2\t3\n")
    (tmp_path / "notes.tsv").write_text("subject\theight\nanna\t1.71\n")
    with pytest.raises(ValueError, match=r"without 3D marker trajectories \(6D\)"):
        load_clip(six)
    assert not holds_markers(six) and not holds_markers(tmp_path / "notes.tsv")
    assert [p.name for p in expand_inputs([str(tmp_path)])] == ["walk.tsv"]
    with pytest.raises(CliError, match="no recordings"):
        expand_inputs([str(_empty(tmp_path))])


def _empty(tmp_path):
    d = tmp_path / "empty"
    d.mkdir()
    (d / "walk_a.tsv").write_text("NO_OF_FRAMES\t1\nDATA_INCLUDED\tANALOG\n")
    return d


def test_motive_csv_reads_the_measured_markers_only(data_dir, tmp_path):
    """CMU 85 (a Vicon take, prefix ``Male:``) as Motive exports it: Y up, metres, a rigid body,
    a bone-marker constraint of the first marker (filled in where the marker is hidden: it must
    not be read as a measurement), blank cells for gaps, an unlabelled marker."""
    c3d = load_clip(data_dir / CMU).slice(100, 220)
    P = _holed(c3d, seed=3)
    stray = P[:, 5:6] + np.array([0.2, 0.0, 0.0])
    names = list(c3d.meta["raw_labels"]) + ["Unlabeled 1001"]
    f = write_motive_csv(tmp_path / "take.csv", np.concatenate([P, stray], 1), names, c3d.rate)
    back = load_clip(f)
    assert back.names == c3d.names and back.meta["format"] == "motive_csv" and back.rate == 120.0
    assert (back.meta["units"], back.meta["up_axis"]) == ("m", "Y")
    np.testing.assert_allclose(back.positions, P, atol=1e-6)
    assert np.array_equal(np.isnan(back.positions), np.isnan(P))
    assert back.meta["unlabelled_names"] == ("Unlabeled 1001",)
    (tmp_path / "rb.csv").write_text("Format Version,1.23,Export Frame Rate,120\n\n,Type,Rigid Body,Rigid Body,"
                                     "Rigid Body\n,Name,wand,wand,wand\n,ID,1,1,1\n,,Position,Position,Position\n"
                                     "Frame,Time (Seconds),X,Y,Z\n0,0,1,2,3\n")
    with pytest.raises(ValueError, match="no Marker position columns \\(columns of Rigid Body\\)"):
        load_clip(tmp_path / "rb.csv")


# -- dtm-label: every format in, a labelled TRC out ----------------------------------------------------
@pytest.fixture(scope="module")
def upper_model(data_dir, tmp_path_factory):
    hdm = load_clip(data_dir / HDM)
    model, _ = train_model([hdm.select(UPPER).slice(1200, 1900)], TrainConfig(seed=0, k_max=2, structure="greedy"))
    return save_model(model, tmp_path_factory.mktemp("models") / "upper12.npz"), hdm


def _label(model, take, capsys, *extra):
    assert label_main([str(model), str(take), "--json", "--quiet", "--calibrate", "off", *extra]) == 0
    return json.loads(capsys.readouterr().out)


def test_dtm_label_gives_the_same_labels_from_every_format(upper_model, tmp_path, capsys):
    """One real stretch (12 named markers with gaps, two knees as unnamed trajectories) as C3D,
    TRC, QTM TSV and Motive CSV: the same accuracy and ghost rejection from each; the labelled
    TRC written from the TSV holds the model's labels at the input's points, in its units."""
    from dtm_labeler.motion.c3d_write import write_c3d
    model, hdm = upper_model
    clip = hdm.select(UPPER).slice(2000, 2090)
    P = np.concatenate([_holed(clip, seed=4, share=0.05), hdm.select(GHOSTS).slice(2000, 2090).positions], 1)
    names = UPPER + ["*0", "*1"]
    files = [write_c3d(tmp_path / "t.c3d", P, names, clip.rate),
             write_trc(tmp_path / "t.trc", P, names, clip.rate, up_axis="Y"),
             write_qtm_tsv(tmp_path / "t.tsv", P, UPPER + ["Unidentified 1", "Unidentified 2"], clip.rate),
             write_motive_csv(tmp_path / "t.csv", P, UPPER + ["Unlabeled 7", "Unlabeled 8"], clip.rate)]
    runs = [_label(model, f, capsys) for f in files]
    first = runs[0]
    assert first["accuracy"] > 0.9 and first["ghosts"] == 2 * clip.n_frames and first["ghost_rejection"] > 0.9
    for r in runs[1:]:
        assert (r["accuracy"], r["ghosts"], r["ghost_rejection"]) == \
            (first["accuracy"], first["ghosts"], first["ghost_rejection"])
    out = tmp_path / "labelled.trc"
    _label(model, files[2], capsys, "--out", str(out))
    head = out.read_text().splitlines()
    assert head[0].startswith("PathFileType") and head[2].split("\t")[4] == "mm"
    back = load_clip(out)
    assert back.names == tuple(UPPER) and back.rate == clip.rate
    right = np.abs(back.positions - P[:, :len(UPPER)]).max(-1) < 1e-6
    seen = np.isfinite(P[:, :len(UPPER)]).all(-1)
    assert right[seen].mean() > 0.9                           # the true samples carry their names
