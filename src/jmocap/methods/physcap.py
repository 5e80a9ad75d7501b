"""``physcap``: Neural PhysCap's dynamic cycle (Shimada et al. 2021, Sec. 3.4), the paper's method.

TPNet's target pose (:func:`~jmocap.methods.stages.target_pose`), then per frame ``k``
iterations of the cycle with ``dt = 1 / (fps k)``, each composed of the shared stages:

1. rigid-body terms ``M``, ``h``, ``J_c`` at the current state;
2. PD gains: fixed ``k_p_ini`` or DyNet's (``use_dynet``), and the PD control of eq. 7;
3. contact state (``p > contact_threshold``) and GRFNet's forces in the friction pyramid
   (``use_grfnet``), compensating the actuation (eq. 13);
4. forward dynamics (eq. 13), the velocity step (eq. 14) and the hard foot-floor projection
   (eqs. 15-16, ``hard_constraint``);
5. pose integration (eqs. 1, 14).

It is causal (frame t depends on frames <= t only) and runs as ``lax.scan`` over frames; a long
clip runs as chunks with the :class:`CycleState` carried (:func:`reconstruct_chunk`).
See docs/method.md for the choices made where the paper is silent.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from jmocap import physics as P
from jmocap.constants import NUM_CONTACTS
from jmocap.inputs import ClipInputs
from jmocap.methods import stages as S
from jmocap.methods.base import Method, Variant, register, register_variant, static
from jmocap.methods.kinematic import KinematicConfig, history
from jmocap.methods.kinematic import init_params as init_tpnet_params
from jmocap.model import Model
from jmocap.motion import Motion

Array = jnp.ndarray


@struct.dataclass
class PhysCapConfig(KinematicConfig):
    """Structure (static) and physical parameters (traced) of the dynamic cycle.

    The static switches reproduce the paper's ablations and baselines; every float is a traced
    leaf: ``jax.grad`` of a loss through :func:`reconstruct` with respect to the config gives
    the gradient with respect to the gains, friction and recovery factor.
    """

    # --- structure (static) ---
    iterations: int = static(6)  # k, dynamic-cycle iterations per frame (paper: 6)
    use_dynet: bool = static(True)  # False: fixed gains k_p = k_p_ini, alpha = 0 (PhysCap-like)
    use_grfnet: bool = static(True)  # False: no GRF, all root motion from the virtual root force
    hard_constraint: bool = static(True)  # False: no foot-floor projection
    metric: str = static("mass")  # projection metric: "mass" or "identity" (eq. 15)
    # where M, h and J_c come from: "jmocap" (physics.smooth_dynamics) or "mjx" (MJX's own
    # smooth-dynamics functions; a reference and benchmark baseline, slow on CPU)
    physics_backend: str = static("jmocap")
    # --- physical parameters (traced) ---
    beta: float = 0.2  # penetration recovery factor of the projection
    contact_threshold: float = 0.5
    max_velocity: float = 30.0  # |qd| bound (rad/s, m/s) before the projection; keeps states finite
    mu: float = 0.8  # friction coefficient (paper Sec. 3.4.2)
    # soft limit of the residual (virtual) root force, in body weights (the torque limit is the
    # same times 1 m); None applies any residual, as eqs. 7 + 13 literally (the default: a limit
    # makes the M-weighted PD inconsistent and the cycle diverges, see docs/method.md). None is
    # an empty pytree, so switching the limit on or off recompiles; changing its value does not.
    root_residual_limit: float | None = None
    # initial PD gains k_p_ini (1/s^2, acceleration units: see docs/method.md) and damping
    kp_root_pos: float = 1600.0
    kp_root_rot: float = 1600.0
    kp_joint: float = 1600.0
    damping_ratio: float = 1.0


def init_params(key: Array, model: Model, config: PhysCapConfig = PhysCapConfig()) -> dict:
    """Fresh parameters of TPNet, DyNet and GRFNet (a pytree of arrays)."""
    k1, k2, k3 = jax.random.split(key, 3)
    return {
        **init_tpnet_params(k1, model, config),
        "dynet": S.init_dynet(k2, model, config.nets),
        "grfnet": S.init_grfnet(k3, model, config.nets),
    }


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


def kp_initial(model: Model, config: PhysCapConfig, dtype=jnp.float32) -> Array:
    """k_p_ini per dof (1/s^2): root translation, root rotation, joints (docs/method.md)."""
    return S.kp_initial(model, config.kp_root_pos, config.kp_root_rot, config.kp_joint, dtype)


def cycle_step(
    params: dict,
    model: Model,
    state: CycleState,
    q_hat: Array,
    contact_prob: Array,
    dt,
    config: PhysCapConfig = PhysCapConfig(),
) -> tuple[CycleState, StepOutput]:
    """One iteration of the dynamic cycle (Sec. 3.4) from ``state`` towards target ``q_hat``."""
    q, qd = state.q, state.qd
    dtype = q.dtype
    body = S.rigid_body_terms(model, q, qd, config.physics_backend)

    # PD control (eq. 7), with DyNet's or the fixed gains
    e = S.pd_error(model, q_hat, q)
    kp0 = kp_initial(model, config, dtype)
    kd = 2.0 * config.damping_ratio * jnp.sqrt(kp0)
    if config.use_dynet:
        gains = S.dynet_gains(params, model, q_hat, q, qd, body.M, e, kp0, kd, config.nets)
    else:
        gains = S.pd_gains(kp0, kd)
    acc_pd, tau = S.pd_control(e, qd, gains, body.M, body.h)

    # contact state and forces (Sec. 3.4.2), compensating the actuation (eq. 13)
    in_contact = S.contact_state(contact_prob, config.contact_threshold)
    if config.use_grfnet:
        grf, raw = S.grfnet_forces(params, model, tau[:6], body.Jc, contact_prob, in_contact, state.grf,
                                   config.mu, config.nets)
    else:
        raw = grf = jnp.zeros((NUM_CONTACTS, 3), dtype)
    tau_star, JtG = S.contact_compensation(tau, body.Jc, grf)
    if config.root_residual_limit is not None:
        limit = config.root_residual_limit * S.body_weight(model, dtype)
        tau_star = tau_star.at[:6].set(S.soft_limit_wrench(tau_star[:6], limit))

    # forward dynamics (eq. 13) and the velocity step (eq. 14)
    L = P.cholesky(body.M)
    if config.root_residual_limit is None:
        # eq. 13 with eq. 7 substituted: M qdd = tau* + J^T G lambda - h = M acc_pd + alpha
        # (the contact force only redistributes tau between joints, residual and contacts)
        qdd = acc_pd + P.cho_solve(L, gains.alpha) if config.use_dynet else acc_pd
    else:
        qdd = P.cho_solve(L, tau_star + JtG - body.h)  # eq. 13
    qd_free = jnp.clip(qd + dt * qdd, -config.max_velocity, config.max_velocity)

    # the hard foot-floor constraint (eqs. 15-16), reusing the factor of M, then eqs. 1, 14
    if config.hard_constraint:
        qd_new = S.hard_constraint(model, q, qd_free, in_contact, dt, metric=config.metric, beta=config.beta,
                                   chol=L, kin=body.kin)
    else:
        qd_new = qd_free
    q_new = P.integrate_positions(model, q, qd_new, dt)
    return CycleState(q_new, qd_new, grf), StepOutput(tau_star, tau, grf, raw, qd_free)


@struct.dataclass
class FrameOutput:
    q: Array
    qd: Array
    tau: Array  # mean tau* over the frame's iterations
    grf: Array  # mean GRF over the frame's iterations
    steps: StepOutput  # every iteration (k, ...), for the losses


def rest_state(q0: Array, nv: int) -> CycleState:
    """The state at rest at pose ``q0``, no previous force."""
    return CycleState(q0, jnp.zeros(nv, q0.dtype), jnp.zeros((NUM_CONTACTS, 3), q0.dtype))


def simulate(
    params: dict,
    model: Model,
    q_hat: Array,
    contact_prob: Array,
    mask: Array,
    fps,
    config: PhysCapConfig = PhysCapConfig(),
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
        init = rest_state(q_hat[0], model.nv)

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


def reconstruct(params: dict, model: Model, inputs: ClipInputs, config: PhysCapConfig = PhysCapConfig()) -> Motion:
    """2D keypoints of one clip -> physically plausible :class:`Motion` (see the module doc)."""
    tp = S.target_pose(params, model, inputs, config)
    prob = S.contact_probability(tp.contact_logits)
    mask = jnp.asarray(inputs.mask)
    _, out = simulate(params, model, tp.q_hat, prob, mask, inputs.fps, config)
    return Motion(out.q, out.qd, out.tau, out.grf, prob, tp.q_hat, mask)


def init_carry(model: Model, config=None, dtype=jnp.float32) -> CycleState:
    """A zero :class:`CycleState` (the shapes of the state carried between chunks)."""
    return CycleState(jnp.zeros(model.nq, dtype), jnp.zeros(model.nv, dtype), jnp.zeros((NUM_CONTACTS, 3), dtype))


def reconstruct_chunk(params, model: Model, inputs: ClipInputs, carry: CycleState, first, config: PhysCapConfig,
                      history: int) -> tuple[CycleState, Motion]:
    """One chunk of one clip: ``inputs`` holds ``history + L`` frames, the chunk's L frames
    preceded by the ``history`` frames before them. ``carry`` is the state at the end of the
    previous chunk; where ``first`` is True (the clip's first chunk) the state starts at rest at
    the first target pose, as in :func:`reconstruct`."""
    H = history
    tp = S.target_pose(params, model, inputs, config)
    q_hat = tp.q_hat[H:]
    prob = S.contact_probability(tp.contact_logits[H:])
    mask = jnp.asarray(inputs.mask)[H:]
    fresh = CycleState(q_hat[0], jnp.zeros_like(carry.qd), jnp.zeros_like(carry.grf))
    init = jax.tree.map(lambda a, b: jnp.where(first, a, b), fresh, carry)
    state, out = simulate(params, model, q_hat, prob, mask, inputs.fps, config, init=init)
    return state, Motion(out.q, out.qd, out.tau, out.grf, prob, q_hat, mask)


METHOD = register(
    Method(
        name="physcap",
        summary="Neural PhysCap's dynamic cycle: PD control, GRFNet forces, forward dynamics, "
        "hard foot-floor projection (the config decides DyNet or fixed gains)",
        paper="000 (Neural PhysCap), Sec. 3.4",
        config_type=PhysCapConfig,
        reconstruct=reconstruct,
        reconstruct_chunk=reconstruct_chunk,
        init_carry=init_carry,
        history=history,
        init_params=init_params,
    )
)

#: the full pipeline's switches (every stage on); the ablations change one of them
FULL_PIPELINE = dict(use_dynet=True, use_grfnet=True, hard_constraint=True, canonicalise=True)

for _name, _change, _summary in (
    ("physionical", {}, "the full pipeline: DyNet gains, GRFNet, hard constraint, canonicalisation"),
    ("fixed_gains", {"use_dynet": False}, "fixed PD gains k_p_ini instead of DyNet (PhysCap-like)"),
    ("no_grfnet", {"use_grfnet": False}, "no contact forces: all root motion from the residual root force"),
    ("no_hard_constraint", {"hard_constraint": False}, "no foot-floor projection"),
    ("no_canonicalisation", {"canonicalise": False}, "C_T sees K_rr instead of K_c"),
):
    register_variant(Variant(_name, "physcap", {**FULL_PIPELINE, **_change}, _summary))

__all__ = [
    "FULL_PIPELINE",
    "METHOD",
    "CycleState",
    "FrameOutput",
    "PhysCapConfig",
    "StepOutput",
    "cycle_step",
    "init_carry",
    "init_params",
    "kp_initial",
    "reconstruct",
    "reconstruct_chunk",
    "rest_state",
    "simulate",
]
