"""Left/right flip repair over a whole track: a two-state Viterbi over the frames.

2D pose detectors confuse the person's left and right, most of all in side views, and keep the
wrong labelling for tens of frames. Over one track, each frame gets a label *as detected* (0) or
*swapped* (1); the labelling minimises

    sum_i  u * s_i  +  D_i(s_{i-1}, s_i) / g_i

where ``D_i(a, b)`` is the mean distance between the limb keypoints (shoulders, elbows, wrists,
hips, knees, ankles, heels, toes) of the previous and this frame under labellings ``a`` and
``b``, divided by the track's body scale (its median torso length: mid-shoulder to mid-hip),
each point weighted by the smaller of its two visibilities; ``g_i`` is the number of frames
between the two observations (a gap weakens the link); ``u`` (``swap_cost``) is a small price
per swapped frame, so the detector's labelling wins where the motion says nothing (a person
seen exactly side-on, legs together). A segment of ``L`` frames flipped between two frames
where the limbs are apart costs two jumps of about the left-right distance, which is larger
than ``u L`` for segments up to ``2 (x - s) / u`` frames (x the cross-label distance, s the
motion per frame; with ``u = 0.01`` and legs half a torso apart, about 100 frames).
"""

from __future__ import annotations

import numpy as np

from jmocap.video.blazepose import BLAZEPOSE_NAMES

__all__ = ["LIMB_PAIRS", "LR_PAIRS", "repair_flips", "swap_left_right"]


def _pairs(names, filt=lambda n: True):
    out = []
    for i, n in enumerate(names):
        if n.startswith("left") and filt(n):
            out.append((i, names.index("right" + n[len("left"):])))
        elif n.endswith("_left") and filt(n):  # mouth_left
            out.append((i, names.index(n[: -len("_left")] + "_right")))
    return tuple(out)


#: every (left, right) pair of the 33 BlazePose landmarks (face, arms, legs, feet)
LR_PAIRS = _pairs(BLAZEPOSE_NAMES)
_LIMBS = ("shoulder", "elbow", "wrist", "hip", "knee", "ankle", "heel", "foot_index")
#: the (left, right) pairs whose motion decides the labelling
LIMB_PAIRS = _pairs(BLAZEPOSE_NAMES, lambda n: any(n.endswith(limb) for limb in _LIMBS))


def swap_left_right(a: np.ndarray, pairs=LR_PAIRS, axis: int = -2) -> np.ndarray:
    """``a`` with the points of each (left, right) pair exchanged along ``axis`` (the landmark
    axis: -2 for (..., 33, 2) points, -1 for (..., 33) scores)."""
    a = np.asarray(a)
    perm = np.arange(a.shape[axis])
    for i, j in pairs:
        perm[i], perm[j] = j, i
    return np.take(a, perm, axis=axis)


def repair_flips(points, visibility, frames=None, *, swap_cost: float = 0.01,
                 pairs=LIMB_PAIRS) -> np.ndarray:
    """The labelling (n,) bool (True: swap this frame's left and right) of one track.

    Args:
      points: (n, K, 2) image points of the track's observed frames, in time order (K >= the
        largest index of ``pairs``; BlazePose order).
      visibility: (n, K) weights in [0, 1] (a point with 0 does not count).
      frames: (n,) increasing frame numbers of the observations (default 0..n-1): a link across
        a gap of g frames counts 1/g.
      swap_cost: the price of one swapped frame, in body scales.
    """
    P = np.asarray(points, np.float64)
    V = np.clip(np.asarray(visibility, np.float64), 0.0, 1.0)
    n = len(P)
    if n == 0:
        return np.zeros(0, bool)
    frames = np.arange(n) if frames is None else np.asarray(frames)
    if frames.shape != (n,) or np.any(np.diff(frames) <= 0):
        raise ValueError("repair_flips: frames must be n increasing frame numbers")
    left = np.array([i for i, _ in pairs])
    right = np.array([j for _, j in pairs])
    idx = np.concatenate([left, right])
    swp = np.concatenate([right, left])
    scale = _torso_scale(P)
    unary = np.array([0.0, swap_cost])
    cost = unary.copy()
    back = np.zeros((n, 2), np.int8)
    for i in range(1, n):
        a, b = P[i - 1], P[i]
        va, vb = V[i - 1], V[i]
        same = _mean_dist(a[idx], b[idx], np.minimum(va[idx], vb[idx]))
        cross = _mean_dist(a[idx], b[swp], np.minimum(va[idx], vb[swp]))
        g = float(frames[i] - frames[i - 1])
        D = np.array([[same, cross], [cross, same]]) / (scale * g)  # D[prev label, this label]
        total = cost[:, None] + D
        back[i] = np.argmin(total, axis=0)
        cost = total[back[i], [0, 1]] + unary
    labels = np.zeros(n, bool)
    labels[-1] = bool(np.argmin(cost))
    for i in range(n - 1, 0, -1):
        labels[i - 1] = bool(back[i, int(labels[i])])
    return labels


def _mean_dist(a, b, w) -> float:
    d = np.linalg.norm(a - b, axis=-1)
    s = w.sum()
    return float((w * d).sum() / s) if s > 0 else 0.0


def _torso_scale(P: np.ndarray) -> float:
    """Median distance mid-shoulder to mid-hip over the track (pixels; >= 1)."""
    names = BLAZEPOSE_NAMES
    sh = 0.5 * (P[:, names.index("left_shoulder")] + P[:, names.index("right_shoulder")])
    hip = 0.5 * (P[:, names.index("left_hip")] + P[:, names.index("right_hip")])
    d = np.linalg.norm(sh - hip, axis=-1)
    d = d[np.isfinite(d)]
    return max(1.0, float(np.median(d))) if len(d) else 1.0
