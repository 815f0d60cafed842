"""Compiled kernel of the clusters' handedness (:class:`~dtm_labeler.model.body.Handedness`).

A fitness call scores up to a few hundred candidate labelings; at 41 markers a calibrated body
holds some 70 quadruples, so each call takes the signed volume of 10^4 point quadruples. In
numpy that was a gather of (P, Q, 4, 3) points, a cross product and an einsum over them: 1.4 ms
per frame, more than every triangle term of the frame (HDM05, 41 markers, calibrated). Here one
loop reads each quadruple's four points where they lie and counts the mirrored ones.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def mirrored_quads(idx, pts, quads, sign):  # pragma: no cover - compiled
    """(P,) number of quadruples each row of ``idx`` (P, M) shows mirrored: for quadruple ``q``
    (label indices ``quads[q]``), the points ``pts[idx[p, quads[q]]]`` (N, 3) whose signed
    volume ``det[x_b - x_a, x_c - x_a, x_d - x_a]`` has the sign opposite to ``sign[q]``; a NaN
    point (missing) leaves the quadruple unmirrored."""
    P = idx.shape[0]
    out = np.zeros(P, dtype=np.int64)
    for p in range(P):
        count = 0
        for q in range(quads.shape[0]):
            a = idx[p, quads[q, 0]]
            b = idx[p, quads[q, 1]]
            c = idx[p, quads[q, 2]]
            d = idx[p, quads[q, 3]]
            u0 = pts[b, 0] - pts[a, 0]
            u1 = pts[b, 1] - pts[a, 1]
            u2 = pts[b, 2] - pts[a, 2]
            v0 = pts[c, 0] - pts[a, 0]
            v1 = pts[c, 1] - pts[a, 1]
            v2 = pts[c, 2] - pts[a, 2]
            w0 = pts[d, 0] - pts[a, 0]
            w1 = pts[d, 1] - pts[a, 1]
            w2 = pts[d, 2] - pts[a, 2]
            vol = (u1 * v2 - u2 * v1) * w0 + (u2 * v0 - u0 * v2) * w1 + (u0 * v1 - u1 * v0) * w2
            if vol * sign[q] < 0:                # NaN compares False
                count += 1
        out[p] = count
    return out


__all__ = ["mirrored_quads"]
