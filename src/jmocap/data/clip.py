"""The jmocap clip: one video's 2D keypoints, its camera and (optionally) ground truth.

A clip is stored as one compressed ``.npz`` (schema ``"jmocap-clip-1"``, see
``docs/formats.md``), written atomically (temp file in the same folder + ``os.replace``), so
an interrupted writer never leaves a half-written clip behind.

Keys of the .npz (all arrays; strings are 0-d unicode arrays, so no pickle is needed):

====================  ==========  ==========  ===============================================
key                   dtype       shape       meaning
====================  ==========  ==========  ===============================================
format                str         ()          ``"jmocap-clip-1"``
name                  str         ()          clip name
layout                str         ()          ``body25`` | ``coco17`` | ``h36m17`` | ``halpe26`` | ``blazepose33``
fps                   float64     ()          frames per second
keypoints             float32     (T, J, 3)   x, y pixels, confidence in [0, 1] (0 = missing,
                                              then x = y = 0)
intrinsics            float64     (4,)        fx, fy, cx, cy (pixels)
image_size            int64       (2,)        width, height (pixels)
extrinsics            float64     (4, 4)      optional; world->camera ``[R t; 0 1]``, OpenCV axes
                                              (with a camera track: its first frame)
camera_track          float64     (T, 4, 4)   optional; per-frame world->camera of a moving camera
gt_q                  float32     (T, nq)     optional; MuJoCo qpos (root pos, quat wxyz, hinges)
gt_qd                 float32     (T, nv)     optional; MuJoCo qvel, nv = nq - 1
gt_keypoints3d        float32     (T, J, 3)   optional; world-frame joints in the clip's layout
                                              (NaN x, y, z: a joint the ground truth lacks)
gt_contacts           float32     (T, 4)      optional; {0, 1}: L heel, L toe, R heel, R toe
gt_tau                float32     (T, nv)     optional; generalised forces
gt_grf                float32     (T, 4, 3)   optional; world-frame force per contact point
gt_residual           float32     (T, 6)      optional; root residual of a simulated clip: force
                                              (world, N), torque (root body frame, N m)
gt_foot_force         float32     (T, 2, 3)   optional; world-frame force per foot (left, right)
gt_cop                float32     (T, 2, 3)   optional; centre of pressure per foot, on the floor
gt_free_moment        float32     (T, 2)      optional; vertical torque per foot about its CoP (N m)
height_m              float64     ()          optional; subject height in metres
mass_kg               float64     ()          optional; subject mass in kilograms
scene                 str         ()          optional; the terrain beyond the floor z = 0, a
                                              ``jmocap-scene-1`` JSON document (boxes:
                                              :mod:`jmocap.scene`); absent: the floor alone
meta                  str         ()          JSON object (motion kind, seed, generator, ...)
====================  ==========  ==========  ===============================================

Both :class:`Clip` construction and :func:`load_clip` validate; problems raise
:class:`ClipFormatError` naming the file (or clip), the field and, for value problems, the
first bad frame.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.constants import GRAVITY, NUM_CONTACTS
from jmocap.data import limits
from jmocap.data.limits import FormatError
from jmocap.io import atomic_write_npz
from jmocap.layouts import LAYOUTS, get_layout

FORMAT = "jmocap-clip-1"

# optional ground-truth fields: name -> (trailing shape, where None = free size to be checked)
GT_FIELDS = ("gt_q", "gt_qd", "gt_keypoints3d", "gt_contacts", "gt_tau", "gt_grf", "gt_residual",
             "gt_foot_force", "gt_cop", "gt_free_moment")
# trailing shapes of the fixed-shape ground-truth fields
_GT_SHAPES = {"gt_contacts": (NUM_CONTACTS,), "gt_grf": (NUM_CONTACTS, 3), "gt_residual": (6,),
              "gt_foot_force": (2, 3), "gt_cop": (2, 3), "gt_free_moment": (2,)}
_ARRAY_FIELDS = ("keypoints", "intrinsics", "image_size", "extrinsics", "camera_track") + GT_FIELDS
#: the largest image width / height accepted (pixels; int32, like the arrays downstream)
MAX_IMAGE_SIDE = 2**31 - 1
#: the fastest a camera track may move between two frames: its centre (m/s) and its rotation
#: (degrees/s); a faster step is a discontinuity (a cut, a lost SLAM track), refused with its
#: frame. A walking hand-held camera moves at 1-2 m/s and pans at up to ~200 deg/s, a fast
#: whip pan ~600 deg/s, a drone 10-20 m/s.
CAMERA_MAX_SPEED_MPS = 50.0
CAMERA_MAX_TURN_DPS = 1500.0


class ClipFormatError(FormatError):
    """A clip file or Clip object that does not follow the ``jmocap-clip-1`` schema."""


@dataclass(frozen=True, eq=False)
class Clip:
    """One clip of 2D keypoints with its camera and optional ground truth (numpy arrays).

    Construction coerces numeric dtypes (float32 keypoints/ground truth, float64 camera) and
    validates everything (raises :class:`ClipFormatError`): strings, booleans, Python objects
    and complex numbers are refused rather than converted (``fps="30"``, a boolean
    ``gt_contacts``), and a clip has at most ``max_frames`` frames
    (:mod:`jmocap.data.limits`, :class:`~jmocap.data.limits.LimitError`). Use :meth:`replace` to derive a
    modified clip. ``meta`` is a JSON-serialisable dict.
    """

    name: str
    layout: str
    fps: float
    keypoints: np.ndarray  # (T, J, 3) float32
    intrinsics: np.ndarray  # (4,) float64
    image_size: np.ndarray  # (2,) int64
    extrinsics: np.ndarray | None = None  # (4, 4) float64 (with a camera track: its first frame)
    camera_track: np.ndarray | None = None  # (T, 4, 4) float64: a moving camera's world->camera
    gt_q: np.ndarray | None = None
    gt_qd: np.ndarray | None = None
    gt_keypoints3d: np.ndarray | None = None
    gt_contacts: np.ndarray | None = None
    gt_tau: np.ndarray | None = None
    gt_grf: np.ndarray | None = None
    gt_residual: np.ndarray | None = None
    gt_foot_force: np.ndarray | None = None
    gt_cop: np.ndarray | None = None
    gt_free_moment: np.ndarray | None = None
    height_m: float | None = None
    mass_kg: float | None = None
    # the terrain beyond the floor (jmocap.scene.Scene; a jmocap-scene-1 document, dict or JSON
    # text, is parsed): foot metrics measure heights against it
    scene: Any = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        checked = _validate(values, f"clip {self.name!r}")
        for k, v in checked.items():
            object.__setattr__(self, k, v)

    # --- conveniences -------------------------------------------------------------------
    @property
    def num_frames(self) -> int:
        return int(self.keypoints.shape[0])

    def __len__(self) -> int:
        return self.num_frames

    @property
    def num_joints(self) -> int:
        return int(self.keypoints.shape[1])

    @property
    def layout_spec(self):
        """The :class:`~jmocap.layouts.Layout` of the keypoints."""
        return get_layout(self.layout)

    @property
    def has_ground_truth(self) -> bool:
        return self.gt_q is not None

    @property
    def residual_percent_bw(self) -> np.ndarray | None:
        """Per frame (T,): the ground truth's root residual force in % of body weight (None
        without ``gt_residual`` or ``mass_kg``); frames where it is > 0 are partly moved by a
        force no person has, so metrics can exclude or report them."""
        if self.gt_residual is None or self.mass_kg is None:
            return None
        return 100.0 * np.linalg.norm(self.gt_residual[:, :3], axis=1) / (self.mass_kg * GRAVITY)

    @property
    def moving_camera(self) -> bool:
        """Whether the clip has a per-frame camera track (``camera_track``)."""
        return self.camera_track is not None

    def world_to_camera(self) -> np.ndarray | None:
        """(T, 4, 4) world->camera of every frame: the camera track, or the static extrinsics
        repeated; None when the clip has no extrinsics."""
        if self.camera_track is not None:
            return self.camera_track
        if self.extrinsics is None:
            return None
        return np.broadcast_to(self.extrinsics, (self.num_frames, 4, 4))

    @property
    def camera(self):
        """The clip's :class:`jmocap.camera.Camera` (identity extrinsics when none stored); for a
        moving camera, its first frame's (what a method that assumes a static camera uses)."""
        from jmocap.camera import Camera

        fx, fy, cx, cy = (float(v) for v in self.intrinsics)
        w, h = (float(v) for v in self.image_size)
        return Camera.from_intrinsics(fx, fy, cx, cy, w, h, extrinsics=self.extrinsics)

    def replace(self, **changes) -> Clip:
        return dataclasses.replace(self, **changes)

    def to_layout(self, layout: str) -> Clip:
        """This clip with its keypoints (and ``gt_keypoints3d``) in ``layout``
        (:func:`jmocap.layouts.conversion`: joints matched by the character's sites, midpoints
        derived, the rest missing: confidence 0 in 2D, NaN in 3D). ``meta["layout_conversion"]``
        records the source layout and what was derived, absent and not used. The clip itself
        when it is in ``layout`` already."""
        from jmocap.layouts import conversion

        conv = conversion(self.layout, layout)
        if conv.src.name == conv.dst.name:
            return self
        meta = dict(self.meta)
        meta["layout_conversion"] = {"from": conv.src.name, "to": conv.dst.name,
                                     "derived": list(conv.derived_joints), "absent": list(conv.absent),
                                     "not_used": list(conv.dropped)}
        gt = None if self.gt_keypoints3d is None else conv.points3d(self.gt_keypoints3d)
        return self.replace(layout=conv.dst.name, keypoints=conv.keypoints(self.keypoints), gt_keypoints3d=gt,
                            meta=meta)

    def slice(self, start: int, stop: int | None = None) -> Clip:
        """Frames ``[start, stop)`` of every per-frame field."""
        changes = {
            k: getattr(self, k)[start:stop]
            for k in ("keypoints", "camera_track") + GT_FIELDS
            if getattr(self, k) is not None
        }
        if self.camera_track is not None:  # the static extrinsics are the track's first frame
            changes["extrinsics"] = changes["camera_track"][0]
        return self.replace(**changes)


# --- validation -------------------------------------------------------------------------


def _first_bad_frame(bad: np.ndarray) -> int:
    """Index of the first frame (axis 0) where ``bad`` has a True entry."""
    per_frame = bad.reshape(bad.shape[0], -1).any(axis=1)
    return int(np.argmax(per_frame))


def _as_array(values, key, dtype, where):
    """``values[key]`` as an array of ``dtype``. Only numbers are converted: an array (or
    list) of strings, booleans, Python objects or complex numbers is a :class:`ClipFormatError`
    naming the field (numpy would turn ``"30"`` into 30.0 and ``True`` into 1.0 silently)."""
    v = values[key]
    try:
        a = np.asarray(v)
        if a.dtype.kind not in "iuf":
            raise TypeError(f"it holds {_KIND_NAMES.get(a.dtype.kind, str(a.dtype))}, not numbers")
        return np.asarray(a, dtype=dtype)
    except (TypeError, ValueError) as e:
        raise ClipFormatError(
            f"{where}: field {key!r} cannot be read as {np.dtype(dtype)}: {e}"
        ) from None


_KIND_NAMES = {
    "b": "booleans",
    "U": "strings",
    "S": "byte strings",
    "O": "Python objects",
    "c": "complex numbers",
    "V": "structured records",
    "M": "dates",
    "m": "time deltas",
}


def _scalar_number(v, key, where) -> float:
    """A scalar field (``fps``, ``height_m``, ``mass_kg``) as a float: an ``int``, ``float``,
    numpy integer / floating scalar or 0-d numeric array; a string, a boolean or anything else
    is a :class:`ClipFormatError` (``float("30")`` and ``float(True)`` would succeed)."""
    ok = isinstance(v, (int, float, np.integer, np.floating)) or (
        isinstance(v, np.ndarray) and v.ndim == 0 and v.dtype.kind in "iuf"
    )
    if not ok or isinstance(v, (bool, np.bool_)):
        raise ClipFormatError(
            f"{where}: field {key!r} must be a number, got {type(v).__name__} {v!r:.40}"
        )
    try:
        return float(v)
    except OverflowError:
        raise ClipFormatError(f"{where}: field {key!r} is too large: {v!r:.40}") from None


def _extrinsics_problem(E: np.ndarray) -> str | None:
    """What is wrong with a (4, 4) float matrix as extrinsics (None when it is a rigid transform
    ``[R t; 0 0 0 1]``, R a rotation: orthonormal within 1e-4, determinant +1)."""
    if E.shape != (4, 4):
        return f"must have shape (4, 4), got {E.shape}"
    if not np.isfinite(E).all():
        return "has non-finite values"
    R = E[:3, :3]
    if (
        not np.allclose(E[3], [0, 0, 0, 1], atol=1e-6)
        or not np.allclose(R @ R.T, np.eye(3), atol=1e-4)
        or np.linalg.det(R) < 0
    ):
        return "must be a rigid transform [R t; 0 0 0 1] with R a rotation"
    return None


def _rigid_frames(E: np.ndarray) -> np.ndarray:
    """(T,) bool: which of the (T, 4, 4) transforms are not rigid (:func:`_extrinsics_problem`'s
    rule, vectorised)."""
    R = E[:, :3, :3]
    RRt = np.einsum("tij,tkj->tik", R, R)
    return (np.abs(E[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(-1) > 1e-6) | (
        np.abs(RRt - np.eye(3)).reshape(len(E), -1).max(-1) > 1e-4) | (np.linalg.det(R) < 0)


def camera_track_problem(track: np.ndarray, fps: float) -> str | None:
    """What is wrong with a (T, 4, 4) float64 camera track at ``fps`` (None when nothing): a
    non-finite value, a transform that is not rigid (a scaled, sheared or reflected rotation)
    or a step between two frames faster than :data:`CAMERA_MAX_SPEED_MPS` /
    :data:`CAMERA_MAX_TURN_DPS` (a cut), each named with its first frame."""
    if track.ndim != 3 or track.shape[1:] != (4, 4):
        return f"must have shape (T, 4, 4), got {track.shape}"
    bad = ~np.isfinite(track)
    if bad.any():
        return f"has non-finite values, first at frame {_first_bad_frame(bad)}"
    bad = _rigid_frames(track)
    if bad.any():
        f = int(np.argmax(bad))
        return (f"is not a rigid transform [R t; 0 0 0 1] with R a rotation at frame {f} "
                f"(a camera track's rotations must be orthonormal with determinant +1)")
    if len(track) < 2:
        return None
    R = track[:, :3, :3]
    centre = -np.einsum("tji,tj->ti", R, track[:, :3, 3])  # -R^T t
    step = np.linalg.norm(np.diff(centre, axis=0), axis=-1) * fps
    rel = np.einsum("tij,tkj->tik", R[1:], R[:-1])  # R_{t+1} R_t^T
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    turn = np.degrees(np.arccos(cos)) * fps
    for name, v, lim, unit in (("moves", step, CAMERA_MAX_SPEED_MPS, "m/s"),
                               ("turns", turn, CAMERA_MAX_TURN_DPS, "deg/s")):
        if (v > lim).any():
            f = int(np.argmax(v > lim))
            return (f"{name} at {v[f]:.4g} {unit} between frames {f} and {f + 1} (at {fps:g} fps; at most "
                    f"{lim:g} {unit}): a discontinuity (a cut or a lost track); split the clip there")
    return None


def _check_finite(arr, key, where, per_frame=True):
    bad = ~np.isfinite(arr)
    if bad.any():
        if per_frame and arr.ndim >= 1 and arr.shape[0] > 0:
            raise ClipFormatError(
                f"{where}: field {key!r} has non-finite values, first at frame {_first_bad_frame(bad)}"
            )
        raise ClipFormatError(f"{where}: field {key!r} has non-finite values")


def _validate(values: dict[str, Any], where: str) -> dict[str, Any]:
    """Coerce and validate clip fields; return the coerced values. Raises ClipFormatError
    (LimitError over ``max_frames``). Numbers only: :func:`_scalar_number` for the scalars,
    :func:`_as_array` for the arrays."""
    out = dict(values)

    # scalars / strings
    name = values.get("name")
    if not isinstance(name, str):
        raise ClipFormatError(f"{where}: field 'name' must be a string, got {type(name).__name__}")
    layout = values.get("layout")
    if not isinstance(layout, str) or layout.lower() not in LAYOUTS:
        raise ClipFormatError(
            f"{where}: field 'layout' is {layout!r}, not one of {sorted(LAYOUTS)}"
        )
    out["layout"] = layout = layout.lower()
    fps = _scalar_number(values.get("fps"), "fps", where)
    if not (np.isfinite(fps) and fps > 0):
        raise ClipFormatError(f"{where}: field 'fps' must be finite and > 0, got {fps}")
    out["fps"] = fps
    for key in ("height_m", "mass_kg"):
        v = values.get(key)
        if v is not None:
            v = _scalar_number(v, key, where)
            if not (np.isfinite(v) and v > 0):
                raise ClipFormatError(f"{where}: field {key!r} must be finite and > 0, got {v}")
            out[key] = v
    meta = values.get("meta")
    if meta is None:
        meta = {}
    if not isinstance(meta, dict):
        raise ClipFormatError(f"{where}: field 'meta' must be a dict, got {type(meta).__name__}")
    try:
        json.dumps(meta)
    except (TypeError, ValueError, RecursionError) as e:
        raise ClipFormatError(f"{where}: field 'meta' is not JSON-serialisable: {e}") from None
    out["meta"] = meta
    scene = values.get("scene")
    if scene is not None:
        from jmocap.scene import Scene, SceneError, parse_scene, scene_document

        try:
            doc = scene_document(scene) if isinstance(scene, Scene) else scene
            out["scene"] = parse_scene(doc, f"{where}: field 'scene'")
        except SceneError as e:
            raise ClipFormatError(str(e)) from None

    J = LAYOUTS[layout].num_joints

    # keypoints
    kp = _as_array(values, "keypoints", np.float32, where)
    if kp.ndim != 3 or kp.shape[1:] != (J, 3):
        raise ClipFormatError(
            f"{where}: field 'keypoints' must have shape (T, {J}, 3) for layout {layout!r}, got {kp.shape}"
        )
    T = kp.shape[0]
    if T == 0:
        raise ClipFormatError(f"{where}: field 'keypoints' has T = 0 frames (an empty clip)")

    limits.check_frames(T, f"{where}: field 'keypoints'")
    _check_finite(kp, "keypoints", where)
    conf = kp[..., 2]
    bad = (conf < 0) | (conf > 1)
    if bad.any():
        f = _first_bad_frame(bad)
        raise ClipFormatError(
            f"{where}: field 'keypoints' has confidence outside [0, 1] "
            f"(e.g. {conf[f][bad[f]][0]}), first at frame {f}"
        )
    # missing joints store zeros (normalise rather than reject: the coordinates are meaningless)
    if (conf == 0).any():
        kp = kp.copy()
        kp[conf == 0, :2] = 0.0
    out["keypoints"] = kp

    # camera
    intr = _as_array(values, "intrinsics", np.float64, where)
    if intr.shape != (4,):
        raise ClipFormatError(
            f"{where}: field 'intrinsics' must have shape (4,) (fx, fy, cx, cy), got {intr.shape}"
        )
    _check_finite(intr, "intrinsics", where, per_frame=False)
    if not (intr[0] > 0 and intr[1] > 0):
        raise ClipFormatError(
            f"{where}: field 'intrinsics' needs fx, fy > 0, got {intr[:2].tolist()}"
        )
    out["intrinsics"] = intr
    size = _as_array(values, "image_size", np.float64, where)
    if size.shape != (2,):
        raise ClipFormatError(
            f"{where}: field 'image_size' must have shape (2,) (width, height), got {size.shape}"
        )
    _check_finite(size, "image_size", where, per_frame=False)
    if not (np.all(size > 0) and np.all(size == np.round(size)) and np.all(size <= MAX_IMAGE_SIDE)):
        raise ClipFormatError(
            f"{where}: field 'image_size' must be positive integers up to {MAX_IMAGE_SIDE}, "
            f"got {size.tolist()}"
        )
    out["image_size"] = size.astype(np.int64)
    if values.get("extrinsics") is not None:
        E = _as_array(values, "extrinsics", np.float64, where)
        problem = _extrinsics_problem(E)
        if problem is not None:
            raise ClipFormatError(f"{where}: field 'extrinsics' {problem}")
        out["extrinsics"] = E
    if values.get("camera_track") is not None:
        track = _as_array(values, "camera_track", np.float64, where)
        if track.ndim != 3 or track.shape[0] != T:
            raise ClipFormatError(
                f"{where}: field 'camera_track' must have shape ({T}, 4, 4) (one world->camera per frame "
                f"of 'keypoints'), got {track.shape}")
        problem = camera_track_problem(track, fps)
        if problem is not None:
            raise ClipFormatError(f"{where}: field 'camera_track' {problem}")
        E = out.get("extrinsics")
        if E is None:
            out["extrinsics"] = track[0].copy()
        elif not np.allclose(E, track[0], atol=1e-6):
            raise ClipFormatError(
                f"{where}: field 'extrinsics' differs from the first frame of 'camera_track' (a clip "
                f"with a moving camera stores its first frame's as 'extrinsics', or none: replace both)")
        out["camera_track"] = track

    # ground truth
    out.update(validate_ground_truth(values, T, J, where))
    return out


def validate_ground_truth(values: dict[str, Any], T: int, J: int | None, where: str,
                          error: type[FormatError] = ClipFormatError,
                          frames_of: str = "keypoints") -> dict[str, np.ndarray]:
    """The optional ground-truth fields of ``values`` (:data:`GT_FIELDS`) coerced to float32 and
    validated; returns ``{field: array}`` for the fields present. Shared by every clip type that
    carries ground truth (the video :class:`Clip`, :class:`jmocap.data.imu.IMUClip`): ``T`` is
    the clip's frame count (read from its field ``frames_of``), ``J`` the joints of its layout
    (None: the clip has no layout, and ``gt_keypoints3d`` is refused). Problems raise ``error``
    naming ``where``, the field and, for values, the first bad frame."""
    out: dict[str, np.ndarray] = {}
    nq = nv = None
    for key in GT_FIELDS:
        if values.get(key) is None:
            continue
        a = _as_array(values, key, np.float32, where)
        if a.ndim == 0 or a.shape[0] != T:
            raise error(
                f"{where}: field {key!r} has {a.shape[0] if a.ndim else 0} frames but '{frames_of}' has {T} "
                f"(shape {a.shape})"
            )
        if key == "gt_q":
            if a.ndim != 2 or a.shape[1] < 7:
                raise error(
                    f"{where}: field 'gt_q' must have shape (T, nq >= 7), got {a.shape}"
                )
            nq = a.shape[1]
        elif key in ("gt_qd", "gt_tau"):
            if a.ndim != 2 or a.shape[1] < 6:
                raise error(
                    f"{where}: field {key!r} must have shape (T, nv >= 6), got {a.shape}"
                )
            if nv is not None and a.shape[1] != nv:
                raise error(
                    f"{where}: field {key!r} has nv = {a.shape[1]} but another field has nv = {nv}"
                )
            nv = a.shape[1]
        elif key == "gt_keypoints3d":
            if J is None:
                raise error(f"{where}: field 'gt_keypoints3d' needs a keypoint layout (field 'layout')")
            if a.shape[1:] != (J, 3):
                raise error(
                    f"{where}: field 'gt_keypoints3d' must have shape (T, {J}, 3), got {a.shape}"
                )
            # a joint the ground truth does not have (in a frame, or at all) is NaN in x, y, z:
            # the metrics leave it out (per-joint masks); anything else non-finite is an error
            _check_finite(np.where(np.isnan(a).all(-1, keepdims=True), 0.0, a), key, where)
        elif key in _GT_SHAPES:
            if a.shape[1:] != _GT_SHAPES[key]:
                shape = ", ".join(["T"] + [str(n) for n in _GT_SHAPES[key]])
                raise error(
                    f"{where}: field {key!r} must have shape ({shape}), got {a.shape}"
                )
        if key != "gt_keypoints3d":
            _check_finite(a, key, where)
        if key == "gt_contacts":
            bad = (a != 0) & (a != 1)
            if bad.any():
                raise error(
                    f"{where}: field 'gt_contacts' must be 0 or 1, first bad value at frame {_first_bad_frame(bad)}"
                )
        out[key] = a
    if nq is not None and nv is not None and nv != nq - 1:
        raise error(
            f"{where}: 'gt_q' has nq = {nq} but velocities/forces have nv = {nv}; a free-root "
            f"model has nv = nq - 1"
        )
    return out


# --- I/O ----------------------------------------------------------------------------------


def clip_to_arrays(clip: Clip) -> dict[str, np.ndarray]:
    """The .npz arrays of a clip (the ``jmocap-clip-1`` keys; absent optional fields omitted)."""
    arrays: dict[str, np.ndarray] = {
        "format": np.array(FORMAT),
        "name": np.array(clip.name),
        "layout": np.array(clip.layout),
        "fps": np.array(clip.fps, dtype=np.float64),
        "meta": np.array(json.dumps(clip.meta, sort_keys=True)),
    }
    if clip.scene is not None:
        from jmocap.scene import scene_document

        arrays["scene"] = np.array(json.dumps(scene_document(clip.scene)))
    for key in _ARRAY_FIELDS:
        v = getattr(clip, key)
        if v is not None:
            arrays[key] = np.asarray(v)
    for key in ("height_m", "mass_kg"):
        v = getattr(clip, key)
        if v is not None:
            arrays[key] = np.array(v, dtype=np.float64)
    return arrays


def save_clip(path: str | os.PathLike, clip: Clip) -> Path:
    """Save ``clip`` to ``path`` (a ``.npz`` file), atomically. Returns the path."""
    if not isinstance(clip, Clip):
        raise TypeError(f"save_clip expects a Clip, got {type(clip).__name__}")
    return atomic_write_npz(path, clip_to_arrays(clip))


def _str_field(data, key, where, required=True):
    if key not in data:
        if required:
            raise ClipFormatError(f"{where}: missing field {key!r}")
        return None
    v = data[key]
    if v.shape != () or v.dtype.kind not in "US":
        raise ClipFormatError(
            f"{where}: field {key!r} must be a string scalar, got {v.dtype} {v.shape}"
        )
    return str(v)


def clip_from_arrays(data, where: str) -> Clip:
    """Build a Clip from a mapping of .npz arrays; errors name ``where`` (usually the file).

    Checked here, besides everything :class:`Clip` checks: ``format``, ``name``, ``layout``,
    ``meta`` are string scalars (``meta`` a JSON object within ``max_json_depth``); ``fps``,
    ``height_m``, ``mass_kg`` are numeric scalars (a string ``"30"`` or a boolean is refused,
    not converted); the array fields hold numbers (not strings, booleans, objects or complex
    numbers)."""
    fmt = _str_field(data, "format", where)
    if fmt != FORMAT:
        raise ClipFormatError(f"{where}: field 'format' is {fmt!r}, expected {FORMAT!r}")
    values: dict[str, Any] = {
        "name": _str_field(data, "name", where),
        "layout": _str_field(data, "layout", where),
    }
    for key in ("fps", "keypoints", "intrinsics", "image_size"):
        if key not in data:
            raise ClipFormatError(f"{where}: missing field {key!r}")
    for key in ("fps", "height_m", "mass_kg"):
        if key in data:
            v = np.asarray(data[key])
            if v.shape != ():
                raise ClipFormatError(f"{where}: field {key!r} must be a scalar, got shape {v.shape}")
            if v.dtype.kind not in "iuf":
                raise ClipFormatError(
                    f"{where}: field {key!r} must be a number, got {v.dtype} {str(v)[:40]!r}"
                )
            values[key] = v.item()
    for key in _ARRAY_FIELDS:
        if key in data:
            values[key] = data[key]
    meta_s = _str_field(data, "meta", where, required=False)
    if meta_s is not None:
        try:
            meta = limits.parse_json(meta_s, f"{where}: field 'meta'")
        except limits.LimitError:
            raise
        except FormatError as e:
            raise ClipFormatError(str(e)) from None
        if not isinstance(meta, dict):
            raise ClipFormatError(
                f"{where}: field 'meta' must be a JSON object, got {type(meta).__name__}"
            )
        values["meta"] = meta
    scene_s = _str_field(data, "scene", where, required=False)
    if scene_s is not None:
        try:
            values["scene"] = limits.parse_json(scene_s, f"{where}: field 'scene'")
        except limits.LimitError:
            raise
        except FormatError as e:
            raise ClipFormatError(str(e)) from None
    try:
        return Clip(**values)
    except FormatError as e:  # ClipFormatError, or LimitError (too many frames)
        # re-word "clip 'name'" into the file name
        msg = str(e)
        prefix = f"clip {values['name']!r}: "
        if msg.startswith(prefix):
            msg = msg[len(prefix) :]
        raise type(e)(f"{where}: {msg}") from None


def load_clip(path: str | os.PathLike) -> Clip:
    """Load and validate a ``jmocap-clip-1`` .npz. Raises :class:`ClipFormatError` on any
    problem (:class:`~jmocap.data.limits.LimitError` when the file or one of its arrays is over
    the limits: read through :func:`jmocap.data.limits.load_npz`, never unpickled)."""

    path = Path(path)
    where = str(path)
    try:
        data = limits.load_npz(path, where)
    except (FileNotFoundError, limits.LimitError):
        raise
    except FormatError as e:  # a member that is not a .npy, pickled objects, a bad header
        raise ClipFormatError(str(e)) from None
    except Exception as e:  # BadZipFile, zlib.error, truncated members, non-npz bytes ...
        raise ClipFormatError(f"{where}: not a readable .npz file ({e})") from None
    return clip_from_arrays(data, where)


def is_clip_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an .npz carrying the jmocap clip ``format`` key."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            return "format" in npz.files and str(npz["format"]) == FORMAT
    except Exception:
        return False


__all__ = [
    "CAMERA_MAX_SPEED_MPS",
    "CAMERA_MAX_TURN_DPS",
    "FORMAT",
    "GT_FIELDS",
    "MAX_IMAGE_SIDE",
    "Clip",
    "ClipFormatError",
    "FormatError",
    "atomic_write_npz",
    "camera_track_problem",
    "clip_from_arrays",
    "clip_to_arrays",
    "is_clip_file",
    "load_clip",
    "save_clip",
    "validate_ground_truth",
]
