"""The shared stages that reconstruction methods compose (pure functions, no flags).

Learned stage (Neural PhysCap, paper Sec. 3.2-3.3):

* :func:`normalise_keypoints` -- root-relative ``K_rr`` and canonical ``K_c`` keypoints;
* :func:`target_pose` -- TPNet: the kinematic target pose, contact logits and the camera-frame
  root; :func:`least_squares_translation` is its closed-form root translation;
* :func:`contact_probability` / :func:`contact_state` -- the contact estimate and the gate
  ``p > threshold`` that switches forces and the no-slip/no-penetration rows on.

Dynamic stages (paper Sec. 3.4; a method's cycle step calls them in order):

* :func:`rigid_body_terms` -- ``M``, ``h``, ``J_c`` (jmocap's physics or MJX);
* :func:`pd_gains` -- fixed gains ``k_p_ini`` or DyNet's gains and offsets;
* :func:`pd_control` -- eq. 7: the PD acceleration and the generalised force ``tau``;
* :func:`grfnet_forces` -- GRFNet's contact forces, friction pyramid, contact gate;
* :func:`contact_compensation` -- eq. 13's ``tau* = tau - J_c^T lambda`` (optionally with a soft
  limit of the residual root wrench);
* :func:`accelerations` -- eq. 13 solved for ``qdd``;
* :func:`hard_constraint` -- eqs. 14-16: the velocity step and its projection onto the
  non-penetration set; :func:`jmocap.physics.integrate_positions` closes the step (eqs. 1, 14).

The physical parameters (gains, friction, recovery factor, ...) are traced arrays of the
method's config, so they can be changed without recompiling and differentiated.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap import physics as P
from jmocap.camera import canonicalise, root_relative
from jmocap.constants import FLOOR_NORMAL, GRAVITY, NUM_CONTACTS
from jmocap.inputs import ClipInputs
from jmocap.layouts import get_layout
from jmocap.model import Model
from jmocap.nets import DyNet, GRFNet, NetConfig, TPNet, rot6d_to_mat
from jmocap.physics.contact import project_friction_pyramid, sole_half_width
from jmocap.physics.linalg import solve_spd3
from jmocap.physics.rotations import mat_to_quat, quat_error

Array = jnp.ndarray


def body_mass(model: Model, dtype=jnp.float32) -> Array:
    """Total mass (kg) as a traceable array: the model may be a jit argument."""
    return jnp.sum(jnp.asarray(model.body_mass, dtype))


def body_weight(model: Model, dtype=jnp.float32) -> Array:
    """Body weight (N), ``mass * GRAVITY``."""
    return body_mass(model, dtype) * GRAVITY


# ---------------------------------------------------------------------------------------
# parameters of the networks
# ---------------------------------------------------------------------------------------


def init_tpnet(key: Array, model: Model, layout: str, nets: NetConfig) -> dict:
    """Fresh TPNet variables for ``layout``'s keypoints."""
    J, W = get_layout(layout).num_joints, nets.window
    tp = TPNet(n_hinges=model.topo.hinge_qadr.size, config=nets)
    return tp.init({"params": key}, jnp.zeros((1, W, J, 3)), jnp.zeros((1, W, ct_features(J))), train=False)


def init_dynet(key: Array, model: Model, nets: NetConfig) -> dict:
    return DyNet(nv=model.nv, width=nets.dyn_width).init(key, jnp.zeros((1, dynet_num_features(model))))["params"]


def init_grfnet(key: Array, model: Model, nets: NetConfig) -> dict:
    grf = GRFNet(n_points=NUM_CONTACTS, width=nets.grf_width)
    return grf.init(key, jnp.zeros((1, grfnet_num_features(model))))["params"]


def ct_features(J: int) -> int:
    """Per-frame input width of C_T: K_c (or K_rr) with confidence, P_rr, closed-form translation."""
    return 3 * J + 3 * J + 3


def dynet_num_features(model: Model) -> int:
    nv, n_h = model.nv, model.topo.hinge_qadr.size
    return nv + nv + 1 + 4 + n_h + 4 + n_h + nv * (nv + 1) // 2


def grfnet_num_features(model: Model) -> int:
    return 6 + 3 * NUM_CONTACTS * model.nv + 3 + NUM_CONTACTS + 3 * NUM_CONTACTS


# ---------------------------------------------------------------------------------------
# the learned stage: keypoint normalisation, TPNet, contact state
# ---------------------------------------------------------------------------------------


def normalise_keypoints(inputs: ClipInputs, layout: str) -> tuple[Array, Array]:
    """``(K_rr, K_c)`` (T, J, 3): root-relative keypoints scaled by the image size (TPNet's
    C_P input) and canonical keypoints ``K^-1 [u v 1]`` (C_T's input), confidence kept."""
    kp = jnp.asarray(inputs.keypoints)
    return root_relative(kp, inputs.image_size, get_layout(layout)), canonicalise(kp, inputs.intrinsics)


@struct.dataclass
class TargetPose:
    q_hat: Array  # (T, nq) world-frame target pose
    contact_logits: Array  # (T, 4)
    rot_cam: Array  # (T, 3, 3) root orientation in the camera frame
    trans_cam: Array  # (T, 3) root position in the camera frame
    trans_ls: Array  # (T, 3) closed-form (least-squares) root position in the camera frame
    p_rr: Array  # (T, J, 3) root-relative 3D keypoints in the camera frame


def causal_windows(x: Array, window: int) -> Array:
    """(T, ...) -> (T, window, ...): frames t-window+1..t, the first frame replicated before 0."""
    T = x.shape[0]
    idx = jnp.clip(jnp.arange(T)[:, None] - (window - 1) + jnp.arange(window)[None], 0, T - 1)
    return x[idx]


def hinge_angles(raw: Array) -> Array:
    """TPNet's joint-angle head: pi tanh(raw) (the paper's demo; L_irr keeps them in range)."""
    return jnp.pi * jnp.tanh(raw)


def target_pose(
    params: dict,
    model: Model,
    inputs: ClipInputs,
    config: Any,
    *,
    train: bool = False,
    rngs: dict | None = None,
    detach_pose: bool = False,
) -> TargetPose:
    """TPNet over a whole clip (each frame sees its causal window of ``config.nets.window``).

    ``config`` supplies the static ``layout``, ``nets`` and ``canonicalise``. ``train`` turns
    dropout on (``rngs={"dropout": key}``); ``detach_pose`` stops C_T's gradient from reaching
    C_P (separate pre-training of the two, Sec. 3.5). jmocap's C_T adds its learned output to
    the weighted least-squares translation that makes ``P_rr`` reproject onto ``K_c``; the
    camera-frame pose is then moved to the z-up world with the extrinsics.
    """
    layout = get_layout(config.layout)
    n_h = model.topo.hinge_qadr.size
    tp = TPNet(n_hinges=n_h, config=config.nets)
    k_rr, k_c = normalise_keypoints(inputs, config.layout)  # (T, J, 3) each
    W = config.nets.window
    variables = params["tpnet"]
    kw = dict(train=train, rngs=rngs or {})

    rot6d, raw, logits = tp.apply(variables, causal_windows(k_rr, W), method=TPNet.pose, **kw)
    rot_cam = rot6d_to_mat(rot6d)
    hinges = hinge_angles(raw)
    dtype = hinges.dtype
    T = k_rr.shape[0]
    q_rr = jnp.zeros((T, model.nq), dtype)
    q_rr = q_rr.at[:, 3:7].set(mat_to_quat(rot_cam)).at[:, model.topo.hinge_qadr].set(hinges)
    p_rr = jax.vmap(lambda q: P.keypoints(model, q, layout))(q_rr)  # camera frame, root at 0
    # C_T's view of the pose; pre-training keeps C_T's loss out of C_P (paper Sec. 3.5)
    p_ct = jax.lax.stop_gradient(p_rr) if detach_pose else p_rr

    if config.canonicalise:
        t_ls = jax.vmap(least_squares_translation)(p_ct, k_c)
        obs = k_c
    else:
        t_ls = jnp.broadcast_to(jnp.array([0.0, 0.0, 4.0], dtype), (T, 3))
        obs = k_rr
    feats = jnp.concatenate([obs.reshape(T, -1), p_ct.reshape(T, -1), t_ls], -1)
    dt_cam = tp.apply(variables, causal_windows(feats, W), method=TPNet.translation, **kw)
    trans_cam = t_ls + dt_cam

    q_hat = root_in_world(q_rr, rot_cam, trans_cam, jnp.asarray(inputs.world_to_camera(), dtype))
    return TargetPose(q_hat, logits, rot_cam, trans_cam, t_ls, p_rr)


def root_in_world(q: Array, rot_cam: Array, trans_cam: Array, extrinsics: Array) -> Array:
    """``q`` (T, nq) with its root set from a camera-frame orientation (T, 3, 3) and position
    (T, 3), moved to the world of ``extrinsics`` (``X_c = R X_w + t``): one camera (4, 4) or
    one per frame (T, 4, 4), a moving camera's track."""
    R, t = extrinsics[..., :3, :3], extrinsics[..., :3, 3]
    rot_w = jnp.matmul(jnp.swapaxes(R, -1, -2), rot_cam)  # R^T R_cam
    pos_w = jnp.einsum("...ji,...j->...i", R, trans_cam - t)  # R^T (t_cam - t)
    return q.at[:, 0:3].set(pos_w).at[:, 3:7].set(mat_to_quat(rot_w))


def least_squares_translation(p_rr: Array, k_c: Array, prior_depth: float = 4.0, prior_weight: float = 1e-4) -> Array:
    """Root translation t (camera frame) making root-relative joints ``p_rr`` (J, 3) project onto
    canonical keypoints ``k_c`` (J, 3: u, v, confidence).

    ``(X + t_x) = u (Z + t_z)`` and ``(Y + t_y) = v (Z + t_z)`` are linear in t; they are solved
    in the confidence-weighted least-squares sense, with a weak prior ``t = (0, 0, prior_depth)``
    so that frames with fewer than two visible joints stay well posed.
    """
    u, v, c = k_c[:, 0], k_c[:, 1], k_c[:, 2]
    X, Y, Z = p_rr[:, 0], p_rr[:, 1], p_rr[:, 2]
    one, zero = jnp.ones_like(u), jnp.zeros_like(u)
    A = jnp.concatenate([jnp.stack([one, zero, -u], -1), jnp.stack([zero, one, -v], -1)])  # (2J, 3)
    b = jnp.concatenate([u * Z - X, v * Z - Y])
    w = jnp.concatenate([c, c])
    prior = jnp.array([0.0, 0.0, prior_depth], p_rr.dtype)
    AtA = (A * w[:, None]).T @ A + prior_weight * jnp.eye(3, dtype=p_rr.dtype)
    Atb = (A * w[:, None]).T @ b + prior_weight * prior
    return solve_spd3(AtA, Atb)


def contact_probability(logits: Array) -> Array:
    """Foot-contact probabilities from TPNet's logits (sigmoid)."""
    return jax.nn.sigmoid(logits)


def contact_state(contact_prob: Array, threshold) -> Array:
    """Which contact points are in contact: ``p > threshold`` (bool, same shape)."""
    return contact_prob > threshold


# ---------------------------------------------------------------------------------------
# the dynamic stages
# ---------------------------------------------------------------------------------------


@struct.dataclass
class RigidBodyTerms:
    M: Array  # (nv, nv) joint-space inertia
    h: Array  # (nv,) bias forces (Coriolis, centrifugal, gravity)
    Jc: Array  # (3 NUM_CONTACTS, nv) contact-point Jacobian
    kin: Any  # physics.Kinematics of the state (None: recomputed where needed)


def rigid_body_terms(model: Model, q: Array, qd: Array, backend: str = "jmocap") -> RigidBodyTerms:
    """``M``, ``h`` and ``J_c`` at ``(q, qd)`` from jmocap's physics (``"jmocap"``) or MJX's own
    smooth-dynamics functions (``"mjx"``: a reference and benchmark baseline, slow on CPU)."""
    if backend == "jmocap":
        dyn = P.smooth_dynamics(model, q, qd)
        return RigidBodyTerms(dyn.M, dyn.h, dyn.Jc, dyn.kin)
    M, h, Jc = mjx_smooth_dynamics(model, q, qd, backend)
    return RigidBodyTerms(M, h, Jc, None)  # the projection's rows then come from jmocap's kinematics


def mjx_smooth_dynamics(model: Model, q: Array, qd: Array, backend: str = "mjx"):
    """``(M, h, J_c)`` from MJX's own functions.

    kinematics, com_pos, crb, com_vel, rne, full_m, and ``mjx.jac`` at the four foot contact
    sites (rows ordered as :func:`jmocap.physics.contact_jacobian`). Needs ``model.mjx``
    (``load_model(with_mjx=True)``), built under the same ``jax_enable_x64`` setting as the run.
    """
    if backend != "mjx":
        raise ValueError(f"physics_backend must be 'jmocap' or 'mjx', got {backend!r}")
    if model.mjx is None:
        raise ValueError("physics_backend='mjx' needs model.mjx: load the model with load_model(with_mjx=True)")
    from jmocap.model import _import_mjx

    mjx, mx, dtype = _import_mjx(), model.mjx, q.dtype
    d = mjx.make_data(mx)
    d = d.replace(qpos=q.astype(d.qpos.dtype), qvel=qd.astype(d.qvel.dtype))
    d = mjx.kinematics(mx, d)
    d = mjx.com_pos(mx, d)
    d = mjx.crb(mx, d)
    d = mjx.com_vel(mx, d)
    d = mjx.rne(mx, d)
    M = mjx.full_m(mx, d)
    sites = model.topo.contact_sites
    Jc = jnp.concatenate(
        [mjx.jac(mx, d, d.site_xpos[s], int(model.topo.site_body[s]))[0].T for s in sites], 0
    )
    return M.astype(dtype), d.qfrc_bias.astype(dtype), Jc.astype(dtype)


def pd_error(model: Model, q_hat: Array, q: Array) -> Array:
    """e_PD = d(q_hat, q) in velocity coordinates (nv,): world position error of the root,
    body-frame rotation vector of the quaternion difference, hinge angle differences."""
    e_rot = quat_error(q_hat[3:7], q[3:7])
    return jnp.concatenate([q_hat[0:3] - q[0:3], e_rot, q_hat[7:] - q[7:]])


def kp_initial(model: Model, kp_root_pos, kp_root_rot, kp_joint, dtype=jnp.float32) -> Array:
    """k_p_ini per dof (1/s^2, acceleration units): root translation, root rotation, joints."""
    kp = jnp.full(model.nv, kp_joint, dtype)
    return kp.at[:3].set(kp_root_pos).at[3:6].set(kp_root_rot)


def _upper(M: Array) -> Array:
    iu = np.triu_indices(M.shape[-1])
    return M[..., iu[0], iu[1]]


def dynet_features(model: Model, q_hat, q, qd, M, e) -> Array:
    """DyNet's input (Sec. 3.4.1): target and current pose, velocity, mass matrix and PD error.

    The root's horizontal position is left out of the poses (the error e carries it), so that the
    network is invariant to where the subject stands; M enters as its upper triangle per kg.
    """
    hq = model.topo.hinge_qadr
    mass = body_mass(model, M.dtype)
    return jnp.concatenate(
        [e, qd, q[2:3], q[3:7], q[hq], q_hat[3:7], q_hat[hq], _upper(M) / mass]
    )


def grfnet_features(model: Model, tau_root, Jc, contact, grf_prev) -> Array:
    """GRFNet's input (Sec. 3.4.2): the root wrench and previous forces per body weight, the
    contact Jacobian, the floor normal and the contact probabilities."""
    weight = body_weight(model, Jc.dtype)
    return jnp.concatenate(
        [tau_root / weight, Jc.reshape(-1), jnp.asarray(FLOOR_NORMAL, Jc.dtype), contact, grf_prev.reshape(-1) / weight]
    )


@struct.dataclass
class PDGains:
    kp: Array  # (nv,) proportional gains (1/s^2)
    kd: Array  # (nv,) derivative gains (1/s)
    alpha: Array  # (nv,) generalised-force offsets (N, N m)


def pd_gains(kp0: Array, kd: Array, alpha=None) -> PDGains:
    """Fixed gains: ``k_p = k_p_ini``, no offset (PhysCap-like)."""
    return PDGains(kp0, kd, jnp.zeros_like(kp0) if alpha is None else alpha)


def dynet_gains(params: dict, model: Model, q_hat, q, qd, M, e, kp0: Array, kd: Array, nets: NetConfig) -> PDGains:
    """DyNet's gains (Sec. 3.4.1): ``k_p = 2 s_g k_p_ini``, ``alpha = gamma s_f``."""
    s_g, s_f = DyNet(nv=model.nv, width=nets.dyn_width).apply(
        {"params": params["dynet"]}, dynet_features(model, q_hat, q, qd, M, e)
    )
    return PDGains(2.0 * s_g * kp0, kd, nets.gamma * s_f)


def pd_control(e: Array, qd: Array, gains: PDGains, M: Array, h: Array) -> tuple[Array, Array]:
    """Eq. 7 with the gains in acceleration units: ``acc = k_p e - k_d qd`` and
    ``tau = M acc + alpha + h``. Returns ``(acc, tau)``."""
    acc = gains.kp * e - gains.kd * qd
    return acc, M @ acc + gains.alpha + h


def grfnet_forces(params: dict, model: Model, tau_root, Jc, contact_prob, in_contact, grf_prev, mu,
                  nets: NetConfig) -> tuple[Array, Array]:
    """GRFNet's contact forces (Sec. 3.4.2), in body weights times the network's output, projected
    onto the friction pyramid (coefficient ``mu``) and zero at points not in contact.
    Returns ``(grf, raw)`` (NUM_CONTACTS, 3) each, world frame, newtons."""
    dtype = Jc.dtype
    raw = body_weight(model, dtype) * GRFNet(n_points=NUM_CONTACTS, width=nets.grf_width).apply(
        {"params": params["grfnet"]}, grfnet_features(model, tau_root, Jc, contact_prob, grf_prev)
    )
    grf = project_friction_pyramid(raw, jnp.asarray(FLOOR_NORMAL, dtype), mu)
    return jnp.where(in_contact[:, None], grf, 0.0), raw


def soft_limit_wrench(wrench: Array, limit) -> Array:
    """Smoothly saturate a root wrench [force (3); torque (3)]: each part is scaled by
    ``1 / sqrt(1 + |part|^2 / limit^2)`` (force limit ``limit`` N, torque limit ``limit`` N m),
    which is the identity for small residuals and tends to ``limit`` in magnitude."""
    f, t = wrench[:3], wrench[3:]

    def sat(x):
        return x / jnp.sqrt(1.0 + jnp.sum(x * x) / (limit * limit))

    return jnp.concatenate([sat(f), sat(t)])


def contact_compensation(tau: Array, Jc: Array, grf: Array) -> tuple[Array, Array]:
    """Eq. 13's actuation: the contact force compensates part of ``tau``,
    ``tau* = tau - J_c^T lambda``. Returns ``(tau_star, J_c^T lambda)``."""
    JtG = Jc.T @ grf.reshape(-1)
    return tau - JtG, JtG


def hard_constraint(model: Model, q, qd_free, in_contact, dt, *, metric: str, beta, chol=None, kin=None) -> Array:
    """Eqs. 15-16: the velocity closest to ``qd_free`` (in the metric ``M`` or the identity)
    that keeps the contact points from penetrating the floor (see
    :func:`jmocap.physics.project_velocity`); ``chol`` reuses a Cholesky factor of ``M``."""
    return P.project_velocity(
        model, q, qd_free, in_contact, dt=dt, metric=metric, beta=beta,
        chol=chol if metric == "mass" else None, kin=kin,
    )




# ---------------------------------------------------------------------------------------
# contact points of the sole (the physical methods' contact model)
# ---------------------------------------------------------------------------------------


def sole_points(model: Model, kin) -> tuple[Array, np.ndarray, Array]:
    """The contact points of the tracking QP: each foot contact site (heel, toe) widened to a pair
    of points at +- the sole's half-width along its body's lateral axis, so that a foot can
    carry a moment about its long axis (PIP uses the four corners of a square per foot joint).
    Returns positions (8, 3), static body ids (8,) and heights above the floor (8,), ordered
    site by site (the pair of site i at 2i, 2i + 1)."""
    sites = np.asarray(model.topo.contact_sites)
    bodies = np.asarray(model.topo.site_body)[sites]
    centre = P.site_positions(model, None, sites, kin=kin)
    lateral = kin.xmat[bodies][:, :, 1]  # the bodies' y axes in the world
    half = sole_half_width(model)
    pts = (centre[:, None, :] + jnp.asarray([-half, half], centre.dtype)[None, :, None] * lateral[:, None, :])
    pts = pts.reshape(-1, 3)
    return pts, np.repeat(bodies, 2), pts[:, 2]


def on_floor(model: Model, q: Array) -> Array:
    """``q`` moved vertically so that its lowest sole point touches the floor: the initial state
    (TPNet's first pose floats or sinks by its depth error; starting there would drop the body
    from that height, or push it out of the floor, before tracking begins)."""
    _, _, height = sole_points(model, P.forward_kinematics(model, q))
    return q.at[2].add(-jnp.min(height))


__all__ = [
    "on_floor",
    "root_in_world",
    "sole_points",
    "PDGains",
    "RigidBodyTerms",
    "TargetPose",
    "body_mass",
    "body_weight",
    "causal_windows",
    "contact_compensation",
    "contact_probability",
    "contact_state",
    "dynet_features",
    "dynet_gains",
    "grfnet_features",
    "grfnet_forces",
    "hard_constraint",
    "hinge_angles",
    "kp_initial",
    "least_squares_translation",
    "mjx_smooth_dynamics",
    "normalise_keypoints",
    "pd_control",
    "pd_error",
    "pd_gains",
    "rigid_body_terms",
    "soft_limit_wrench",
    "target_pose",
]
