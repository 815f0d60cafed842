"""The running level of a heavily hidden stream is set again on its first frame with velocities
(:meth:`~dtm_labeler.labeling.tracked.TrackedLabeler._level_with_velocities`): inline recovery
only, and only where that frame would teach the level little (``UNTAUGHT_WEIGHT``)."""
from dtm_labeler.evaluation.corruption import corrupt_clip
from dtm_labeler.evaluation.pipeline import model_clip
from dtm_labeler.labeling.recovery import DeferredRecovery
from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler


def _levels(lab, frames, k: int = 12) -> list[float]:
    """The first model's level after each of the first ``k`` frames."""
    out = []
    for fr in frames[:k]:
        lab.process(fr.xyz, fr.stamp)
        out.append(float(lab.level[0]))
    return out


def test_a_half_hidden_stream_is_judged_by_a_level_with_velocities(hdm05_calibrated, hdm05_half_hidden):
    """Inline: the first frame (positions only) sets a level several nats per label below what
    a frame with velocities gives; the second frame sets it again, and restarts are judged on
    each frame's observation pattern from then on."""
    with StreamLabeler(hdm05_calibrated, LabelerSettings(recovery="inline")) as lab:
        levels = _levels(lab, hdm05_half_hidden)
        assert lab._level_from_model[0] and not lab._level_on_positions.any()
    assert levels[1] > levels[0] + 3.0                     # nats per label
    # the level a frame with velocities gives is the one kept (frames this hidden barely move it)
    assert abs(levels[-1] - levels[1]) < 0.5


def test_a_fully_seen_stream_keeps_its_start(hdm05_calibrated, hdm05_take):
    """Every marker seen: the second frame teaches the level itself, nothing is set again."""
    frames = list(corrupt_clip(model_clip(hdm05_calibrated, hdm05_take.slice(2400, 2460)), noise_mm=1.0, seed=1))
    with StreamLabeler(hdm05_calibrated, LabelerSettings(recovery="inline")) as lab:
        _levels(lab, frames)
        assert not lab._level_from_model.any() and not lab._level_on_positions.any()


def test_background_recovery_keeps_the_first_frames_level(hdm05_calibrated, hdm05_half_hidden):
    """Background (the node): the stream's first level stays (module ``tracked``: every frame of
    such a stream would be doubted and its confidence halved)."""
    lab = StreamLabeler(hdm05_calibrated, LabelerSettings(recovery="background", audit_period_s=0))
    lab.recovery.close()
    lab.recovery = DeferredRecovery(lab, delay_frames=25, interim_frames=2)
    try:
        levels = _levels(lab, hdm05_half_hidden)
        assert not lab._level_from_model.any()
    finally:
        lab.close()
    assert abs(levels[-1] - levels[0]) < 0.5
