"""Keypoint layouts and their mapping onto the character's sites: the one place for it.

Every layout is an ordered tuple of joint names exactly as the format's own documentation
orders them, and a parallel tuple of the model sites that produce each joint:

* ``body25``: OpenPose BODY_25 (``openpose/doc/02_output.md``, ``POSE_BODY_25_BODY_PARTS``).
* ``coco17``: COCO keypoints (``person_keypoints`` category of the COCO 2017 annotations).
* ``h36m17``: the 17 Human3.6M joints used by VideoPose3D / most lifting work
  (pelvis, right leg, left leg, spine, thorax, neck/nose, head, left arm, right arm).
* ``halpe26``: AlphaPose's Halpe-26 (COCO-17, head top, neck, mid-hip and BODY_25's feet).
* ``blazepose33``: MediaPipe / BlazePose's 33 landmarks; its face-corner, mouth and finger
  landmarks have no site on the character (site ``""``) and are dropped when converted.

Site names are those of ``jmocap/assets/mjcf/humanoid.xml``; ``tests/test_humanoid_xml.py``
checks that every site named here exists in the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jmocap.constants import CONTACT_SITES as _CONTACT_SITES


@dataclass(frozen=True)
class Layout:
    name: str
    joints: tuple[str, ...]  # joint names in the format's own order
    sites: tuple[str, ...]  # model site producing each joint
    # joints whose mean is the root (pelvis) for root-relative coordinates
    root: tuple[str, ...]
    # pairs of (left index, right index), for left/right swap augmentation and flipping
    flip_pairs: tuple[tuple[int, int], ...]
    # joints whose mean stands in for the root in a frame where no root joint is seen but all of
    # these are: the two hips, whose 3D midpoint is the character's mid-hip site exactly (so
    # their 2D midpoint is the root's projection up to perspective); () for none
    root_fallback: tuple[str, ...] = ()

    @property
    def sited(self) -> bool:
        """Whether every joint is a site of the character (a layout can be synthesised, and its
        3D joints computed, only then; BlazePose-33's face and finger landmarks are not)."""
        return all(self.sites)

    def require_sites(self, what: str) -> None:
        """Raise ``ValueError`` naming ``what`` unless :attr:`sited`."""
        if not self.sited:
            missing = [j for j, s in zip(self.joints, self.sites, strict=True) if not s]
            raise ValueError(f"{what} needs a character site for every joint; layout {self.name!r} has none for "
                             f"{', '.join(missing)} (use body25, or convert: Clip.to_layout)")

    @property
    def num_joints(self) -> int:
        return len(self.joints)

    def index(self, joint: str) -> int:
        return self.joints.index(joint)

    @property
    def root_indices(self) -> tuple[int, ...]:
        return tuple(self.joints.index(j) for j in self.root)

    @property
    def root_fallback_indices(self) -> tuple[int, ...]:
        return tuple(self.joints.index(j) for j in self.root_fallback)


def _pairs(joints: tuple[str, ...]) -> tuple[tuple[int, int], ...]:
    pairs = []
    for i, name in enumerate(joints):
        for left, right in (("L", "R"), ("left_", "right_")):
            if name.startswith(left):
                mate = right + name[len(left):]
                if mate in joints:
                    pairs.append((i, joints.index(mate)))
    return tuple(pairs)


def _layout(name: str, spec: tuple[tuple[str, str], ...], root: tuple[str, ...],
            root_fallback: tuple[str, ...] = ()) -> Layout:
    joints = tuple(j for j, _ in spec)
    return Layout(name, joints, tuple(s for _, s in spec), root, _pairs(joints), root_fallback)


BODY25 = _layout(
    "body25",
    (
        ("Nose", "kp_nose"),
        ("Neck", "kp_neck"),
        ("RShoulder", "kp_right_shoulder"),
        ("RElbow", "kp_right_elbow"),
        ("RWrist", "kp_right_wrist"),
        ("LShoulder", "kp_left_shoulder"),
        ("LElbow", "kp_left_elbow"),
        ("LWrist", "kp_left_wrist"),
        ("MidHip", "kp_mid_hip"),
        ("RHip", "kp_right_hip"),
        ("RKnee", "kp_right_knee"),
        ("RAnkle", "kp_right_ankle"),
        ("LHip", "kp_left_hip"),
        ("LKnee", "kp_left_knee"),
        ("LAnkle", "kp_left_ankle"),
        ("REye", "kp_right_eye"),
        ("LEye", "kp_left_eye"),
        ("REar", "kp_right_ear"),
        ("LEar", "kp_left_ear"),
        ("LBigToe", "kp_left_big_toe"),
        ("LSmallToe", "kp_left_small_toe"),
        ("LHeel", "kp_left_heel"),
        ("RBigToe", "kp_right_big_toe"),
        ("RSmallToe", "kp_right_small_toe"),
        ("RHeel", "kp_right_heel"),
    ),
    root=("MidHip",),
    root_fallback=("RHip", "LHip"),
)

COCO17 = _layout(
    "coco17",
    (
        ("nose", "kp_nose"),
        ("left_eye", "kp_left_eye"),
        ("right_eye", "kp_right_eye"),
        ("left_ear", "kp_left_ear"),
        ("right_ear", "kp_right_ear"),
        ("left_shoulder", "kp_left_shoulder"),
        ("right_shoulder", "kp_right_shoulder"),
        ("left_elbow", "kp_left_elbow"),
        ("right_elbow", "kp_right_elbow"),
        ("left_wrist", "kp_left_wrist"),
        ("right_wrist", "kp_right_wrist"),
        ("left_hip", "kp_left_hip"),
        ("right_hip", "kp_right_hip"),
        ("left_knee", "kp_left_knee"),
        ("right_knee", "kp_right_knee"),
        ("left_ankle", "kp_left_ankle"),
        ("right_ankle", "kp_right_ankle"),
    ),
    # COCO has no pelvis joint: the root is the midpoint of the two hips
    root=("left_hip", "right_hip"),
)

H36M17 = _layout(
    "h36m17",
    (
        ("Hip", "kp_mid_hip"),
        ("RHip", "kp_right_hip"),
        ("RKnee", "kp_right_knee"),
        ("RFoot", "kp_right_ankle"),
        ("LHip", "kp_left_hip"),
        ("LKnee", "kp_left_knee"),
        ("LFoot", "kp_left_ankle"),
        ("Spine", "kp_spine"),
        ("Thorax", "kp_thorax"),
        ("Neck/Nose", "kp_nose"),
        ("Head", "kp_head_top"),
        ("LShoulder", "kp_left_shoulder"),
        ("LElbow", "kp_left_elbow"),
        ("LWrist", "kp_left_wrist"),
        ("RShoulder", "kp_right_shoulder"),
        ("RElbow", "kp_right_elbow"),
        ("RWrist", "kp_right_wrist"),
    ),
    root=("Hip",),
    root_fallback=("RHip", "LHip"),
)

# AlphaPose's Halpe-26 (Fang et al. 2022, "AlphaPose: whole-body regional multi-person pose
# estimation and tracking"): COCO-17's joints, then head top, neck, mid-hip and the feet as
# BODY_25 has them (big toes, small toes, heels), every one a site of the character
HALPE26 = _layout(
    "halpe26",
    (
        ("Nose", "kp_nose"),
        ("LEye", "kp_left_eye"),
        ("REye", "kp_right_eye"),
        ("LEar", "kp_left_ear"),
        ("REar", "kp_right_ear"),
        ("LShoulder", "kp_left_shoulder"),
        ("RShoulder", "kp_right_shoulder"),
        ("LElbow", "kp_left_elbow"),
        ("RElbow", "kp_right_elbow"),
        ("LWrist", "kp_left_wrist"),
        ("RWrist", "kp_right_wrist"),
        ("LHip", "kp_left_hip"),
        ("RHip", "kp_right_hip"),
        ("LKnee", "kp_left_knee"),
        ("RKnee", "kp_right_knee"),
        ("LAnkle", "kp_left_ankle"),
        ("RAnkle", "kp_right_ankle"),
        ("Head", "kp_head_top"),
        ("Neck", "kp_neck"),
        ("Hip", "kp_mid_hip"),
        ("LBigToe", "kp_left_big_toe"),
        ("RBigToe", "kp_right_big_toe"),
        ("LSmallToe", "kp_left_small_toe"),
        ("RSmallToe", "kp_right_small_toe"),
        ("LHeel", "kp_left_heel"),
        ("RHeel", "kp_right_heel"),
    ),
    root=("Hip",),
    root_fallback=("RHip", "LHip"),
)

# MediaPipe / BlazePose's 33 landmarks (Bazarevsky et al. 2020, "BlazePose: on-device real-time
# body pose tracking"; MediaPipe's PoseLandmark order, left/right of the person). The character
# has no site for the inner and outer eye corners, the mouth or the fingers: those landmarks have
# no site ("") and are dropped by every conversion; BlazePose's foot index (the tip of the foot)
# is the big toe's site, as in ``jmocap video``'s mapping to BODY_25 (jmocap.video.mapping).
BLAZEPOSE33 = _layout(
    "blazepose33",
    (
        ("nose", "kp_nose"),
        ("left_eye_inner", ""),
        ("left_eye", "kp_left_eye"),
        ("left_eye_outer", ""),
        ("right_eye_inner", ""),
        ("right_eye", "kp_right_eye"),
        ("right_eye_outer", ""),
        ("left_ear", "kp_left_ear"),
        ("right_ear", "kp_right_ear"),
        ("mouth_left", ""),
        ("mouth_right", ""),
        ("left_shoulder", "kp_left_shoulder"),
        ("right_shoulder", "kp_right_shoulder"),
        ("left_elbow", "kp_left_elbow"),
        ("right_elbow", "kp_right_elbow"),
        ("left_wrist", "kp_left_wrist"),
        ("right_wrist", "kp_right_wrist"),
        ("left_pinky", ""),
        ("right_pinky", ""),
        ("left_index", ""),
        ("right_index", ""),
        ("left_thumb", ""),
        ("right_thumb", ""),
        ("left_hip", "kp_left_hip"),
        ("right_hip", "kp_right_hip"),
        ("left_knee", "kp_left_knee"),
        ("right_knee", "kp_right_knee"),
        ("left_ankle", "kp_left_ankle"),
        ("right_ankle", "kp_right_ankle"),
        ("left_heel", "kp_left_heel"),
        ("right_heel", "kp_right_heel"),
        ("left_foot_index", "kp_left_big_toe"),
        ("right_foot_index", "kp_right_big_toe"),
    ),
    # BlazePose has no pelvis landmark: the root is the midpoint of the two hips (as COCO's)
    root=("left_hip", "right_hip"),
)

LAYOUTS: dict[str, Layout] = {layout.name: layout for layout in (BODY25, COCO17, H36M17, HALPE26, BLAZEPOSE33)}

# The four foot contact points (named once in jmocap.constants), re-exported here.
CONTACT_SITES = _CONTACT_SITES


def get_layout(layout: str | Layout) -> Layout:
    """Return a :class:`Layout` by name (``body25``, ``coco17``, ``h36m17``, ``halpe26``,
    ``blazepose33``) or pass one through."""
    if isinstance(layout, Layout):
        return layout
    try:
        return LAYOUTS[layout.lower()]
    except KeyError:
        raise ValueError(
            f"unknown keypoint layout {layout!r}; known layouts: {sorted(LAYOUTS)}"
        ) from None


def all_keypoint_sites() -> tuple[str, ...]:
    """Every site named by any layout, in first-seen order."""
    seen: dict[str, None] = {}
    for layout in LAYOUTS.values():
        seen.update(dict.fromkeys(s for s in layout.sites if s))
    return tuple(seen)


# ---------------------------------------------------------------------------------------
# converting keypoints between layouts
# ---------------------------------------------------------------------------------------

#: Sites that are (nearly) the midpoint of two other sites on the character, so a layout
#: without them can give them from its own joints: ``site: (site_a, site_b, exact)``.
#: ``kp_mid_hip`` is exactly the midpoint of the hip centres (both on the pelvis,
#: ``humanoid.xml``); ``kp_neck`` is the midpoint of the shoulder centres only with the collar
#: joints at zero (shrugging moves the shoulders up to ~4 cm from it), so it is derived for the
#: 2D input (where it is close to what a BODY_25 detector reports) but never for ground truth.
MIDPOINT_SITES: dict[str, tuple[str, str, bool]] = {
    "kp_mid_hip": ("kp_left_hip", "kp_right_hip", True),
    "kp_neck": ("kp_left_shoulder", "kp_right_shoulder", False),
}


@dataclass(frozen=True)
class Conversion:
    """How the joints of layout ``dst`` are read from keypoints in layout ``src``.

    Joints map by the character's site: a ``dst`` joint whose site a ``src`` joint has is copied
    (``copied``); one whose site is the midpoint of two ``src`` sites (:data:`MIDPOINT_SITES`) is
    their mean (``derived``); every other ``dst`` joint is absent (``absent``: confidence 0 in
    2D, NaN in 3D). ``src`` joints with no place in ``dst`` are ``dropped``.
    """

    src: Layout
    dst: Layout
    index: tuple[int, ...]  # per dst joint: the src joint copied, or -1
    derived: tuple[tuple[int, int, int, bool], ...]  # (dst joint, src a, src b, exact)

    @property
    def copied(self) -> tuple[str, ...]:
        return tuple(self.dst.joints[j] for j, i in enumerate(self.index) if i >= 0)

    @property
    def derived_joints(self) -> tuple[str, ...]:
        return tuple(self.dst.joints[j] for j, *_ in self.derived)

    @property
    def absent(self) -> tuple[str, ...]:
        made = {j for j, *_ in self.derived}
        return tuple(n for j, n in enumerate(self.dst.joints) if self.index[j] < 0 and j not in made)

    @property
    def dropped(self) -> tuple[str, ...]:
        used = set(self.index) | {a for _, a, _, _ in self.derived} | {b for _, _, b, _ in self.derived}
        return tuple(n for i, n in enumerate(self.src.joints) if i not in used)

    @property
    def identity(self) -> bool:
        return self.index == tuple(range(self.src.num_joints)) and self.src.num_joints == self.dst.num_joints

    def keypoints(self, keypoints):
        """2D keypoints (..., J_src, 3) (x, y, confidence) -> (..., J_dst, 3) numpy float32.

        Copied joints keep their values; a derived joint is the mean of its two source joints
        where both are detected (confidence > 0), with the smaller of their confidences, else
        missing; absent joints are (0, 0, 0)."""
        kp = np.asarray(keypoints, np.float32)
        if kp.ndim < 2 or kp.shape[-2:] != (self.src.num_joints, 3):
            raise ValueError(f"keypoints must be (..., {self.src.num_joints}, 3) for layout "
                             f"{self.src.name!r}, got {kp.shape}")
        out = np.zeros(kp.shape[:-2] + (self.dst.num_joints, 3), np.float32)
        for j, i in enumerate(self.index):
            if i >= 0:
                out[..., j, :] = kp[..., i, :]
        for j, a, b, _ in self.derived:
            both = (kp[..., a, 2] > 0) & (kp[..., b, 2] > 0)
            out[..., j, :2] = np.where(both[..., None], (kp[..., a, :2] + kp[..., b, :2]) / 2, 0.0)
            out[..., j, 2] = np.where(both, np.minimum(kp[..., a, 2], kp[..., b, 2]), 0.0)
        return out

    def points3d(self, points):
        """3D joints (..., J_src, 3) -> (..., J_dst, 3) numpy float32: copied joints, derived
        joints whose midpoint is exact (:data:`MIDPOINT_SITES`), NaN for every other joint
        (ground truth is never approximated)."""
        X = np.asarray(points, np.float32)
        if X.ndim < 2 or X.shape[-2:] != (self.src.num_joints, 3):
            raise ValueError(f"points must be (..., {self.src.num_joints}, 3) for layout "
                             f"{self.src.name!r}, got {X.shape}")
        out = np.full(X.shape[:-2] + (self.dst.num_joints, 3), np.nan, np.float32)
        for j, i in enumerate(self.index):
            if i >= 0:
                out[..., j, :] = X[..., i, :]
        for j, a, b, exact in self.derived:
            if exact:
                out[..., j, :] = (X[..., a, :] + X[..., b, :]) / 2
        return out

    def describe(self) -> str:
        """One line for logs and result warnings."""
        parts = [f"keypoints converted from {self.src.name} to {self.dst.name}"]
        if self.derived:
            parts.append(f"derived: {', '.join(self.derived_joints)} (midpoints)")
        if self.absent:
            parts.append(f"absent: {', '.join(self.absent)}")
        if self.dropped:
            parts.append(f"not used: {', '.join(self.dropped)}")
        return "; ".join(parts)


def conversion(src: str | Layout, dst: str | Layout) -> Conversion:
    """The :class:`Conversion` from ``src`` to ``dst`` (any two layouts: joints are matched by the
    character's sites)."""
    src, dst = get_layout(src), get_layout(dst)
    if src.name == dst.name:  # every joint to itself, those without a site included
        return Conversion(src, dst, tuple(range(src.num_joints)), ())
    where = {s: i for i, s in enumerate(src.sites) if s}  # joints without a site match nothing
    index = tuple(where.get(s, -1) if s else -1 for s in dst.sites)
    derived = []
    for j, s in enumerate(dst.sites):
        if index[j] < 0 and s in MIDPOINT_SITES:
            a, b, exact = MIDPOINT_SITES[s]
            if a in where and b in where:
                derived.append((j, where[a], where[b], exact))
    return Conversion(src, dst, index, tuple(derived))


def through_layout(keypoints, layout: str | Layout, other: str | Layout):
    """2D keypoints (..., J, 3) of ``layout`` as a detector of ``other`` would give them, back in
    ``layout``: the joints ``other`` lacks missing, its midpoints derived (:func:`conversion`
    there and back; what ``jmocap reconstruct`` makes of an ``other`` clip). numpy float32."""
    return conversion(other, layout).keypoints(conversion(layout, other).keypoints(keypoints))
