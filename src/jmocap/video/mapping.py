"""BlazePose's 33 landmarks -> OpenPose BODY_25, the layout of jmocap's shipped weights.

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

from jmocap.layouts import BODY25
from jmocap.video.blazepose import BLAZEPOSE_NAMES

__all__ = ["BODY25_FROM_BLAZEPOSE", "to_body25"]

#: BODY_25 joint -> the BlazePose landmark(s) it is made of (two: their mid-point; none: missing)
BODY25_FROM_BLAZEPOSE: dict[str, tuple[str, ...]] = {
    "Nose": ("nose",),
    "Neck": ("left_shoulder", "right_shoulder"),
    "RShoulder": ("right_shoulder",),
    "RElbow": ("right_elbow",),
    "RWrist": ("right_wrist",),
    "LShoulder": ("left_shoulder",),
    "LElbow": ("left_elbow",),
    "LWrist": ("left_wrist",),
    "MidHip": ("left_hip", "right_hip"),
    "RHip": ("right_hip",),
    "RKnee": ("right_knee",),
    "RAnkle": ("right_ankle",),
    "LHip": ("left_hip",),
    "LKnee": ("left_knee",),
    "LAnkle": ("left_ankle",),
    "REye": ("right_eye",),
    "LEye": ("left_eye",),
    "REar": ("right_ear",),
    "LEar": ("left_ear",),
    "LBigToe": ("left_foot_index",),
    "LSmallToe": (),
    "LHeel": ("left_heel",),
    "RBigToe": ("right_foot_index",),
    "RSmallToe": (),
    "RHeel": ("right_heel",),
}
assert tuple(BODY25_FROM_BLAZEPOSE) == BODY25.joints


def to_body25(points, confidence) -> np.ndarray:
    """BODY_25 keypoints (..., 25, 3) (x, y pixels, confidence; missing: 0, 0, 0) from BlazePose
    points (..., >=33, 2) and per-landmark confidences (..., >=33) in [0, 1]."""
    P = np.asarray(points, np.float64)
    C = np.asarray(confidence, np.float64)
    out = np.zeros(P.shape[:-2] + (BODY25.num_joints, 3))
    for j, src in enumerate(BODY25_FROM_BLAZEPOSE.values()):
        if not src:
            continue
        ids = [BLAZEPOSE_NAMES.index(s) for s in src]
        out[..., j, :2] = P[..., ids, :].mean(-2)
        out[..., j, 2] = C[..., ids].min(-1)
    ok = (out[..., 2] > 0) & np.isfinite(out).all(-1)
    out[~ok] = 0.0
    return out.astype(np.float32)
