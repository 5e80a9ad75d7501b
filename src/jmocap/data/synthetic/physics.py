"""The physics variant: track a kinematic motion in a MuJoCo C simulation.

:func:`simulate_tracking` drives the hinges with PD plus an inverse-dynamics feed-forward
(:func:`_feedforward`: contact forces distributed over the planted contact points by
non-negative least squares in a friction pyramid) and the root with the residual wrench the
contacts cannot explain plus a weak PD; it records the applied generalised forces (``gt_tau``)
and the foot contact forces (``gt_grf``). :class:`PhysicsConfig` holds its settings.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.optimize import nnls

from jmocap.constants import GRAVITY
from jmocap.data.synthetic.character import Character
from jmocap.data.synthetic.curves import _wrap
from jmocap.data.synthetic.errors import GenerationError
from jmocap.data.synthetic.ground_truth import velocities


@dataclass(frozen=True)
class PhysicsConfig:
    """Tracking controller of the physics variant (see ``docs/data.md``).

    Hinges: ``tau = tau_ff + kp (q_ref - q) + kd (qd_ref - qd)`` with ``kp = M_jj w^2``,
    ``kd = 2 zeta M_jj w`` (``M_jj``: the joint-space inertia at the standing pose), the damping
    part integrated implicitly (as MuJoCo ``dof_damping`` with the ``implicitfast``
    integrator); ``tau_ff`` is inverse dynamics of the reference with the contact forces
    distributed over the planted contact points (non-negative least squares in a friction
    pyramid). Root: the part of the reference's root wrench the contacts cannot explain, plus a
    weak PD on the root pose (``root_freq_hz``); both are the *residual* force / torque.
    """

    substeps_per_frame: int = 0  # 0: as many as make the step <= max_dt
    max_dt: float = 0.004
    joint_freq_hz: float = 6.0
    joint_zeta: float = 1.0
    min_inertia: float = 0.02
    root_freq_hz: float = 1.0
    root_zeta: float = 1.0
    friction: float = 0.9
    contact_timeconst: float = 0.008  # MuJoCo solref time constant of the contacts (s)
    fall_height: float = 0.5  # fraction of the standing pelvis height
    fall_tilt_deg: float = 60.0


def _pyramid(mu):
    d = np.array([[mu, 0, 1], [-mu, 0, 1], [0, mu, 1], [0, -mu, 1]], float)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _feedforward(ch: Character, mj, q, qd, qdd, planted, mu):
    """Inverse dynamics of the reference (T frames): hinge feed-forward torques (T, nv) and the
    root wrench the planted contacts cannot supply (T, 6)."""
    T = len(q)
    mj = copy.deepcopy(mj)  # rigid-body inverse dynamics only: no contacts, limits, damping
    mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    mj.dof_damping[:] = 0.0
    d = mujoco.MjData(mj)
    ff = np.zeros((T, mj.nv))
    res = np.zeros((T, 6))
    jp = np.zeros((3, mj.nv))
    D = _pyramid(mu)
    w, l = 0.035 * ch.scale, 0.03 * ch.scale
    patch = ([np.array([0.0, w, 0.0]), np.array([0.0, -w, 0.0]), np.array([l, 0.0, 0.0])],  # heel
             [np.array([0.0, w, 0.0]), np.array([0.0, -w, 0.0]), np.array([l, 0.0, 0.0]),
              np.array([-l, 0.0, 0.0])])  # toe
    for k in range(T):
        d.qpos[:], d.qvel[:], d.qacc[:] = q[k], qd[k], qdd[k]
        mujoco.mj_inverse(mj, d)
        tau = d.qfrc_inverse.copy()
        pts = np.nonzero(planted[k])[0]
        force_gen = np.zeros(mj.nv)
        if len(pts):
            mujoco.mj_kinematics(mj, d)
            mujoco.mj_comPos(mj, d)
            cols = []
            for i in pts:
                sid = int(ch.contact_sites[i])
                body = int(mj.site_bodyid[sid])
                R = d.xmat[body].reshape(3, 3)
                for off in patch[i % 2]:  # a small sole patch around the contact site
                    p = d.site_xpos[sid] + R @ off
                    mujoco.mj_jac(mj, d, jp, None, p, body)
                    cols.append(jp.T @ D.T)  # (nv, 4)
            A = np.concatenate(cols, axis=1)  # (nv, 4n)
            n = A.shape[1]
            Aw = np.vstack([A[:6], 1e-2 * np.eye(n)])
            bw = np.concatenate([tau[:6], np.zeros(n)])
            c, _ = nnls(Aw, bw, maxiter=50 * n)
            force_gen = A @ c
        ff[k] = tau - force_gen
        res[k] = ff[k, :6]
        ff[k, :6] = 0.0
    return ff, res


def simulate_tracking(ch: Character, q_ref: np.ndarray, fps: float, planted: np.ndarray,
                      cfg: PhysicsConfig = PhysicsConfig()) -> dict:
    """Track a kinematic motion in MuJoCo C (floor contact, PD + feed-forward hinges, residual
    root wrench). Returns q, qd (T, nq/nv) of the simulated motion sampled at the frames,
    ``tau`` (T, nv) applied generalised forces and ``grf`` (T, 4, 3) world-frame foot contact
    forces (each averaged over the frame's substeps), and residual / tracking statistics."""
    T = len(q_ref)
    mj = copy.deepcopy(ch.mj)
    frame_dt = 1.0 / fps
    n = cfg.substeps_per_frame or max(1, int(math.ceil(frame_dt / cfg.max_dt - 1e-9)))
    dt = frame_dt / n
    mj.opt.timestep = dt
    mj.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    # stiffer contacts than MuJoCo's default (time constant 0.02 s): less sinking on impact
    mj.geom_solref[:, 0] = max(cfg.contact_timeconst, 2 * dt)
    mj.geom_solref[:, 1] = 1.0
    nv = mj.nv
    qd_ref = velocities(mj, q_ref, fps)
    qdd_ref = np.zeros_like(qd_ref)
    if T > 1:
        qdd_ref[1:-1] = (qd_ref[2:] - qd_ref[:-2]) * fps / 2
        qdd_ref[0], qdd_ref[-1] = (qd_ref[1] - qd_ref[0]) * fps, (qd_ref[-1] - qd_ref[-2]) * fps
    ff, id_res = _feedforward(ch, mj, q_ref, qd_ref, qdd_ref, planted, cfg.friction)
    # gains from the joint-space inertia at the standing pose
    d0 = mujoco.MjData(mj)
    d0.qpos[:] = ch.q_stand
    mujoco.mj_forward(mj, d0)
    M = np.zeros((nv, nv))
    mujoco.mj_fullM(mj, d0, M)
    Mjj = np.maximum(np.diag(M)[6:], cfg.min_inertia)
    w = 2 * np.pi * cfg.joint_freq_hz
    kp = Mjj * w * w
    kd = 2 * cfg.joint_zeta * Mjj * w
    mj.dof_damping[6:] = kd
    mass = float(np.sum(mj.body_mass))
    weight = mass * GRAVITY
    wr = 2 * np.pi * cfg.root_freq_hz
    I_root = np.diag(M)[3:6].copy()
    # foot geoms -> which foot; contact sites
    foot_bodies = {ch.legs[0].ankle_body, ch.legs[0].toe_body, ch.legs[1].ankle_body, ch.legs[1].toe_body}
    floor = [g for g in range(mj.ngeom) if mj.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
    if not floor:
        raise ValueError("the model has no floor plane")
    floor = set(floor)
    d = mujoco.MjData(mj)
    d.qpos[:] = q_ref[0]
    d.qvel[:] = qd_ref[0]
    mujoco.mj_forward(mj, d)
    q_out = np.zeros((T, mj.nq))
    qd_out = np.zeros((T, nv))
    tau_out = np.zeros((T, nv))
    grf_out = np.zeros((T, 4, 3))
    resid = np.zeros((T, 6))
    f6 = np.zeros(6)
    nonfoot = 0
    z_fall = cfg.fall_height * ch.z_stand
    cos_tilt = math.cos(math.radians(cfg.fall_tilt_deg))
    foot_geom = np.array([mj.geom_bodyid[g] in foot_bodies for g in range(mj.ngeom)])
    is_floor = np.zeros(mj.ngeom, bool)
    is_floor[list(floor)] = True
    e_rot = np.zeros(3)
    quat = np.zeros(4)
    qfrc = np.zeros(nv)
    for k in range(T):
        q_out[k], qd_out[k] = d.qpos, d.qvel
        k1 = min(k + 1, T - 1)
        qa_ref, qb_ref = q_ref[k], q_ref[k1]
        if np.dot(qa_ref[3:7], qb_ref[3:7]) < 0:
            qb_ref = qb_ref.copy()
            qb_ref[3:7] *= -1
        acc_tau = np.zeros(nv)
        acc_grf = np.zeros((4, 3))
        for i in range(n):
            a = i / n
            qr = (1 - a) * qa_ref + a * qb_ref
            qdr = (1 - a) * qd_ref[k] + a * qd_ref[k1]
            quat[:] = qr[3:7] / np.linalg.norm(qr[3:7])
            qfrc[6:] = ((1 - a) * ff[k, 6:] + a * ff[k1, 6:] + kp * (qr[7:] - d.qpos[7:])
                        + kd * qdr[6:])
            mujoco.mju_subQuat(e_rot, quat, d.qpos[3:7])  # body-frame rotation to the reference
            qfrc[:3] = ((1 - a) * id_res[k, :3] + a * id_res[k1, :3]
                        + mass * (wr * wr * (qr[:3] - d.qpos[:3])
                                  + 2 * cfg.root_zeta * wr * (qdr[:3] - d.qvel[:3])))
            qfrc[3:6] = ((1 - a) * id_res[k, 3:] + a * id_res[k1, 3:]
                         + I_root * (wr * wr * e_rot + 2 * cfg.root_zeta * wr * (qdr[3:6] - d.qvel[3:6])))
            d.qfrc_applied[:] = qfrc
            mujoco.mj_step(mj, d)
            acc_tau += qfrc
            acc_tau[6:] -= kd * d.qvel[6:]  # the implicit damping acted with the new velocity
            if d.ncon:
                g1 = d.contact.geom1[: d.ncon]
                g2 = d.contact.geom2[: d.ncon]
                sp = None
                for c in range(d.ncon):
                    if is_floor[g1[c]]:
                        other, sign = g2[c], 1.0
                    elif is_floor[g2[c]]:
                        other, sign = g1[c], -1.0
                    else:
                        continue
                    if not foot_geom[other]:
                        nonfoot += 1
                        continue
                    mujoco.mj_contactForce(mj, d, c, f6)
                    con = d.contact[c]
                    fw = sign * (con.frame.reshape(3, 3).T @ f6[:3])
                    if sp is None:
                        sp = d.site_xpos[ch.contact_sites]
                    j = int(np.argmin(((sp - con.pos) ** 2).sum(axis=1)))
                    acc_grf[j] += fw
        tau_out[k] = acc_tau / n
        grf_out[k] = acc_grf / n
        resid[k] = tau_out[k, :6]
        z = d.qpos[2]
        up = d.xmat[ch.pelvis].reshape(3, 3)[2, 2]
        if not np.all(np.isfinite(d.qpos)) or z < z_fall or up < cos_tilt:
            raise GenerationError(f"the simulated character fell at frame {k}")
    F = np.linalg.norm(resid[:, :3], axis=1) / weight
    Tq = np.linalg.norm(resid[:, 3:], axis=1) / (weight * ch.height)
    hinge_err = np.abs(_wrap(q_out[:, 7:] - q_ref[:, 7:]))
    stats = dict(
        substeps=n,
        timestep=dt,
        residual_force_mean=float(F.mean()),
        residual_force_max=float(F.max()),
        residual_torque_mean=float(Tq.mean()),
        residual_torque_max=float(Tq.max()),
        feedforward_residual_force_mean=float(np.mean(np.linalg.norm(id_res[:, :3], axis=1)) / weight),
        tracking_root_mm=float(np.mean(np.linalg.norm(q_out[:, :3] - q_ref[:, :3], axis=1)) * 1000),
        tracking_joint_deg=float(np.degrees(hinge_err.mean())),
        grf_vertical_mean_over_weight=float(grf_out[..., 2].sum(axis=1).mean() / weight),
        nonfoot_contacts=int(nonfoot),
    )
    return dict(q=q_out, qd=qd_out, tau=tau_out, grf=grf_out, stats=stats)
