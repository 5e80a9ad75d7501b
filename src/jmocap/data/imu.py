"""IMU clips: six body-worn inertial sensors (PIP, Yi et al. 2022; TransPose, Yi et al. 2021),
their calibration and optional ground truth.

A clip is stored as one compressed ``.npz`` (schema ``"jmocap-imu-clip-1"``, see
``docs/formats.md``), written atomically; strings are 0-d (or 1-d) unicode arrays, so no pickle
is needed to read it.

**Sensors** (:data:`SENSORS`, the order of PIP / TransPose: their ``imu_mask`` picks DIP-IMU's
sensors 7, 8, 11, 12, 0, 2 in this order): left forearm, right forearm, left lower leg, right
lower leg, head, pelvis; on jmocap's character the bodies :data:`SENSOR_BODIES` (``left_elbow``,
``right_elbow``, ``left_knee``, ``right_knee``, ``head``, ``pelvis``: MuJoCo bodies whose frame
moves with that bone, as SMPL's joints 18, 19, 4, 5, 15, 0 that TransPose's ``ji_mask`` uses).

**Frames.** ``I`` is the sensors' own world (the "inertial" frame their orientation filter
reports in: gravity-aligned, heading arbitrary); ``W`` is jmocap's world (z up, metres, floor
z = 0); ``S`` a sensor's frame; ``B`` the frame of the MuJoCo body the sensor is on (jmocap's
character at its rest pose, a T-pose facing +x with the left arm along +y, has every body frame
equal to ``W``). ``R_XY`` maps coordinates in ``Y`` to coordinates in ``X``.

========================  =======  ===========  =================================================
key                       dtype    shape        meaning
========================  =======  ===========  =================================================
format                    str      ()           ``"jmocap-imu-clip-1"``
name                      str      ()           clip name
fps                       float64  ()           frames per second (> 0)
sensors                   str      (6,)         sensor names, the order of axis 1 below
ori                       float32  (T, 6, 3, 3) sensor orientation ``R_IS`` (columns: the sensor's
                                                axes in ``I``); (T, 6, 4) wxyz quaternions are
                                                accepted on input
acc                       float32  (T, 6, 3)    free acceleration (gravity removed) in ``I``, m/s^2
world_from_inertial       float64  (3, 3)       calibration ``R_WI``
bone_from_sensor          float64  (6, 3, 3)    calibration ``R_BS``: the sensor's mounting on its bone
acc_bias                  float64  (6, 3)       calibration: accelerometer offset in ``W`` (subtracted)
sensor_offset             float64  (6, 3)       optional; sensor origin in its body's frame (m)
filled                    bool     (T, 6)       optional; True where a dropout was filled (gap rule)
layout                    str      ()           optional; keypoint layout of ``gt_keypoints3d``
gt_q ... gt_free_moment                         optional; the video clip's ground-truth fields, same
                                                meaning, shapes and checks (``jmocap.data.clip``)
gt_smpl_pose              float32  (T, 24, 3)   optional; SMPL pose (axis-angle) as a dataset gives
                                                it, in its own (SMPL, y-up) world
height_m, mass_kg         float64  ()           optional; the subject
meta                      str      ()           JSON object
========================  =======  ===========  =================================================

What a method reads is :meth:`IMUClip.calibrated`: per frame the six bone orientations
``R_WB = R_WI R_IS R_BS^T`` (T, 6, 3, 3) and accelerations ``a_W = R_WI a_I - acc_bias``
(T, 6, 3), both in jmocap's world, and :attr:`IMUClip.fps`. :func:`calibrate_tpose` computes
the calibration from a still T-pose (TransPose's procedure). Every problem raises
:class:`IMUClipFormatError` naming the file (or clip), the field, the sensor and the first bad
frame.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data import limits
from jmocap.data.clip import (
    GT_FIELDS,
    ClipFormatError,
    FormatError,
    _as_array,
    _scalar_number,
    validate_ground_truth,
)
from jmocap.data.rotations import matrix_to_quat, quat_to_matrix
from jmocap.io import atomic_write, atomic_write_npz
from jmocap.layouts import LAYOUTS

FORMAT = "jmocap-imu-clip-1"
JSON_FORMAT = "jmocap-imu-json-1"

#: the six sensors, in PIP / TransPose order
SENSORS = ("left_forearm", "right_forearm", "left_lower_leg", "right_lower_leg", "head", "pelvis")
#: the MuJoCo body of jmocap's character each sensor is on
SENSOR_BODIES = ("left_elbow", "right_elbow", "left_knee", "right_knee", "head", "pelvis")
NUM_SENSORS = len(SENSORS)
#: a rotation matrix is accepted when ``max |R R^T - I| <= ORTHO_TOL`` and ``det R > 0``
ORTHO_TOL = 1e-3
#: a quaternion is accepted when ``| |q| - 1 | <= QUAT_NORM_TOL`` (then normalised)
QUAT_NORM_TOL = 1e-3
#: longest run of missing frames of one sensor that the gap rule fills (TransPose / PIP fill
#: 4 frames from each side of a gap and drop sequences with longer ones: 8 frames)
DEFAULT_MAX_GAP = 8
#: SMPL's (and DIP-IMU's / TotalCapture-in-DIP-format's) world axes in jmocap's: SMPL's x (the
#: subject's left at rest) -> jmocap y, SMPL y (up) -> z, SMPL z (forward) -> x
SMPL_TO_JMOCAP = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

IMU_GT_FIELDS = GT_FIELDS + ("gt_smpl_pose",)
_CAL_FIELDS = ("world_from_inertial", "bone_from_sensor", "acc_bias", "sensor_offset")


class IMUClipFormatError(ClipFormatError):
    """An IMU clip file, IMU dataset file or :class:`IMUClip` that breaks the schema."""


# --- rotations (numpy) ------------------------------------------------------------------------


def slerp(R0: np.ndarray, R1: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Rotations on the shortest arc from ``R0`` (3, 3) to ``R1`` (3, 3) at fractions ``h`` (n,)."""
    q0, q1 = matrix_to_quat(R0), matrix_to_quat(R1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    h = np.asarray(h, np.float64)[:, None]
    th = np.arccos(min(d, 1.0))
    if th < 1e-8:
        q = (1 - h) * q0 + h * q1
    else:
        q = (np.sin((1 - h) * th) * q0 + np.sin(h * th) * q1) / np.sin(th)
    return quat_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))


def mean_rotation(R: np.ndarray) -> np.ndarray:
    """The chordal mean of rotations (N, ..., 3, 3) over axis 0: the rotation nearest (in the
    Frobenius norm) to their arithmetic mean (SVD projection)."""
    M = np.asarray(R, np.float64).mean(axis=0)
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(M.shape[:-1])
    D[..., -1] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def rotation_z(yaw: float) -> np.ndarray:
    """The rotation by ``yaw`` radians about jmocap's vertical (z) axis."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _not_rotation(R: np.ndarray) -> np.ndarray:
    """Boolean mask (...) of the matrices (..., 3, 3) that are not rotations within ORTHO_TOL
    (NaN entries count as bad)."""
    with np.errstate(invalid="ignore"):
        err = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(axis=(-2, -1))
        det = np.linalg.det(np.where(np.isfinite(R), R, 0.0))
    return ~(err <= ORTHO_TOL) | ~(det > 0)


def _first(mask: np.ndarray) -> tuple[int, int]:
    """(frame, sensor) of the first True of a (T, S) mask, frame-major."""
    t = int(np.argmax(mask.any(axis=1)))
    return t, int(np.argmax(mask[t]))


# --- the clip ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Calibration:
    """What maps raw sensor readings to bones in jmocap's world: ``world_from_inertial`` ``R_WI``
    (3, 3), ``bone_from_sensor`` ``R_BS`` (6, 3, 3) and ``acc_bias`` (6, 3) in ``W`` (m/s^2)."""

    world_from_inertial: np.ndarray
    bone_from_sensor: np.ndarray
    acc_bias: np.ndarray

    @staticmethod
    def identity() -> Calibration:
        return Calibration(np.eye(3), np.tile(np.eye(3), (NUM_SENSORS, 1, 1)), np.zeros((NUM_SENSORS, 3)))


@dataclass(frozen=True, eq=False)
class IMUClip:
    """Six IMUs' orientations and free accelerations with their calibration and optional ground
    truth (numpy arrays; the schema in the module docstring and ``docs/formats.md``).

    Construction coerces (float32 readings and ground truth, float64 calibration; (T, 6, 4)
    quaternions to matrices) and validates everything, raising :class:`IMUClipFormatError`
    (a :class:`~jmocap.data.clip.ClipFormatError`). Calibration fields left ``None`` are the
    identity / zero. Use :meth:`replace` to derive a modified clip.
    """

    name: str
    fps: float
    ori: np.ndarray  # (T, 6, 3, 3) float32, R_IS
    acc: np.ndarray  # (T, 6, 3) float32, in I
    world_from_inertial: np.ndarray | None = None  # (3, 3)
    bone_from_sensor: np.ndarray | None = None  # (6, 3, 3)
    acc_bias: np.ndarray | None = None  # (6, 3)
    sensor_offset: np.ndarray | None = None  # (6, 3)
    filled: np.ndarray | None = None  # (T, 6) bool
    layout: str | None = None
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
    gt_smpl_pose: np.ndarray | None = None
    height_m: float | None = None
    mass_kg: float | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        checked = _validate(values, f"IMU clip {self.name!r}")
        for k, v in checked.items():
            object.__setattr__(self, k, v)

    @property
    def num_frames(self) -> int:
        return int(self.ori.shape[0])

    def __len__(self) -> int:
        return self.num_frames

    @property
    def sensors(self) -> tuple[str, ...]:
        return SENSORS

    @property
    def has_ground_truth(self) -> bool:
        return self.gt_q is not None or self.gt_smpl_pose is not None

    @property
    def calibration(self) -> Calibration:
        return Calibration(self.world_from_inertial, self.bone_from_sensor, self.acc_bias)

    def with_calibration(self, cal: Calibration) -> IMUClip:
        return self.replace(world_from_inertial=cal.world_from_inertial,
                            bone_from_sensor=cal.bone_from_sensor, acc_bias=cal.acc_bias)

    def sensor_orientations(self) -> np.ndarray:
        """Sensor orientations in jmocap's world, ``R_WS = R_WI R_IS`` (T, 6, 3, 3) float32."""
        return (self.world_from_inertial @ self.ori.astype(np.float64)).astype(np.float32)

    def calibrated(self) -> tuple[np.ndarray, np.ndarray]:
        """What a method reads: bone orientations ``R_WB = R_WI R_IS R_BS^T`` (T, 6, 3, 3) and the
        sensors' free accelerations ``R_WI a_I - acc_bias`` (T, 6, 3), both in jmocap's world,
        float32, in :data:`SENSORS` order."""
        R = self.world_from_inertial @ self.ori.astype(np.float64) @ np.swapaxes(self.bone_from_sensor, -1, -2)
        a = self.acc.astype(np.float64) @ self.world_from_inertial.T - self.acc_bias
        return R.astype(np.float32), a.astype(np.float32)

    def replace(self, **changes) -> IMUClip:
        return dataclasses.replace(self, **changes)

    def slice(self, start: int, stop: int | None = None) -> IMUClip:
        """Frames ``[start, stop)`` of every per-frame field."""
        keys = ("ori", "acc", "filled") + IMU_GT_FIELDS
        return self.replace(**{k: getattr(self, k)[start:stop] for k in keys if getattr(self, k) is not None})


def _validate(values: dict[str, Any], where: str) -> dict[str, Any]:
    try:
        return _validate_fields(values, where)
    except IMUClipFormatError:
        raise
    except limits.LimitError:
        raise
    except ClipFormatError as e:  # from the shared helpers of jmocap.data.clip
        raise IMUClipFormatError(str(e)) from None


def _validate_fields(values: dict[str, Any], where: str) -> dict[str, Any]:
    out = dict(values)
    err = IMUClipFormatError
    name = values.get("name")
    if not isinstance(name, str):
        raise err(f"{where}: field 'name' must be a string, got {type(name).__name__}")
    fps = _scalar_number(values.get("fps"), "fps", where)
    if not (np.isfinite(fps) and fps > 0):
        raise err(f"{where}: field 'fps' must be finite and > 0, got {fps}")
    out["fps"] = fps
    for key in ("height_m", "mass_kg"):
        if values.get(key) is not None:
            v = _scalar_number(values[key], key, where)
            if not (np.isfinite(v) and v > 0):
                raise err(f"{where}: field {key!r} must be finite and > 0, got {v}")
            out[key] = v
    meta = values.get("meta") or {}
    if not isinstance(meta, dict):
        raise err(f"{where}: field 'meta' must be a dict, got {type(meta).__name__}")
    try:
        json.dumps(meta)
    except (TypeError, ValueError, RecursionError) as e:
        raise err(f"{where}: field 'meta' is not JSON-serialisable: {e}") from None
    out["meta"] = meta
    layout = values.get("layout")
    J = None
    if layout is not None:
        if not isinstance(layout, str) or layout.lower() not in LAYOUTS:
            raise err(f"{where}: field 'layout' is {layout!r}, not one of {sorted(LAYOUTS)}")
        out["layout"] = layout = layout.lower()
        J = LAYOUTS[layout].num_joints

    # readings
    ori = _as_array(values, "ori", np.float64, where)
    if ori.ndim == 3 and ori.shape[1:] == (NUM_SENSORS, 4):
        ori = quaternions_to_matrices(ori, where, "ori")
    if ori.ndim != 4 or ori.shape[1:] != (NUM_SENSORS, 3, 3):
        raise err(f"{where}: field 'ori' must have shape (T, 6, 3, 3) (or (T, 6, 4) quaternions wxyz), "
                  f"got {ori.shape}")
    T = ori.shape[0]
    if T == 0:
        raise err(f"{where}: field 'ori' has T = 0 frames (an empty clip)")
    limits.check_frames(T, f"{where}: field 'ori'")
    _check_finite_sensors(ori, "ori", where)
    check_rotations(ori, "ori", where)
    out["ori"] = ori.astype(np.float32)
    acc = _as_array(values, "acc", np.float64, where)
    if acc.shape != (T, NUM_SENSORS, 3):
        raise err(f"{where}: field 'acc' must have shape (T, 6, 3) with T = {T} (as 'ori'), got {acc.shape}")
    _check_finite_sensors(acc, "acc", where)
    out["acc"] = acc.astype(np.float32)
    if values.get("filled") is not None:
        f = np.asarray(values["filled"])
        if f.dtype.kind not in "bui" or f.shape != (T, NUM_SENSORS) or not np.isin(f, (0, 1)).all():
            raise err(f"{where}: field 'filled' must be (T, 6) booleans with T = {T}, got {f.dtype} {f.shape}")
        out["filled"] = f.astype(bool)

    # calibration
    R_WI = np.eye(3) if values.get("world_from_inertial") is None else _as_array(
        values, "world_from_inertial", np.float64, where)
    if R_WI.shape != (3, 3) or _not_rotation(R_WI):
        raise err(f"{where}: field 'world_from_inertial' must be a (3, 3) rotation "
                  f"(orthonormal within {ORTHO_TOL}, det +1), got shape {R_WI.shape}")
    out["world_from_inertial"] = R_WI
    R_BS = np.tile(np.eye(3), (NUM_SENSORS, 1, 1)) if values.get("bone_from_sensor") is None else _as_array(
        values, "bone_from_sensor", np.float64, where)
    if R_BS.shape != (NUM_SENSORS, 3, 3):
        raise err(f"{where}: field 'bone_from_sensor' must have shape (6, 3, 3), got {R_BS.shape}")
    bad = _not_rotation(R_BS)
    if bad.any():
        s = int(np.argmax(bad))
        raise err(f"{where}: field 'bone_from_sensor': sensor {SENSORS[s]!r} is not a rotation "
                  f"(orthonormal within {ORTHO_TOL}, det +1)")
    out["bone_from_sensor"] = R_BS
    for key, required in (("acc_bias", True), ("sensor_offset", False)):
        if values.get(key) is None:
            out[key] = np.zeros((NUM_SENSORS, 3)) if required else None
            continue
        a = _as_array(values, key, np.float64, where)
        if a.shape != (NUM_SENSORS, 3):
            raise err(f"{where}: field {key!r} must have shape (6, 3), got {a.shape}")
        if not np.isfinite(a).all():
            raise err(f"{where}: field {key!r}: sensor {SENSORS[int(np.argmax(~np.isfinite(a).all(1)))]!r} "
                      f"has non-finite values")
        out[key] = a

    # ground truth: the video clip's fields and checks, plus the SMPL pose of IMU datasets
    out.update(validate_ground_truth(values, T, J, where, error=err, frames_of="ori"))
    if values.get("gt_smpl_pose") is not None:
        p = _as_array(values, "gt_smpl_pose", np.float32, where)
        if p.ndim == 2 and p.shape[1] == 72:
            p = p.reshape(-1, 24, 3)
        if p.shape != (T, 24, 3):
            raise err(f"{where}: field 'gt_smpl_pose' must have shape (T, 24, 3) (or (T, 72)) with T = {T}, "
                      f"got {p.shape}")
        bad = ~np.isfinite(p)
        if bad.any():
            raise err(f"{where}: field 'gt_smpl_pose' has non-finite values, first at frame "
                      f"{int(np.argmax(bad.reshape(T, -1).any(1)))}")
        out["gt_smpl_pose"] = p
    return out


def _check_finite_sensors(a: np.ndarray, key: str, where: str) -> None:
    bad = (~np.isfinite(a)).reshape(a.shape[0], NUM_SENSORS, -1).any(-1)
    if bad.any():
        t, s = _first(bad)
        raise IMUClipFormatError(f"{where}: field {key!r}: sensor {SENSORS[s]!r} has non-finite values, "
                                 f"first at frame {t} (dropouts: fill them, see gaps=)")


def check_rotations(ori: np.ndarray, key: str, where: str, missing: np.ndarray | None = None) -> None:
    """Raise :class:`IMUClipFormatError` naming the sensor and first frame where ``ori``
    (T, 6, 3, 3) is not a rotation within :data:`ORTHO_TOL` (frames in ``missing`` skipped)."""
    bad = _not_rotation(ori)
    if missing is not None:
        bad &= ~missing
    if bad.any():
        t, s = _first(bad)
        R = ori[t, s]
        e = float(np.abs(R @ R.T - np.eye(3)).max())
        raise IMUClipFormatError(
            f"{where}: field {key!r}: sensor {SENSORS[s]!r} is not a rotation matrix at frame {t} "
            f"(max |R R^T - I| = {e:.3g}, det = {float(np.linalg.det(R)):.3g}; tolerance {ORTHO_TOL}, det > 0)"
        )


def quaternions_to_matrices(q: np.ndarray, where: str, key: str) -> np.ndarray:
    """(T, 6, 4) wxyz quaternions -> (T, 6, 3, 3) matrices, after checking their norms
    (:data:`QUAT_NORM_TOL`); NaN quaternions stay NaN (dropouts)."""
    q = np.asarray(q, np.float64)
    n = np.linalg.norm(q, axis=-1)
    bad = np.isfinite(n) & (np.abs(n - 1.0) > QUAT_NORM_TOL)
    if bad.any():
        t, s = _first(bad)
        raise IMUClipFormatError(
            f"{where}: field {key!r}: sensor {SENSORS[s]!r} has a quaternion of norm {n[t, s]:.4g} at frame {t} "
            f"(a unit quaternion wxyz is expected, tolerance {QUAT_NORM_TOL})"
        )
    with np.errstate(invalid="ignore"):
        return quat_to_matrix(q / n[..., None])


# --- gaps (dropouts) --------------------------------------------------------------------------


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) runs of True in a 1-d mask."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.nonzero(d == 1)[0].tolist(), np.nonzero(d == -1)[0].tolist(), strict=True))


def fill_gaps(ori: np.ndarray, acc: np.ndarray, missing: np.ndarray, where: str,
              max_gap: int = DEFAULT_MAX_GAP) -> tuple[np.ndarray, np.ndarray, dict[str, list[list[int]]]]:
    """Fill the sensor frames marked ``missing`` (T, 6) in ``ori`` (T, 6, 3, 3) and ``acc``
    (T, 6, 3) (copies are returned, with the filled runs per sensor).

    The rule: a run of missing frames between two valid frames gets the geodesic interpolation
    (slerp) of the two orientations and the linear interpolation of the two accelerations; a
    run at the start or the end of the clip holds the nearest valid frame. A run longer than
    ``max_gap`` frames, or a sensor with no valid frame, is an :class:`IMUClipFormatError`
    naming the sensor and the frames."""
    ori, acc = np.array(ori, np.float64), np.array(acc, np.float64)
    T = len(ori)
    runs: dict[str, list[list[int]]] = {}
    for s, name in enumerate(SENSORS):
        m = missing[:, s]
        if not m.any():
            continue
        if m.all():
            raise IMUClipFormatError(f"{where}: sensor {name!r} has no valid frame (all {T} missing)")
        for a, b in _runs(m):
            if b - a > max_gap:
                raise IMUClipFormatError(
                    f"{where}: sensor {name!r}: {b - a} missing frames in a row (frames {a}-{b - 1}), more "
                    f"than max_gap = {max_gap}; pass a larger max_gap= to interpolate them anyway"
                )
            if a == 0:
                ori[a:b, s], acc[a:b, s] = ori[b, s], acc[b, s]
            elif b == T:
                ori[a:b, s], acc[a:b, s] = ori[a - 1, s], acc[a - 1, s]
            else:
                h = (np.arange(a, b) - (a - 1)) / (b - (a - 1))
                ori[a:b, s] = slerp(ori[a - 1, s], ori[b, s], h)
                acc[a:b, s] = (1 - h)[:, None] * acc[a - 1, s] + h[:, None] * acc[b, s]
            runs.setdefault(name, []).append([a, b])
    return ori, acc, runs


def readings_with_gaps(ori: np.ndarray, acc: np.ndarray, where: str, gaps: str = "fill",
                       max_gap: int = DEFAULT_MAX_GAP, fields: tuple[str, str] = ("ori", "acc")):
    """Raw readings that may hold NaN for dropouts -> ``(ori, acc, filled, meta)`` without NaN.

    A sensor frame is missing when any of its orientation or acceleration values is NaN; an
    infinite value is an error (not a dropout). ``gaps="fill"`` fills them (:func:`fill_gaps`),
    ``gaps="error"`` refuses any, naming the field, sensor and first frame. Orientations of the
    other frames must be rotations (:func:`check_rotations`)."""
    ori, acc = np.asarray(ori, np.float64), np.asarray(acc, np.float64)
    for a, key in ((ori, fields[0]), (acc, fields[1])):
        inf = np.isinf(a).reshape(a.shape[0], NUM_SENSORS, -1).any(-1)
        if inf.any():
            t, s = _first(inf)
            raise IMUClipFormatError(f"{where}: field {key!r}: sensor {SENSORS[s]!r} has an infinite value at "
                                     f"frame {t}")
    miss_o = np.isnan(ori).reshape(len(ori), NUM_SENSORS, -1).any(-1)
    miss_a = np.isnan(acc).reshape(len(acc), NUM_SENSORS, -1).any(-1)
    missing = miss_o | miss_a
    if gaps not in ("fill", "error"):
        raise ValueError(f"gaps must be 'fill' or 'error', got {gaps!r}")
    if missing.any() and gaps == "error":
        t, s = _first(missing)
        key = fields[0] if miss_o[t, s] else fields[1]
        raise IMUClipFormatError(
            f"{where}: field {key!r}: sensor {SENSORS[s]!r} has NaN (a dropout), first at frame {t} "
            f"({int(missing.sum())} sensor frames in all); gaps='fill' fills them"
        )
    check_rotations(ori, fields[0], where, missing)
    meta: dict[str, Any] = {}
    if missing.any():
        ori, acc, runs = fill_gaps(ori, acc, missing, where, max_gap)
        meta = {"gaps": runs, "gap_rule": f"slerp / linear between valid neighbours, held at the ends, "
                                          f"at most {max_gap} frames"}
    return ori, acc, (missing if missing.any() else None), meta


# --- calibration ------------------------------------------------------------------------------


def _rotations(x, where: str, lead: tuple[int, ...]) -> np.ndarray:
    """Matrices or wxyz quaternions with leading shape ``lead`` (one frame) or ``(N,) + lead``
    -> (N, *lead, 3, 3)."""
    a = np.asarray(x, np.float64)
    if a.shape[-1:] == (4,) and a.shape[:-1] in (lead, a.shape[:1] + lead):
        n = np.linalg.norm(a, axis=-1)
        if not np.all(np.abs(n - 1) <= QUAT_NORM_TOL):
            raise ValueError(f"{where}: quaternions must have unit norm (tolerance {QUAT_NORM_TOL})")
        a = quat_to_matrix(a / n[..., None])
    if a.shape == lead + (3, 3):
        a = a[None]
    if a.shape[1:] != lead + (3, 3) or len(a) == 0:
        raise ValueError(f"{where}: expected shape {lead + (3, 3)} or (N, {', '.join(map(str, lead))}, 3, 3) "
                         f"(or quaternions), got {np.shape(x)}")
    if not np.isfinite(a).all() or _not_rotation(a).any():
        raise ValueError(f"{where}: not rotation matrices (orthonormal within {ORTHO_TOL}, det +1)")
    return a


def tpose_bone_orientations(heading: float = 0.0) -> np.ndarray:
    """The six bones' orientations (6, 3, 3) in jmocap's world when the subject stands in a
    T-pose facing ``heading`` (radians about z from +x): jmocap's character at its rest pose is
    that T-pose, every body frame aligned with the world, so each is ``Rz(heading)``."""
    return np.tile(rotation_z(heading), (NUM_SENSORS, 1, 1))


def calibrate_tpose(tpose_ori, bone_ori=None, *, reference_ori=None, world_from_inertial=None,
                    tpose_acc=None) -> Calibration:
    """The calibration of TransPose's live demo (and PIP's, "similar to TransPose"), from a
    still T-pose with known bone orientations.

    1. World alignment ``R_WI``: either ``world_from_inertial`` given, or ``reference_ori``:
       the orientation(s) ``R_IS`` of one sensor held with its axes on jmocap's world axes
       (x forward of the subject, y left, z up; TransPose's "x = Left, y = Up, z = Forward" in
       SMPL's axes), so ``R_WI = R_IS^T`` (averaged over the frames given).
    2. Mounting: ``tpose_ori`` (6, 3, 3) or (N, 6, 3, 3) (or wxyz quaternions) read while the
       subject holds the T-pose, averaged (:func:`mean_rotation`), and ``bone_ori`` (6, 3, 3)
       the bones' known orientations ``R_WB`` then (default :func:`tpose_bone_orientations`,
       facing +x): ``R_WB = R_WI R_IS R_BS^T`` gives ``R_BS = R_WB^T R_WI R_IS``.
    3. Accelerometer offset: ``tpose_acc`` (6, 3) or (N, 6, 3), the free accelerations read
       during the still T-pose (truly zero): ``acc_bias = mean(R_WI a_I)``; zero when not given.

    Raises ``ValueError`` for shapes, non-rotations or not exactly one of ``reference_ori`` /
    ``world_from_inertial``."""
    if (reference_ori is None) == (world_from_inertial is None):
        raise ValueError("calibrate_tpose: give exactly one of reference_ori= (a sensor aligned with "
                         "jmocap's world axes) and world_from_inertial=")
    if world_from_inertial is not None:
        R_WI = _rotations(world_from_inertial, "world_from_inertial", ())[0]
    else:
        R_WI = mean_rotation(_rotations(reference_ori, "reference_ori", ())).T
    R_IS = mean_rotation(_rotations(tpose_ori, "tpose_ori", (NUM_SENSORS,)))
    R_WB = tpose_bone_orientations() if bone_ori is None else _rotations(bone_ori, "bone_ori", (NUM_SENSORS,))[0]
    R_BS = np.swapaxes(R_WB, -1, -2) @ R_WI @ R_IS
    bias = np.zeros((NUM_SENSORS, 3))
    if tpose_acc is not None:
        a = np.asarray(tpose_acc, np.float64)
        a = a[None] if a.shape == (NUM_SENSORS, 3) else a
        if a.ndim != 3 or a.shape[1:] != (NUM_SENSORS, 3) or not np.isfinite(a).all() or len(a) == 0:
            raise ValueError(f"tpose_acc: expected finite (6, 3) or (N, 6, 3), got {np.shape(tpose_acc)}")
        bias = (a @ R_WI.T).mean(axis=0)
    return Calibration(R_WI, R_BS, bias)


# --- I/O: npz ---------------------------------------------------------------------------------


def imu_clip_to_arrays(clip: IMUClip) -> dict[str, np.ndarray]:
    """The ``.npz`` arrays of an IMU clip (absent optional fields omitted)."""
    arrays: dict[str, np.ndarray] = {
        "format": np.array(FORMAT),
        "name": np.array(clip.name),
        "fps": np.array(clip.fps, dtype=np.float64),
        "sensors": np.array(SENSORS),
        "ori": clip.ori,
        "acc": clip.acc,
        "meta": np.array(json.dumps(clip.meta, sort_keys=True)),
    }
    for key in _CAL_FIELDS + ("filled",) + IMU_GT_FIELDS:
        v = getattr(clip, key)
        if v is not None:
            arrays[key] = np.asarray(v)
    for key in ("height_m", "mass_kg"):
        if getattr(clip, key) is not None:
            arrays[key] = np.array(getattr(clip, key), dtype=np.float64)
    if clip.layout is not None:
        arrays["layout"] = np.array(clip.layout)
    return arrays


def save_imu_clip(path: str | os.PathLike, clip: IMUClip) -> Path:
    """Save ``clip`` to ``path`` (``.npz``), atomically and deterministically. Returns the path."""
    if not isinstance(clip, IMUClip):
        raise TypeError(f"save_imu_clip expects an IMUClip, got {type(clip).__name__}")
    return atomic_write_npz(path, imu_clip_to_arrays(clip))


def _str(data, key: str, where: str, required: bool = True) -> str | None:
    if key not in data:
        if required:
            raise IMUClipFormatError(f"{where}: missing field {key!r}")
        return None
    v = np.asarray(data[key])
    if v.shape != () or v.dtype.kind not in "US":
        raise IMUClipFormatError(f"{where}: field {key!r} must be a string scalar, got {v.dtype} {v.shape}")
    return str(v)


def sensor_order(names, where: str, key: str = "sensors") -> np.ndarray:
    """Indices ``idx`` such that ``data[:, idx]`` is in :data:`SENSORS` order, for data whose
    sensor axis is ordered by ``names``. Missing, unknown or repeated names are an error."""
    names = [str(n) for n in names]
    missing = [s for s in SENSORS if s not in names]
    unknown = [n for n in names if n not in SENSORS]
    dup = sorted({n for n in names if names.count(n) > 1})
    if missing or unknown or dup:
        parts = []
        if missing:
            parts.append(f"missing sensor(s) {missing}")
        if unknown:
            parts.append(f"unknown sensor(s) {unknown}")
        if dup:
            parts.append(f"repeated sensor(s) {dup}")
        raise IMUClipFormatError(f"{where}: field {key!r}: {'; '.join(parts)} (an IMU clip has the six "
                                 f"sensors {list(SENSORS)})")
    return np.array([names.index(s) for s in SENSORS])


def _json_object(text, where: str, expected: str) -> dict:
    """``text`` parsed as JSON (:func:`jmocap.data.limits.parse_json`, its limits kept) that must
    be an object; otherwise an :class:`IMUClipFormatError` naming ``where`` (``"<expected> a JSON
    object, got <type>"``)."""
    try:
        doc = limits.parse_json(text, where)
    except limits.LimitError:
        raise
    except FormatError as e:
        raise IMUClipFormatError(str(e)) from None
    if not isinstance(doc, dict):
        raise IMUClipFormatError(f"{expected} a JSON object, got {type(doc).__name__}")
    return doc


def imu_clip_from_arrays(data, where: str) -> IMUClip:
    """An :class:`IMUClip` from a mapping of ``.npz`` arrays; errors name ``where``."""
    fmt = _str(data, "format", where)
    if fmt != FORMAT:
        raise IMUClipFormatError(f"{where}: field 'format' is {fmt!r}, expected {FORMAT!r}")
    for key in ("fps", "sensors", "ori", "acc"):
        if key not in data:
            raise IMUClipFormatError(f"{where}: missing field {key!r}")
    sensors = np.asarray(data["sensors"])
    if sensors.ndim != 1 or sensors.dtype.kind not in "US":
        raise IMUClipFormatError(f"{where}: field 'sensors' must be a list of names, got {sensors.dtype} "
                                 f"{sensors.shape}")
    idx = sensor_order(sensors.tolist(), where)
    values: dict[str, Any] = {"name": _str(data, "name", where), "layout": _str(data, "layout", where, False)}
    for key in ("fps", "height_m", "mass_kg"):
        if key in data:
            v = np.asarray(data[key])
            if v.shape != () or v.dtype.kind not in "iuf":
                raise IMUClipFormatError(f"{where}: field {key!r} must be a numeric scalar, got {v.dtype} {v.shape}")
            values[key] = v.item()
    n = len(SENSORS)
    for key, axis in (("ori", 1), ("acc", 1), ("filled", 1), ("bone_from_sensor", 0), ("acc_bias", 0),
                      ("sensor_offset", 0)):
        if key in data:
            a = np.asarray(data[key])
            if a.ndim <= axis or a.shape[axis] != len(sensors):
                raise IMUClipFormatError(f"{where}: field {key!r} has shape {a.shape}, expected {len(sensors)} "
                                         f"sensors (field 'sensors') on axis {axis}")
            values[key] = np.take(a, idx, axis=axis) if len(sensors) == n else a
    for key in ("world_from_inertial",) + IMU_GT_FIELDS:
        if key in data:
            values[key] = data[key]
    meta_s = _str(data, "meta", where, False)
    if meta_s is not None:
        values["meta"] = _json_object(meta_s, f"{where}: field 'meta'", f"{where}: field 'meta' must be")
    try:
        return IMUClip(**values)
    except FormatError as e:
        msg = str(e)
        prefix = f"IMU clip {values['name']!r}: "
        raise type(e)(f"{where}: {msg.removeprefix(prefix)}") from None


def load_imu_clip(path: str | os.PathLike) -> IMUClip:
    """Load and validate a ``jmocap-imu-clip-1`` ``.npz`` (read without pickle, within the
    limits of :mod:`jmocap.data.limits`)."""
    where = str(path)
    try:
        data = limits.load_npz(Path(path), where)
    except (FileNotFoundError, limits.LimitError):
        raise
    except FormatError as e:
        raise IMUClipFormatError(str(e)) from None
    except Exception as e:  # BadZipFile, zlib.error, truncated members, ...
        raise IMUClipFormatError(f"{where}: not a readable .npz file ({' '.join(str(e).split())})") from None
    return imu_clip_from_arrays(data, where)


def is_imu_clip_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an ``.npz`` whose ``format`` is ``jmocap-imu-clip-1``."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            return "format" in npz.files and str(npz["format"]) == FORMAT
    except Exception:
        return False


# --- I/O: JSON --------------------------------------------------------------------------------

_JSON_KEYS = {"format", "name", "fps", "sensors", "calibration", "meta"}
_JSON_SENSOR_KEYS = {"ori", "quat", "acc"}
_JSON_CAL_KEYS = {"world_from_inertial", "bone_from_sensor", "acc_bias", "sensor_offset"}


def _is_number(x) -> bool:
    return type(x) in (int, float)


def _json_numbers(x, shape: tuple[int, ...], where: str, key: str) -> np.ndarray:
    """A nested list of JSON numbers of exactly ``shape`` -> float64 array."""
    def check(v, shp, at):
        if not shp:
            if not _is_number(v):
                raise IMUClipFormatError(f"{where}: field {key!r}{at}: expected a number, got {json.dumps(v)[:40]}")
            return
        if not isinstance(v, list) or len(v) != shp[0]:
            raise IMUClipFormatError(f"{where}: field {key!r}{at}: expected a list of {shp[0]}, got "
                                     f"{json.dumps(v)[:40]}")
        for i, u in enumerate(v):
            check(u, shp[1:], f"{at}[{i}]")
    check(x, shape, "")
    return np.array(x, np.float64)


def _json_frames(x, tail: tuple[int, ...], where: str, key: str) -> np.ndarray:
    """A list of frames, each ``null`` (a dropout: NaN) or a nested list of shape ``tail``."""
    if not isinstance(x, list):
        raise IMUClipFormatError(f"{where}: field {key!r}: expected a list of frames, got {type(x).__name__}")
    out = np.full((len(x),) + tail, np.nan)
    for t, v in enumerate(x):
        if v is not None:
            out[t] = _json_numbers(v, tail, where, f"{key}[{t}]")
    return out


def read_imu_json(path: str | os.PathLike, *, name: str | None = None, gaps: str = "fill",
                  max_gap: int = DEFAULT_MAX_GAP) -> IMUClip:
    """Read the JSON layout (``docs/formats.md``, "IMU clips"): ``fps``, ``sensors`` (an object
    with the six sensors, each ``ori`` (T x 3 x 3) or ``quat`` (T x 4, wxyz) and ``acc``
    (T x 3), a frame ``null`` where the sensor dropped out), optional ``name``, ``calibration``,
    ``meta`` and ``format`` (``"jmocap-imu-json-1"``). Any other key is an error."""
    path = Path(path)
    where = str(path)
    limits.check_file_size(path, where)
    doc = _json_object(path.read_bytes(), where, f"{where}: expected")
    unknown = sorted(set(doc) - _JSON_KEYS)
    if unknown:
        raise IMUClipFormatError(f"{where}: unknown key(s) {unknown}; known: {sorted(_JSON_KEYS)}")
    if "format" in doc and doc["format"] != JSON_FORMAT:
        raise IMUClipFormatError(f"{where}: field 'format' is {doc['format']!r}, expected {JSON_FORMAT!r}")
    if "fps" not in doc or not _is_number(doc["fps"]):
        raise IMUClipFormatError(f"{where}: field 'fps' must be a number (frames per second)")
    sensors = doc.get("sensors")
    if not isinstance(sensors, dict):
        raise IMUClipFormatError(f"{where}: field 'sensors' must be an object of the six sensors {list(SENSORS)}")
    sensor_order(list(sensors), where)
    oris, accs = [], []
    for s in SENSORS:
        d = sensors[s]
        if not isinstance(d, dict):
            raise IMUClipFormatError(f"{where}: field 'sensors.{s}' must be an object with 'ori' or 'quat' and 'acc'")
        bad = sorted(set(d) - _JSON_SENSOR_KEYS)
        if bad or "acc" not in d or (("ori" in d) == ("quat" in d)):
            raise IMUClipFormatError(f"{where}: field 'sensors.{s}' needs 'acc' and one of 'ori' / 'quat'"
                                     + (f"; unknown key(s) {bad}" if bad else ""))
        if "ori" in d:
            oris.append(_json_frames(d["ori"], (3, 3), where, f"sensors.{s}.ori"))
        else:
            q = _json_frames(d["quat"], (4,), where, f"sensors.{s}.quat")
            n = np.linalg.norm(q, axis=1)
            badq = np.isfinite(n) & (np.abs(n - 1) > QUAT_NORM_TOL)
            if badq.any():
                t = int(np.argmax(badq))
                raise IMUClipFormatError(f"{where}: field 'sensors.{s}.quat': frame {t} has norm {n[t]:.4g} "
                                         f"(unit wxyz quaternions, tolerance {QUAT_NORM_TOL})")
            with np.errstate(invalid="ignore"):
                oris.append(quat_to_matrix(q / n[:, None]))
        accs.append(_json_frames(d["acc"], (3,), where, f"sensors.{s}.acc"))
    lengths = {s: len(o) for s, o in zip(SENSORS, oris, strict=True)} | {
        f"{s}.acc": len(a) for s, a in zip(SENSORS, accs, strict=True)}
    if len(set(lengths.values())) != 1:
        raise IMUClipFormatError(f"{where}: field 'sensors': the sensors have different frame counts {lengths}")
    ori_raw, acc_raw = np.stack(oris, 1), np.stack(accs, 1)
    if len(ori_raw) == 0:
        raise IMUClipFormatError(f"{where}: contains no frames")
    ori, acc, filled, gap_meta = readings_with_gaps(ori_raw, acc_raw, where, gaps, max_gap)
    values: dict[str, Any] = {}
    cal = doc.get("calibration", {})
    if not isinstance(cal, dict) or set(cal) - _JSON_CAL_KEYS:
        raise IMUClipFormatError(f"{where}: field 'calibration' must be an object with keys among "
                                 f"{sorted(_JSON_CAL_KEYS)}")
    if "world_from_inertial" in cal:
        values["world_from_inertial"] = _json_numbers(cal["world_from_inertial"], (3, 3), where,
                                                      "calibration.world_from_inertial")
    for key, tail in (("bone_from_sensor", (3, 3)), ("acc_bias", (3,)), ("sensor_offset", (3,))):
        if key in cal:
            per = cal[key]
            if not isinstance(per, dict):
                raise IMUClipFormatError(f"{where}: field 'calibration.{key}' must be an object by sensor")
            sensor_order(list(per), where, f"calibration.{key}")
            values[key] = np.stack([_json_numbers(per[s], tail, where, f"calibration.{key}.{s}") for s in SENSORS])
    meta = doc.get("meta", {})
    if not isinstance(meta, dict):
        raise IMUClipFormatError(f"{where}: field 'meta' must be an object")
    meta = {**meta, "source": where, **gap_meta}
    clip_name = name or doc.get("name") or path.stem
    if not isinstance(clip_name, str):
        raise IMUClipFormatError(f"{where}: field 'name' must be a string")
    try:
        return IMUClip(name=clip_name, fps=doc["fps"], ori=ori, acc=acc, filled=filled, meta=meta, **values)
    except FormatError as e:
        raise type(e)(f"{where}: {str(e).removeprefix(f'IMU clip {clip_name!r}: ')}") from None


def write_imu_json(path: str | os.PathLike, clip: IMUClip) -> Path:
    """Write the readings and calibration of ``clip`` in the JSON layout (no ground truth),
    atomically. Filled frames are written as filled (their values), not as ``null``."""
    doc = {
        "format": JSON_FORMAT,
        "name": clip.name,
        "fps": clip.fps,
        "sensors": {s: {"ori": clip.ori[:, i].astype(np.float64).tolist(),
                        "acc": clip.acc[:, i].astype(np.float64).tolist()} for i, s in enumerate(SENSORS)},
        "calibration": {
            "world_from_inertial": clip.world_from_inertial.tolist(),
            "bone_from_sensor": {s: clip.bone_from_sensor[i].tolist() for i, s in enumerate(SENSORS)},
            "acc_bias": {s: clip.acc_bias[i].tolist() for i, s in enumerate(SENSORS)},
        },
        "meta": clip.meta,
    }
    if clip.sensor_offset is not None:
        doc["calibration"]["sensor_offset"] = {s: clip.sensor_offset[i].tolist() for i, s in enumerate(SENSORS)}
    return atomic_write(path, json.dumps(doc).encode())


__all__ = [
    "DEFAULT_MAX_GAP",
    "FORMAT",
    "JSON_FORMAT",
    "NUM_SENSORS",
    "ORTHO_TOL",
    "QUAT_NORM_TOL",
    "SENSORS",
    "SENSOR_BODIES",
    "SMPL_TO_JMOCAP",
    "Calibration",
    "IMUClip",
    "IMUClipFormatError",
    "calibrate_tpose",
    "check_rotations",
    "fill_gaps",
    "imu_clip_from_arrays",
    "imu_clip_to_arrays",
    "is_imu_clip_file",
    "load_imu_clip",
    "matrix_to_quat",
    "mean_rotation",
    "quat_to_matrix",
    "read_imu_json",
    "readings_with_gaps",
    "rotation_z",
    "save_imu_clip",
    "sensor_order",
    "slerp",
    "tpose_bone_orientations",
    "write_imu_json",
]
