"""How far D&D's point-mass inertial force (Li et al. 2022, eq. 3) is from the exact rigid-body
one (``jmocap.physics.inertial_force``) for a walking person seen from a hand-held camera.

D&D sums ``m_i J_i^T (a + omega x (omega x r_i) + 2 omega x v_i)`` over point masses at the
joints (here: each body's mass at its joint, the body origin, as the paper; and, kinder to it,
at its centre of mass), leaving out each segment's rotational inertia and the Euler term
``alpha x r`` of the camera's angular acceleration. The body: the demo walk's ground truth
(world frame, 30 fps); the camera: walking alongside at 2 m with a 2 Hz bob of 3 cm, a 1 Hz
sway of 2 cm, panning to follow and rolling a few degrees (angular velocities up to about 1
rad/s). Prints the relative error of each approximation on the root's force, the root's torque
and the hinges.

    .venv/bin/python experiments/inertial_force_point_masses.py
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jmocap import physics as P
from jmocap.data.clip import load_clip
from jmocap.demo import demo_assets
from jmocap.model import character
from jmocap.physics.rotations import axis_angle_to_mat, mat_to_quat, quat_mul


def camera(t):
    """Camera orientation (axes in the world) and position at time t (s)."""
    base = jnp.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # OpenCV axes, looking along +y
    yaw = axis_angle_to_mat(jnp.array([0.0, 0, 1]), 0.35 * jnp.sin(0.8 * t))
    roll = axis_angle_to_mat(jnp.array([0.0, 1, 0]), 0.05 * jnp.sin(2.1 * t))
    pitch = axis_angle_to_mat(jnp.array([1.0, 0, 0]), -0.1 + 0.04 * jnp.sin(1.7 * t))
    pos = jnp.array([0.0, -2.0, 1.5]) + jnp.array([1.2 * t, 0.0, 0.0]) + jnp.array(
        [0.02 * jnp.sin(2 * jnp.pi * 1.0 * t), 0.0, 0.03 * jnp.sin(2 * jnp.pi * 2.0 * t)])
    return yaw @ roll @ pitch @ base, pos


def frame_motion(t):
    def omega(s):
        R, _ = camera(s)
        dR = jax.jacfwd(lambda u: camera(u)[0])(s)
        W = R.T @ dR
        return jnp.array([W[2, 1], W[0, 2], W[1, 0]])

    w, al = jax.jvp(omega, (t,), (jnp.ones_like(t),))
    R, _ = camera(t)
    acc = jax.jacfwd(jax.jacfwd(lambda u: camera(u)[1]))(t)
    return P.FrameMotion(w, al, R.T @ acc), R


def point_mass_force(model, q, qd, fm, at_com: bool, euler: bool):
    """D&D's eq. 3 as a fictitious force: -sum m_i J_i^T (a + [alpha x r_i] + w x (w x r_i) + 2 w x v_i)."""
    kin = P.forward_kinematics(model, q)
    pts = kin.xipos if at_com else kin.xpos
    bodies = np.arange(model.topo.nbody)
    jacp, _ = P.point_jacobian(model, kin, pts, bodies)  # (nbody, 3, nv)
    v = jnp.einsum("bkn,n->bk", jacp, qd)
    m = jnp.asarray(model.body_mass, q.dtype)
    acc = fm.accel + jnp.cross(fm.omega, jnp.cross(fm.omega, pts)) + 2 * jnp.cross(fm.omega, v)
    if euler:
        acc = acc + jnp.cross(fm.alpha, pts)
    return -jnp.einsum("b,bkn,bk->n", m, jacp, acc)


def main() -> None:
    clip = load_clip(demo_assets() / "ground_truth" / "demo_walk.npz")
    model = character(clip.height_m, clip.mass_kg)
    fps = clip.fps
    T = clip.num_frames
    ts = np.arange(T) / fps
    qw = np.asarray(clip.gt_q, np.float64)
    qc = qw.copy()
    for k, t in enumerate(ts):
        R, c = (np.asarray(x, np.float64) for x in camera(jnp.asarray(t)))
        qc[k, :3] = R.T @ (qw[k, :3] - c)
        qc[k, 3:7] = np.asarray(quat_mul(mat_to_quat(jnp.asarray(R.T)), jnp.asarray(qw[k, 3:7])))
    qdc = np.asarray(P.finite_difference_velocity(model, jnp.asarray(qc, jnp.float32), fps))
    rows = {"exact (jmocap)": [], "point masses at joints, no Euler term (D&D eq. 3)": [],
            "point masses at the centres of mass, no Euler term": [],
            "point masses at the centres of mass, with the Euler term": []}
    for k in range(1, T - 1):
        fm, _ = frame_motion(jnp.asarray(ts[k], jnp.float32))
        q, qd = jnp.asarray(qc[k], jnp.float32), jnp.asarray(qdc[k], jnp.float32)
        exact = P.inertial_force(model, q, qd, fm)
        rows["exact (jmocap)"].append(exact)
        rows["point masses at joints, no Euler term (D&D eq. 3)"].append(point_mass_force(model, q, qd, fm, False, False))
        rows["point masses at the centres of mass, no Euler term"].append(point_mass_force(model, q, qd, fm, True, False))
        rows["point masses at the centres of mass, with the Euler term"].append(point_mass_force(model, q, qd, fm, True, True))
    ex = np.stack(rows["exact (jmocap)"])
    print(f"demo walk, {T - 2} frames; exact inertial force: root force {np.abs(ex[:, :3]).mean():.1f} N, "
          f"root torque {np.abs(ex[:, 3:6]).mean():.2f} N m, hinges {np.abs(ex[:, 6:]).mean():.3f} N m (mean |.|)")
    print("| approximation | root force rel. error | root torque rel. error | hinge rel. error |")
    print("|---|---:|---:|---:|")
    for name, vals in rows.items():
        if name.startswith("exact"):
            continue
        a = np.stack(vals)

        def rel(sl, a=a):
            return np.linalg.norm(a[:, sl] - ex[:, sl]) / np.linalg.norm(ex[:, sl])

        print(f"| {name} | {100 * rel(slice(0, 3)):.1f} % | {100 * rel(slice(3, 6)):.1f} % | {100 * rel(slice(6, None)):.1f} % |")


if __name__ == "__main__":
    main()
