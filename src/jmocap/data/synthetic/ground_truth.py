"""Ground truth of a clip: velocities, 3D keypoints and contact labels.

Velocities by MuJoCo's ``mj_differentiatePos``; 3D keypoints are the layout's sites by MuJoCo C
forward kinematics; contact labels follow Rempe et al. (2020), Sec. 3.2: a heel/toe point is
in contact when it moved less than 2 cm since the previous frame and is less than 5 cm above
the floor.
"""

from __future__ import annotations

import mujoco
import numpy as np

from jmocap.data.synthetic.character import Character, site_trajectories
from jmocap.scene import height_above

# Rempe et al. (2020), Sec. 3.2: a heel/toe point is in contact when it moved less than 2 cm
# since the previous frame and is less than 5 cm above the floor.
CONTACT_MAX_STEP_M = 0.02
CONTACT_MAX_HEIGHT_M = 0.05


def velocities(mj: mujoco.MjModel, q: np.ndarray, fps: float) -> np.ndarray:
    """qd (T, nv) by ``mj_differentiatePos``: central differences inside the clip, one-sided at
    the first and last frame (MuJoCo conventions: root angular velocity in the body frame)."""
    T = len(q)
    qd = np.zeros((T, mj.nv))
    if T < 2:
        return qd
    dt = 1.0 / fps
    for t in range(T):
        a, b = max(t - 1, 0), min(t + 1, T - 1)
        mujoco.mj_differentiatePos(mj, qd[t], (b - a) * dt, q[a], q[b])
    return qd


def contact_labels(points: np.ndarray, max_step: float = CONTACT_MAX_STEP_M,
                   max_height: float = CONTACT_MAX_HEIGHT_M, scene=None) -> np.ndarray:
    """Rempe et al.'s rule: a point (T, 4, 3) is in contact at frame t when it moved less than
    ``max_step`` since frame t-1 and is less than ``max_height`` above the floor (above the
    terrain under it, :func:`jmocap.scene.height_above`, when a ``scene`` is given). Frame 0 has
    no previous frame and uses its displacement to frame 1 (the same one frame 1 uses)."""
    T = len(points)
    step = np.zeros(points.shape[:2])
    if T > 1:
        step[1:] = np.linalg.norm(np.diff(points, axis=0), axis=-1)
        step[0] = step[1]
    return ((step < max_step) & (height_above(scene, points) < max_height)).astype(np.float32)


def _ground_truth(ch: Character, q: np.ndarray, layout, fps: float, scene=None):
    sites = np.array([ch.mj.site(s).id for s in layout.sites] + list(ch.contact_sites))
    pos = site_trajectories(ch, q, sites)
    kp3d = pos[:, : layout.num_joints]
    contacts = contact_labels(pos[:, layout.num_joints:], scene=scene)
    return kp3d, contacts
