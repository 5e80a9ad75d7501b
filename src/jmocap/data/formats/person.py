"""Choosing one person per frame from a multi-person detector's output.

Formats that store several people per frame (OpenPose, COCO results, MMPose) turn each into a
:class:`Candidate`; :func:`select_person` picks one per frame, following a track.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Candidate:
    """One detected person in one frame: cleaned (J, 3) keypoints, a score, optional track id."""

    keypoints: np.ndarray
    score: float
    track_id: int | None = None


def _pose_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean distance of joints visible in both poses, in units of ``b``'s bounding-box diagonal.

    1.0 (the cap) when they share no visible joint.
    """
    common = (a[:, 2] > 0) & (b[:, 2] > 0)
    vis_b = b[:, 2] > 0
    if not common.any():
        return 1.0
    pts = b[vis_b, :2]
    diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) if len(pts) > 1 else 0.0
    scale = max(diag, 1.0)
    d = float(np.mean(np.linalg.norm(a[common, :2] - b[common, :2], axis=-1))) / scale
    return min(d, 1.0)


def select_person(
    frames: Sequence[Sequence[Candidate]], num_joints: int, mode: str = "track"
) -> tuple[np.ndarray, np.ndarray]:
    """Pick one person per frame; returns ((T, J, 3) keypoints, (T,) picked index or -1).

    ``mode="best"``: the highest-scoring person of each frame, independently.

    ``mode="track"`` (default): the first frame with anyone picks the highest score; later
    frames keep following the last picked person:

    1. if the last pick had a tracker id (OpenPose ``person_id``, MMPose ``track_id``) and a
       candidate has the same id, that candidate;
    2. otherwise the candidate minimising ``d - 0.5 * score / max_score``, where ``d`` is the
       mean image distance of the joints visible in both poses, divided by the bounding-box
       diagonal of the last pick and capped at 1 (1 also when no joint is shared).

    The last pick is kept across frames where nobody is detected. Frames with no candidate
    are all-missing (confidence 0).
    """
    if mode not in ("track", "best"):
        raise ValueError(f"person selection mode must be 'track' or 'best', got {mode!r}")
    T = len(frames)
    out = np.zeros((T, num_joints, 3), np.float32)
    picked = np.full(T, -1, np.int64)
    prev: Candidate | None = None
    for t, cands in enumerate(frames):
        if not cands:
            continue
        scores = np.array([c.score for c in cands], dtype=np.float64)
        if mode == "best" or prev is None:
            i = int(np.argmax(scores))
        else:
            i = -1
            if prev.track_id is not None:
                same = [k for k, c in enumerate(cands) if c.track_id == prev.track_id]
                if same:
                    i = max(same, key=lambda k: scores[k])
            if i < 0:
                smax = scores.max() if scores.max() > 0 else 1.0
                cost = [
                    _pose_distance(c.keypoints, prev.keypoints) - 0.5 * s / smax
                    for c, s in zip(cands, scores, strict=True)
                ]
                i = int(np.argmin(cost))
        out[t] = cands[i].keypoints
        picked[t] = i
        prev = cands[i]
    return out, picked


__all__ = ["Candidate", "select_person"]
