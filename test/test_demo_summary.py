"""dtm-demo's per-frame summary (pure Python, no node): frames with errors, the start-up
before the first fully right frame, and the accuracy from that frame on; and its model cache."""
from dtm_labeler.cli.demo import _frames_with_errors, cached_model_path
from dtm_labeler.model import io as model_io


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
    """A model cached by an older version (another file format: fewer model terms) is not
    reused: the cache name changes with the format."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    key = {"seed": 0, "frames": 600}
    path = cached_model_path(key)
    assert path.parent == tmp_path / "dtm_labeler" and path == cached_model_path(dict(key))
    assert cached_model_path({"seed": 1, "frames": 600}) != path
    monkeypatch.setattr(model_io, "FORMAT_VERSION", model_io.FORMAT_VERSION + 1)
    assert cached_model_path(key) != path
