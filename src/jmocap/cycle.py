"""The physionical pipeline: TPNet's target pose, then the dynamic cycle (paper Sec. 3.3-3.4).

``reconstruct(params, model, inputs, config=...)`` maps one clip of 2D keypoints to a
:class:`~jmocap.motion.Motion`. It is a pure function: ``jax.vmap`` it over clips (padded to a
common length, ``inputs.mask`` marking real frames) and ``jax.jit`` it once per shape bucket.
It is causal — frame t depends on frames <= t only — so the same function serves streaming.

Stages (equation numbers are the paper's):

1. **Keypoint normalisation** (Sec. 3.2): root-relative ``K_rr`` and canonical ``K_c``.
2. **TPNet** (Sec. 3.3): on a causal window of 10 frames of ``K_rr``, C_P predicts the root
   orientation (camera frame), the hinge angles and four foot-contact probabilities; forward
   kinematics of that root-relative pose gives ``P_rr``; C_T predicts the root translation from
   ``P_rr`` and ``K_c``. jmocap's C_T adds its learned output to the weighted least-squares
   translation that makes ``P_rr`` reproject onto ``K_c`` (a closed form that is exact for
   noise-free input); the camera-frame pose is then moved to the z-up world with the extrinsics.
3. **Dynamic cycle** (Sec. 3.4), ``k`` iterations per frame with ``dt = 1 / (fps k)``:
   DyNet gains, PD forces (eq. 7), GRFNet forces, forward dynamics (eq. 13), the velocity update
   and the hard no-penetration projection (eqs. 14-16), pose integration (eqs. 1, 14).

See docs/method.md for the choices made where the paper is silent.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap import physics as P
from jmocap.camera import canonicalise, root_relative
from jmocap.layouts import get_layout
from jmocap.model import Model
from jmocap.motion import Motion
from jmocap.nets import DyNet, GRFNet, NetConfig, TPNet, rot6d_to_mat
from jmocap.physics.contact import project_friction_pyramid
from jmocap.physics.linalg import solve_spd3
from jmocap.physics.rotations import mat_to_quat, quat_error

Array = jnp.ndarray
FLOOR_NORMAL = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class CycleConfig:
    """Static configuration of the pipeline (hashable: a jit static argument).

    The switches reproduce the paper's ablations and baselines.
    """

    layout: str = "body25"
    iterations: int = 6  # k, dynamic-cycle iterations per frame (paper: 6)
    use_dynet: bool = True  # False: fixed gains k_p = k_p_ini, alpha = 0 (PhysCap-like)
    use_grfnet: bool = True  # False: no GRF, all root motion from the virtual root force
    hard_constraint: bool = True  # False: no foot-floor projection
    canonicalise: bool = True  # False: C_T sees K_rr instead of K_c (and no closed form)
    kinematic_only: bool = False  # True: TPNet's output is the result
    metric: str = "mass"  # projection metric: "mass" or "identity" (eq. 15)
    beta: float = 0.2  # penetration recovery factor of the projection
    contact_threshold: float = 0.5
    max_velocity: float = 30.0  # |qd| bound (rad/s, m/s) before the projection; keeps states finite
    mu: float = 0.8  # friction coefficient (paper Sec. 3.4.2)
    # soft limit of the residual (virtual) root force, in body weights (the torque limit is the
    # same times 1 m); None applies any residual, as eqs. 7 + 13 literally (the default: a limit
    # makes the M-weighted PD inconsistent and the cycle diverges, see docs/method.md)
    root_residual_limit: float | None = None
    # initial PD gains k_p_ini (1/s^2, acceleration units: see docs/method.md) and damping
    kp_root_pos: float = 1600.0
    kp_root_rot: float = 1600.0
    kp_joint: float = 1600.0
    damping_ratio: float = 1.0
    nets: NetConfig = field(default_factory=NetConfig)
    # where M, h and J_c come from: "jmocap" (physics.smooth_dynamics) or "mjx" (MJX's own
    # smooth-dynamics functions; a reference and benchmark baseline, slow on CPU)
    physics_backend: str = "jmocap"


# ---------------------------------------------------------------------------------------
# inputs and parameters
# ---------------------------------------------------------------------------------------


@struct.dataclass
class ClipInputs:
    """What the pipeline reads from one clip (a batch adds a leading axis to every field)."""

    keypoints: Array  # (T, J, 3) pixels x, y and confidence
    intrinsics: Array  # (4,) fx, fy, cx, cy
    image_size: Array  # (2,) width, height
    extrinsics: Array  # (4, 4) world -> camera (OpenCV axes)
    fps: Array  # () frames per second
    mask: Array  # (T,) bool, real frames

    @staticmethod
    def from_clip(clip, length: int | None = None) -> ClipInputs:
        """Inputs of a :class:`jmocap.data.clip.Clip`, optionally padded to ``length`` frames."""
        kp = np.asarray(clip.keypoints, np.float32)
        T = kp.shape[0]
        L = T if length is None else int(length)
        if L < T:
            raise ValueError(f"clip {clip.name!r} has {T} frames, more than the padded length {L}")
        pad = np.zeros((L - T, *kp.shape[1:]), np.float32)
        ext = clip.extrinsics if clip.extrinsics is not None else default_extrinsics()
        return ClipInputs(
            keypoints=np.concatenate([kp, pad]),
            intrinsics=np.asarray(clip.intrinsics, np.float32),
            image_size=np.asarray(clip.image_size, np.float32),
            extrinsics=np.asarray(ext, np.float32),
            fps=np.float32(clip.fps),
            mask=np.arange(L) < T,
        )


def default_extrinsics(height: float = 1.0, distance: float = 4.0) -> np.ndarray:
    """The camera assumed when a clip has no extrinsics: level, at (0, -distance, height),
    looking along world +y at (0, 0, height); OpenCV axes (x right, y down, z forward)."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # world -> camera
    eye = np.array([0.0, -distance, height])
    E = np.eye(4)
    E[:3, :3] = R
    E[:3, 3] = -R @ eye
    return E


def init_params(key: Array, model: Model, config: CycleConfig = CycleConfig()) -> dict:
    """Fresh parameters of TPNet, DyNet and GRFNet (a pytree of arrays)."""
    layout = get_layout(config.layout)
    J, W = layout.num_joints, config.nets.window
    n_h = model.topo.hinge_qadr.size
    k1, k2, k3 = jax.random.split(key, 3)
    tp = TPNet(n_hinges=n_h, config=config.nets)
    tp_vars = tp.init(
        {"params": k1}, jnp.zeros((1, W, J, 3)), jnp.zeros((1, W, _ct_features(J))), train=False
    )
    dyn = DyNet(nv=model.nv, width=config.nets.dyn_width)
    grf = GRFNet(n_points=4, width=config.nets.grf_width)
    return {
        "tpnet": tp_vars,
        "dynet": dyn.init(k2, jnp.zeros((1, _dynet_features(model))))["params"],
        "grfnet": grf.init(k3, jnp.zeros((1, _grfnet_features(model))))["params"],
    }


def _ct_features(J: int) -> int:
    return 3 * J + 3 * J + 3  # K_c (or K_rr) with confidence, P_rr, closed-form translation


def _dynet_features(model: Model) -> int:
    nv, n_h = model.nv, model.topo.hinge_qadr.size
    return nv + nv + 1 + 4 + n_h + 4 + n_h + nv * (nv + 1) // 2


def _grfnet_features(model: Model) -> int:
    return 6 + 12 * model.nv + 3 + 4 + 12


# ---------------------------------------------------------------------------------------
# TPNet: the target pose
# ---------------------------------------------------------------------------------------


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
    config: CycleConfig = CycleConfig(),
    *,
    train: bool = False,
    rngs: dict | None = None,
    detach_pose: bool = False,
) -> TargetPose:
    """TPNet over a whole clip (each frame sees its causal window).

    ``train`` turns dropout on (``rngs={"dropout": key}``); ``detach_pose`` stops C_T's
    gradient from reaching C_P (separate pre-training of the two, Sec. 3.5).
    """
    layout = get_layout(config.layout)
    n_h = model.topo.hinge_qadr.size
    tp = TPNet(n_hinges=n_h, config=config.nets)
    kp = jnp.asarray(inputs.keypoints)
    k_rr = root_relative(kp, inputs.image_size, layout)  # (T, J, 3)
    k_c = canonicalise(kp, inputs.intrinsics)  # (T, J, 3)
    W = config.nets.window
    variables = params["tpnet"]
    kw = dict(train=train, rngs=rngs or {})

    rot6d, raw, logits = tp.apply(variables, causal_windows(k_rr, W), method=TPNet.pose, **kw)
    rot_cam = rot6d_to_mat(rot6d)
    hinges = hinge_angles(raw)
    dtype = hinges.dtype
    T = kp.shape[0]
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

    # camera frame -> world: X_c = R X_w + t
    E = jnp.asarray(inputs.extrinsics, dtype)
    R, t = E[:3, :3], E[:3, 3]
    rot_w = jnp.matmul(R.T, rot_cam)  # R^T R_cam
    pos_w = (trans_cam - t) @ R  # R^T (t_cam - t), row-vector form
    q_hat = q_rr.at[:, 0:3].set(pos_w).at[:, 3:7].set(mat_to_quat(rot_w))
    return TargetPose(q_hat, logits, rot_cam, trans_cam, t_ls, p_rr)


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


# ---------------------------------------------------------------------------------------
# the dynamic cycle
# ---------------------------------------------------------------------------------------


@struct.dataclass
class CycleState:
    q: Array  # (nq,)
    qd: Array  # (nv,)
    grf: Array  # (4, 3) previous GRF (GRFNet input, L_smooth)


@struct.dataclass
class StepOutput:
    tau: Array  # (nv,) tau* (joint torques; residual root force/torque in [:6])
    tau_pd: Array  # (nv,) tau of eq. 7 (before contact compensation)
    grf: Array  # (4, 3)
    grf_raw: Array  # (4, 3) GRFNet output before the friction pyramid
    qd_free: Array  # (nv,) velocity before the projection


def pd_error(model: Model, q_hat: Array, q: Array) -> Array:
    """e_PD = d(q_hat, q) in velocity coordinates (nv,): world position error of the root,
    body-frame rotation vector of the quaternion difference, hinge angle differences."""
    e_rot = quat_error(q_hat[3:7], q[3:7])
    return jnp.concatenate([q_hat[0:3] - q[0:3], e_rot, q_hat[7:] - q[7:]])


def kp_initial(model: Model, config: CycleConfig) -> np.ndarray:
    """k_p_ini per dof (1/s^2): root translation, root rotation, joints (docs/method.md)."""
    kp = np.full(model.nv, config.kp_joint)
    kp[:3] = config.kp_root_pos
    kp[3:6] = config.kp_root_rot
    return kp


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


def body_mass(model: Model, dtype=jnp.float32) -> Array:
    """Total mass as a (traceable) array: the model may be a jit argument."""
    return jnp.sum(jnp.asarray(model.body_mass, dtype))


def grfnet_features(model: Model, tau_root, Jc, contact, grf_prev) -> Array:
    weight = body_mass(model, Jc.dtype) * 9.81
    return jnp.concatenate(
        [tau_root / weight, Jc.reshape(-1), jnp.asarray(FLOOR_NORMAL, Jc.dtype), contact, grf_prev.reshape(-1) / weight]
    )


def cycle_step(
    params: dict,
    model: Model,
    state: CycleState,
    q_hat: Array,
    contact_prob: Array,
    dt,
    config: CycleConfig = CycleConfig(),
) -> tuple[CycleState, StepOutput]:
    """One iteration of the dynamic cycle (Sec. 3.4) from ``state`` towards target ``q_hat``."""
    q, qd = state.q, state.qd
    dtype = q.dtype
    if config.physics_backend == "jmocap":
        dyn = P.smooth_dynamics(model, q, qd)
        M, h, Jc, kin = dyn.M, dyn.h, dyn.Jc, dyn.kin
    else:
        M, h, Jc = mjx_smooth_dynamics(model, q, qd, config.physics_backend)
        kin = None  # the projection's constraint rows then come from jmocap's kinematics
    e = pd_error(model, q_hat, q)
    kp0 = jnp.asarray(kp_initial(model, config), dtype)
    kd = 2.0 * config.damping_ratio * jnp.sqrt(kp0)
    if config.use_dynet:
        s_g, s_f = DyNet(nv=model.nv, width=config.nets.dyn_width).apply(
            {"params": params["dynet"]}, dynet_features(model, q_hat, q, qd, M, e)
        )
        kp = 2.0 * s_g * kp0
        alpha = config.nets.gamma * s_f
    else:
        kp, alpha = kp0, jnp.zeros_like(kp0)
    # eq. 7 with the gains in acceleration units: tau = M (k_p e - k_d qd) + alpha + h
    acc_pd = kp * e - kd * qd
    tau = M @ acc_pd + alpha + h

    in_contact = contact_prob > config.contact_threshold
    if config.use_grfnet:
        weight = body_mass(model, dtype) * 9.81
        raw = weight * GRFNet(n_points=4, width=config.nets.grf_width).apply(
            {"params": params["grfnet"]},
            grfnet_features(model, tau[:6], Jc, contact_prob, state.grf),
        )
        grf = project_friction_pyramid(raw, jnp.asarray(FLOOR_NORMAL, dtype), config.mu)
        grf = jnp.where(in_contact[:, None], grf, 0.0)
    else:
        raw = grf = jnp.zeros((4, 3), dtype)
    JtG = Jc.T @ grf.reshape(-1)
    tau_star = tau - JtG  # the contact force compensates the actuation (eq. 13)
    if config.root_residual_limit is not None:
        limit = config.root_residual_limit * body_mass(model, dtype) * 9.81
        tau_star = tau_star.at[:6].set(soft_limit_wrench(tau_star[:6], limit))
    L = P.cholesky(M)
    if config.root_residual_limit is None:
        # eq. 13 with eq. 7 substituted: M qdd = tau* + J^T G lambda - h = M acc_pd + alpha
        # (the contact force only redistributes tau between joints, residual and contacts)
        qdd = acc_pd + P.cho_solve(L, alpha) if config.use_dynet else acc_pd
    else:
        qdd = P.cho_solve(L, tau_star + JtG - h)  # eq. 13
    qd_free = qd + dt * qdd  # eq. 14
    qd_free = jnp.clip(qd_free, -config.max_velocity, config.max_velocity)
    if config.hard_constraint:
        qd_new = P.project_velocity(
            model, q, qd_free, in_contact, dt=dt, metric=config.metric, beta=config.beta,
            chol=L if config.metric == "mass" else None, kin=kin,
        )  # eqs. 15-16, reusing the factor of M
    else:
        qd_new = qd_free
    q_new = P.integrate_positions(model, q, qd_new, dt)  # eqs. 1, 14
    return CycleState(q_new, qd_new, grf), StepOutput(tau_star, tau, grf, raw, qd_free)


def mjx_smooth_dynamics(model: Model, q: Array, qd: Array, backend: str = "mjx"):
    """``(M, h, J_c)`` from MJX's own functions (``CycleConfig(physics_backend="mjx")``).

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


def soft_limit_wrench(wrench: Array, limit) -> Array:
    """Smoothly saturate a root wrench [force (3); torque (3)]: each part is scaled by
    ``1 / sqrt(1 + |part|^2 / limit^2)`` (force limit ``limit`` N, torque limit ``limit`` N m),
    which is the identity for small residuals and tends to ``limit`` in magnitude."""
    f, t = wrench[:3], wrench[3:]

    def sat(x):
        return x / jnp.sqrt(1.0 + jnp.sum(x * x) / (limit * limit))

    return jnp.concatenate([sat(f), sat(t)])


@struct.dataclass
class FrameOutput:
    q: Array
    qd: Array
    tau: Array  # mean tau* over the frame's iterations
    grf: Array  # mean GRF over the frame's iterations
    steps: StepOutput  # every iteration (k, ...), for the losses


def simulate(
    params: dict,
    model: Model,
    q_hat: Array,
    contact_prob: Array,
    mask: Array,
    fps,
    config: CycleConfig = CycleConfig(),
    *,
    init: CycleState | None = None,
    truncate_gradient: bool = False,
) -> tuple[CycleState, FrameOutput]:
    """The dynamic cycle over frames (``lax.scan``), ``k`` iterations per frame.

    ``init`` defaults to the first target pose at rest. Padding frames (mask False) leave the
    state unchanged. ``truncate_gradient`` stops gradients at the state entering each frame
    (truncated backpropagation through time: a frame's losses reach the networks through that
    frame's ``k`` iterations only; training uses it, see docs/method.md).
    """
    dtype = q_hat.dtype
    k = config.iterations
    dt = (1.0 / jnp.asarray(fps, dtype)) / k
    if init is None:
        init = CycleState(q_hat[0], jnp.zeros(model.nv, dtype), jnp.zeros((4, 3), dtype))

    def frame(state, xs):
        target, prob, real = xs
        if truncate_gradient:
            state = jax.lax.stop_gradient(state)

        def iteration(s, _):
            return cycle_step(params, model, s, target, prob, dt, config)

        new, steps = jax.lax.scan(iteration, state, None, length=k)
        new = jax.tree.map(lambda a, b: jnp.where(real, a, b), new, state)
        out = FrameOutput(new.q, new.qd, steps.tau.mean(0), steps.grf.mean(0), steps)
        return new, out

    return jax.lax.scan(frame, init, (q_hat, contact_prob, mask))


def reconstruct(
    params: dict, model: Model, inputs: ClipInputs, config: CycleConfig = CycleConfig()
) -> Motion:
    """2D keypoints of one clip -> physically plausible :class:`Motion` (see the module doc)."""
    tp = target_pose(params, model, inputs, config)
    prob = jax.nn.sigmoid(tp.contact_logits)
    mask = jnp.asarray(inputs.mask)
    if config.kinematic_only:
        qd = finite_difference_velocity(model, tp.q_hat, inputs.fps)
        z = jnp.zeros_like(qd)
        return Motion(tp.q_hat, qd, z, jnp.zeros((*prob.shape, 3), z.dtype), prob, tp.q_hat, mask)
    _, out = simulate(params, model, tp.q_hat, prob, mask, inputs.fps, config)
    return Motion(out.q, out.qd, out.tau, out.grf, prob, tp.q_hat, mask)


def finite_difference_velocity(model: Model, q: Array, fps) -> Array:
    """Backward-difference velocities (T, nv) of a pose sequence (MuJoCo's differentiatePos);
    the first frame gets zero velocity."""
    dt = 1.0 / jnp.asarray(fps, q.dtype)
    q0 = jnp.concatenate([q[:1], q[:-1]])

    def diff(a, b):
        rot = quat_error(b[3:7], a[3:7])  # body-frame rotation from a to b
        return jnp.concatenate([b[0:3] - a[0:3], rot, b[7:] - a[7:]]) / dt

    return jax.vmap(diff)(q0, q)


__all__ = [
    "ClipInputs",
    "CycleConfig",
    "CycleState",
    "TargetPose",
    "causal_windows",
    "cycle_step",
    "default_extrinsics",
    "finite_difference_velocity",
    "init_params",
    "least_squares_translation",
    "pd_error",
    "reconstruct",
    "simulate",
    "target_pose",
]
