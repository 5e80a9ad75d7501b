"""AMASS-style ``.npz`` files of 3D joints (``joints`` or ``Jtr``): the one 3D reference format.

:func:`read_amass_joints` returns :class:`Joints3D`; SMPL joint names in :data:`SMPL_JOINT_NAMES`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jmocap.data import limits
from jmocap.data.clip import FormatError
from jmocap.data.formats.common import _READ_ERRORS, _check_nonempty, _ferr

# SMPL body joint names (AMASS ``Jtr`` order; SMPL-H/X continue with hand joints after 22)
SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
)


@dataclass(frozen=True, eq=False)
class Joints3D:
    """3D reference joints: ``joints`` (T, J, 3) float64 in the file's frame and units."""

    joints: np.ndarray
    fps: float
    joint_names: tuple[str, ...] | None
    source: str = ""


def read_amass_joints(path: str | os.PathLike) -> Joints3D:
    """Read 3D joints from an AMASS-style ``.npz``.

    AMASS itself stores SMPL(-H/X) parameters (``poses``, ``trans``, ``betas``,
    ``mocap_framerate``); this reader needs files where the joints were already computed:
    an array ``joints`` or ``Jtr`` of shape (T, J, 3), and the frame rate in
    ``mocap_framerate`` (AMASS SMPL+H), ``mocap_frame_rate`` (AMASS SMPL-X) or ``fps``. The
    joints are returned as stored (AMASS: metres, z-up world, like jmocap). For J = 22 / 24 the
    SMPL joint names are attached (:data:`SMPL_JOINT_NAMES`); for 52 (SMPL-H) the first 22.
    Read without pickle within :mod:`jmocap.data.limits`; the joints and the frame rate must be
    numbers (not strings or booleans).
    """
    path = Path(path)
    try:
        npz = limits.load_npz(path, str(path))
    except FormatError:
        raise
    except (*_READ_ERRORS, MemoryError) as e:
        raise _ferr(path, f"not a readable .npz file: {e}") from None
    files = list(npz)
    key = "joints" if "joints" in files else ("Jtr" if "Jtr" in files else None)
    if key is None:
        raise _ferr(
            path,
            f"has no 'joints' or 'Jtr' array (arrays: {files}); AMASS SMPL parameters "
            "need a body model to give joints",
            field="joints",
        )
    fkey = next((k for k in ("mocap_framerate", "mocap_frame_rate", "fps") if k in files), None)
    if fkey is None:
        raise _ferr(
            path,
            "has no frame rate ('mocap_framerate', 'mocap_frame_rate' or 'fps')",
            field="mocap_framerate",
        )
    for k, want in ((key, "(T, J, 3) numbers"), (fkey, "a number")):
        if npz[k].dtype.kind not in "iuf" or (k == fkey and npz[k].shape != ()):
            raise _ferr(
                path, f"has shape {npz[k].shape} ({npz[k].dtype}), expected {want}", field=k
            )
    J = np.asarray(npz[key], np.float64)
    fps = float(npz[fkey])
    if J.ndim != 3 or J.shape[2] != 3:
        raise _ferr(path, f"has shape {J.shape}, expected (T, J, 3)", field=key)
    _check_nonempty(path, J.shape[0])
    limits.check_frames(J.shape[0], f"{path}: field {key!r}")
    bad = ~np.isfinite(J)
    if bad.any():
        raise _ferr(
            path, "has non-finite values", int(np.argmax(bad.reshape(len(J), -1).any(axis=1))), key
        )
    if not (np.isfinite(fps) and fps > 0):
        raise _ferr(path, f"is {fps}, expected > 0", field=fkey)
    n = J.shape[1]
    names = SMPL_JOINT_NAMES[:n] if n in (22, 24) else (SMPL_JOINT_NAMES[:22] if n == 52 else None)
    if n == 52:
        names = names + tuple(f"hand_{i}" for i in range(30))
    return Joints3D(joints=J, fps=fps, joint_names=names, source=str(path))


__all__ = ["SMPL_JOINT_NAMES", "Joints3D", "read_amass_joints"]
