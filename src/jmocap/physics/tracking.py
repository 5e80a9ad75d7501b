r"""PIP's motion-tracking optimiser (Yi et al. 2022, Sec. 3.2.3, eq. 7) as one exact QP.

Given the state ``(q, qd)``, desired accelerations from a dual PD controller (rotational dofs and
global body positions) and the contact state, find the generalised acceleration ``qdd`` and the
contact forces ``lambda`` that track them as well as physics allows; the generalised force
follows from the equation of motion (eq. 1), ``tau = M qdd + h - J_c^T lambda``, so it is
eliminated (PIP eq. 7's equality constraint). ``tau[:6]`` is the residual (virtual) root
wrench, which the objective penalises heavily: the root moves by gravity, the contact forces and
that penalised residual only.

Variables and units
-------------------
``x = (qdd, c)`` with ``qdd`` (nv,) and ``c`` (P K,) >= 0 the coefficients of the K edges of the
friction pyramid at each of the P contact points (:func:`jmocap.physics.qp.friction_pyramid_edges`,
jmocap's one friction model: MuJoCo's pyramidal cone, ``mu = FRICTION_MU`` by default), so
``lambda_p = E^T c_p`` lies in the pyramid exactly when ``c_p >= 0``. Forces are per kilogram of
body mass (m/s^2) inside the QP, so that one set of weights serves every subject.

Objective (all terms squared residuals; weights in :class:`TrackingWeights`)::

    k_rot  || qdd[3:] - acc_rot_des ||^2                       rotation PD (PIP E_theta)
  + k_pos  sum_b || J_b qdd + Jdot_b qd - acc_pos_des_b ||^2    position PD (PIP E_r)
  + k_res  || tau[:6] / m ||^2                                  residual root wrench (E_res)
  + k_tau  || tau[6:] / m ||^2                                  joint torques (E_tau)
  + k_sig  sum_p max(d_p, 0) || lambda_p / m ||^2               Signorini (E_lambda)
  + k_slip sum_{p in contact} || J_p (qd / dt + qdd) + n d_p / dt^2 ||^2   sticking contact
  + k_reg  || c ||^2                                            strict convexity

Constraints (``G x >= lower``, m = P K + P rows, + 4 with ``net_force_cone``):

* friction: ``c_p >= 0`` at points in contact; a point not in contact carries no force (its
  columns are zero and its coefficients are exactly 0);
* non-penetration, *unconditional* (every point, in contact or not): the point's height after
  the semi-implicit step, ``d_p + dt n . J_p (qd + dt qdd) >= 0`` -- a point above the floor
  may always move down to it, a penetrating point is fully recovered within the step;
* optionally (``net_force_cone``) the net external force, contacts plus residual, in the same
  pyramid (4 rows on the root's translational rows of the equation of motion);

No sliding at points in contact (PIP eq. 11 bounds the tangential velocity by ``sigma = 1 cm/s``
with four rows per point) is a penalty here instead: ``k_slip || t . J_p (qd / dt + qdd) ||^2``
for the two floor tangents, the tangential acceleration that would stop the point within the
step, and likewise ``k_slip || n . J_p (qd / dt + qdd) + d_p / dt^2 ||^2`` along the normal,
which brings a point in contact that hovers above the floor (PIP's rule admits up to 3 cm) down
to it within the step, so that forces act at the floor and do not hold the body up. With 8 sole points PIP's rows would double the QP's constraints (72 instead of 40) and the
active-set solve's cost, which grows with their square; the penalty keeps the contact stiff
(its weight is ten times a tracked body's) without making the QP infeasible when a target
asks a planted foot to move.

The QP is solved by :func:`jmocap.physics.qp.solve_projection_info` (the dual active-set method
on the Cholesky factor of the Hessian): exact, batched, differentiable, with a KKT certificate
per solve (:attr:`TrackingSolution.certified`). It is always feasible (``qdd`` is free and the
constraints bound only the next velocities of distinct points).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap.constants import FLOOR_NORMAL, FRICTION_MU
from jmocap.model import Model
from jmocap.physics.dynamics import bias_velocities
from jmocap.physics.kinematics import Kinematics, point_jacobian
from jmocap.physics.linalg import cho_solve, cholesky
from jmocap.physics.qp import friction_pyramid_edges, solve_projection_info, tangent_basis

Array = jnp.ndarray

#: edges of the friction pyramid per contact point (MuJoCo's pyramidal cone for condim 3)
PYRAMID_EDGES = 4


@struct.dataclass
class TrackingWeights:
    """Weights of the tracking QP's objective (dimensionless: every term is in (m/s^2)^2 or
    (rad/s^2)^2 per kg; see the module docstring)."""

    rotation: float = 1.0  # k_rot (PIP: k_theta = 1)
    position: float = 1.0  # k_pos (PIP: k_r = 1)
    residual: float = 300.0  # k_res on the residual root wrench per kg
    torque: float = 0.01  # k_tau on the joint torques per kg
    signorini: float = 100.0  # k_sig per metre of height (force far from the floor)
    regularisation: float = 0.1  # k_reg on the pyramid coefficients
    slip: float = 1.0  # k_slip on the tangential acceleration that stops a sliding contact


@struct.dataclass
class TrackingQP:
    """The assembled QP ``min 1/2 x^T H x - g^T x s.t. G x >= lower`` in the projection form
    the solver takes (``v = H^-1 g``, ``L`` the Cholesky factor of H), and what maps its
    solution back to forces and torques."""

    H: Array  # (n, n)
    g: Array  # (n,)
    L: Array  # (n, n) lower Cholesky factor of H
    v: Array  # (n,) the unconstrained minimiser
    G: Array  # (m, n)
    lower: Array  # (m,) (-inf: row off)
    A_eom: Array  # (nv, n): tau / m = A_eom x + h / m
    h_per_kg: Array  # (nv,)
    edges: Array  # (K, 3) friction pyramid edges
    mass: Array  # ()
    in_contact: Array  # (P,) bool


@struct.dataclass
class TrackingSolution:
    qdd: Array  # (nv,) generalised acceleration
    grf: Array  # (P, 3) world-frame contact forces (N)
    tau: Array  # (nv,) generalised force: residual root wrench [:6] (N, N m), joint torques (N m)
    certified: Array  # () bool: the KKT conditions hold to rounding
    kkt_violation: Array  # () the largest relative KKT violation


def point_bias_acceleration(model: Model, kin: Kinematics, qd: Array, points: Array, bodies) -> Array:
    """``Jdot qd`` of points (P, 3) fixed to ``bodies``: their world acceleration when
    ``qdd = 0`` (classical acceleration from the spatial one: ``a + alpha x r + omega x v``)."""
    vel, acc = bias_velocities(model, kin, qd)
    b = np.asarray(bodies, int)
    w, u = vel[b, :3], vel[b, 3:]
    alpha, a = acc[b, :3], acc[b, 3:]
    r = points - kin.origin
    v = u + jnp.cross(w, r)
    return a + jnp.cross(alpha, r) + jnp.cross(w, v)


def contact_state(height: Array, contact_prob: Array, *, touch: float = 0.005, near: float = 0.03,
                  threshold: float = 0.5) -> Array:
    """PIP's contact rule (Sec. 3.2.3): a foot point is in contact when it is less than
    ``touch`` (0.5 cm) above the floor, or less than ``near`` (3 cm) above it and its contact
    probability exceeds ``threshold``. Returns bool (P,)."""
    return (height < touch) | ((height < near) & (contact_prob > threshold))


def tracking_qp(
    model: Model,
    kin: Kinematics,
    M: Array,
    h: Array,
    qd: Array,
    acc_rot_des: Array,
    pos_bodies,
    acc_pos_des: Array,
    contact_pos: Array,
    contact_bodies,
    height: Array,
    in_contact: Array,
    dt,
    *,
    mu=FRICTION_MU,
    weights: TrackingWeights = TrackingWeights(),
    net_force_cone: bool = False,
) -> TrackingQP:
    """Assemble one tracking QP (see the module docstring; :func:`solve_tracking` solves it).

    Args:
      kin, M, h: kinematics, joint-space inertia and bias forces at the current state.
      qd: (nv,) current velocity.
      acc_rot_des: (nv - 3,) desired accelerations of the rotational dofs (root rotation, hinges).
      pos_bodies: static ids of the B bodies whose origins the position PD tracks.
      acc_pos_des: (B, 3) desired world accelerations of those origins.
      contact_pos, contact_bodies, height: (P, 3) world positions, static body ids and (P,)
        heights above the floor of the contact points.
      in_contact: (P,) bool contact state (forces and the no-slip penalty act only there).
      dt: the step the acceleration is integrated over.
      mu: friction coefficient of the pyramid.
      net_force_cone: (static) add the 4 rows that keep the net external force, contacts plus
        residual (the root's translational rows of the equation of motion, ``M[:3] qdd + h[:3]``),
        in the same friction pyramid: the residual may make up for what the model misses, but
        not with a force no floor could give (pulling down, or beyond friction).
    """
    dtype = M.dtype
    nv = model.nv
    P = contact_pos.shape[0]
    K = PYRAMID_EDGES
    nc = P * K
    mass = jnp.sum(jnp.asarray(model.body_mass, dtype))
    qd = jnp.asarray(qd, dtype)
    normal = jnp.asarray(FLOOR_NORMAL, dtype)
    t1, t2 = tangent_basis(normal)
    on = jnp.asarray(in_contact, bool)

    # contact Jacobians and the generalised force of each pyramid edge, per kg
    Jc, _ = point_jacobian(model, kin, contact_pos, contact_bodies)  # (P, 3, nv)
    E = friction_pyramid_edges(normal, mu, K)  # (K, 3)
    B = jnp.einsum("kd,pdv->vpk", E, Jc) * on[None, :, None]
    B = B.reshape(nv, nc)  # J_c^T lambda / m = B c
    Mb, hb = M / mass, h / mass

    # least-squares rows  sqrt(w) (A x - b)
    zc = jnp.zeros((nv - 3, nc), dtype)
    A_rot = jnp.concatenate([jnp.eye(nv, dtype=dtype)[3:], zc], 1)
    pos_bodies = np.asarray(pos_bodies, int)
    Jp, _ = point_jacobian(model, kin, kin.xpos[pos_bodies], pos_bodies)  # (B, 3, nv)
    bias = point_bias_acceleration(model, kin, qd, kin.xpos[pos_bodies], pos_bodies)
    A_pos = jnp.concatenate([Jp.reshape(-1, nv), jnp.zeros((Jp.shape[0] * 3, nc), dtype)], 1)
    b_pos = (acc_pos_des - bias).reshape(-1)
    A_eom = jnp.concatenate([Mb, -B], 1)  # tau / m = A_eom x + hb
    w = weights
    # points in contact stick: the acceleration that stops a sliding point and brings a point
    # hovering above the floor down to it within the step
    Jn = jnp.einsum("d,pdv->pv", normal, Jc)  # (P, nv)
    Jt = jnp.concatenate([jnp.einsum("d,pdv->pv", t1, Jc), jnp.einsum("d,pdv->pv", t2, Jc), Jn])  # (3P, nv)
    on_t = jnp.tile(on, 3)[:, None]
    A_slip = jnp.concatenate([Jt * on_t, jnp.zeros((3 * P, nc), dtype)], 1)
    settle = jnp.concatenate([jnp.zeros(2 * P, dtype), jnp.maximum(height, 0.0) / (dt * dt)])
    b_slip = -((Jt @ qd) / dt + settle) * on_t[:, 0]
    rows = [
        (w.slip, A_slip, b_slip),
        (w.rotation, A_rot, acc_rot_des),
        (w.position, A_pos, b_pos),
        (w.residual, A_eom[:6], -hb[:6]),
        (w.torque, A_eom[6:], -hb[6:]),
    ]
    H = sum(k * (A.T @ A) for k, A, _ in rows)
    g = sum(k * (A.T @ b) for k, A, b in rows)  # the objective is 1/2 x^T H x - g^T x
    # Signorini and regularisation on the coefficients: ||lambda_p||^2 = c_p^T (E E^T) c_p
    EEt = E @ E.T
    sig = w.signorini * jnp.maximum(height, 0.0)  # one (K, K) block per point
    H = H.at[nv:, nv:].add(jnp.kron(jnp.diag(sig), EEt) + w.regularisation * jnp.eye(nc, dtype=dtype))
    H = 0.5 * (H + H.T)
    L = cholesky(H)
    v = cho_solve(L, g)  # the unconstrained minimiser

    # constraints G x >= lower
    neg_inf = jnp.asarray(-jnp.inf, dtype)
    G_fric = jnp.concatenate([jnp.zeros((nc, nv), dtype), jnp.eye(nc, dtype=dtype)], 1)
    lo_fric = jnp.where(jnp.repeat(on, K), 0.0, neg_inf)
    G_pen = jnp.concatenate([Jn, jnp.zeros((P, nc), dtype)], 1)
    lo_pen = -(height + dt * (Jn @ qd)) / (dt * dt)
    G_rows, lo_rows = [G_fric, G_pen], [lo_fric, lo_pen]
    if net_force_cone:
        # the pyramid's faces (mu n + s1 t1 + s2 t2) . f >= 0, s1, s2 = +-1, on f / m = Mb[:3] qdd + hb[:3]
        faces = jnp.stack([mu * normal + s1 * t1 + s2 * t2 for s1 in (1.0, -1.0) for s2 in (1.0, -1.0)])
        G_rows.append(jnp.concatenate([faces @ Mb[:3], jnp.zeros((4, nc), dtype)], 1))
        lo_rows.append(-(faces @ hb[:3]))
    G = jnp.concatenate(G_rows)
    lower = jnp.concatenate(lo_rows)
    return TrackingQP(H, g, L, v, G, lower, A_eom, hb, E, mass, on)


def solve_tracking(*args, **kwargs) -> TrackingSolution:
    """Assemble (:func:`tracking_qp`, same arguments) and solve one tracking QP."""
    return solve_qp(tracking_qp(*args, **kwargs))


def solve_qp(qp: TrackingQP) -> TrackingSolution:
    """Solve an assembled tracking QP exactly (dual active set on H's Cholesky factor).

    A solve whose KKT check fails (``certified`` False; never seen on the demo clips or in the
    tests, see docs/method.md) is made safe rather than trusted: its edge coefficients are
    clipped to ``c >= 0``, so the forces lie in the friction pyramid and vanish off contact, and
    the torques are recomputed from the equation of motion with them (the residual absorbs the
    difference). It stays counted as uncertified."""
    info = solve_projection_info(None, qp.G, qp.v, qp.lower, chol=qp.L)
    nv = qp.A_eom.shape[0]
    x = jnp.where(info.converged, info.x, info.x.at[nv:].set(jnp.maximum(info.x[nv:], 0.0)))
    return solution(qp, x, info.converged, info.kkt_violation)


def solution(qp: TrackingQP, x: Array, certified=True, kkt_violation=0.0) -> TrackingSolution:
    """Acceleration, forces and torques of a QP solution ``x = (qdd, c)``."""
    nv = qp.A_eom.shape[0]
    P, K = qp.in_contact.shape[0], qp.edges.shape[0]
    c = x[nv:].reshape(P, K)
    grf = qp.mass * jnp.einsum("pk,kd->pd", c, qp.edges) * qp.in_contact[:, None]
    tau = qp.mass * (qp.A_eom @ x + qp.h_per_kg)
    return TrackingSolution(x[:nv], grf, tau, jnp.asarray(certified), jnp.asarray(kkt_violation, x.dtype))


__all__ = [
    "PYRAMID_EDGES",
    "TrackingQP",
    "TrackingSolution",
    "TrackingWeights",
    "contact_state",
    "point_bias_acceleration",
    "solution",
    "solve_qp",
    "solve_tracking",
    "tracking_qp",
]
