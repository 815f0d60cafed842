"""A subject calibration fits each triangle's broad weight again on its window
(training/body_fit.py ``window_broad_weights``): a person and a motion the training never
showed -- subject 9's run under a model of subjects 5, 7 and 55 (walk, lambada, pirouette) --
is labelled right after a calibration on the run's first 55 frames only when the window's
novelty opens the triangles it shows; the weights only rise, stay below the cap, keep the
training's where the window does not show a triangle whole, and do not compound over
calibrations."""
import numpy as np
import pytest

from dtm_labeler.evaluation import generalisation as gen
from dtm_labeler.evaluation.pipeline import label_clip_run, model_clip
from dtm_labeler.labeling.stream import LabelerSettings
from dtm_labeler.model.io import load_model, save_model
from dtm_labeler.training.calibrate import CalibrationSettings, calibrate, self_calibrate
from dtm_labeler.training.train import TrainConfig

WINDOW = 55                      # the eval's window for this take: a third of its 165 frames


@pytest.fixture(scope="module")
def run_case(data_dir):
    """A model of subjects 7, 55 and 5 (no run in it) and subject 9's run: window, rest."""
    train = [gen.load_source(data_dir, s, "body14") for s in ("W1", "D2", "D3")]
    model, _ = gen.train_case_model(train, TrainConfig(mixture="fixed", k_fixed=2, structure="given", seed=0))
    run = model_clip(model, gen.load_source(data_dir, "R1", "body14"))
    walk = model_clip(model, train[0]).slice(0, WINDOW)
    return model, run.slice(0, WINDOW), run.slice(WINDOW, None), walk


def test_an_unseen_motion_is_labelled_once_the_window_opens_its_triangles(run_case):
    """Measured: with the training's weights 88.3 % (the left elbow and wrist exchanged in 90 of
    110 frames); with the window's 100 %."""
    model, window, rest, _ = run_case
    acc = {}
    for min_frames in (0, 20):
        cal, _ = self_calibrate(model, window.positions, window.rate, CalibrationSettings(broad_min_frames=min_frames))
        acc[min_frames] = label_clip_run(cal, rest, LabelerSettings(seed=0), seed=0).accumulator.metrics().accuracy
        broad = cal.provenance["calibration"].get("broad")
        if min_frames == 0:
            assert broad is None and np.array_equal(cal.broad.weights, model.broad.weights)
        else:
            assert broad["triangles_raised"] >= 1 and broad["largest_weight"] <= 0.5
    assert acc[0] < 0.95 and acc[20] > 0.99


def test_weights_rise_only_where_the_window_shows_a_triangle_whole(run_case, tmp_path):
    model, window, _, walk = run_case
    trained = model.broad.weights
    P = window.positions.copy()
    hidden = model.labels.index("lwrist")
    P[:, hidden] = np.nan
    cal = calibrate(model, P, check_labels=False, rate=window.rate)
    w = cal.broad.weights
    assert (w >= trained - 1e-12).all() and (w <= 0.5).all() and (w > trained).any()
    with_wrist = np.array([hidden in t for t in model.triangles])
    assert with_wrist.any() and np.array_equal(w[with_wrist], trained[with_wrist])
    assert cal.settings["broad_weights_training"] == pytest.approx(trained.tolist())
    # without the frames' rate there are no velocities to measure a triangle's novelty on
    assert np.array_equal(calibrate(model, P, check_labels=False).broad.weights, trained)
    # a calibration of a calibrated model starts from the training's weights: on a window of a
    # trained motion the run's weights fall back
    run_cal = calibrate(model, window.positions, check_labels=False, rate=window.rate)
    again = calibrate(run_cal, walk.positions, check_labels=False, rate=walk.rate)
    assert again.settings["broad_weights_training"] == pytest.approx(trained.tolist())
    assert (again.broad.weights >= trained - 1e-12).all()
    assert (again.broad.weights < run_cal.broad.weights - 0.05).any()
    # the weights and the training's floor travel with the model file
    save_model(cal, tmp_path / "cal.npz")
    back = load_model(tmp_path / "cal.npz")
    assert np.array_equal(back.broad.weights, w)
    assert back.settings["broad_weights_training"] == pytest.approx(trained.tolist())
