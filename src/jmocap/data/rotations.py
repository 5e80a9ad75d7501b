"""Quaternion <-> rotation-matrix conversions on numpy arrays, shared by the data layer's readers
(:mod:`jmocap.data.imu`) and the synthetic generator (:mod:`jmocap.data.synthetic.rotations`,
which says why the generator stays numpy). Quaternions are MuJoCo's wxyz."""

from __future__ import annotations

import mujoco
import numpy as np


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit wxyz quaternions (..., 4) (not renormalised)."""
    q = np.asarray(q, np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit wxyz quaternions (..., 4), w >= 0, of rotation matrices (..., 3, 3): MuJoCo C's
    ``mju_mat2Quat``."""
    R = np.asarray(R, np.float64)
    m = R.reshape(-1, 3, 3)
    q = np.empty((len(m), 4))
    for i, Ri in enumerate(m):
        mujoco.mju_mat2Quat(q[i], Ri.reshape(9))
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


__all__ = ["matrix_to_quat", "quat_to_matrix"]
