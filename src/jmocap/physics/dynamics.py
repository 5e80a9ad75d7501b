"""Rigid-body dynamics: mass matrix, bias forces, forward/inverse dynamics, integration.

Equation of motion (MuJoCo's, and the paper's eq. 2):

    M(q) qdd + h(q, qd) = tau + J_c(q)^T f

with ``h`` MuJoCo's ``qfrc_bias`` (gravity + Coriolis + centrifugal) and ``J_c`` the stacked
linear Jacobians of the contact points. Spatial algebra uses 6-vectors ``[angular; linear]`` in
world orientation about the spatial origin of :class:`~jmocap.physics.kinematics.Kinematics`.

* Mass matrix: composite rigid bodies (CRBA) without recursion. Subtree composite inertias are a
  single static-mask matmul over bodies; then ``M[d, k] = cdof_d . (I^c_{body(k)} cdof_k)`` for
  every dof pair on one root-to-leaf path, zero elsewhere.
* Bias forces: recursive Newton-Euler (RNE) with ``qdd = 0`` and the base accelerating at
  ``-gravity``, again as dense masked matmuls over (bodies x dofs).
* Forward dynamics: Cholesky of ``M``; the factor can be returned and reused (the contact
  projection needs ``M^-1`` and never refactorises).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap.model import Model
from jmocap.physics import linalg
from jmocap.physics.kinematics import Kinematics, _c, _dtype, contact_jacobian, forward_kinematics
from jmocap.physics.rotations import quat_error, quat_exp, quat_mul, quat_normalize

Array = jnp.ndarray


# ---- spatial algebra ([angular; linear]) -------------------------------------------------


def cross_motion(v: Array, m: Array) -> Array:
    """Spatial motion cross product v x m."""
    w, u = v[..., :3], v[..., 3:]
    a, b = m[..., :3], m[..., 3:]
    return jnp.concatenate([jnp.cross(w, a), jnp.cross(w, b) + jnp.cross(u, a)], -1)


def cross_force(v: Array, f: Array) -> Array:
    """Spatial force cross product v x* f."""
    w, u = v[..., :3], v[..., 3:]
    n, g = f[..., :3], f[..., 3:]
    return jnp.concatenate([jnp.cross(w, n) + jnp.cross(u, g), jnp.cross(w, g)], -1)


@struct.dataclass
class SpatialInertia:
    """Spatial inertias about the spatial origin, as (mass, first moment, rotational inertia).

    Linear in the body parameters, so subtree (composite) inertias are plain sums.
    """

    mass: Array  # (..., )
    h: Array  # (..., 3) mass * (com - origin)
    I: Array  # (..., 3, 3) rotational inertia about the origin

    def apply(self, v: Array) -> Array:
        """Momentum I v of a spatial motion v = [w; u] (u: velocity of the origin point)."""
        w, u = v[..., :3], v[..., 3:]
        ang = jnp.einsum("...ij,...j->...i", self.I, w) + jnp.cross(self.h, u)
        lin = self.mass[..., None] * u - jnp.cross(self.h, w)
        return jnp.concatenate([ang, lin], -1)


def body_inertias(model: Model, kin: Kinematics) -> SpatialInertia:
    """Spatial inertia of every body about ``kin.origin``."""
    dtype = kin.xpos.dtype
    mass = _c(model.body_mass, dtype)
    c = kin.xipos - kin.origin
    Ic = jnp.einsum("bij,bj,bkj->bik", kin.ximat, _c(model.body_inertia, dtype), kin.ximat)
    # parallel axis: I_o = I_c + m (|c|^2 1 - c c^T)
    cc = jnp.einsum("bi,bj->bij", c, c)
    I = Ic + mass[:, None, None] * (jnp.sum(c * c, -1)[:, None, None] * jnp.eye(3, dtype=dtype) - cc)
    return SpatialInertia(mass=mass, h=mass[:, None] * c, I=I)


# ---- mass matrix ---------------------------------------------------------------------------


def mass_matrix(model: Model, q: Array, *, kin: Kinematics | None = None) -> Array:
    """Joint-space inertia M(q), (nv, nv), including joint armature (equals ``mj_fullM``)."""
    kin = forward_kinematics(model, q) if kin is None else kin
    topo = model.topo
    dtype = kin.cdof.dtype
    inert = body_inertias(model, kin)
    # composite inertia of every body's subtree: sum over descendants (static mask)
    sub = jnp.asarray(topo.body_ancestor.T, dtype)  # [a, b]: b in subtree(a)
    comp = SpatialInertia(
        mass=sub @ inert.mass,
        h=sub @ inert.h,
        I=jnp.einsum("ab,bij->aij", sub, inert.I),
    )
    dof_body = np.asarray(topo.dof_body, int)
    comp_k = jax.tree.map(lambda x: x[dof_body], comp)
    F = comp_k.apply(kin.cdof)  # (nv, 6): composite momentum of dof k's unit motion
    A = kin.cdof @ F.T  # A[d, k] = cdof_d . Ic_{body(k)} cdof_k
    anc = jnp.asarray(topo.dof_ancestor)
    lower = jnp.asarray(topo.dof_ancestor.T & ~topo.dof_ancestor)
    M = jnp.where(anc, A, 0.0) + jnp.where(lower, A.T, 0.0)
    return M + jnp.diag(_c(model.dof_armature, dtype))


# ---- bias forces ---------------------------------------------------------------------------


def bias_velocities(model: Model, kin: Kinematics, qd: Array, base_velocity: Array | None = None) -> tuple[Array, Array]:
    """Body spatial velocities and bias accelerations (the accelerations when ``qdd = 0``),
    each (nbody, 6) ``[angular; linear]`` about ``kin.origin`` in world orientation, without
    gravity. ``base_velocity`` (6,): the spatial velocity of a moving base (a camera) that
    carries every body and every dof's axis (None: a fixed base)."""
    dtype = kin.cdof.dtype
    qd = jnp.asarray(qd, dtype)
    moves = jnp.asarray(model.topo.dof_moves_body, dtype)  # (nbody, nv)
    before = jnp.asarray(model.topo.velocity_before, dtype)  # (nv, nv)
    scaled = kin.cdof * qd[:, None]  # (nv, 6)
    carrier = before @ scaled if base_velocity is None else base_velocity + before @ scaled
    cdof_dot = cross_motion(carrier, kin.cdof)  # the frame carrying each dof's axis moves
    vel = moves @ scaled if base_velocity is None else base_velocity + moves @ scaled
    return vel, moves @ (cdof_dot * qd[:, None])


@struct.dataclass
class FrameMotion:
    """The motion of a non-inertial reference frame (a moving camera) relative to the inertial
    world, in the frame's own coordinates at the instant: angular velocity ``omega`` (3,), angular
    acceleration ``alpha`` (3,) (``d omega / dt``, the same in either frame since
    ``omega x omega = 0``) and the classical linear acceleration ``accel`` (3,) of the frame's
    origin. The frame's linear velocity is not needed: forces do not depend on it (Galilean
    invariance)."""

    omega: Array
    alpha: Array
    accel: Array

    @staticmethod
    def at_rest(dtype=jnp.float32) -> FrameMotion:
        z = jnp.zeros(3, dtype)
        return FrameMotion(z, z, z)


def rnea(model: Model, q: Array, qd: Array, qdd: Array, *, kin: Kinematics | None = None,
         gravity: Array | None = None, frame: FrameMotion | None = None) -> Array:
    """Inverse dynamics without the mass matrix: ``M(q) qdd + h(q, qd)``, (nv,), by the
    recursive Newton-Euler algorithm (MuJoCo's ``mj_rne`` with accelerations, plus the joint
    armature). O(nbody nv); cheaper than forming ``M`` when only the generalised force is needed
    (whole-clip trajectory optimisation evaluates it at every frame of every iteration).

    ``gravity`` (3,) replaces ``model.gravity`` (gravity as seen in a rotated frame, e.g. a
    camera's). ``frame``: ``q``, ``qd``, ``qdd`` are relative to a moving frame (a camera) whose
    motion relative to the inertial world is ``frame`` (:class:`FrameMotion`); the result is then
    the generalised force that moves the body so in the *inertial* world (the root's force in
    the moving frame's coordinates, its torque in the root's own frame, as ``qd``'s): the
    recursion starts from a base that moves with the frame instead of a fixed one.
    """
    kin = forward_kinematics(model, q) if kin is None else kin
    dtype = kin.cdof.dtype
    cdof = kin.cdof
    qd = jnp.asarray(qd, dtype)
    qdd = jnp.asarray(qdd, dtype)
    moves = jnp.asarray(model.topo.dof_moves_body, dtype)  # (nbody, nv)
    g = _c(model.gravity, dtype) if gravity is None else jnp.asarray(gravity, dtype)
    grav = jnp.concatenate([jnp.zeros(3, dtype), -g])
    if frame is None:
        vel, acc = bias_velocities(model, kin, qd)
    else:
        # the base: the moving frame's spatial velocity and acceleration about the spatial
        # origin O (its origin's own velocity taken as zero: Galilean invariance); Featherstone's
        # spatial acceleration has linear part a_P + alpha x (O - P) - omega x v_P, P the origin
        w, al, a = (jnp.asarray(x, dtype) for x in (frame.omega, frame.alpha, frame.accel))
        O = kin.origin
        vel, acc = bias_velocities(model, kin, qd, base_velocity=jnp.concatenate([w, jnp.cross(w, O)]))
        acc = jnp.concatenate([al, a + jnp.cross(al, O)]) + acc
    acc = acc + moves @ (cdof * qdd[:, None]) + grav  # MuJoCo's trick: accelerate the base against gravity
    inert = body_inertias(model, kin)
    f = inert.apply(acc) + cross_force(vel, inert.apply(vel))  # (nbody, 6)
    f_sub = moves.T @ f  # (nv, 6): net force on the subtree moved by each dof
    return jnp.sum(cdof * f_sub, -1) + _c(model.dof_armature, dtype) * qdd


def inertial_force(model: Model, q: Array, qd: Array, frame: FrameMotion, gravity: Array | None = None, *,
                   kin: Kinematics | None = None) -> Array:
    """The generalised inertial force (nv,) on a body whose configuration and velocity ``q``,
    ``qd`` are relative to a moving frame with motion ``frame`` (D&D, Li et al. 2022, eqs. 2-3:
    linear, centripetal and Coriolis; exact for jmocap's rigid bodies, with the Euler force of
    the frame's angular acceleration and each body's rotational inertia, where D&D's eq. 3 sums
    point masses at the joints and omits the Euler term).

    With it the equation of motion written in the moving frame as if it were inertial holds:
    ``M qdd + h(q, qd; gravity) = tau + J^T f + I`` (``gravity``: the world's gravity in the
    frame's coordinates), i.e. ``I = rnea(.., gravity) - rnea(.., gravity, frame=frame)``, for
    any ``qdd`` (both are affine in it with the same ``M``). A frame accelerating by ``a``
    pushes a body of mass ``m`` at rest in it by ``-m a``."""
    kin = forward_kinematics(model, q) if kin is None else kin
    z = jnp.zeros(model.nv, kin.cdof.dtype)
    return rnea(model, q, qd, z, kin=kin, gravity=gravity) - rnea(model, q, qd, z, kin=kin, gravity=gravity, frame=frame)


def bias_forces(model: Model, q: Array, qd: Array, *, kin: Kinematics | None = None) -> Array:
    """h(q, qd): gravity + Coriolis + centrifugal generalised forces (``qfrc_bias``), (nv,):
    :func:`rnea` at zero acceleration."""
    kin = forward_kinematics(model, q) if kin is None else kin
    return rnea(model, q, qd, jnp.zeros(model.nv, kin.cdof.dtype), kin=kin)


# ---- everything the dynamic cycle needs, from one kinematics pass -------------------------


@struct.dataclass
class SmoothDynamics:
    """M, h and the contact Jacobian from a single forward-kinematics pass."""

    kin: Kinematics
    M: Array  # (nv, nv)
    h: Array  # (nv,)
    Jc: Array  # (4*3, nv), or (0, nv) for models without contact sites


def smooth_dynamics(model: Model, q: Array, qd: Array) -> SmoothDynamics:
    """Mass matrix, bias forces and contact Jacobian at (q, qd), sharing one kinematics pass."""
    kin = forward_kinematics(model, q)
    Jc = (
        contact_jacobian(model, q, kin=kin)
        if model.topo.contact_sites
        else jnp.zeros((0, model.nv), kin.cdof.dtype)
    )
    return SmoothDynamics(
        kin=kin,
        M=mass_matrix(model, q, kin=kin),
        h=bias_forces(model, q, qd, kin=kin),
        Jc=Jc,
    )


# ---- forward / inverse dynamics --------------------------------------------------------------


def cholesky(M: Array) -> Array:
    """Lower Cholesky factor L of the (symmetric positive definite) mass matrix (pure JAX, no
    LAPACK call: see :mod:`jmocap.physics.linalg`)."""
    return linalg.cholesky(M)


def cho_solve(L: Array, b: Array) -> Array:
    """Solve M x = b given M's lower Cholesky factor; b may be (nv,) or (nv, k)."""
    return linalg.cho_solve(L, b)


def mass_inverse(L: Array) -> Array:
    """M^-1 from its Cholesky factor (for the contact projection's metric)."""
    Linv = linalg.solve_lower(L, jnp.broadcast_to(jnp.eye(L.shape[-1], dtype=L.dtype), L.shape))
    return jnp.swapaxes(Linv, -1, -2) @ Linv  # M^-1 = L^-T L^-1: one substitution pass, not two


def _generalised_contact(Jc: Array, contact_force: Array | None, dtype) -> Array | float:
    if contact_force is None:
        return 0.0
    f = jnp.asarray(contact_force, dtype).reshape(-1)
    if f.shape[0] != Jc.shape[0]:
        raise ValueError(
            f"contact_force has {f.shape[0]} entries, the contact Jacobian {Jc.shape[0]} rows"
        )
    return Jc.T @ f


def forward_dynamics(
    model: Model,
    q: Array,
    qd: Array,
    tau: Array,
    contact_force: Array | None = None,
    *,
    return_factor: bool = False,
):
    """Accelerations qdd solving ``M qdd = tau + J_c^T f - h`` (paper eq. 13).

    Args:
      tau: generalised forces (nv,), root entries included.
      contact_force: world-frame forces at the contact points, (4, 3) or (12,), or None.
      return_factor: also return the Cholesky factor of M (and the SmoothDynamics) for reuse.
    """
    dyn = smooth_dynamics(model, q, qd)
    dtype = dyn.M.dtype
    rhs = jnp.asarray(tau, dtype) + _generalised_contact(dyn.Jc, contact_force, dtype) - dyn.h
    L = cholesky(dyn.M)
    qdd = cho_solve(L, rhs)
    return (qdd, L, dyn) if return_factor else qdd


def inverse_dynamics(
    model: Model, q: Array, qd: Array, qdd: Array, contact_force: Array | None = None
) -> Array:
    """Generalised forces ``tau = M qdd + h - J_c^T f`` producing qdd (inverse of eq. 13)."""
    dyn = smooth_dynamics(model, q, qd)
    dtype = dyn.M.dtype
    return dyn.M @ jnp.asarray(qdd, dtype) + dyn.h - _generalised_contact(
        dyn.Jc, contact_force, dtype
    )


# ---- integration -----------------------------------------------------------------------------


def integrate_positions(model: Model, q: Array, qd: Array, dt) -> Array:
    """q advanced by velocity qd over dt (MuJoCo's ``mj_integratePos``).

    Hinge and slide coordinates move by ``qd dt``; a free root moves its position by the
    world-frame linear velocity and its quaternion by the exact exponential of the body-frame
    angular velocity, ``quat <- quat ⊗ exp(omega dt)`` (the paper's eq. 1 integrated exactly:
    ``d quat/dt = 1/2 quat ⊗ [0, omega_body] = 1/2 [0, omega_world] ⊗ quat``), renormalised.
    """
    topo = model.topo
    dtype = _dtype(q)
    q = jnp.asarray(q, dtype)
    qd = jnp.asarray(qd, dtype)
    hq = topo.hinge_qadr
    if hq.size:
        q = q.at[hq].add(qd[topo.hinge_dofadr] * dt)
    for qa, da in zip(topo.free_qadr, topo.free_dof, strict=True):
        pos = q[qa : qa + 3] + qd[da : da + 3] * dt
        quat = quat_normalize(quat_mul(q[qa + 3 : qa + 7], quat_exp(qd[da + 3 : da + 6] * dt)))
        q = q.at[qa : qa + 3].set(pos).at[qa + 3 : qa + 7].set(quat)
    return q


def finite_difference_velocity(model: Model, q: Array, fps) -> Array:
    """Backward-difference velocities (T, nv) of a pose sequence ``q`` (T, nq) sampled at
    ``fps`` (MuJoCo's ``mj_differentiatePos`` between consecutive frames: world-frame root
    displacement, body-frame rotation vector of the root quaternion difference, hinge angle
    differences, each over ``1 / fps``); the first frame gets zero velocity."""
    dt = 1.0 / jnp.asarray(fps, q.dtype)
    q0 = jnp.concatenate([q[:1], q[:-1]])

    def diff(a, b):
        rot = quat_error(b[3:7], a[3:7])  # body-frame rotation from a to b
        return jnp.concatenate([b[0:3] - a[0:3], rot, b[7:] - a[7:]]) / dt

    return jax.vmap(diff)(q0, q)


def integrate(model: Model, q: Array, qd: Array, qdd: Array, dt) -> tuple[Array, Array]:
    """Semi-implicit Euler step (paper eq. 14): ``qd' = qd + dt qdd``, ``q' = q (+) dt qd'``."""
    dtype = _dtype(q)
    qd_new = jnp.asarray(qd, dtype) + jnp.asarray(qdd, dtype) * dt
    return integrate_positions(model, q, qd_new, dt), qd_new
