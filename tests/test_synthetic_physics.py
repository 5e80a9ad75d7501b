"""The physics variant of the synthetic clips (``jmocap.data.synthetic.physics``): tracking a
kinematic motion in MuJoCo C.

References: the body weight (``mass * 9.81``) for the vertical ground reaction force of a
standing subject, MuJoCo's ``mj_integratePos`` / ``mju_quat2Mat`` for consistency of the
simulated positions, velocities and orientation.

Tolerances: standing GRF within 10 % of the weight (soft contacts and the tracking
controller's small root residual); one-frame integration 2 mm (a 30 fps frame holds several
simulation substeps, the stored qd is the frame's last).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from jmocap.data import synthetic as S


def _upright(quat):
    """World z component of the body z axis (R[2, 2]) for each quaternion (MuJoCo C)."""
    R = np.zeros(9)
    out = []
    for q in np.asarray(quat, np.float64):
        mujoco.mju_quat2Mat(R, q / np.linalg.norm(q))
        out.append(R[8])
    return np.array(out)


def test_physics_standing_grf_and_residual():
    clip = S.generate_clip(3, 0, S.SynthConfig(frames=45, kinds=("stand",), physics=True))
    ch = S.character(round(clip.height_m, 2))
    weight = ch.mass * 9.81
    assert clip.gt_tau is not None and clip.gt_tau.shape == (45, ch.nv)
    assert clip.gt_grf.shape == (45, 4, 3)
    fz = clip.gt_grf[..., 2].sum(axis=1)
    assert abs(fz.mean() / weight - 1.0) < 0.10
    assert np.all(clip.gt_grf[..., 2] >= -1e-6)  # the floor only pushes
    # upright, and residual reported (small when standing)
    assert np.all(_upright(clip.gt_q[:, 3:7]) > np.cos(np.radians(30)))
    p = clip.meta["physics"]
    for k in ("residual_force_mean", "residual_force_max", "residual_torque_mean"):
        assert k in p
    assert p["residual_force_mean"] < 0.05
    res = np.linalg.norm(clip.gt_tau[:, :3], axis=1) / weight
    assert abs(res.mean() - p["residual_force_mean"]) < 1e-3
    # velocities are the simulation's (consistent with the positions)
    mj = ch.mj
    x = clip.gt_q[0].astype(np.float64).copy()
    mujoco.mj_integratePos(mj, x, clip.gt_qd[0].astype(np.float64), 1.0 / clip.fps)
    np.testing.assert_allclose(x[:3], clip.gt_q[1, :3], atol=2e-3)


@pytest.mark.slow
def test_physics_walking_stays_upright():
    clip = S.generate_clip(1, 0, S.SynthConfig(frames=150, kinds=("walk",), physics=True))
    assert np.all(_upright(clip.gt_q[:, 3:7]) > np.cos(np.radians(30)))
    assert clip.meta["physics"]["residual_force_mean"] < 0.1
