"""Keypoint layouts and their mapping onto the character's sites: the one place for it.

Every layout is an ordered tuple of joint names exactly as the format's own documentation
orders them, and a parallel tuple of the model sites that produce each joint:

* ``body25``: OpenPose BODY_25 (``openpose/doc/02_output.md``, ``POSE_BODY_25_BODY_PARTS``).
* ``coco17``: COCO keypoints (``person_keypoints`` category of the COCO 2017 annotations).
* ``h36m17``: the 17 Human3.6M joints used by VideoPose3D / most lifting work
  (pelvis, right leg, left leg, spine, thorax, neck/nose, head, left arm, right arm).

Site names are those of ``jmocap/assets/mjcf/humanoid.xml``; ``tests/test_model.py`` checks that
every site named here exists in the model.
"""

from __future__ import annotations

from dataclasses import dataclass

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

    @property
    def num_joints(self) -> int:
        return len(self.joints)

    def index(self, joint: str) -> int:
        return self.joints.index(joint)

    @property
    def root_indices(self) -> tuple[int, ...]:
        return tuple(self.joints.index(j) for j in self.root)


def _pairs(joints: tuple[str, ...]) -> tuple[tuple[int, int], ...]:
    pairs = []
    for i, name in enumerate(joints):
        for left, right in (("L", "R"), ("left_", "right_")):
            if name.startswith(left):
                mate = right + name[len(left):]
                if mate in joints:
                    pairs.append((i, joints.index(mate)))
    return tuple(pairs)


def _layout(name: str, spec: tuple[tuple[str, str], ...], root: tuple[str, ...]) -> Layout:
    joints = tuple(j for j, _ in spec)
    return Layout(name, joints, tuple(s for _, s in spec), root, _pairs(joints))


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
)

LAYOUTS: dict[str, Layout] = {layout.name: layout for layout in (BODY25, COCO17, H36M17)}

# The four foot contact points (named once in jmocap.constants), re-exported here.
CONTACT_SITES = _CONTACT_SITES


def get_layout(layout: str | Layout) -> Layout:
    """Return a :class:`Layout` by name (``body25``, ``coco17``, ``h36m17``) or pass one through."""
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
        seen.update(dict.fromkeys(layout.sites))
    return tuple(seen)
