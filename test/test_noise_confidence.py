"""A known system noise (``noise_mm``) widens the model (``TriangulatedModel.with_noise``) and
moves the confidence's yardstick by the fit the noise costs a right labeling
(``noise_fit_drop``): the published confidences stay calibrated, the labels unchanged."""
import numpy as np
import pytest

from dtm_labeler.evaluation.generalisation import load_source, model_clip
from dtm_labeler.evaluation.pipeline import label_clip_run
from dtm_labeler.labeling.stream import LabelerSettings
from dtm_labeler.model.features import canonicalise, lateral_yaw, point_states
from dtm_labeler.training.gaps import fill_yaw
from dtm_labeler.training.train import TrainConfig, train_model

NOISE_M = 0.01


@pytest.fixture(scope="module")
def walk(data_dir):
    train = load_source(data_dir, "W1@0:0.5", "body14")
    test = load_source(data_dir, "W1@0.5:1", "body14")
    model, _ = train_model([train], TrainConfig(mixture="fixed", k_fixed=2, structure="given", seed=0))
    return model, test


def _floor(sd: float, rate: float = 120.0) -> np.ndarray:
    pos, vel = np.sqrt(2.0) * sd, np.sqrt(2.0) * sd * rate
    return np.r_[np.full(9, vel ** 2), np.full(6, pos ** 2)]


def test_noise_fit_drop_matches_what_noisy_frames_lose(walk):
    """The closed form (per component ``1/2 log det(I + S^-1 D)``, conditionals as joint minus
    parents) against real frames: a walk's true labels fit the clean model, the same frames with
    10 mm of noise the widened one; per label the fit falls by about the predicted amount."""
    model, test = walk
    mc = model_clip(model, test.slice(0, 240))
    rng = np.random.default_rng(0)

    def states(P):
        return canonicalise(point_states(P, mc.rate), fill_yaw(lateral_yaw(P, model.heading_pairs)))
    clean = model.frame_log_likelihood(states(mc.positions)[1:]).mean()
    noisy = model.with_noise(NOISE_M).frame_log_likelihood(
        states(mc.positions + rng.normal(0.0, NOISE_M, mc.positions.shape))[1:]).mean()
    measured = (clean - noisy) / model.n_labels
    predicted = model.noise_fit_drop(_floor(NOISE_M))
    assert measured > 3.0 and 0.6 * measured < predicted < 1.25 * measured


def test_with_noise_moves_the_confidence_yardstick_only(walk):
    model, _ = walk
    wide = model.with_noise(NOISE_M)
    drop = model.noise_fit_drop(_floor(NOISE_M))
    base = model.settings.get("fit_reference_per_label", model.settings["loglik_per_label"])
    assert wide.settings["fit_reference_per_label"] == pytest.approx(base - drop)
    assert wide.settings["loglik_per_label"] == model.settings["loglik_per_label"]     # the loss checks' level
    assert model.with_noise(0.0) is model


def test_noisy_stream_confidence_stays_calibrated(walk):
    """10 mm of noise on every coordinate, ``noise_mm`` told: 98 % of the labels right; expected
    calibration error 2.5 % (4.9 % with the training fit as the yardstick: every frame then fits
    'below' it and every confidence is lowered)."""
    model, test = walk
    run = label_clip_run(model, test.slice(0, 240), LabelerSettings(noise_mm=NOISE_M * 1e3), noise_mm=NOISE_M * 1e3,
                         seed=0)
    m = run.metrics
    assert m.accuracy > 0.95
    assert m.calibration_error < 0.037
