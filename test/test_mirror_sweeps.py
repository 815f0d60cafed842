"""The full search's mirrored sweeps (search/label_search.py ``sweep_regions(mirrored=True)``,
search/dtm_dp.py ``mirrored_regions``, setting ``mirror_sweeps``): each label's body
neighbourhood joined with its mirror image and relabelled exactly as a whole -- on real frames
of CMU 85's floor moves, the two arms' chains interleaved (labels handed across the body, which
no region of one side holds) are put right."""
import numpy as np
import pytest

from dtm_labeler.evaluation.pipeline import model_clip
from dtm_labeler.labeling.config import LabelerSettings
from dtm_labeler.labeling.stream import StreamLabeler
from dtm_labeler.search.dtm_dp import mirrored_regions, regions_of
from dtm_labeler.search.label_search import GASettings, sweep_regions

#: the arms of a cold search's labeling of CMU 85's crouched breakdance (``dtm-eval``'s
#: markers section, frame 91 of the held-out tenth, 62 nats below the truth): each label here
#: on the point of the one it names, None = missing; the others on their own points
INTERLEAVED = {"LFIN": "RELB", "LUPA": "LWRB", "RWRB": "LFRM", "LWRA": "RFRM", "LWRB": "RWRB", "LFRM": "RFIN",
               "RELB": "LFIN", "RFIN": "LELB", "RFRM": "LWRA", "LSHO": None, "LELB": None}


@pytest.fixture(scope="module")
def floor(case_cell):
    """``dtm-eval``'s floor-moves cell: a generic body of CMU 85's jump + twist and HDM05's
    standing take, and the breakdance on the floor (its first 130 frames)."""
    model, test = case_cell("m_floor")
    return model, model_clip(model, test.slice(0, 130))


def test_mirrored_regions_hold_both_sides(floor):
    model, _ = floor
    L = list(model.labels)
    one_sided = regions_of(model, 7, partner=False)
    both = mirrored_regions(model, 7)
    assert len(both) == model.n_labels and mirrored_regions(model, 7) is both      # computed once
    partner = {int(a): int(b) for p in model.mirror_pairs for a, b in (p, p[::-1])}
    for lab, (r1, r2) in enumerate(zip(one_sided, both)):
        assert set(r1) <= set(r2) and lab in r2
        assert {partner[m] for m in r1 if m in partner} <= set(r2)   # every label's mirror partner too
    lfin = both[L.index("LFIN")]
    assert {"LFIN", "RFIN", "LWRA", "RWRA"} <= {L[i] for i in lfin}


def _interleaved(model, clip) -> dict[bool, list[bool]]:
    """Frames 21, 31, ..., 121 labelled with true point ids; from each frame's truth with the
    arms as :data:`INTERLEAVED`, the sweeps' result with and without the mirror images (one
    stream): whether the arms' labels are back on their points, or a labeling the model prefers
    to the truth was found."""
    L = list(model.labels)
    M = len(L)
    truth = np.arange(M)
    arms = np.array([L.index(n) for n in INTERLEAVED])
    moved = truth.copy()
    for lab, onto in INTERLEAVED.items():
        moved[L.index(lab)] = M if onto is None else L.index(onto)
    s = GASettings()
    out = {True: [], False: []}
    with StreamLabeler(model, LabelerSettings(recovery="inline")) as lab:
        for f in range(clip.n_frames):
            lab.process(clip.positions[f], f / clip.rate, ids=truth)
            if f >= 21 and f % 10 == 1:
                problems, _, found = lab.last_frame
                problem = problems[found.best_model]
                start = np.where(moved < M, moved, problem.n)
                f0 = float(problem.fitness(start[None])[0])
                ft = float(problem.fitness(truth[None])[0])
                for mirrored in (True, False):
                    ind, f1, _ = sweep_regions(problem, start, f0, 3, s.wide_size, s.polish_rounds, None,
                                               s.mirror_branches if mirrored else 0,
                                               wide=s.mirror_candidates if mirrored else s.wide_candidates,
                                               mirrored=mirrored)
                    assert f1 >= f0                   # a sweep never returns a worse labeling
                    out[mirrored].append(bool(np.array_equal(ind[arms], truth[arms])) or f1 >= ft - 1e-6)
    return out


def test_arms_interleaved_across_the_body_are_put_right(floor):
    model, clip = floor
    got = _interleaved(model, clip)
    on, off = got[True], got[False]
    assert sum(on) >= 9 and sum(on) - sum(off) >= 2, (on, off)      # today 10 and 7 of 11
