"""dtm-demo's per-frame summary (pure Python, no node): frames with errors, the start-up
before the first fully right frame, and the accuracy from that frame on."""
from dtm_labeler.cli.demo import _frames_with_errors


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
