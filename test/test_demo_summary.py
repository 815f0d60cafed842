"""dtm-demo's per-frame summary (pure Python, no node): frames with errors, the start-up
before the first fully right frame, and the accuracy from that frame on; and its model cache,
calibrated to the recording's person unless asked not to."""
from dtm_labeler.cli import demo
from dtm_labeler.cli.demo import (_train_cached, build_parser, cached_model_path, _frames_with_errors,
                                  training_revision)
from dtm_labeler.model import io as model_io
from dtm_labeler.model.body import SEGMENT
from dtm_labeler.motion import synthesize


def test_start_up_and_steady_accuracy():
    # (stamp, right, visible): two wrong frames at the start, then one wrong later
    per_frame = [(0, 0, 12), (1, 6, 12), (2, 12, 12), (3, 11, 12), (4, 12, 12)]
    d = _frames_with_errors(per_frame)
    assert d["total"] == 3 and d["before_first_right_frame"] == 2
    assert d["accuracy_from_first_right_frame"] == 35 / 36


def test_no_right_frame_and_no_frames():
    d = _frames_with_errors([(0, 0, 12), (1, 3, 12)])
    assert d["before_first_right_frame"] == 2 and d["accuracy_from_first_right_frame"] is None
    d = _frames_with_errors([])
    assert d == dict(total=0, before_first_right_frame=0, accuracy_from_first_right_frame=None)


def test_cached_model_is_named_by_key_and_model_format(monkeypatch, tmp_path):
    """A model cached by an older version (another file format: fewer model terms, or training
    code that has changed) is not reused: the cache name changes with the format and with the
    training code's revision."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    key = {"seed": 0, "frames": 600}
    path = cached_model_path(key)
    assert path.parent == tmp_path / "dtm_labeler" and path == cached_model_path(dict(key))
    assert cached_model_path({"seed": 1, "frames": 600}) != path
    with monkeypatch.context() as m:
        m.setattr(model_io, "FORMAT_VERSION", model_io.FORMAT_VERSION + 1)
        assert cached_model_path(key) != path
    rev = training_revision()
    assert len(rev) == 12 and rev == training_revision()
    with monkeypatch.context() as m:
        m.setattr(demo, "training_revision", lambda: "0" * 12)          # the training code changed
        assert cached_model_path(key) != path
    assert cached_model_path(key) == path


def test_recording_model_is_calibrated_to_its_person(monkeypatch, tmp_path):
    """``--data``: the model trained on the recording's first part is calibrated to its one
    person (``dtm-train --calibrate``: segment lengths applied) and cached apart from the
    generic model ``--no-calibrate`` keeps."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    clips = lambda: [synthesize(duration=2.0, rate=120.0, seed=3)]    # noqa: E731
    cal = model_io.load_model(_train_cached({"t": 1, "calibrated": True}, clips, True, lambda *_: None,
                                            calibrate=True))
    gen = model_io.load_model(_train_cached({"t": 1}, clips, True, lambda *_: None))
    assert cal.provenance["calibration"]["source"] == "training takes" and cal.body.calibration
    assert not gen.body.calibration and "calibration" not in gen.provenance
    assert SEGMENT in cal.body.applied_kinds and SEGMENT not in gen.body.applied_kinds
    assert len(list((tmp_path / "dtm_labeler").glob("demo_model_*.npz"))) == 2
    assert not build_parser().parse_args([]).no_calibrate
    assert build_parser().parse_args(["--no-calibrate"]).no_calibrate
