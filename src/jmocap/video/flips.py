"""Left/right flip repair over a whole track: a Viterbi over the frames' left/right labellings.

2D pose detectors confuse the person's left and right, most of all in side views, and keep the
wrong labelling for tens of frames. Over one track, each frame gets a label: *as detected* (0)
or *swapped* (1). The labelling minimises

    sum_i  u * s_i  +  C_i(s_{i-2}, s_{i-1}, s_i)

where ``C_i`` is how far the limb keypoints (shoulders, elbows, wrists, hips, knees, ankles,
heels, toes) of frame i, labelled ``s_i``, are from their constant-velocity prediction from the
two frames before (labelled ``s_{i-2}``, ``s_{i-1}``): the weighted mean distance in pixels,
divided by the track's body scale (its median torso length, mid-shoulder to mid-hip), each
point weighted by the smallest of its three visibilities, and divided by the frames ``g`` since
the previous observation (a gap weakens the link; the prediction extrapolates over it). The
first link (no velocity yet) uses the distance between the two frames. ``u`` (``swap_cost``) is
a small price per swapped frame, so the detector's labelling wins where the motion says
nothing (a person seen exactly side-on with the legs together).

Why the velocity and not only the position: a walker's legs cross twice per stride, and at a
crossing both labellings put the legs in the same places, so a labelling that switches there
costs nothing in position. A detector flip that begins or ends at a crossing is then invisible
to a position-only cost (and the cheapest labelling may swap the wrong half of the segment);
in velocity it is not: after the switch each leg would reverse, a jump of twice the legs'
relative speed. A flip of L frames is repaired when its two boundary jumps cost more than
``u L`` (with ``u = 0.01`` and a jump of a quarter torso, segments up to 50 frames; a jump
where the limbs are apart is far larger).

The Viterbi runs over the pairs (s_{i-1}, s_i) (four states), exactly.
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
      points: (n, K, 2) image points of the track's observed frames, in time order (BlazePose
        order; K > the largest index of ``pairs``).
      visibility: (n, K) weights in [0, 1] (a point with 0 does not count).
      frames: (n,) increasing frame numbers of the observations (default 0..n-1).
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
    left = [i for i, _ in pairs]
    right = [j for _, j in pairs]
    order = (np.array(left + right), np.array(right + left))  # the limb points, as detected / swapped
    L = np.stack([P[:, o] for o in order], axis=1)  # (n, 2, M, 2): frame, labelling, point, xy
    W = np.stack([V[:, o] for o in order], axis=1)  # (n, 2, M)
    scale = _torso_scale(P)
    u = np.array([0.0, swap_cost])
    if n == 1:
        return np.zeros(1, bool)
    g = np.diff(frames).astype(np.float64)  # g[i - 1]: frames from observation i - 1 to i

    # first link: distance between frames 0 and 1 under labellings (a, b)
    d1 = _wmean(L[1][None, :] - L[0][:, None], np.minimum(W[1][None, :], W[0][:, None]))
    cost = u[:, None] + u[None, :] + d1 / (scale * g[0])  # cost[a, b] of (s0, s1)
    back = np.zeros((n, 2, 2), np.int8)  # back[i, b, c]: best s_{i-2} for (s_{i-1}, s_i) = (b, c)
    for i in range(2, n):
        r = g[i - 1] / g[i - 2]
        # prediction of frame i from frames i-2 (label a) and i-1 (label b): (a, b, M, 2)
        pred = L[i - 1][None, :] + r * (L[i - 1][None, :] - L[i - 2][:, None])
        resid = L[i][None, None, :] - pred[:, :, None]  # (a, b, c, M, 2)
        w = np.minimum(np.minimum(W[i - 2][:, None, None], W[i - 1][None, :, None]), W[i][None, None, :])
        c2 = _wmean(resid, w) / (scale * g[i - 1])  # (a, b, c)
        total = cost[:, :, None] + c2  # (a, b, c)
        back[i] = np.argmin(total, axis=0)
        cost = np.min(total, axis=0) + u[None, :]  # (b, c)
    b, c = np.unravel_index(int(np.argmin(cost)), cost.shape)
    labels = np.zeros(n, bool)
    labels[n - 1], labels[n - 2] = bool(c), bool(b)
    for i in range(n - 1, 1, -1):
        labels[i - 2] = bool(back[i, int(labels[i - 1]), int(labels[i])])
    return labels


def _wmean(diff: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted mean over the points (axis -2 of ``diff``) of the distances |diff|."""
    d = np.linalg.norm(diff, axis=-1)
    s = w.sum(-1)
    return np.where(s > 0, (w * d).sum(-1) / np.where(s > 0, s, 1.0), 0.0)


def _torso_scale(P: np.ndarray) -> float:
    """Median distance mid-shoulder to mid-hip over the track (pixels; >= 1)."""
    names = BLAZEPOSE_NAMES
    sh = 0.5 * (P[:, names.index("left_shoulder")] + P[:, names.index("right_shoulder")])
    hip = 0.5 * (P[:, names.index("left_hip")] + P[:, names.index("right_hip")])
    d = np.linalg.norm(sh - hip, axis=-1)
    d = d[np.isfinite(d)]
    return max(1.0, float(np.median(d))) if len(d) else 1.0
