"""Fixed reflections in the clutter model (``Background.fixed_share``): a point that has stayed put
longer than its label ever did in training is as likely clutter as body, so a floor reflection no
longer takes the label of a marker whose triangle neighbours are hidden (every term of that label
marginalised, eq. 30-31) and keeps it. Share 0: the paper's clutter, exactly."""
import numpy as np
import pytest

from dtm_labeler.evaluation.corruption import corrupt_clip, realistic_gaps, static_ghosts
from dtm_labeler.labeling.stream import LabelerSettings, StreamLabeler
from dtm_labeler.motion import load_clip, to_point_set
from dtm_labeler.search.problem import Background
from dtm_labeler.training.train import TrainConfig, train_model

SHARE = 0.002                 # the default share


def test_a_still_point_is_likelier_clutter_a_moving_one_is_not():
    assert Background().fixed_share == SHARE
    b = Background(fixed_share=SHARE)
    v = np.array([[0.0, 0.0, 0.0], [0.03, 0.0, 0.0], [0.06, 0.0, 0.0], [0.0, 0.5, 0.0], [1.0, 1.0, 1.0],
                  [np.nan] * 3])
    loss = b.fixed_loss(v)
    assert 8.0 < loss[0] < 10.0
    assert loss[0] > loss[1] > loss[2] > 3.0
    assert loss[3] < 1e-100 and loss[4] == 0.0 and loss[5] == 0.0     # the uniform density
    assert (Background(fixed_share=0.0).fixed_loss(v) == 0.0).all()
    with pytest.raises(ValueError):
        Background(fixed_share=1.0)
    with pytest.raises(ValueError):
        Background(fixed_speed_mps=0.0)


def test_fixed_reflections_do_not_take_hidden_markers_labels(data_dir):
    """22 of HDM05's 41 markers (one draw), a model of 600 frames, the next 720 frames (6 s)
    live, a quarter of the samples in real-looking gaps and three fixed reflections in the
    volume (two draws of them pooled). Uniform clutter -> the default, measured once the
    reflections have rested 2.5 s: 60.47 -> 95.71 % right, reflections left unlabelled 25.2 ->
    95.7 % (over the whole stream 64.22 -> 86.81 %; with half of the samples hidden 54.16 -> 60.07
    %; the instantaneous form, every still point paying: 87.75 % over the stream). Since the
    level of a heavily hidden stream is set again with velocities (``tracked.UNTAUGHT_WEIGHT``)
    the uniform clutter's searches find more of it: 78.72 -> 95.90 % right, 57.6 -> 97.0 %
    left unlabelled."""
    clip = to_point_set(load_clip(data_dir / "markers_c3d/hdm05_bd_05-01_01_120.c3d"), "all")
    rng = np.random.default_rng(5)
    sub = clip.select([clip.names[i] for i in sorted(rng.choice(clip.n_points, 22, replace=False))])
    model = train_model([sub.slice(2360, 2960)], TrainConfig(mixture="fixed", k_fixed=1, seed=0))[0]
    limits = model.rest_limits(Background().fixed_after_s)
    assert limits.min() == 2.0 and limits.max() > 5.0      # the standing foot's labels may rest longer
    test = sub.slice(2960, 3680)
    P = test.positions.copy()
    P[realistic_gaps(P.shape[0], P.shape[1], test.rate, missing=0.25, mean_gap_s=0.25, spread=20.0, seed=5)] = np.nan
    gapped = test._replace(positions=P)
    late = int(2.5 * test.rate)
    score = {}
    for name, background in (("uniform", Background(fixed_share=0.0)), ("default", Background())):
        right = true = kept_out = fake = 0
        for draw in (0, 2):
            stream = corrupt_clip(gapped, extra=static_ghosts(test.positions, 3, seed=draw), seed=draw)
            with StreamLabeler(model, LabelerSettings(recovery="inline", background=background)) as lab:
                for i, f in enumerate(stream):
                    r = lab.process(f.xyz, f.stamp)
                    if i < late:
                        continue
                    t = f.truth >= 0
                    right += int((r.labels[t] == f.truth[t]).sum())
                    true += int(t.sum())
                    kept_out += int((r.labels[~t] < 0).sum())
                    fake += int((~t).sum())
        score[name] = (right / true, kept_out / fake)
    print(score)
    accuracy, rejected = score["default"]
    assert accuracy >= 0.92 and rejected >= 0.7
    assert accuracy - score["uniform"][0] >= 0.12 and rejected - score["uniform"][1] >= 0.25
