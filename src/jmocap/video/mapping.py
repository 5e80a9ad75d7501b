"""BlazePose's 33 landmarks -> OpenPose BODY_25, the layout of jmocap's shipped weights.

The mapping is :data:`jmocap.layouts.BLAZEPOSE33`'s conversion to BODY_25 (joints matched by the
character's sites, :func:`jmocap.layouts.conversion`), the one any ``blazepose33`` clip gets:

Direct: nose, eyes (BlazePose's eye centres), ears, shoulders, elbows, wrists, hips, knees,
ankles, heels; BigToe = BlazePose's foot index (the tip of the foot). Derived: Neck = the
mid-point of the shoulders, MidHip = the mid-point of the hips (confidence: the smaller of the
two). SmallToe has no BlazePose counterpart and is written as missing (confidence 0, x = y = 0):
jmocap treats a missing joint as absent, never as a position, and the shipped networks were
trained with missing joints.

Confidence of a landmark: sigmoid(visibility) x sigmoid(presence) (both are the model's
per-landmark logits: occluded, and outside the image). BlazePose's hip points are not OpenPose's
(nor the character's hip sites, which jmocap's BODY_25 follows): on rendered walks its mid-hip
sits about 1 % of the body's height higher, and its hips are about 25 % closer together seen
from the front (docs/formats.md, "Video input"): a small systematic offset.
"""

from __future__ import annotations

import numpy as np

from jmocap.layouts import BLAZEPOSE33, BODY25, conversion

__all__ = ["to_body25"]

_CONVERSION = conversion(BLAZEPOSE33, BODY25)


def to_body25(points, confidence) -> np.ndarray:
    """BODY_25 keypoints (..., 25, 3) (x, y pixels, confidence; missing: 0, 0, 0) from BlazePose
    points (..., >=33, 2) and per-landmark confidences (..., >=33) in [0, 1]; a landmark that is
    not finite counts as missing."""
    P = np.asarray(points, np.float64)[..., :33, :]
    C = np.asarray(confidence, np.float64)[..., :33]
    ok = (C > 0) & np.isfinite(P).all(-1) & np.isfinite(C)
    kp = np.where(ok[..., None], np.concatenate([P, C[..., None]], -1), 0.0)
    return _CONVERSION.keypoints(kp)
