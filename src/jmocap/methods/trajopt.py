r"""``trajopt``: fit the whole clip to its 2D evidence, then make it obey the equations of motion
(Rempe et al. 2020, "Contact and Human Dynamics from Monocular Video", Sec. 3.1-3.3), offline.

Every frame of the causal methods is decided once, by networks that never look back at the
keypoints. ``trajopt`` instead optimises the trajectory of the whole clip (or of overlapping
windows of it, stitched) against the 2D keypoints through the clip's camera, on jmocap's
character (its bone lengths, joint limits and mass distribution), in two stages:

1. **Kinematic fit** (Rempe et al. Sec. 3.3 / App. B, on jmocap's character): the root
   position, root orientation and hinge angles of every frame minimise

   * a confidence-weighted robust reprojection error (Geman-McClure, in percent of the person's
     height in the image, so one set of weights serves every resolution and distance);
   * a prior towards TPNet's root-relative 3D joints (their ``E_data``: it holds the depth that
     one view cannot see) and joint-limit penalties from the model (a ball joint's three Euler
     angles judged in whichever of its two triples violates them less, :func:`limit_angles`);
   * smoothness: 3D joint accelerations (their ``E_acc``), and in the physics stage the change
     of the root wrench the motion needs from frame to frame (the centre of mass's jerk) and a
     robust prior on the net external force, centred on the net vertical force a network
     estimates from the 2D keypoints (:mod:`jmocap.methods.support`; ``support_prior``): the 2D
     evidence fixes the centre of mass's path only to centimetres, whose 30 fps second
     differences are noise of metres per second squared;
   * contacts (their ``E_cont``, ``E_floor``): a foot point labelled in contact stays still and
     its sole lies on the floor; no sole point is below the floor, labelled or not.

   Labels come from the contact estimator (``contact_source``): by default Rempe et al.'s MLP
   over 2D keypoint windows with jmocap's temporal refiner over its outputs (about a second of
   context on each side; :mod:`jmocap.methods.contact_estimation`), or the MLP's votes alone,
   or TPNet's contact head. As in their App. B.4, labels whose point is far from the floor after a first fit are
   outliers and are dropped before the second fit.

2. **Physics** (Rempe et al. Sec. 3.1 with jmocap's full-body dynamics instead of their
   centroidal model): the trajectory is optimised again, now also penalising the residual root
   wrench of the equations of motion ``M(q) qdd + h(q, qd) = S tau + J_c(q)^T lambda``, with
   ``qd``, ``qdd`` the finite differences of the trajectory (the semi-implicit Euler step of the
   causal methods: ``q_{t+1} = q_t (+) dt qd_{t+1}``). The contact forces are optimised with it,
   by *variable projection*: at every frame, for the current trajectory, the forces are the
   best non-negative combination of the friction-pyramid edges (jmocap's one friction model,
   MuJoCo's pyramidal cone, ``mu = FRICTION_MU``) at the sole points in contact that produce the
   root wrench the motion needs (a 32-variable NNLS, solved by FISTA); zero force elsewhere.
   What the forces cannot produce is the residual, penalised in units of body weight; by
   Danskin's theorem its gradient with respect to the trajectory is that of the residual at
   the optimal forces, so the forces enter the outer problem exactly without being its
   variables (the outer problem stays well conditioned; the constraint ``lambda in cone`` holds
   exactly at every iterate). The kinematic terms stay, plus a pull towards the kinematic fit.

The joint torques are then ``tau = M qdd + h - J_c^T lambda`` (:func:`jmocap.physics.rnea`): the
residual root wrench ``tau[:6]`` is what the optimisation could not remove.

A first stage fits every frame on its own by Levenberg-Marquardt (:func:`per_frame_fit`:
TPNet's pose is far from the evidence, and each frame's small system is solved exactly), each
frame's root depth held towards the clip's depth track (:func:`depth_track`: frames with few
keypoints left cannot fix their own depth) and its labelled feet on the floor (with the camera
known, a foot on the floor fixes the frame's depth); the
whole-clip stages run L-BFGS (optax, zoom line search) in the variables of their block-banded
Gauss-Newton curvature (:func:`banded_preconditioner`: per frame a 47 x 47 block, coupled to the
frames two or three away by the temporal terms, factorised by one scan over the frames;
:func:`kinematic_normal_equations`, :func:`physics_curvature`), or the kinematic stage by
Levenberg-Marquardt on the same normal equations (:func:`gauss_newton`, an option). Every stage has a fixed number of
iterations, so the program is ``jax.jit``-ed once per length bucket; ``jax.vmap`` over clips runs their
optimisations one after another in that program (:func:`fit_clip`); each clip's
convergence report (objective before and after, the terms, gradient norm, residual,
penetration) is part of its result (:attr:`jmocap.motion.Motion.diagnostics`). The result is a
deterministic function of the input. See docs/method.md ("trajopt") for every weight.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from jmocap import physics as P
from jmocap.camera import Camera, project
from jmocap.constants import FRICTION_MU
from jmocap.inputs import ClipInputs
from jmocap.layouts import get_layout
from jmocap.methods import stages as S
from jmocap.methods.base import Method, Variant, register, register_variant, static, whole_clip
from jmocap.methods.kinematic import LEARNED_STAGE_FIELDS, KinematicConfig
from jmocap.methods.kinematic import init_params as init_tpnet_params
from jmocap.model import Model
from jmocap.motion import Motion
from jmocap.physics.linalg import (
    banded_factor,
    banded_inverse_root,
    banded_solve,
    cho_solve,
    cholesky,
    spd_inverse,
)
from jmocap.physics.qp import friction_pyramid_edges
from jmocap.physics.rotations import quat_error, quat_exp, quat_mul, quat_normalize, quat_to_mat
from jmocap.scene import Scene, sdf

Array = jnp.ndarray

CONFIDENT = 0.1  # a keypoint with more confidence than this counts as seen (scales, jitter, frames to fit)


@struct.dataclass
class TrajOptConfig(KinematicConfig):
    """Structure (static) and weights (traced) of ``trajopt``. Every energy is a mean over the
    clip's real frames of squared residuals, each residual divided by its ``*_sigma`` (the size
    of error that costs as much as one unit of the reprojection term)."""

    frame_iterations: int = static(30)  # Levenberg-Marquardt iterations of the per-frame fit
    frame_tile: int = static(64)  # frames per tile of the per-frame fit (per_frame_fit's tile; 0: all at once)
    min_keypoints: int = static(8)  # confident keypoints a frame needs to be fitted on its own
    kinematic_iterations: int = static(30)  # iterations of the whole-clip kinematic fit
    kinematic_solver: str = static("lbfgs")  # its optimiser: "lbfgs" or "gauss_newton" (Levenberg-Marquardt)
    precondition: str = static("banded")  # L-BFGS's variables: "banded" (Gauss-Newton curvature) or "diagonal"
    physics_iterations: int = static(30)  # L-BFGS iterations of the physics stage
    memory: int = static(10)  # L-BFGS history
    # the L-BFGS line search: "zoom" (optax's default, strong Wolfe conditions) or "backtracking"
    # (Armijo, the accepted trial's gradient kept): the same accuracy on the held-out archive,
    # 1.2-1.3x slower (docs/performance.md, section 7, stop 52)
    linesearch: str = static("zoom")
    window: int = static(0)  # frames per window (0: the whole clip is one window)
    overlap: int = static(32)  # frames shared by consecutive windows (cross-faded)
    # "refined" (Rempe's estimator and jmocap's temporal refiner over it), "mlp" (Rempe's voted
    # estimator alone) or "tpnet" (TPNet's head)
    contact_source: str = static("refined")
    # fit on the clip's terrain (its scene: every height above the boxes and the floor) or, False,
    # on the floor z = 0 whatever the clip carries (the ablation trajopt_no_scene)
    use_scene: bool = static(True)
    nnls_iterations: int = static(60)  # FISTA iterations of the per-frame force problem
    # the centre of the centre-of-mass prior (w_com_accel): "learned", the net vertical force
    # jmocap.methods.support estimates from the 2D keypoints, or "standing", one body weight
    # straight up in every frame (until stop 59)
    support_prior: str = static("learned")
    # --- 2D evidence ---
    w_reproj: float = 1.0
    gm_scale: float = 4.0  # Geman-McClure scale, % of person height in the image
    gm_scale_initial: float = 25.0  # the per-frame fit's first (annealed to gm_scale)
    # the reprojection unit is at least this times the clip's measured keypoint jitter
    # (keypoint_jitter_px; 0: off, the default: docs/method.md, "The reprojection unit")
    noise_unit: float = 0.0
    # --- priors ---
    w_pose: float = 4.0  # TPNet's root-relative 3D joints, turned as prior_rotation says (2 before stop 57)
    pose_sigma_m: float = 0.1
    # the prior's joints turned to the fit's each frame (:func:`prior_facing_fit`, since stop 57):
    # "full" by any rotation, so the prior holds the articulation and leaves the body's heading
    # and lean to the 2D evidence, the floor and the smoothness; "yaw" about the vertical only
    # (TPNet's lean kept); "tpnet": not turned (stops 41-56)
    prior_rotation: str = static("full")
    w_limits: float = 10.0
    # the per-frame fit run a second time from TPNet's pose with the arms hanging (ARMS_DOWN_DEG),
    # each frame keeping the start whose fit scores lower (stop 58: TPNet's shoulder angles)
    arm_restart: bool = static(True)
    limit_branches: bool = static(True)  # a ball joint's limits judge the better of its two Euler triples (limit_angles)
    limit_sigma_rad: float = 0.05
    # the per-frame fit's prior on the root's camera depth (log depth) towards the clip's depth
    # track (:func:`depth_track`); it only matters where the frame's own evidence is weak
    w_depth: float = 1.0
    depth_sigma: float = 0.15  # of log depth: 15 %
    depth_model_sigma: float = 0.1  # TPNet's depth error on a fully seen frame (log depth)
    depth_accel_sigma: float = 3.0  # the track's log-depth acceleration (1/s^2)
    min_depth_m: float = 0.3  # a TPNet root nearer the camera than this is no depth evidence
    w_accel: float = 20.0  # 3D joint accelerations
    w_accel_kinematic: float = 2.5  # the kinematic stage's own w_accel (< 0: w_accel; 5 in stop 55)
    accel_sigma: float = 10.0  # m/s^2
    # --- contacts ---
    contact_threshold: float = 0.5
    w_contact_vel: float = 5.0  # labelled points stay still
    contact_vel_sigma: float = 0.05  # m/s
    w_contact_height: float = 2.0  # labelled points' soles on the floor
    contact_height_sigma: float = 0.01  # m
    frame_contacts: bool = static(True)  # labelled soles on the floor in the per-frame fit too
    contact_robust_m: float = 0.05  # its Geman-McClure scale (a label the 2D holds higher: outlier)
    # labels further from the floor after the first fit are dropped: that fit holds labelled feet
    # on the floor with a robust scale of contact_robust_m, so a labelled foot the 2D evidence
    # still holds this high is a wrong label (0.1 before the per-frame contact rows)
    outlier_height_m: float = 0.05
    w_floor: float = 10.0  # every sole point above the floor
    floor_sigma: float = 0.005  # m
    floor_margin_m: float = 0.005  # the floor term acts below this height: the trade-off against
    # smoothness then settles above the floor, not a few millimetres into it
    # --- physics ---
    mu: float = FRICTION_MU
    w_dynamics: float = 20.0  # residual root wrench
    dynamics_sigma: float = 0.05  # body weights (force), body weight x 1 m (torque)
    w_wrench_rate: float = 10.0  # smooth external forces (the root wrench the motion needs)
    wrench_rate_sigma: float = 0.3  # body weights per frame
    # prior on the external force: the centre of mass accelerates as the learned support says
    # (support_prior; 100 until stop 59, when it centred on one body weight)
    w_com_accel: float = 300.0
    com_accel_sigma: float = 0.15  # of |c''| / g, i.e. of the net external force minus the weight, body weights
    com_accel_robust: float = 3.0  # Geman-McClure scale of that residual, in com_accel_sigma (0: quadratic)
    w_stay: float = 30.0  # pull of the physics stage towards the kinematic fit (3 before stop 56)
    stay_sigma_m: float = 0.03
    force_regularisation: float = 1e-3  # of the edge coefficients (body weights): unique forces
    touch_m: float = 0.01  # a sole point this close to the floor may carry force, labelled or not
    touch_in_flight: bool = False  # ... even in a frame the labels call a flight (no site labelled):
    # off, the estimator's flight holds, and a sole the fit brings near the floor cannot carry the
    # body through it (the centre-of-mass prior would have it do so, at about one body weight)


def init_params(key: Array, model: Model, config: TrajOptConfig = TrajOptConfig()) -> dict:  # noqa: B008
    """Fresh parameters: TPNet (the contact estimator ships its own, see
    :mod:`jmocap.methods.contact_estimation`)."""
    return init_tpnet_params(key, model, config)


# ---------------------------------------------------------------------------------------
# the trajectory: variables <-> configurations, finite differences
# ---------------------------------------------------------------------------------------


@struct.dataclass
class Trajectory:
    """The optimisation variables of a clip: root position, a rotation-vector offset of the root
    orientation from ``base`` (held in :class:`Problem`), hinge angles."""

    root_pos: Array  # (T, 3)
    root_rot: Array  # (T, 3)
    hinges: Array  # (T, nh)


def to_q(model: Model, x: Trajectory, base_quat: Array) -> Array:
    """Configurations (T, nq) of the variables."""
    quat = quat_normalize(quat_mul(base_quat, quat_exp(x.root_rot)))
    T = x.root_pos.shape[0]
    q = jnp.zeros((T, model.nq), x.hinges.dtype)
    return q.at[:, 0:3].set(x.root_pos).at[:, 3:7].set(quat).at[:, model.topo.hinge_qadr].set(x.hinges)


def from_q(model: Model, q: Array) -> tuple[Trajectory, Array]:
    """Variables (zero rotation offsets) and base quaternions of configurations (T, nq)."""
    return Trajectory(q[:, 0:3], jnp.zeros_like(q[:, 0:3]), q[:, model.topo.hinge_qadr]), q[:, 3:7]


def frame_velocities(q: Array, fps, length) -> tuple[Array, Array]:
    """``(qd, qdd)`` (T, nv) of a trajectory whose first ``length`` frames are real.

    ``v_t = (q_t (-) q_{t-1}) fps`` (MuJoCo's ``mj_differentiatePos``: world-frame root velocity,
    body-frame angular velocity) is the velocity that the semi-implicit step
    ``q_t = q_{t-1} (+) dt v_t`` reaches q_t with; then ``qdd_t = (v_{t+1} - v_t) fps`` and
    ``qd_t = (v_t + v_{t+1}) / 2`` (second order). The first and last real frames take their
    neighbour's acceleration; frames past ``length`` repeat the last real one.
    """
    T = q.shape[0]
    dt = 1.0 / fps

    def diff(a, b):
        return jnp.concatenate([b[0:3] - a[0:3], quat_error(b[3:7], a[3:7]), b[7:] - a[7:]]) / dt

    v = jax.vmap(diff)(jnp.concatenate([q[:1], q[:-1]]), q)  # v[0] = 0, unused
    t = jnp.arange(T)
    last = jnp.maximum(length - 1, 1)
    a = jnp.clip(t, 1, jnp.maximum(last - 1, 1))  # acceleration between v[a] and v[a + 1]
    qdd = (v[jnp.minimum(a + 1, last)] - v[a]) / dt
    qd = 0.5 * (v[jnp.clip(t, 1, last)] + v[jnp.clip(t + 1, 1, last)])
    return qd, qdd


# ---------------------------------------------------------------------------------------
# the clip's data
# ---------------------------------------------------------------------------------------


@struct.dataclass
class Problem:
    """What the energies of one clip read (all arrays; a batch adds a leading axis)."""

    keypoints: Array  # (T, J, 3) pixels and confidence
    intrinsics: Array
    extrinsics: Array  # (T, 4, 4) world -> camera of every frame (a static camera repeated)
    unit_px: Array  # () one percent of the person's height in the image, pixels
    fps: Array
    mask: Array  # (T,) bool
    length: Array  # () number of real frames (a prefix)
    base_quat: Array  # (T, 4)
    prior_rr: Array  # (T, J, 3) TPNet's root-relative joints (world orientation)
    contacts: Array  # (T, 4) contact labels in {0, 1}
    anchor_kp: Array  # (T, J, 3) joints of the kinematic fit (the physics stage's anchor)
    scene: Scene | None = None  # the terrain (jmocap.scene); None or no boxes: the floor z = 0
    supported: Array | None = None  # (T,) the estimator labelled some site (before the outlier
    # test); None: any of ``contacts``
    support: Array | None = None  # (T,) net vertical force the centre-of-mass prior centres on,
    # body weights (config.support_prior "learned"); None: one body weight


def is_flat(scene: Scene | None) -> bool:
    """Whether a scene is the floor alone (None, or no boxes): static, from its shape."""
    return scene is None or scene.centers.shape[-2] == 0


def surface_heights(scene: Scene | None, points: Array) -> Array:
    """Heights (...,) of points (..., 3) above the terrain: their signed distance to the scene
    (:func:`jmocap.scene.sdf`: the floor and the boxes), ``z`` without a scene (or without boxes,
    static). Every floor and contact term of the method measures heights with it."""
    if is_flat(scene):
        return points[..., 2]
    return sdf(scene, points)


def surface_heights_and_normals(scene: Scene | None, points: Array) -> tuple[Array, Array]:
    """:func:`surface_heights` of points (P, 3) and their gradients (P, 3) (the unit normal of
    the nearest surface; ``z`` without boxes)."""
    if is_flat(scene):
        return points[..., 2], jnp.zeros_like(points).at[..., 2].set(1.0)
    return jax.vmap(jax.value_and_grad(lambda p: sdf(scene, p)))(points)


def _vertical_extent(keypoints: Array, mask: Array) -> Array:
    """(T,) the vertical extent of each frame's confident keypoints (pixels); NaN where the
    frame is not real or has fewer than two."""
    kp = jnp.asarray(keypoints)
    ok = kp[..., 2] > CONFIDENT
    v = kp[..., 1]
    ext = jnp.max(jnp.where(ok, v, -jnp.inf), -1) - jnp.min(jnp.where(ok, v, jnp.inf), -1)
    return jnp.where(mask & (jnp.sum(ok, -1) >= 2), ext, jnp.nan)


def person_height_px(keypoints: Array, mask: Array) -> Array:
    """The median over real frames of the vertical extent of the confident keypoints (pixels),
    at least 20 px."""
    ext = _vertical_extent(keypoints, mask)
    return jnp.maximum(jnp.nan_to_num(jnp.nanmedian(ext), nan=200.0), 20.0)


def keypoint_jitter_px(keypoints: Array, mask: Array) -> Array:
    """The clip's frame-to-frame keypoint noise, pixels: the standard deviation that white noise
    would need to make the median absolute second difference of the confident keypoints over
    real frames (``|k_{t+1} - 2 k_t + k_{t-1}|``, per coordinate; a body's own motion adds
    little to it at video rates) what it is: ``median / (0.6745 sqrt(6))``. 0 without any."""
    kp = jnp.asarray(keypoints)
    ok = (kp[..., 2] > CONFIDENT) & mask[:, None]
    ok3 = ok[2:] & ok[1:-1] & ok[:-2]
    d2 = jnp.abs(kp[2:, :, :2] - 2 * kp[1:-1, :, :2] + kp[:-2, :, :2])
    med = jnp.nanmedian(jnp.where(ok3[..., None], d2, jnp.nan))
    return jnp.nan_to_num(med, nan=0.0) / (0.6745 * np.sqrt(6.0))


def person_height_px_causal(keypoints: Array, mask: Array, frames: int) -> Array:
    """(T,) per frame, the median of :func:`person_height_px`'s per-frame extents over the frame
    and the ``frames`` real frames before it (at least 20 px; 200 px without any): a local,
    causal image scale, so that a chunked run (``pip``) sees the same value as a whole-clip one."""
    ext = _vertical_extent(keypoints, mask)
    T = ext.shape[0]
    idx = jnp.arange(T)[:, None] - jnp.arange(frames + 1)[None, :]
    win = jnp.where(idx >= 0, ext[jnp.clip(idx, 0, T - 1)], jnp.nan)
    return jnp.maximum(jnp.nan_to_num(jnp.nanmedian(win, axis=1), nan=200.0), 20.0)


# ---------------------------------------------------------------------------------------
# energies
# ---------------------------------------------------------------------------------------


def root_depth(q: Array, extrinsics: Array) -> Array:
    """(T,) the root's depth in the camera frame (m): the third row of ``[R t] (x, 1)``, with
    one camera (4, 4) or one per frame (T, 4, 4)."""
    E = jnp.asarray(extrinsics, q.dtype)
    return jnp.sum(q[:, :3] * E[..., 2, :3], -1) + E[..., 2, 3]


def to_depth(q: Array, extrinsics: Array, depth: Array) -> Array:
    """Poses (T, nq) moved along the camera rays through their roots so that the roots' camera
    depths are ``depth`` (T,): the root's image point stays; frames whose root is behind or at
    the camera (no such ray) move straight along the optical axis instead."""
    E = jnp.asarray(extrinsics, q.dtype)
    R, t = E[..., :3, :3], E[..., :3, 3]
    xc = jnp.einsum("...ij,...j->...i", R, q[:, :3]) + t
    z = xc[:, 2:3]
    ok = z > 1e-3
    moved = jnp.where(ok, xc * depth[:, None] / jnp.where(ok, z, 1.0), xc.at[:, 2].set(depth))
    return q.at[:, :3].set(jnp.einsum("...ji,...j->...i", R, moved - t))


def _rts_smooth(y: Array, r: Array, accel: Array) -> Array:
    """Rauch-Tung-Striebel smoother of a scalar series ``y`` (T,) measured with variances ``r``
    (T,; ``inf`` where unmeasured) under a constant-velocity model whose acceleration is white
    with standard deviation ``accel`` per frame^2 (``s_{t+1} = F s_t + (1/2, 1) a_t``), from a
    broad prior on the first state: the posterior mean of the positions, which is the batch
    least-squares solution of that model (tested), in O(T). A roughness penalty on the second
    differences, in other words, with gaps bridged and the ends extrapolated linearly."""
    dtype = y.dtype
    F = jnp.asarray([[1.0, 1.0], [0.0, 1.0]], dtype)
    Q = accel**2 * jnp.asarray([[0.25, 0.5], [0.5, 1.0]], dtype)
    seen = jnp.isfinite(r)
    w = jnp.where(seen, 1.0 / jnp.where(seen, r, 1.0), 0.0)
    x0 = jnp.stack([jnp.sum(w * jnp.where(seen, y, 0.0)) / jnp.maximum(jnp.sum(w), 1e-12), jnp.zeros((), dtype)])
    P0 = jnp.diag(jnp.asarray([1e2, 1.0], dtype))

    def forward(carry, obs):
        x, P = carry
        yt, rt, st = obs
        x, P = F @ x, F @ P @ F.T + Q  # predict
        k = P[:, 0] / (P[0, 0] + jnp.where(st, rt, 1.0))
        x_u = x + k * (yt - x[0])
        P_u = P - jnp.outer(k, P[0, :])
        x, P = jnp.where(st, x_u, x), jnp.where(st, 0.5 * (P_u + P_u.T), P)
        return (x, P), (x, P)

    # the first frame's prior is the prediction from (x0, P0): F x0 = x0 (its velocity is 0), and
    # the covariance F P0 F^T + Q is broad
    (_, _), (xs, Ps) = jax.lax.scan(forward, (x0, P0), (y, r, seen))

    def backward(nxt, cur):
        xn, Pn = nxt
        x, P = cur
        Pp = F @ P @ F.T + Q
        C = cho_solve(cholesky(Pp), F @ P).T  # P F^T Pp^-1 (P, Pp symmetric)
        xs_ = x + C @ (xn - F @ x)
        Ps_ = P + C @ (Pn - Pp) @ C.T
        return (xs_, Ps_), xs_[0]

    _, smooth = jax.lax.scan(backward, (xs[-1], Ps[-1]), (xs[:-1], Ps[:-1]), reverse=True)
    return jnp.concatenate([smooth, xs[-1:, 0]])


def depth_track(q: Array, prob: Problem, config: TrajOptConfig, passes: int = 5) -> Array:
    """(T,) the clip's root depth track, in log depth: the starting poses' root depths (TPNet's)
    smoothed over time, each frame weighted by how much evidence it has.

    One view fixes a person's depth only through the size of their image, and TPNet's
    translation is a per-frame estimate: where most of the body has left the image it can put
    the root anywhere, behind the camera included, and a per-frame fit of the few keypoints
    left can too (a run towards the camera ended 0.1 m from it instead of 2 m). The track
    carries the depth of the well-seen frames across those: each frame's log depth is measured
    with variance ``depth_model_sigma^2 (J / n)^2`` (``n`` the confidence-weighted count of its
    ``J`` keypoints: TPNet's depth degrades faster than the count as the body leaves the image)
    plus ``u^2 / S`` (``u`` 1 % of the person's image height, ``S`` the confidence-weighted
    spread of the keypoints about their mean, pixels^2: the precision of a scale measured from
    them), not at all where the root is nearer than ``min_depth_m`` or the frame is padding, and
    smoothed by :func:`_rts_smooth` with ``depth_accel_sigma``; then ``passes - 1`` times
    reweighted (Geman-McClure weights at 2.5 standard deviations) so that frames far off the
    track stop pulling it. A prior built from the data: no gradient flows through it."""
    q, prob = jax.lax.stop_gradient((q, prob))
    z = root_depth(q, prob.extrinsics)
    conf = prob.keypoints[..., 2] * prob.mask[:, None]
    uv = prob.keypoints[..., :2]
    n = jnp.sum(conf, -1)
    mean = jnp.sum(conf[..., None] * uv, 1) / jnp.maximum(n, 1e-6)[:, None]
    spread = jnp.sum(conf * jnp.sum((uv - mean[:, None]) ** 2, -1), -1)
    J = conf.shape[-1]
    var = config.depth_model_sigma**2 * (J / jnp.maximum(n, 1e-6)) ** 2 + prob.unit_px**2 / jnp.maximum(spread, 1e-6)
    ok = prob.mask & (z > config.min_depth_m) & (n >= 1.0)
    y = jnp.log(jnp.maximum(z, config.min_depth_m))
    var = jnp.where(ok, var, jnp.inf)
    accel = config.depth_accel_sigma / prob.fps**2
    track = _rts_smooth(y, var, accel)
    for _ in range(passes - 1):
        e2 = (y - track) ** 2 / jnp.where(ok, var, 1.0)
        track = _rts_smooth(y, var * (1.0 + e2 / 2.5**2) ** 2, accel)
    return track


def _frames_mean(x: Array, w: Array) -> Array:
    return jnp.sum(x * w) / jnp.maximum(jnp.sum(w), 1.0)


def ball_triples(model: Model) -> np.ndarray:
    """(K, 3) positions in the hinge list (``model.topo.hinge_qadr``) of the joints that are a
    ball joint written as three Euler angles: a body's three hinges about mutually orthogonal
    axes through one point, in the order they compose (hips, ankles, spine, neck and shoulders
    of jmocap's humanoid). Static: read from the MuJoCo model at trace time."""
    mj = model.mj
    where = {int(a): i for i, a in enumerate(np.asarray(model.topo.hinge_qadr))}
    by_body: dict[int, list[int]] = {}
    for j in range(mj.njnt):
        if int(mj.jnt_type[j]) == 3:  # mjJNT_HINGE
            by_body.setdefault(int(mj.jnt_bodyid[j]), []).append(j)
    out = []
    for js in by_body.values():
        if len(js) != 3:
            continue
        axes = np.asarray(mj.jnt_axis[js], float)
        axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
        if np.abs(axes @ axes.T - np.eye(3)).max() < 1e-9 and np.ptp(np.asarray(mj.jnt_pos[js]), 0).max() < 1e-12:
            out.append([where[int(mj.jnt_qposadr[j])] for j in js])
    return np.asarray(out, int).reshape(-1, 3)


def _wrap(x: Array) -> Array:
    """Angles taken within pi of 0."""
    return x - 2 * jnp.pi * jnp.round(x / (2 * jnp.pi))


def _other_triple(a: Array) -> Array:
    """A ball joint's other Euler triple (..., 3) of the same rotation: ``(a + pi, pi - b, c + pi)``."""
    return jnp.stack([a[..., 0] + jnp.pi, jnp.pi - a[..., 1], a[..., 2] + jnp.pi], -1)


def limit_angles(model: Model, h: Array, config: TrajOptConfig) -> tuple[Array, Array]:
    """The hinge angles (..., H) the joint limits judge, and the derivative (..., H) (+-1) of each
    in the hinge's own angle. A ball joint's Euler angles ``(a, b, c)`` about orthogonal axes
    ``u, v, w`` and ``(a + pi, pi - b, c + pi)`` (mod 2 pi) are the same rotation
    (``R_u(pi) R_v(pi - b) R_w(pi) = R_v(b)``), so with ``config.limit_branches`` each ball
    joint (:func:`ball_triples`) is judged in the triple, each angle taken within pi of 0,
    that violates its limits less (the choice held by a gradient stop; the current one on a
    tie). A pose its limits allow in either triple is then allowed, and a fit started in
    TPNet's triple can reach the other (a raised arm: docs/method.md, stop 58). Without it,
    the angles as they are."""
    sign = jnp.ones_like(h)
    tri = ball_triples(model)
    if not config.limit_branches or tri.size == 0:
        return h, sign
    lo = jnp.asarray(model.q_lower, h.dtype)[model.topo.hinge_qadr][tri]
    hi = jnp.asarray(model.q_upper, h.dtype)[model.topo.hinge_qadr][tri]
    a = h[..., tri]  # (..., K, 3)
    a, other = _wrap(a), _wrap(_other_triple(a))

    def violation(x):
        return jnp.sum(jax.nn.relu(lo - x) ** 2 + jax.nn.relu(x - hi) ** 2, -1)

    use = jax.lax.stop_gradient(violation(other) < violation(a))  # (..., K)
    chosen = jnp.where(use[..., None], other, a)
    h = h.at[..., tri.ravel()].set(chosen.reshape(*chosen.shape[:-2], -1))
    sign = sign.at[..., tri[:, 1]].set(jnp.where(use, -1.0, 1.0).astype(h.dtype))
    return h, sign


def continuous_hinges(model: Model, q: Array, config: TrajOptConfig) -> Array:
    """A trajectory ``q`` (T, nq) with each ball joint (:func:`ball_triples`) written, frame by
    frame, in the Euler triple nearest the previous frame's, and each angle within pi of it;
    the first frame in the triple :func:`limit_angles` judges. The same poses; what changes is
    that the angles are continuous where the rotation is, so finite differences of ``q`` (the
    physics stage's velocities) are the joints' motion, where the per-frame fit, free to reach
    either triple (:func:`limit_angles`), can leave neighbouring frames in different ones."""
    tri = ball_triples(model)
    if not config.limit_branches or tri.size == 0:
        return q
    hq = np.asarray(model.topo.hinge_qadr)
    cols = hq[tri]  # (K, 3) q addresses
    a = q[:, cols]  # (T, K, 3)
    first = limit_angles(model, q[0, hq], config)[0][tri]

    def step(prev, x):
        x, other = prev + _wrap(x - prev), prev + _wrap(_other_triple(x) - prev)
        use = jnp.sum((other - prev) ** 2, -1) < jnp.sum((x - prev) ** 2, -1)
        out = jnp.where(use[..., None], other, x)
        return out, out

    _, rest = jax.lax.scan(step, first, a[1:])
    a = jnp.concatenate([first[None], rest], 0)
    return q.at[:, cols.ravel()].set(a.reshape(q.shape[0], -1))


def geman_mcclure(r2: Array, c: Array) -> Array:
    """Geman-McClure robust cost of squared residuals: ``c^2 r^2 / (c^2 + r^2)`` (~ r^2 near 0,
    bounded by c^2)."""
    c2 = c * c
    return c2 * r2 / (c2 + r2)


# The ten entries (i <= j) of a symmetric 4x4 matrix, in the order :func:`_best_rotation` keeps them.
_SYM4 = ((0, 0), (0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3))
_SYM4_AT = {ij: k for k, ij in enumerate(_SYM4)} | {(j, i): k for k, (i, j) in enumerate(_SYM4)}


def _best_rotation(rr: Array, p: Array) -> Array:
    """The rotation ``R`` (..., 3, 3) minimising ``sum_j |rr_j - R p_j|^2`` over proper rotations
    (Horn 1987): the unit quaternion of the largest eigenvalue of the symmetric 4x4 ``N`` of
    ``S = sum_j p_j rr_j^T``. The eigenvector by repeated squaring of ``N + c I`` (``c`` = the
    bound ``sqrt(3) |S|_F`` on the eigenvalues' magnitude, so the shifted matrix is positive
    semi-definite and its largest eigenvalue dominates), normalised at each of 16 squarings,
    then its largest column: no LAPACK call (a batched one can deadlock XLA's CPU pool,
    :mod:`jmocap.physics.linalg`), and always a proper rotation, where the polar factor of ``S``
    can be a reflection.

    The squarings work on the ten distinct entries of the symmetric matrix, each an array over
    the batch, written out as products: XLA fuses them into one loop over the frames, where a
    batched 4x4 ``matmul`` is a small-matrix call per frame (6x slower on the CPU at 64 clips of
    300 frames; docs/performance.md). 16 squarings raise the eigenvalue ratio to the 65,536th
    power: on body-like point sets 10 reach 1e-8 in the quaternion (worst of 20,000)."""
    S = jnp.einsum("...ja,...jb->...ab", p, rr)
    xx, xy, xz = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    yx, yy, yz = S[..., 1, 0], S[..., 1, 1], S[..., 1, 2]
    zx, zy, zz = S[..., 2, 0], S[..., 2, 1], S[..., 2, 2]
    c = jnp.sqrt(3.0) * jnp.sqrt(jnp.sum(S * S, (-1, -2))) + 1e-12
    m = jnp.stack([xx + yy + zz + c, yz - zy, zx - xz, xy - yx,  # row 0 of N + c I
                   xx - yy - zz + c, xy + yx, zx + xz,  # row 1 from the diagonal
                   -xx + yy - zz + c, yz + zy,
                   -xx - yy + zz + c]) / c

    def square(_, m):
        m2 = jnp.stack([sum(m[_SYM4_AT[i, k]] * m[_SYM4_AT[k, j]] for k in range(4)) for i, j in _SYM4])
        norm2 = sum((1.0 if i == j else 2.0) * m2[k] ** 2 for k, (i, j) in enumerate(_SYM4))
        return m2 / jnp.sqrt(norm2)

    m = jax.lax.fori_loop(0, 16, square, m)
    M = jnp.stack([jnp.stack([m[_SYM4_AT[i, j]] for j in range(4)], -1) for i in range(4)], -2)
    cols = jnp.sum(M * M, -2)  # (..., 4): squared norms of the columns of ~ v v^T
    v = jnp.take_along_axis(M, jnp.argmax(cols, -1)[..., None, None], -1)[..., 0]
    v = v / jnp.sqrt(jnp.sum(v * v, -1, keepdims=True))
    return quat_to_mat(v)


def prior_facing_fit(rr: Array, prior_rr: Array, config: TrajOptConfig) -> Array:
    """The pose prior's root-relative joints ``prior_rr`` (..., J, 3) turned by the rotation that
    brings them closest to the fit's ``rr`` (least squares), as ``prior_rotation`` says: "yaw",
    about the world's vertical (closed form: ``atan2(sum r_y p_x - r_x p_y, sum r_x p_x + r_y
    p_y)``); "full", any rotation (:func:`_best_rotation`); "tpnet", none.

    A gradient stop holds the rotation. That is exact for the gradient of the energy the prior
    then is, ``min_R |rr - R prior_rr|^2`` (the envelope theorem: at the minimising rotation the
    energy's derivative in it is zero), and for its value, not for its second derivatives: the
    Gauss-Newton rows built from it hold the turn, and so overstate the curvature of a turn of
    the whole body, which this energy does not resist (measured better than rows with the turn
    taken out: docs/method.md, stop 57)."""
    if config.prior_rotation == "tpnet":
        return prior_rr
    rr, p = jax.lax.stop_gradient((rr, prior_rr))
    if config.prior_rotation == "yaw":
        num = jnp.sum(rr[..., 1] * p[..., 0] - rr[..., 0] * p[..., 1], -1)
        den = jnp.sum(rr[..., 0] * p[..., 0] + rr[..., 1] * p[..., 1], -1)
        phi = jnp.arctan2(num, den)[..., None]
        c, s = jnp.cos(phi), jnp.sin(phi)
        return jnp.stack([c * p[..., 0] - s * p[..., 1], s * p[..., 0] + c * p[..., 1], p[..., 2]], -1)
    if config.prior_rotation == "full":
        return jnp.einsum("...ab,...jb->...ja", _best_rotation(rr, p), p)
    raise ValueError(f"prior_rotation must be 'tpnet', 'yaw' or 'full', got {config.prior_rotation!r}")


def kinematic_terms(model: Model, q: Array, geo: FrameGeometry, prob: Problem, config: TrajOptConfig,
                    gm_scale) -> dict[str, Array]:
    """The kinematic energies of a trajectory (see the module docstring), each a frame mean."""
    layout = get_layout(config.layout)
    m = prob.mask.astype(q.dtype)
    cam = Camera(prob.intrinsics, jnp.zeros(2, q.dtype), prob.extrinsics)  # frame t seen by camera t
    uv = project(cam, geo.keypoints3d)
    conf = prob.keypoints[..., 2]
    r2 = jnp.sum((uv - prob.keypoints[..., :2]) ** 2, -1) / prob.unit_px**2
    reproj = jnp.sum(conf * geman_mcclure(r2, gm_scale), -1)

    root = jnp.mean(geo.keypoints3d[:, np.asarray(layout.root_indices)], 1, keepdims=True)
    rr = geo.keypoints3d - root
    pose = jnp.sum((rr - prior_facing_fit(rr, prob.prior_rr, config)) ** 2, (-1, -2)) / config.pose_sigma_m**2

    h, _ = limit_angles(model, q[:, model.topo.hinge_qadr], config)
    lo = jnp.asarray(model.q_lower, q.dtype)[model.topo.hinge_qadr]
    hi = jnp.asarray(model.q_upper, q.dtype)[model.topo.hinge_qadr]
    limits = jnp.sum(jax.nn.relu(lo - h) ** 2 + jax.nn.relu(h - hi) ** 2, -1) / config.limit_sigma_rad**2

    # accelerations of the 3D joints at interior frames whose neighbours are real
    x = geo.keypoints3d
    acc = (x[2:] - 2 * x[1:-1] + x[:-2]) * prob.fps**2
    m3 = m[2:] * m[1:-1] * m[:-2]
    accel = jnp.sum(acc**2, (-1, -2)) / config.accel_sigma**2

    # contacts: a labelled site's pair of sole points on the floor (the terrain) and still
    sole = geo.sole.reshape(q.shape[0], 4, 2, 3)
    if is_flat(prob.scene):  # the floor: z
        sole_h, pair_h = geo.sole[..., 2], sole[..., 2]
    else:
        sole_h = surface_heights(prob.scene, geo.sole)  # (T, 8)
        pair_h = sole_h.reshape(q.shape[0], 4, 2)
    c = prob.contacts.astype(q.dtype)
    height = jnp.sum(c * jnp.sum(pair_h**2, -1), -1) / config.contact_height_sigma**2
    step = jnp.sum((sole[1:] - sole[:-1]) ** 2, (-1, -2)) * prob.fps**2  # (T-1, 4)
    still = jnp.sum(c[1:] * c[:-1] * step, -1) / config.contact_vel_sigma**2
    floor = jnp.sum(jax.nn.relu(config.floor_margin_m - sole_h) ** 2, -1) / config.floor_sigma**2

    return dict(
        reproj=_frames_mean(reproj, m),
        pose=_frames_mean(pose, m),
        limits=_frames_mean(limits, m),
        accel=_frames_mean(accel, m3),
        contact_height=_frames_mean(height, m),
        contact_still=_frames_mean(still, m[1:] * m[:-1]),
        floor=_frames_mean(floor, m),
    )


# ---------------------------------------------------------------------------------------
# the physics: root wrench, contact forces by variable projection
# ---------------------------------------------------------------------------------------


def nnls(H: Array, g: Array, iterations: int) -> Array:
    """``argmin_{c >= 0} 1/2 c^T H c - g^T c`` (H symmetric positive definite) by FISTA with the
    Gershgorin bound of H's largest eigenvalue as the Lipschitz constant; from c = 0."""
    L = jnp.max(jnp.sum(jnp.abs(H), -1))
    step = 1.0 / jnp.maximum(L, 1e-12)

    def body(_, s):
        c, y, t = s
        c_new = jax.nn.relu(y - step * (H @ y - g))
        t_new = 0.5 * (1.0 + jnp.sqrt(1.0 + 4.0 * t * t))
        y = c_new + ((t - 1.0) / t_new) * (c_new - c)
        return c_new, y, t_new

    z = jnp.zeros_like(g)
    c, _, _ = jax.lax.fori_loop(0, iterations, body, (z, z, jnp.ones((), g.dtype)))
    return c


@struct.dataclass
class FrameDynamics:
    residual: Array  # (6,) root wrench the contact forces cannot produce, body weights (scaled)
    need: Array  # (6,) root wrench the motion needs, body weights (scaled)
    coeff: Array  # (8, 4) edge coefficients, body weights
    wrench: Array  # (nv,) M qdd + h
    Jt: Array  # (nv, 8, 3) contact Jacobians, transposed
    points: Array  # (8, 3) sole points


def frame_dynamics(model: Model, kin, q: Array, qd: Array, qdd: Array, allowed: Array, config: TrajOptConfig,
                   edges: Array, scene: Scene | None = None, may_touch: Array | bool = True) -> FrameDynamics:
    """One frame's root-wrench residual after the best contact forces (variable projection):
    forces only at ``allowed`` sole points (8,) bool (those of labelled sites) and, where
    ``may_touch`` (a frame the labels do not call a flight, :func:`dynamics_inputs`), at any within
    ``config.touch_m`` of the floor or the ``scene``'s terrain (:func:`surface_heights`; its
    current height, a constant of the step), each a non-negative combination of the
    pyramid edges ``edges`` (4, 3). Units: the force rows in body weights, the torque rows in
    body weight x 1 m."""
    pts, bodies, _ = S.sole_points(model, kin)
    wrench = P.rnea(model, q, qd, qdd, kin=kin)
    jacp, _ = P.point_jacobian(model, kin, pts, bodies)  # (8, 3, nv)
    weight = S.body_weight(model, q.dtype)
    # generalised root force of a unit body-weight force along each edge at each point
    A = jnp.einsum("pkv,ek->vpe", jacp[..., :6], edges)[:6] * weight  # (6, 8, 4)
    touching = jax.lax.stop_gradient(surface_heights(scene, pts)) < config.touch_m
    touching = touching & may_touch
    allowed = allowed | touching  # touching: may push too
    A = A * allowed[None, :, None]
    A = A.reshape(6, -1) / weight
    b = wrench[:6] / weight
    H = A.T @ A + config.force_regularisation * jnp.eye(A.shape[1], dtype=A.dtype)
    c = jax.lax.stop_gradient(nnls(jax.lax.stop_gradient(H), jax.lax.stop_gradient(A.T @ b), config.nnls_iterations))
    residual = A @ c - b
    return FrameDynamics(residual, b, c.reshape(8, 4), wrench, jnp.transpose(jacp, (2, 0, 1)), pts)


@struct.dataclass
class FrameGeometry:
    keypoints3d: Array  # (T, J, 3)
    sole: Array  # (T, 8, 3)
    dynamics: FrameDynamics | None = None


def geometry(model: Model, q: Array, layout: str, *, dynamics=None) -> FrameGeometry:
    """Per frame, from one forward-kinematics pass: the layout's joints, the sole points and,
    with ``dynamics = (qd, qdd, allowed, may_touch, config, scene)`` (:func:`dynamics_inputs`),
    the frame's dynamics (:func:`frame_dynamics`)."""
    if dynamics is None:
        def one(qt):
            kin = P.forward_kinematics(model, qt)
            pts, _, _ = S.sole_points(model, kin)
            return P.keypoints(model, qt, layout, kin=kin), pts

        kp, sole = jax.vmap(one)(q)
        return FrameGeometry(kp, sole)
    qd, qdd, allowed, may_touch, config, scene = dynamics
    edges = friction_pyramid_edges(jnp.asarray([0.0, 0.0, 1.0], q.dtype), config.mu)

    def one_dyn(qt, v, a, ok, touch):
        kin = P.forward_kinematics(model, qt)
        return P.keypoints(model, qt, layout, kin=kin), frame_dynamics(model, kin, qt, v, a, ok, config, edges, scene,
                                                                       touch)

    kp, fd = jax.vmap(one_dyn)(q, qd, qdd, allowed, may_touch)
    return FrameGeometry(kp, fd.points, fd)


def dynamics_inputs(model: Model, q: Array, prob: Problem, config: TrajOptConfig):
    """``(qd, qdd, labelled, may_touch, config, scene)`` for :func:`geometry`: the finite
    differences, the sole points (T, 8) of labelled sites, and the frames (T,) where a sole
    touching the floor or the problem's terrain may push too (:func:`frame_dynamics`): those the
    estimator did not call a flight (``prob.supported``: some site labelled before the outlier
    test, whose removed labels touching soles stand in for), every frame with
    ``config.touch_in_flight``."""
    qd, qdd = frame_velocities(q, prob.fps, prob.length)
    supported = jnp.any(prob.contacts > 0.5, -1) if prob.supported is None else prob.supported
    may_touch = supported | jnp.asarray(config.touch_in_flight, bool)
    return qd, qdd, jnp.repeat(prob.contacts > 0.5, 2, axis=-1), may_touch, config, prob.scene


def dynamics_term(fd: FrameDynamics, prob: Problem, config: TrajOptConfig) -> Array:
    r2 = jnp.sum(fd.residual**2, -1) / config.dynamics_sigma**2
    return _frames_mean(r2, prob.mask.astype(r2.dtype))


def wrench_rate_term(fd: FrameDynamics, prob: Problem, config: TrajOptConfig) -> Array:
    """Change of the root wrench the motion needs from frame to frame (body weights per frame):
    the external forces of a body change smoothly (the centre of mass's jerk), where finite
    differences of a trajectory fitted to noisy keypoints do not."""
    d = jnp.sum((fd.need[1:] - fd.need[:-1]) ** 2, -1) / config.wrench_rate_sigma**2
    m = prob.mask.astype(d.dtype)
    return _frames_mean(d, m[1:] * m[:-1])


def com_accel_residual(fd: FrameDynamics, prob: Problem) -> Array:
    """(T, 3) net external force the motion needs minus the prior's centre, body weights: one
    body weight straight up, or where ``prob.support`` is given (the learned support prior,
    :mod:`jmocap.methods.support`), that vertical force."""
    up = 1.0 if prob.support is None else prob.support
    return fd.need[:, :3].at[:, 2].add(-up)


def com_accel_term(fd: FrameDynamics, prob: Problem, config: TrajOptConfig) -> Array:
    """Prior on the net external force the motion needs (body weights): ``need[:3] - (0, 0, s)``
    with ``s`` the learned support (:func:`com_accel_residual`), or ``need[:3] - (0, 0, 1) = c''
    / g``, the centre of mass's acceleration, without it. The 2D evidence fixes the centre of
    mass's path only to centimetres, and finite differences of that at 30 fps are accelerations
    of metres per second squared, which the full-body dynamics can always balance (limb motion
    absorbs the torque): without a prior the estimated horizontal forces are noise."""
    f = com_accel_residual(fd, prob)
    r2 = jnp.sum(f**2, -1) / config.com_accel_sigma**2
    r2 = jnp.where(config.com_accel_robust > 0, geman_mcclure(r2, config.com_accel_robust), r2)
    return _frames_mean(r2, prob.mask.astype(r2.dtype))


def stay_term(keypoints3d: Array, prob: Problem, config: TrajOptConfig) -> Array:
    """Squared distance of the joints (world frame) from those of the anchor (the kinematic fit)."""
    d = jnp.sum((keypoints3d - prob.anchor_kp) ** 2, (-1, -2)) / config.stay_sigma_m**2
    return _frames_mean(d, prob.mask.astype(d.dtype))


KINEMATIC_WEIGHTS = ("reproj", "pose", "limits", "accel", "contact_height", "contact_still", "floor")


def _weight(config: TrajOptConfig, name: str):
    return {"reproj": config.w_reproj, "pose": config.w_pose, "limits": config.w_limits,
            "accel": config.w_accel, "contact_height": config.w_contact_height,
            "contact_still": config.w_contact_vel, "floor": config.w_floor,
            "dynamics": config.w_dynamics, "stay": config.w_stay, "wrench_rate": config.w_wrench_rate,
            "com_accel": config.w_com_accel}[name]


def objective_terms(model: Model, x: Trajectory, prob: Problem, config: TrajOptConfig, *, physics: bool,
                    heights: bool = True, gm_scale=None) -> dict[str, Array]:
    """Every energy of a stage, unweighted (``heights`` False: without the contact-height term;
    ``gm_scale``: the robust scale of the reprojection term, default ``config.gm_scale``)."""
    q = to_q(model, x, prob.base_quat)
    gm = config.gm_scale if gm_scale is None else gm_scale
    geo = geometry(model, q, config.layout, dynamics=dynamics_inputs(model, q, prob, config) if physics else None)
    terms = kinematic_terms(model, q, geo, prob, config, gm)
    if not heights:
        terms["contact_height"] = jnp.zeros_like(terms["reproj"])
    if physics:
        terms["dynamics"] = dynamics_term(geo.dynamics, prob, config)
        terms["stay"] = stay_term(geo.keypoints3d, prob, config)
        terms["wrench_rate"] = wrench_rate_term(geo.dynamics, prob, config)
        terms["com_accel"] = com_accel_term(geo.dynamics, prob, config)
    return terms


def objective(model: Model, x: Trajectory, prob: Problem, config: TrajOptConfig, *, physics: bool,
              heights: bool = True, gm_scale=None) -> Array:
    terms = objective_terms(model, x, prob, config, physics=physics, heights=heights, gm_scale=gm_scale)
    return sum(_weight(config, k) * v for k, v in terms.items())


# ---------------------------------------------------------------------------------------
# the optimiser
# ---------------------------------------------------------------------------------------


@struct.dataclass
class StageReport:
    initial: Array  # () objective before
    final: Array  # () objective after
    grad_norm: Array  # () gradient norm at the end
    iterations: Array  # () int


def lbfgs(fun, x0, iterations: int, memory: int, scale=None, linesearch: str = "zoom"):
    """``iterations`` L-BFGS steps (optax; ``linesearch`` "zoom", optax's default, or
    "backtracking"; static) on ``fun`` from ``x0``, in the variables ``y`` of ``x = x0 + scale
    * y`` (a diagonal preconditioner, default 1), or of ``x = x0 + scale(y)`` when ``scale`` is a
    linear function (e.g. :func:`banded_preconditioner`); the best iterate seen is returned (a
    failed line search cannot make the result worse)."""
    if callable(scale):
        step_of = scale
    else:
        scale = jax.tree.map(jnp.ones_like, x0) if scale is None else scale
        step_of = lambda y: jax.tree.map(lambda s, b: s * b, scale, y)  # noqa: E731
    if linesearch == "zoom":
        opt = optax.lbfgs(memory_size=memory)
    elif linesearch == "backtracking":
        search = optax.scale_by_backtracking_linesearch(max_backtracking_steps=15, store_grad=True)
        opt = optax.lbfgs(memory_size=memory, linesearch=search)
    else:
        raise ValueError(f"unknown linesearch {linesearch!r} (zoom, backtracking)")

    def to_x(y):
        return jax.tree.map(lambda a, b: a + b, x0, step_of(y))

    g_fun = lambda y: fun(to_x(y))  # noqa: E731
    value_and_grad = optax.value_and_grad_from_state(g_fun)
    y0 = jax.tree.map(jnp.zeros_like, x0)
    f0 = g_fun(y0)

    def step(carry, _):
        y, state, best, fbest = carry
        value, grad = value_and_grad(y, state=state)
        updates, state = opt.update(grad, state, y, value=value, grad=grad, value_fn=g_fun)
        y_new = optax.apply_updates(y, updates)
        better = value < fbest
        best = jax.tree.map(lambda a, b: jnp.where(better, a, b), y, best)
        return (y_new, state, best, jnp.where(better, value, fbest)), None

    (y, state, best, fbest), _ = jax.lax.scan(step, (y0, opt.init(y0), y0, f0), None, length=iterations)
    f_last = g_fun(y)
    better = f_last < fbest
    best = jax.tree.map(lambda a, b: jnp.where(better, a, b), y, best)
    fbest = jnp.minimum(f_last, fbest)
    gnorm = optax.tree_utils.tree_l2_norm(jax.grad(g_fun)(best))
    return to_x(best), StageReport(f0, fbest, gnorm, jnp.asarray(iterations))


def diagonal_scale(model: Model, x: Trajectory, prob: Problem, config: TrajOptConfig) -> Trajectory:
    """A diagonal preconditioner: ``1 / sqrt(diag(J^T J))`` of the per-frame Gauss-Newton
    approximation of the reprojection and pose-prior terms at ``x`` (each frame's variables
    move its own joints only; the root's position and orientation move all of them, a distal
    hinge two or three: their curvatures differ by orders of magnitude, which L-BFGS's scalar
    initial Hessian cannot absorb in a few dozen iterations)."""
    layout = get_layout(config.layout)
    roots = np.asarray(layout.root_indices)
    T = x.root_pos.shape[0]

    def residual(v, base, kp, prior_rr, E):
        cam = Camera(prob.intrinsics, jnp.zeros(2, x.hinges.dtype), E)
        xt = Trajectory(v[:3][None], v[3:6][None], v[6:][None])
        q = to_q(model, xt, base[None])[0]
        p3 = P.keypoints(model, q, config.layout)
        conf = jnp.sqrt(jnp.maximum(kp[:, 2], 1e-3))
        r1 = (conf[:, None] * (project(cam, p3) - kp[:, :2]) / prob.unit_px).ravel()
        rr = p3 - jnp.mean(p3[roots], 0)
        r2 = (jnp.sqrt(config.w_pose) * (rr - prior_facing_fit(rr, prior_rr, config)) / config.pose_sigma_m).ravel()
        # the diagonal of the acceleration term's [1, -2, 1] stencil: 1 + 4 + 1
        r3 = (jnp.sqrt(6.0 * config.w_accel) * prob.fps**2 / config.accel_sigma * p3).ravel()
        return jnp.concatenate([jnp.sqrt(config.w_reproj) * r1, r2, r3])

    v = jnp.concatenate([x.root_pos, x.root_rot, x.hinges], -1)
    J = jax.vmap(jax.jacfwd(residual))(v, prob.base_quat, prob.keypoints, prob.prior_rr, prob.extrinsics)  # (T, R, n)
    d = jnp.sum(J * J, 1)  # (T, n)
    d = d + 1e-3 * jnp.mean(d, -1, keepdims=True) + 1e-6
    s = jnp.sqrt(T / d)  # the objective is a frame mean: its curvature is d / T
    return Trajectory(s[:, :3], s[:, 3:6], s[:, 6:])


def _frame_jacobians(model: Model, q: Array, cam: Camera, scene: Scene | None, layout: str):
    """One frame's geometry and its Jacobians with respect to a step ``dq`` (nv,) of the
    configuration (``q (+) dq``), from one forward-kinematics pass (the analytic point
    Jacobians): the layout's joints ``p3`` (J, 3) with (J, 3, nv), their projections ``uv`` (J, 2)
    in pixels with (J, 2, nv), the sole points (8, 3) with (8, 3, nv) and their heights above the
    floor or the ``scene``'s terrain (8,) with (8, nv) (:func:`surface_heights_and_normals`: the
    surface normal's component of the points' Jacobians). Returns ``(p3, jk, uv, j_uv, sole, js,
    sole_h, j_h)``."""
    kin = P.forward_kinematics(model, q)
    ids = model.site_ids(get_layout(layout).sites)
    p3 = P.keypoints(model, q, layout, kin=kin)
    pts, bodies, _ = S.sole_points(model, kin)
    jac, _ = P.point_jacobian(model, kin, jnp.concatenate([p3, pts]),
                              np.concatenate([np.asarray(model.topo.site_body)[np.asarray(ids)], bodies]))
    jk, js = jac[: p3.shape[0]], jac[p3.shape[0]:]
    if is_flat(scene):
        sole_h, j_h = pts[:, 2], js[:, 2, :]
    else:
        sole_h, normal = surface_heights_and_normals(scene, pts)
        j_h = jnp.einsum("pk,pkv->pv", normal, js)
    # pinhole projection and its derivative
    R, t = cam.extrinsics[:3, :3], cam.extrinsics[:3, 3]
    xc = p3 @ R.T + t
    z = jnp.maximum(xc[:, 2], 1e-3)
    f, c = cam.intrinsics[:2], cam.intrinsics[2:]
    uv = f * xc[:, :2] / z[:, None] + c
    dproj = jnp.zeros((p3.shape[0], 2, 3), q.dtype)
    dproj = dproj.at[:, 0, 0].set(f[0] / z).at[:, 1, 1].set(f[1] / z)
    dproj = dproj.at[:, :, 2].set(-f * xc[:, :2] / (z * z)[:, None])
    j_uv = jnp.einsum("jab,bc,jcv->jav", dproj, R, jk)
    return p3, jk, uv, j_uv, pts, js, sole_h, j_h


def _frame_residuals(model: Model, q: Array, prior_rr: Array, cam: Camera, config: TrajOptConfig,
                     depth: Array | None = None, contacts: Array | None = None, scene: Scene | None = None):
    """One frame's residuals and their Jacobians with respect to a step ``dq`` (nv,) of the
    configuration (``q (+) dq``, :func:`jmocap.physics.integrate_positions`), from one
    forward-kinematics pass (the analytic point Jacobians): the projected joints (J, 2) in
    pixels with (J, 2, nv), and the weighted prior residuals (pose prior, joint limits, floor)
    whose squares are their terms of the per-frame objective, with their Jacobian. With
    ``depth`` (the frame's log-depth target, :func:`depth_track`) the prior residuals end with
    ``sqrt(w_depth) (log z - depth) / depth_sigma`` of the root's camera depth ``z``. With
    ``contacts`` (4,), the frame's contact labels, they end with the robust height residuals of
    the labelled sites' sole points, :func:`robust_height`. Sole heights are above the
    ``scene``'s terrain (:func:`surface_heights_and_normals`: their Jacobian is the surface
    normal's component of the points' Jacobians)."""
    layout = get_layout(config.layout)
    roots = np.asarray(layout.root_indices)
    p3, jk, uv, j_uv, pts, _, sole_h, j_h = _frame_jacobians(model, q, cam, scene, config.layout)
    R, t = cam.extrinsics[:3, :3], cam.extrinsics[:3, 3]
    # priors
    rr = p3 - jnp.mean(p3[roots], 0)
    turned = prior_facing_fit(rr, prior_rr, config)
    j_rr = jk - jnp.mean(jk[roots], 0)  # the turn held (prior_facing_fit; docs/method.md, stop 57)
    hinge, lim_sign = limit_angles(model, q[model.topo.hinge_qadr], config)
    lo = jnp.asarray(model.q_lower, q.dtype)[model.topo.hinge_qadr]
    hi = jnp.asarray(model.q_upper, q.dtype)[model.topo.hinge_qadr]
    sel = jnp.zeros((hinge.shape[0], model.nv), q.dtype).at[np.arange(hinge.shape[0]), model.topo.hinge_dofadr].set(1.0)
    out_lo, out_hi = lo - hinge, hinge - hi
    a_pose = jnp.sqrt(config.w_pose) / config.pose_sigma_m
    a_lim = jnp.sqrt(config.w_limits) / config.limit_sigma_rad
    a_floor = jnp.sqrt(config.w_floor) / config.floor_sigma
    other = jnp.concatenate([
        a_pose * (rr - turned).ravel(),
        a_lim * (jax.nn.relu(out_lo) - jax.nn.relu(out_hi)),
        a_floor * jax.nn.relu(config.floor_margin_m - sole_h),
    ])
    j_other = jnp.concatenate([
        a_pose * j_rr.reshape(-1, model.nv),
        -a_lim * (lim_sign * ((out_lo > 0).astype(q.dtype) + (out_hi > 0).astype(q.dtype)))[:, None] * sel,
        -a_floor * (sole_h < config.floor_margin_m).astype(q.dtype)[:, None] * j_h,
    ])
    if depth is not None:
        # the free joint's first three velocity coordinates move the root in the world frame
        a_depth = jnp.sqrt(config.w_depth) / config.depth_sigma
        z_root = q[:3] @ R[2] + t[2]
        zc = jnp.maximum(z_root, 1e-2)
        other = jnp.concatenate([other, a_depth * (jnp.log(zc) - depth)[None]])
        row = jnp.zeros((1, model.nv), q.dtype).at[0, :3].set(a_depth * (z_root > 1e-2) * R[2] / zc)
        j_other = jnp.concatenate([j_other, row])
    if contacts is not None:
        lab = jnp.repeat(contacts.astype(q.dtype), pts.shape[0] // contacts.shape[0])  # (8,)
        rh, drh = robust_height(sole_h, config)
        other = jnp.concatenate([other, lab * rh])
        j_other = jnp.concatenate([j_other, (lab * drh)[:, None] * j_h])
    return uv, j_uv, other, j_other


def robust_height(h: Array, config: TrajOptConfig) -> tuple[Array, Array]:
    """The per-frame fit's residual of a labelled sole point at height ``h`` (m), and its
    derivative: ``a c h / sqrt(c^2 + h^2)`` with ``a = sqrt(w_contact_height) /
    contact_height_sigma`` and ``c = contact_robust_m``, whose square is the Geman-McClure cost
    of ``a h`` (quadratic near the floor, bounded for a wrong label that the 2D evidence holds
    in the air)."""
    a = jnp.sqrt(config.w_contact_height) / config.contact_height_sigma
    c = jnp.asarray(config.contact_robust_m, h.dtype)
    den = jnp.sqrt(c * c + h * h)
    return a * c * h / den, a * c**3 / den**3


#: the per-frame fit's second start for the arms (``arm_restart``; degrees, jmocap's humanoid): hanging
#: at the sides, the upper arms turned about the shoulders' x axes and the elbows bent a little, the
#: mean shoulder and elbow angles of the walk of ``data/val`` (clip 0)
ARMS_DOWN_DEG = {"left_shoulder_x": -77.0, "left_shoulder_z": 0.0, "left_shoulder_y": 0.0, "left_elbow_z": -11.0,
                 "right_shoulder_x": 77.0, "right_shoulder_z": 0.0, "right_shoulder_y": 0.0, "right_elbow_z": 11.0}


def arms_down(model: Model, q: Array) -> Array | None:
    """``q`` (..., nq) with the arms of :data:`ARMS_DOWN_DEG`, or None for a character without
    those joints (static: read from the MuJoCo model at trace time)."""
    mj = model.mj
    names = {mj.joint(j).name: int(mj.jnt_qposadr[j]) for j in range(mj.njnt)}
    if not all(n in names for n in ARMS_DOWN_DEG):
        return None
    adr = np.asarray([names[n] for n in ARMS_DOWN_DEG])
    return q.at[..., adr].set(jnp.deg2rad(jnp.asarray(list(ARMS_DOWN_DEG.values()), q.dtype)))


def frame_objective(model: Model, q: Array, prob: Problem, config: TrajOptConfig, depth: Array | None) -> Array:
    """The per-frame fit's objective (T,) at its last robust scale (``config.gm_scale``): what
    :func:`per_frame_fit` lowers, frame by frame, to compare two of its fits."""
    def one(qt, prior, kp, cf, unit, E, dz, lab):
        cam = Camera(prob.intrinsics, jnp.zeros(2, q.dtype), E)
        uv, _, other, _ = _frame_residuals(model, qt, prior, cam, config, dz, lab, prob.scene)
        r2 = jnp.sum((uv - kp) ** 2, -1) / unit**2
        return config.w_reproj * jnp.sum(cf * geman_mcclure(r2, config.gm_scale)) + jnp.sum(other**2)

    units = jnp.broadcast_to(prob.unit_px, q.shape[:1])
    contacts = prob.contacts if config.frame_contacts else None
    return jax.vmap(one, in_axes=(0, 0, 0, 0, 0, 0, None if depth is None else 0, None if contacts is None else 0))(
        q, prob.prior_rr, prob.keypoints[..., :2], prob.keypoints[..., 2], units, prob.extrinsics, depth, contacts)


def per_frame_fit(model: Model, q: Array, prob: Problem, config: TrajOptConfig, iterations: int,
                  gm_start, gm_end, depth: Array | None = None, contacts: Array | None = None,
                  tile: int = 0) -> Array:
    """Every frame fitted on its own (no temporal terms) by Levenberg-Marquardt on
    the configuration manifold (steps ``q (+) dq``, analytic Jacobians): the robust
    reprojection (Geman-McClure, iteratively reweighted, its scale annealed from ``gm_start``
    to ``gm_end`` % of the person's image height over the iterations, a graduated
    non-convexity: far-off starting poses first see every keypoint, then stop seeing the
    outliers), the pose prior, joint limits and the floor. Each frame's damped Gauss-Newton
    system (nv x nv) is solved exactly at every step, which a first-order method over the whole
    clip, with one line search for all frames, cannot do in few iterations when frames start
    at very different distances from their evidence.

    Frames with too little evidence (fewer than ``config.min_keypoints`` confident keypoints,
    e.g. the person leaving the image) cannot be fitted on their own: they take the root
    position interpolated between, and the rest of the configuration of, the nearest frames
    that have it (the temporal terms of the next stage then refine them).

    ``depth`` (T,), a log-depth track of the root (:func:`depth_track`), starts every frame at
    its track's depth (:func:`to_depth`) and adds a prior on each frame's root depth: a frame
    with a few keypoints left (the person leaving the image) otherwise fits them as well
    anywhere along a range of depths, up to the camera itself.

    ``contacts`` (T, 4), contact labels, hold each labelled site's sole points on the floor
    (:func:`robust_height`): with the camera known, a foot on the floor fixes the frame's depth,
    which the body's image otherwise leaves to its pose (a limb turned towards the camera and a
    body further away project alike).

    ``tile`` > 0 fits the frames in tiles of that many (``lax.map`` over tiles, ``vmap`` within
    one; under an enclosing ``vmap`` over clips a tile holds that many frames of every clip):
    the same result, faster on a CPU, whose cache then holds a tile's working set
    (docs/performance.md). 0 fits all frames at once.
    Returns (T, nq)."""
    conf = prob.keypoints[..., 2]
    target = prob.keypoints[..., :2]
    if depth is not None:
        q = to_depth(q, prob.extrinsics, jnp.exp(depth))
    units = jnp.broadcast_to(prob.unit_px, q.shape[:1])  # the clip's scale, or one per frame

    def solve_frame(qt, prior, kp, cf, unit, E, dz, lab):
        cam = Camera(prob.intrinsics, jnp.zeros(2, q.dtype), E)

        def robust(uv, c):
            r2 = jnp.sum((uv - kp) ** 2, -1) / unit**2
            return config.w_reproj * jnp.sum(cf * geman_mcclure(r2, c)), r2

        def linearise(qt):
            return _frame_residuals(model, qt, prior, cam, config, dz, lab, prob.scene)

        def step(k, s):
            # ``s`` holds the current point's residuals and Jacobians: a trial point's
            # linearisation is computed once and, when the step is accepted, is the next step's
            # (one forward-kinematics pass per iteration instead of two)
            qt, lin, lam = s
            uv, j_uv, other, j_other = lin
            frac = k / jnp.maximum(iterations - 1, 1)
            c = gm_start * (gm_end / gm_start) ** frac
            f_old, r2 = robust(uv, c)
            f_old = f_old + jnp.sum(other**2)
            w = jnp.sqrt(config.w_reproj * cf * (c * c / (c * c + r2)) ** 2)  # IRLS: sqrt(rho')
            r = jnp.concatenate([(w[:, None] * (uv - kp) / unit).ravel(), other])
            Jm = jnp.concatenate([(w[:, None, None] * j_uv / unit).reshape(-1, model.nv), j_other])
            H = Jm.T @ Jm
            g = Jm.T @ r
            D = jnp.diag(H) + 1e-6 * jnp.trace(H) / model.nv + 1e-9
            # jmocap's own Cholesky, not LAPACK's: two LAPACK calls at once deadlock XLA's CPU
            # pool when the batch is sharded over host devices (physics.linalg)
            dq = -cho_solve(cholesky(H + lam * jnp.diag(D)), g)
            q_new = P.integrate_positions(model, qt, dq, 1.0)
            lin_new = linearise(q_new)
            f_new = robust(lin_new[0], c)[0] + jnp.sum(lin_new[2] ** 2)
            ok = jnp.isfinite(f_new) & (f_new < f_old)
            qt = jnp.where(ok, q_new, qt)
            lin = jax.tree.map(lambda a, b: jnp.where(ok, a, b), lin_new, lin)
            lam = jnp.clip(jnp.where(ok, lam * 0.3, lam * 10.0), 1e-7, 1e7)
            return qt, lin, lam

        if iterations == 0:
            return qt
        qt, _, _ = jax.lax.fori_loop(0, iterations, step, (qt, linearise(qt), jnp.asarray(1e-3, qt.dtype)))
        return qt

    args = (q, prob.prior_rr, target, conf, units, prob.extrinsics, depth, contacts)
    if tile > 0:
        # in tiles of ``tile`` frames (times the clips of an enclosing vmap): the fit is bound by
        # memory traffic (each LM step streams every frame's Jacobians, normal matrix and
        # column-by-column Cholesky), which stays in the CPU's cache for a tile
        fitted = jax.lax.map(lambda a: solve_frame(*a), args, batch_size=tile)
    else:
        fitted = jax.vmap(solve_frame, in_axes=(0, 0, 0, 0, 0, 0, None if depth is None else 0,
                                                None if contacts is None else 0))(*args)
    # frames without enough evidence: from their neighbours
    T = q.shape[0]
    t = jnp.arange(T)
    good = prob.mask & (jnp.sum(conf > CONFIDENT, -1) >= config.min_keypoints)
    prev = jax.lax.cummax(jnp.where(good, t, -1), axis=0)
    nxt = jax.lax.cummin(jnp.where(good, t, T), axis=0, reverse=True)
    has_prev, has_next = prev >= 0, nxt < T
    p_i, n_i = jnp.clip(prev, 0, T - 1), jnp.clip(nxt, 0, T - 1)
    near = jnp.where(has_prev & (~has_next | (t - prev <= nxt - t)), p_i, n_i)
    a = jnp.where(has_prev & has_next, (t - prev) / jnp.maximum(nxt - prev, 1), 0.0).astype(q.dtype)
    pos = jnp.where((has_prev & has_next)[:, None], (1 - a[:, None]) * fitted[p_i, :3] + a[:, None] * fitted[n_i, :3],
                    fitted[near, :3])
    filled = fitted[near].at[:, :3].set(pos)
    keep = good | ~(jnp.any(good))
    return jnp.where(keep[:, None], fitted, filled)


@struct.dataclass
class NormalEquations:
    """The Gauss-Newton model of a whole-clip objective at a trajectory, in the steps ``dq``
    (T, nv) of its configurations: ``f(q (+) dq) ~ f + g . dq + 1/2 dq^T H dq``, ``H`` block-banded
    (the temporal terms couple frames at most two apart)."""

    grad: Array  # (T, nv) the objective's exact gradient
    blocks: Array  # (3, T, nv, nv) H[t, t], H[t, t+1], H[t, t+2] (physics.linalg.banded_matvec)


def kinematic_normal_equations(model: Model, q: Array, prob: Problem, config: TrajOptConfig) -> NormalEquations:
    """Gradient and Gauss-Newton matrix of the kinematic stage's objective (:func:`objective`
    with ``physics=False``: every term of :func:`kinematic_terms`) at configurations ``q`` (T, nq),
    from one forward-kinematics pass per frame and its analytic Jacobians
    (:func:`_frame_jacobians`). Each term is a frame mean of squared residuals, so ``g = 2 sum
    J^T W r`` and ``H = 2 sum J^T W J``; the robust reprojection (Geman-McClure ``rho(s)``, ``s``
    the squared residual) enters with its IRLS weight ``rho'(s)``, which makes ``g`` exact and
    ``H`` the usual approximation without ``rho''``. The acceleration term couples frames ``t``
    and ``t +- 1, 2``, the contact-stillness term ``t`` and ``t + 1``. ``g`` equals the
    autodiff gradient of :func:`objective` in the variables of ``from_q(q)`` (tested)."""
    layout = get_layout(config.layout)
    roots = np.asarray(layout.root_indices)
    T, nv = q.shape[0], model.nv
    dt = q.dtype
    p3, jk, uv, j_uv, sole, js, sole_h, j_h = jax.vmap(
        lambda qt, E: _frame_jacobians(model, qt, Camera(prob.intrinsics, jnp.zeros(2, dt), E), prob.scene,
                                       config.layout))(q, prob.extrinsics)
    m = prob.mask.astype(dt)
    n1 = jnp.maximum(jnp.sum(m), 1.0)
    m3 = m[2:] * m[1:-1] * m[:-2]
    n3 = jnp.maximum(jnp.sum(m3), 1.0)
    m2 = m[1:] * m[:-1]
    n2 = jnp.maximum(jnp.sum(m2), 1.0)

    def gram(a, b):  # (T, K, nv), (T, K, nv) -> (T, nv, nv): a_t^T b_t
        return jnp.einsum("tkv,tkw->tvw", a, b)

    # reprojection: sum_j conf rho(|e|^2), e = (uv - kp) / unit
    unit = jnp.broadcast_to(prob.unit_px, (T,))[:, None, None]
    e = (uv - prob.keypoints[..., :2]) / unit
    s = jnp.sum(e * e, -1)
    c2 = config.gm_scale**2
    w = 2.0 * config.w_reproj / n1 * m[:, None] * prob.keypoints[..., 2] * c2 * c2 / (c2 + s) ** 2  # (T, J)
    je = j_uv / unit[..., None]
    g = jnp.einsum("tj,tja,tjav->tv", w, e, je)
    rows = [(jnp.sqrt(w)[..., None, None] * je).reshape(T, -1, nv)]

    # pose prior on the root-relative joints
    rr = p3 - jnp.mean(p3[:, roots], 1, keepdims=True)
    # the prior's rows with its turn held (prior_facing_fit; docs/method.md, stop 57)
    r = rr - prior_facing_fit(rr, prob.prior_rr, config)
    jr = jk - jnp.mean(jk[:, roots], 1, keepdims=True)
    wp = 2.0 * config.w_pose / n1 * m / config.pose_sigma_m**2
    g = g + wp[:, None] * jnp.einsum("tja,tjav->tv", r, jr)
    rows.append(jnp.sqrt(wp)[:, None, None] * jr.reshape(T, -1, nv))

    # contact heights and the floor: sole-point heights
    lab = jnp.repeat(prob.contacts.astype(dt), 2, axis=-1)  # (T, 8)
    a_h = config.w_contact_height / config.contact_height_sigma**2
    a_f = config.w_floor / config.floor_sigma**2
    wh = 2.0 / n1 * m[:, None] * (a_h * lab + a_f * (sole_h < config.floor_margin_m).astype(dt))  # (T, 8)
    rh = 2.0 / n1 * m[:, None] * (a_h * lab * sole_h - a_f * jax.nn.relu(config.floor_margin_m - sole_h))
    g = g + jnp.einsum("tp,tpv->tv", rh, j_h)
    rows.append(jnp.sqrt(wh)[..., None] * j_h)
    rows = jnp.concatenate(rows, 1)
    H0 = gram(rows, rows)

    # joint limits (the hinge coordinates are dq's own)
    h, lim_sign = limit_angles(model, q[:, model.topo.hinge_qadr], config)
    lo = jnp.asarray(model.q_lower, dt)[model.topo.hinge_qadr]
    hi = jnp.asarray(model.q_upper, dt)[model.topo.hinge_qadr]
    wl = 2.0 * config.w_limits / n1 * m[:, None] / config.limit_sigma_rad**2
    dof = np.asarray(model.topo.hinge_dofadr)
    g = g.at[:, dof].add(wl * lim_sign * (jax.nn.relu(h - hi) - jax.nn.relu(lo - h)))
    H0 = H0.at[:, dof, dof].add(wl * ((h > hi) | (h < lo)).astype(dt))

    # 3D joint accelerations: a_i = (x_{i+2} - 2 x_{i+1} + x_i) fps^2 at the centre i + 1
    fps2 = prob.fps**2
    acc = (p3[2:] - 2.0 * p3[1:-1] + p3[:-2]) * fps2
    wa = 2.0 * config.w_accel / n3 * m3 / config.accel_sigma**2  # (T-2,)
    ga = (wa * fps2)[:, None, None] * acc
    for k, coef in enumerate((1.0, -2.0, 1.0)):
        g = g.at[k:T - 2 + k].add(coef * jnp.einsum("tja,tjav->tv", ga, jk[k:T - 2 + k]))
    wa = (wa * fps2 * fps2)[:, None, None]
    jf = jk.reshape(T, -1, nv)
    G0 = gram(jf, jf)
    H0 = H0.at[:-2].add(wa * G0[:-2]).at[1:-1].add(4.0 * wa * G0[1:-1]).at[2:].add(wa * G0[2:])
    G1 = gram(jf[:-1], jf[1:])  # (T-1, nv, nv): J_t^T J_{t+1}
    H1 = jnp.zeros((T, nv, nv), dt).at[: T - 2].add(-2.0 * wa * G1[:-1]).at[1 : T - 1].add(-2.0 * wa * G1[1:])
    H2 = jnp.zeros((T, nv, nv), dt).at[: T - 2].add(wa * gram(jf[:-2], jf[2:]))

    # labelled sole points stay still: d_t = sole_{t+1} - sole_t
    ls = jnp.repeat(prob.contacts[1:] * prob.contacts[:-1], 2, axis=-1).astype(dt)  # (T-1, 8)
    wv = 2.0 * config.w_contact_vel / n2 * m2[:, None] * ls * fps2 / config.contact_vel_sigma**2  # (T-1, 8)
    gd = wv[..., None] * (sole[1:] - sole[:-1])
    g = g.at[1:].add(jnp.einsum("tpa,tpav->tv", gd, js[1:])).at[:-1].add(-jnp.einsum("tpa,tpav->tv", gd, js[:-1]))
    sv = jnp.sqrt(wv)[..., None, None]
    a0, a1 = (sv * js[:-1]).reshape(T - 1, -1, nv), (sv * js[1:]).reshape(T - 1, -1, nv)
    H0 = H0.at[:-1].add(gram(a0, a0)).at[1:].add(gram(a1, a1))
    H1 = H1.at[:-1].add(-gram(a0, a1))
    return NormalEquations(g, jnp.stack([H0, H1, H2]))


def gauss_newton(model: Model, q: Array, prob: Problem, config: TrajOptConfig, iterations: int) -> tuple[Array, StageReport]:
    """``iterations`` Levenberg-Marquardt steps on the kinematic stage's objective over the whole
    clip, on the configuration manifold (``q (+) dq``): each step solves the damped block-banded
    normal equations (:func:`kinematic_normal_equations`; Marquardt's scaling by the diagonal)
    exactly (:func:`jmocap.physics.linalg.banded_solve`) and is kept only if it lowers the
    objective; the damping falls (x 0.3) after a kept step and rises (x 10) after a refused one.
    One objective value, one forward-kinematics pass with its Jacobians and one banded solve per
    iteration, where L-BFGS spends 2-3 objective evaluations with their gradients on each line
    search and needs several times the iterations (docs/performance.md)."""

    def value(qc):
        x, base = from_q(model, qc)
        return objective(model, x, prob.replace(base_quat=base), config, physics=False)

    def linearise(qc):
        return value(qc), kinematic_normal_equations(model, qc, prob, config)

    def step(_, s):
        qc, f, ne, lam = s
        diag = jnp.diagonal(ne.blocks[0], axis1=-2, axis2=-1)  # (T, nv)
        damp = lam * (diag + 1e-6 * jnp.mean(diag) + 1e-12)
        A = ne.blocks.at[0].add(jax.vmap(jnp.diag)(damp))
        dq = -banded_solve(A, ne.grad)
        q_new = jax.vmap(lambda a, b: P.integrate_positions(model, a, b, 1.0))(qc, dq)
        f_new, ne_new = linearise(q_new)
        ok = jnp.isfinite(f_new) & (f_new < f)
        pick = lambda a, b: jnp.where(ok, a, b)  # noqa: E731
        return (pick(q_new, qc), pick(f_new, f), jax.tree.map(pick, ne_new, ne),
                jnp.clip(jnp.where(ok, lam * 0.3, lam * 10.0), 1e-7, 1e7))

    f0, ne0 = linearise(q)
    q, f, ne, _ = jax.lax.fori_loop(0, iterations, step, (q, f0, ne0, jnp.asarray(1e-3, q.dtype)))
    return q, StageReport(f0, f, jnp.sqrt(jnp.sum(ne.grad**2)), jnp.asarray(iterations))


def _stencil_blocks(J: Array, w: Array, T: int, K: int, start: int) -> Array:
    """Upper block diagonals (K, T, nv, nv) of ``sum_i w_i J_i^T J_i`` for residual groups ``i``
    (N of them) that each depend on F consecutive frames, group ``i`` on frames ``start + i``
    to ``start + i + F - 1``: ``J`` (N, F, R, nv) their Jacobians with respect to those frames'
    steps, ``w`` (N,) their weights."""
    N, F, _, nv = J.shape
    blocks = jnp.zeros((K, T, nv, nv), J.dtype)
    Jw = J * w[:, None, None, None]
    for a in range(F):
        for b in range(a, F):
            if b - a < K:
                g = jnp.einsum("nrv,nrw->nvw", Jw[:, a], J[:, b])
                blocks = blocks.at[b - a, start + a:start + a + N].add(g)
    return blocks


def physics_curvature(model: Model, q: Array, prob: Problem, config: TrajOptConfig) -> Array:
    """An approximate Gauss-Newton matrix (4, T, nv, nv) of the physics stage's objective at
    ``q``, for preconditioning (:func:`banded_preconditioner`): the kinematic terms' exact one
    (:func:`kinematic_normal_equations`), the pull to the anchor, and the root-wrench terms with
    the wrench the motion needs linearised as ``b_t ~ M(q_t)[:6] qdd_t / (m g)`` with ``qdd_t =
    (dq_{t+1} - 2 dq_t + dq_{t-1}) fps^2`` (at 30 fps the mass matrix's part of the wrench's
    derivative exceeds the configuration's and the velocities' by one to two orders of
    magnitude). The dynamics residual ``A c - b`` enters projected off the span of the frame's
    active contact forces (Kaufman's variable-projection approximation: what the forces absorb
    costs nothing), the centre-of-mass prior with its robust weight; the wrench-rate term
    couples frames three apart, hence four block diagonals. Interior frames only."""
    T, nv = q.shape[0], model.nv
    dt = q.dtype
    kin = kinematic_normal_equations(model, q, prob, config).blocks
    blocks = jnp.concatenate([kin, jnp.zeros((1, T, nv, nv), dt)])
    m = prob.mask.astype(dt)
    n1 = jnp.maximum(jnp.sum(m), 1.0)
    m2 = m[1:] * m[:-1]
    n2 = jnp.maximum(jnp.sum(m2), 1.0)
    geo = geometry(model, q, config.layout, dynamics=dynamics_inputs(model, q, prob, config))
    fd = geo.dynamics
    # the pull to the anchor: the joints' Jacobians
    jk = jax.vmap(lambda qt: _frame_jacobians(model, qt, Camera(prob.intrinsics, jnp.zeros(2, dt), prob.extrinsics[0]),
                                              prob.scene, config.layout)[1])(q)
    ws = 2.0 * config.w_stay / n1 * m / config.stay_sigma_m**2
    jf = jk.reshape(T, -1, nv)
    blocks = blocks.at[0].add(ws[:, None, None] * jnp.einsum("tkv,tkw->tvw", jf, jf))
    # the wrench the motion needs, per body weight, and its second-difference stencil
    weight = S.body_weight(model, dt)
    M6 = jax.vmap(lambda qt: P.mass_matrix(model, qt)[:6])(q) * (prob.fps**2 / weight)  # (T, 6, nv)
    stencil = jnp.asarray([1.0, -2.0, 1.0], dt)
    Jb = stencil[None, :, None, None] * M6[1:-1, None]  # (T-2, 3, 6, nv): b_t over frames t-1, t, t+1
    # dynamics residual, projected off the active forces' span
    edges = friction_pyramid_edges(jnp.asarray([0.0, 0.0, 1.0], dt), config.mu)
    A = jnp.einsum("tvpk,ek->tvpe", fd.Jt[:, :6], edges).reshape(T, 6, -1)
    active = (fd.coeff.reshape(T, -1) > 1e-9).astype(dt)
    G = jnp.einsum("tip,tp,tjp->tij", A, active, A)
    eps = 1e-6 * jnp.trace(G, axis1=-2, axis2=-1)[:, None, None] + 1e-9
    proj = jnp.eye(6, dtype=dt) - jnp.einsum("tij,tjk->tik", G, spd_inverse(G + eps * jnp.eye(6, dtype=dt)))
    Jr = jnp.einsum("tij,tfjv->tfiv", proj[1:-1], Jb)
    wd = 2.0 * config.w_dynamics / n1 * m[1:-1] / config.dynamics_sigma**2
    blocks = blocks + _stencil_blocks(Jr, wd, T, 4, 0)
    # the centre-of-mass prior (robust: its IRLS weight)
    f = com_accel_residual(fd, prob)
    s2 = jnp.sum(f**2, -1) / config.com_accel_sigma**2
    c2 = config.com_accel_robust**2
    rho1 = jnp.where(config.com_accel_robust > 0, c2 * c2 / (c2 + s2) ** 2, 1.0)
    wc = 2.0 * config.w_com_accel / n1 * (m * rho1)[1:-1] / config.com_accel_sigma**2
    blocks = blocks + _stencil_blocks(Jb[:, :, :3], wc, T, 4, 0)
    # the wrench rate: b_t - b_{t-1} over frames t-2 .. t+1 (t = 2 .. T-2)
    z = jnp.zeros_like(Jb[:-1, :1])
    Jd = jnp.concatenate([z, Jb[1:]], 1) - jnp.concatenate([Jb[:-1], z], 1)  # (T-3, 4, 6, nv)
    wr = 2.0 * config.w_wrench_rate / n2 * m2[1:-1][: T - 3] / config.wrench_rate_sigma**2
    blocks = blocks + _stencil_blocks(Jd, wr, T, 4, 0)
    return blocks


def banded_preconditioner(blocks: Array, damping: float = 1e-3):
    """``y -> dx`` (:class:`Trajectory` to :class:`Trajectory`, linear) with ``S S^T = (H +
    damping diag(H) + floor)^-1`` (the floor: 1e-3 of the frame's median hinge curvature) for
    the block-banded curvature ``H`` (``blocks``, e.g.
    :func:`physics_curvature`): the variables in which L-BFGS (:func:`lbfgs`) sees that
    curvature as the identity. The trajectory's variables at zero rotation offsets are the
    steps ``dq`` (root position, body-frame rotation, hinges) the curvature is written in."""
    diag = jnp.diagonal(blocks[0], axis1=-2, axis2=-1)
    # a floor at 1e-3 of the frame's median hinge curvature: a joint without curvature (a wrist,
    # which no keypoint sees; the real hinges' curvatures lie within about 1e-2 of each other)
    # keeps a bounded scale instead of taking every stray physics gradient at 1e9x
    reg = damping * diag + 1e-3 * jnp.median(diag[:, 6:], -1, keepdims=True) + 1e-12
    root = banded_inverse_root(banded_factor(jax.lax.stop_gradient(blocks.at[0].add(jax.vmap(jnp.diag)(reg)))))

    def apply(y: Trajectory) -> Trajectory:
        dx = root(jnp.concatenate([y.root_pos, y.root_rot, y.hinges], -1))
        return Trajectory(dx[:, :3], dx[:, 3:6], dx[:, 6:])

    return apply


# ---------------------------------------------------------------------------------------
# the method
# ---------------------------------------------------------------------------------------


def contact_labels(params: dict, inputs: ClipInputs, tpnet_prob: Array, config: TrajOptConfig,
                   depth: Array | None = None) -> Array:
    """(T, 4) contact probabilities of the configured source; ``depth`` (T,), TPNet's root depth
    in every frame's camera, lets the estimator take a moving camera's motion out of its windows
    (:func:`jmocap.methods.contact_estimation.window_probabilities`)."""
    if config.contact_source == "tpnet":
        return tpnet_prob
    if config.contact_source in ("mlp", "refined"):
        from jmocap.methods import contact_estimation as CE

        refiner = CE.refiner_params(params) if config.contact_source == "refined" else None
        return CE.estimate_contacts(CE.contact_params(params), inputs, config.layout, depth=depth, refiner=refiner)
    raise ValueError(f"unknown contact_source {config.contact_source!r} (refined, mlp, tpnet)")


def support_prior(params: dict, inputs: ClipInputs, config: TrajOptConfig, depth: Array | None = None) -> Array | None:
    """(T,) the net vertical force the centre-of-mass prior centres on (body weights), or None
    for one body weight (``config.support_prior``); ``depth`` as for :func:`contact_labels`."""
    if config.support_prior == "standing":
        return None
    if config.support_prior == "learned":
        from jmocap.methods import contact_estimation as CE
        from jmocap.methods import support as SP

        return SP.support_force(CE.contact_params(params), SP.support_params(params), inputs, config.layout,
                                depth=depth)
    raise ValueError(f"unknown support_prior {config.support_prior!r} (learned, standing)")


def problem(model: Model, inputs: ClipInputs, q_hat: Array, contacts: Array, config: TrajOptConfig) -> Problem:
    layout = get_layout(config.layout)
    mask = jnp.asarray(inputs.mask)
    kp = jnp.asarray(inputs.keypoints)
    kp = kp.at[..., 2].set(jnp.where(mask[:, None], kp[..., 2], 0.0))
    prior = jax.vmap(lambda x: P.keypoints(model, x, config.layout))(q_hat)
    prior_rr = prior - jnp.mean(prior[:, np.asarray(layout.root_indices)], 1, keepdims=True)
    _, base = from_q(model, q_hat)
    unit = jnp.maximum(person_height_px(kp, mask) / 100.0, config.noise_unit * keypoint_jitter_px(kp, mask))
    return Problem(
        keypoints=kp, intrinsics=jnp.asarray(inputs.intrinsics, q_hat.dtype),
        extrinsics=jnp.asarray(inputs.world_to_camera(), q_hat.dtype),
        unit_px=unit, fps=jnp.asarray(inputs.fps, q_hat.dtype), mask=mask,
        length=jnp.sum(mask.astype(jnp.int32)), base_quat=base, prior_rr=prior_rr,
        contacts=(contacts > config.contact_threshold).astype(q_hat.dtype) * mask[:, None], anchor_kp=prior,
        supported=jnp.any(contacts > config.contact_threshold, -1) & mask,
        scene=None if inputs.scene is None or not config.use_scene
        else jax.tree.map(lambda a: jnp.asarray(a, q_hat.dtype), inputs.scene),
    )


def _sole_heights(model: Model, q: Array, scene: Scene | None) -> Array:
    """(T, 8) heights of the sole points of every frame above the terrain (:func:`surface_heights`)."""
    return jax.vmap(lambda x: surface_heights(scene, S.sole_points(model, P.forward_kinematics(model, x))[0]))(q)


def initial_trajectory(model: Model, q_hat: Array, mask: Array, scene: Scene | None = None) -> Array:
    """TPNet's poses, moved vertically as a whole so that the lowest sole point over the clip's
    real frames touches the floor, or the ``scene``'s terrain (TPNet's depth error floats or
    sinks the body)."""
    sole_h = _sole_heights(model, q_hat, scene)
    low = jnp.min(jnp.where(mask[:, None], sole_h, jnp.inf))
    low = jnp.where(jnp.isfinite(low), low, 0.0)
    return q_hat.at[:, 2].add(-low)


@struct.dataclass
class Fit:
    q: Array  # (T, nq)
    force: Array  # (T, 8, 3) world-frame forces at the sole points (N)
    contacts: Array  # (T, 4) the labels the fit used
    diagnostics: dict
    q_kinematic: Array  # (T, nq) the kinematic fit (before the physics stage)


def _preconditioner(model: Model, x: Trajectory, prob: Problem, config: TrajOptConfig, *, physics: bool):
    """The L-BFGS variables of a whole-clip stage (``config.precondition``): a diagonal scale
    (:func:`diagonal_scale`) or the stage's block-banded Gauss-Newton curvature at ``x``
    (:func:`banded_preconditioner` of :func:`kinematic_normal_equations` or
    :func:`physics_curvature`; ``x`` has zero rotation offsets)."""
    if config.precondition == "diagonal":
        return diagonal_scale(model, x, prob, config)
    if config.precondition == "banded":
        q = to_q(model, x, prob.base_quat)
        blocks = (physics_curvature(model, q, prob, config) if physics
                  else kinematic_normal_equations(model, q, prob, config).blocks)
        return banded_preconditioner(blocks)
    raise ValueError(f"unknown precondition {config.precondition!r} (diagonal, banded)")


def fit(model: Model, prob: Problem, q_init: Array, config: TrajOptConfig) -> Fit:
    """The stages on one window (see the module docstring)."""
    x0, base = from_q(model, q_init)
    prob = prob.replace(base_quat=base)
    # stage 0: every frame on its own (no temporal or contact-height terms), Levenberg-Marquardt
    # with an annealed robust scale: TPNet's pose is far from the evidence, and the temporal
    # terms would make these first, large moves ill-conditioned (Rempe App. B.4: first pass
    # without the floor)
    per_frame = config.replace(w_accel=0.0, w_contact_vel=0.0)
    f0 = lambda x, pr: objective(model, x, pr, per_frame, physics=False, heights=False)  # noqa: E731
    dtrack = depth_track(q_init, prob, config)
    q1 = per_frame_fit(model, q_init, prob, per_frame, config.frame_iterations, config.gm_scale_initial,
                       config.gm_scale, dtrack,
                       prob.contacts if config.frame_contacts else None, tile=config.frame_tile)
    q_arms = arms_down(model, q_init) if config.arm_restart else None
    if q_arms is not None:
        q1b = per_frame_fit(model, q_arms, prob, per_frame, config.frame_iterations,
                            config.gm_scale_initial, config.gm_scale, dtrack,
                            prob.contacts if config.frame_contacts else None, tile=config.frame_tile)
        better = frame_objective(model, q1b, prob, per_frame, dtrack) < frame_objective(model, q1, prob, per_frame, dtrack)
        q1 = jnp.where(better[:, None], q1b, q1)
    before = f0(x0, prob)
    q1 = continuous_hinges(model, q1, config)
    x1, base = from_q(model, q1)
    prob = prob.replace(base_quat=base)
    rep1 = StageReport(before, f0(x1, prob), jnp.zeros((), q1.dtype), jnp.asarray(config.frame_iterations))
    # outlier labels: points labelled in contact that the fit holds far above the floor (their
    # App. B.4 fits the floor robustly; here the floor is known, z = 0, or the clip's terrain)
    sole_h = _sole_heights(model, q1, prob.scene)
    low = jnp.min(jnp.where(prob.mask[:, None], sole_h, jnp.inf))
    x1 = x1.replace(root_pos=x1.root_pos.at[:, 2].add(-jnp.where(jnp.isfinite(low), low, 0.0)))
    site_h = jnp.min(sole_h.reshape(-1, 4, 2), -1) - jnp.where(jnp.isfinite(low), low, 0.0)
    contacts = prob.contacts * (site_h < config.outlier_height_m)
    prob = prob.replace(contacts=contacts)
    # stage 1: the full kinematic fit
    kin_config = config.replace(w_accel=jnp.where(config.w_accel_kinematic >= 0, config.w_accel_kinematic,
                                                  config.w_accel))
    if config.kinematic_solver == "gauss_newton":
        q_kin, rep2 = gauss_newton(model, to_q(model, x1, prob.base_quat), prob, kin_config,
                                  config.kinematic_iterations)
        x2, base = from_q(model, q_kin)
        prob = prob.replace(base_quat=base)
    elif config.kinematic_solver == "lbfgs":
        f1 = lambda x: objective(model, x, prob, kin_config, physics=False)  # noqa: E731
        x2, rep2 = lbfgs(f1, x1, config.kinematic_iterations, config.memory,
                         _preconditioner(model, x1, prob, kin_config, physics=False), config.linesearch)
        q_kin = to_q(model, x2, prob.base_quat)
    else:
        raise ValueError(f"unknown kinematic_solver {config.kinematic_solver!r} (lbfgs, gauss_newton)")
    # each ball joint's angles continuous over the clip (the same poses): the physics stage's
    # finite differences are then the joints' motion
    q_kin = continuous_hinges(model, q_kin, config)
    x2 = x2.replace(hinges=q_kin[:, model.topo.hinge_qadr])
    # stage 2: physics, anchored to the kinematic fit
    prob = prob.replace(anchor_kp=jax.vmap(lambda x: P.keypoints(model, x, config.layout))(q_kin))
    if config.precondition == "banded":  # the curvature is written at zero rotation offsets
        x2, base = from_q(model, q_kin)
        prob = prob.replace(base_quat=base)
    f2 = lambda x: objective(model, x, prob, config, physics=True)  # noqa: E731
    x3, rep3 = lbfgs(f2, x2, config.physics_iterations, config.memory,
                     _preconditioner(model, x2, prob, config, physics=True), config.linesearch)
    q = to_q(model, x3, prob.base_quat)

    fd = geometry(model, q, config.layout, dynamics=dynamics_inputs(model, q, prob, config)).dynamics
    edges = friction_pyramid_edges(jnp.asarray([0.0, 0.0, 1.0], q.dtype), config.mu)
    force = jnp.einsum("tpe,ek->tpk", fd.coeff, edges) * S.body_weight(model, q.dtype)  # (T, 8, 3)
    terms = objective_terms(model, x3, prob, config, physics=True)
    diagnostics = dict(
        objective_initial=rep1.initial, objective_kinematic=rep2.final, objective_physics_initial=rep3.initial,
        objective_final=rep3.final, grad_norm=rep3.grad_norm,
        iterations=rep1.iterations + rep2.iterations + rep3.iterations,
        **{f"term_{k}": v for k, v in terms.items()},
    )
    return Fit(q, force * prob.mask[:, None, None], contacts, diagnostics, q_kin)


def outputs(model: Model, q: Array, force: Array, mask: Array, fps,
            scene: Scene | None = None) -> tuple[Array, Array, Array, dict]:
    """``(qd, tau, grf, report)`` of a trajectory and its sole-point forces (T, 8, 3):
    ``tau = M qdd + h - J_c^T lambda`` at the finite differences of :func:`frame_velocities`
    (``tau[:6]`` the residual root wrench), the forces summed per contact site (T, 4, 3), and
    the residual and penetration (into the floor or the ``scene``'s terrain) that remain."""
    length = jnp.sum(mask.astype(jnp.int32))
    qd, qdd = frame_velocities(q, jnp.asarray(fps, q.dtype), length)

    def one(qt, v, a, f):
        kin = P.forward_kinematics(model, qt)
        pts, bodies, _ = S.sole_points(model, kin)
        jacp, _ = P.point_jacobian(model, kin, pts, bodies)
        return P.rnea(model, qt, v, a, kin=kin) - jnp.einsum("pkv,pk->v", jacp, f), surface_heights(scene, pts)

    tau, height = jax.vmap(one)(q, qd, qdd, force)
    m = mask.astype(q.dtype)
    res = jnp.linalg.norm(tau[:, :3], axis=-1) / S.body_weight(model, q.dtype)
    report = dict(residual_mean_bw=_frames_mean(res, m), residual_max_bw=jnp.max(jnp.where(mask, res, 0.0)),
                  penetration_max_m=jnp.max(jnp.where(mask[:, None], jax.nn.relu(-height), 0.0)))
    grf = force.reshape(-1, 4, 2, 3).sum(2) * m[:, None, None]
    return qd * m[:, None], tau * m[:, None], grf, report


def window_starts(T: int, window: int, overlap: int) -> tuple[int, ...]:
    """Static start frames of the windows covering T frames (the last one ends at T)."""
    if window <= 0 or T <= window:
        return (0,)
    if not 0 <= overlap < window:
        raise ValueError(f"overlap must be in [0, window), got {overlap} for window {window}")
    starts = list(range(0, T - window, window - overlap)) + [T - window]
    return tuple(sorted(set(starts)))


def window_weights(T: int, starts: tuple[int, ...], window: int, overlap: int) -> np.ndarray:
    """(n, T) cross-fade weights of the windows (linear ramps over each overlap, summing to 1)."""
    n = len(starts)
    w = np.zeros((n, T))
    t = np.arange(T)
    for k, s in enumerate(starts):
        inside = (t >= s) & (t < s + window)
        up = np.clip((t - s + 1) / (overlap + 1), 0, 1) if k > 0 else np.ones(T)
        down = np.clip((s + window - t) / (overlap + 1), 0, 1) if k < n - 1 else np.ones(T)
        w[k] = inside * up * down
    return w / np.maximum(w.sum(0, keepdims=True), 1e-12)


def _blend_q(qs: Array, w: Array) -> Array:
    """Weighted mean (T, nq) of window trajectories (n, T, nq): positions and angles linearly,
    quaternions sign-aligned to the first window's and renormalised."""
    ref = qs[0, :, 3:7]
    sign = jnp.where(jnp.sum(qs[:, :, 3:7] * ref, -1, keepdims=True) < 0, -1.0, 1.0)
    qs = qs.at[:, :, 3:7].multiply(sign)
    q = jnp.sum(w[..., None] * qs, 0)
    return q.at[:, 3:7].set(quat_normalize(q[:, 3:7]))


@jax.custom_batching.custom_vmap
def fit_clip(model: Model, prob: Problem, q_init: Array, config: TrajOptConfig) -> Fit:
    """:func:`fit` over the whole clip, or over overlapping windows of ``config.window`` frames
    cross-faded over their ``config.overlap`` shared frames. A clip no longer than a window is
    one window.

    Batched (``jax.vmap``, e.g. over the clips of a bucket), the clips' optimisations run one
    after another in one program (``lax.map``, :func:`_fit_clips`), as do the windows: each
    clip's line searches stop when it converges instead of waiting for the slowest lane, and
    XLA's CPU backend crashed (a segfault in its runtime, jax 0.10.2) running the vmapped
    optimiser. Differentiate :func:`fit` (not vmapped over clips) to take gradients."""
    T = q_init.shape[0]
    W, O = config.window, config.overlap
    starts = window_starts(T, W, O)
    if len(starts) == 1:
        return fit(model, prob, q_init, config)
    idx = np.asarray(starts)[:, None] + np.arange(W)[None]  # (n, W)

    def cut(a):
        return a[idx] if (hasattr(a, "ndim") and a.ndim and a.shape[0] == T) else a

    probs = jax.tree.map(cut, prob.replace(scene=None))  # the scene is the clip's, not per frame
    local = jnp.asarray(prob.mask)[idx]
    windows = lambda a: jnp.broadcast_to(a, (len(starts), *jnp.shape(a)))  # noqa: E731
    probs = probs.replace(mask=local, length=jnp.sum(local.astype(jnp.int32), -1),
                          scene=None if prob.scene is None else jax.tree.map(windows, prob.scene),
                          unit_px=jnp.broadcast_to(prob.unit_px, (len(starts),)),
                          intrinsics=jnp.broadcast_to(prob.intrinsics, (len(starts), *prob.intrinsics.shape)),
                          fps=jnp.broadcast_to(prob.fps, (len(starts),)))
    fits = jax.lax.map(lambda a: fit(model, a[0], a[1], config), (probs, q_init[idx]))
    wnp = window_weights(T, starts, W, O)
    # only a window's real frames count; renormalise where the weights no longer sum to one
    wm = jnp.asarray(wnp, q_init.dtype) * jnp.zeros((len(starts), T), q_init.dtype).at[
        np.repeat(np.arange(len(starts)), W), idx.ravel()].set(local.ravel().astype(q_init.dtype))
    wm = wm / jnp.maximum(jnp.sum(wm, 0, keepdims=True), 1e-12)

    def spread(a):  # (n, W, ...) -> (n, T, ...) in clip frames
        out = jnp.zeros((len(starts), T, *a.shape[2:]), a.dtype)
        return out.at[np.repeat(np.arange(len(starts)), W), idx.ravel()].set(a.reshape(-1, *a.shape[2:]))

    q = _blend_q(spread(fits.q), wm)
    q_kin = _blend_q(spread(fits.q_kinematic), wm)
    force = jnp.sum(wm[..., None, None] * spread(fits.force), 0)
    contacts = jnp.sum(wm[..., None] * spread(fits.contacts), 0)
    share = jnp.sum(local, -1) / jnp.maximum(jnp.sum(local), 1)
    diagnostics = {k: jnp.sum(share * v) for k, v in fits.diagnostics.items()}
    diagnostics["iterations"] = jnp.sum(fits.diagnostics["iterations"])
    return Fit(q, force * prob.mask[:, None, None], contacts, diagnostics, q_kin)


@fit_clip.def_vmap
def _fit_clips(axis_size, in_batched, model, prob, q_init, config):
    args = jax.tree.map(lambda a, b: a if b else jnp.broadcast_to(a, (axis_size, *jnp.shape(a))),
                        (model, prob, q_init, config), (*in_batched,))
    out = jax.lax.map(lambda a: fit_clip(*a), args)
    return out, jax.tree.map(lambda _: True, out)


def reconstruct(params: dict, model: Model, inputs: ClipInputs,
                config: TrajOptConfig = TrajOptConfig()) -> Motion:  # noqa: B008
    """2D keypoints of one clip -> a :class:`Motion` fitted to them and to the equations of
    motion (see the module docstring)."""
    tp = S.target_pose(params, model, inputs, config)
    mask = jnp.asarray(inputs.mask)
    prob_c = contact_labels(params, inputs, S.contact_probability(tp.contact_logits), config, tp.trans_cam[:, 2])
    prob = problem(model, inputs, tp.q_hat, prob_c, config)
    prob = prob.replace(support=support_prior(params, inputs, config, tp.trans_cam[:, 2]))
    q0 = initial_trajectory(model, tp.q_hat, mask, prob.scene)
    out = fit_clip(model, prob, q0, config)
    qd, tau, grf, report = outputs(model, out.q, out.force, mask, inputs.fps, prob.scene)
    return Motion(out.q, qd, tau, grf, prob_c * mask[:, None], tp.q_hat, mask,
                  diagnostics={**out.diagnostics, **report})


METHOD = register(
    Method(
        name="trajopt",
        summary="offline: whole-clip robust fit to the 2D keypoints, then physics-based trajectory "
        "optimisation (equations of motion, contact forces in friction pyramids)",
        paper="001 (Rempe et al. 2020), Sec. 3.1-3.3, on 000's (Neural PhysCap) kinematic target",
        config_type=TrajOptConfig,
        reconstruct=reconstruct,
        init_params=init_params,
        **whole_clip(reconstruct),
        from_weights=LEARNED_STAGE_FIELDS,
    )
)

register_variant(Variant("trajopt_tpnet_contacts", "trajopt", {"contact_source": "tpnet"},
                         "trajopt with TPNet's contact head instead of Rempe et al.'s estimator (ablation)"))
register_variant(Variant("trajopt_voted_contacts", "trajopt", {"contact_source": "mlp"},
                         "trajopt with Rempe et al.'s voted contact MLP alone, without jmocap's temporal "
                         "refiner (ablation)"))
register_variant(Variant("trajopt_diagonal", "trajopt",
                         {"precondition": "diagonal", "kinematic_iterations": 60, "physics_iterations": 80,
                          "w_accel_kinematic": -1.0, "w_stay": 0.2, "touch_in_flight": True,
                          "prior_rotation": "tpnet", "w_pose": 2.0, "limit_branches": False, "arm_restart": False,
                          "support_prior": "standing", "w_com_accel": 100.0},
                         "trajopt as before stop 55: L-BFGS with the diagonal preconditioner, 60 + 80 iterations, "
                         "one acceleration weight for both stages, w_stay 0.2, the prior on TPNet's orientation "
                         "with w_pose 2, joint limits on the Euler angles as written, one start of the per-frame fit, "
                         "the centre-of-mass prior on one body weight (ablation of the banded Gauss-Newton preconditioner)"))
register_variant(Variant("trajopt_touch_in_flight", "trajopt", {"touch_in_flight": True},
                         "trajopt with a sole point near the floor allowed to carry force even in a frame the "
                         "contact labels call a flight, as before stop 56 (ablation)"))
register_variant(Variant("trajopt_tpnet_orientation", "trajopt",
                         {"prior_rotation": "tpnet", "w_pose": 2.0, "limit_branches": False, "arm_restart": False,
                          "support_prior": "standing", "w_com_accel": 100.0},
                         "trajopt with the pose prior on TPNet's orientation of the body as well as its "
                         "articulation, w_pose 2, joint limits on the Euler angles as written, one start, the "
                         "centre-of-mass prior on one body weight: stop 56's configuration (ablation of prior_rotation)"))
register_variant(Variant("trajopt_written_triples", "trajopt",
                         {"limit_branches": False, "arm_restart": False, "support_prior": "standing", "w_com_accel": 100.0},
                         "trajopt with each ball joint's limits on its three Euler angles as written, not on the "
                         "better of its two triples, one start of the per-frame fit and the centre-of-mass prior on one body weight: "
                         "stop 57's configuration "
                         "(ablation of limit_branches)"))
register_variant(Variant("trajopt_one_start", "trajopt", {"arm_restart": False},
                         "trajopt with the per-frame fit started from TPNet's pose only, not also with the arms "
                         "hanging (ablation of arm_restart)"))
register_variant(Variant("trajopt_standing_support", "trajopt", {"support_prior": "standing", "w_com_accel": 100.0},
                         "trajopt with the centre-of-mass prior centred on one body weight in every frame, not on "
                         "the learned support, at its weight then (w_com_accel 100): stop 58's configuration "
                         "(ablation of support_prior)"))
register_variant(Variant("trajopt_no_scene", "trajopt", {"use_scene": False},
                         "trajopt on the floor z = 0 whatever terrain the clip carries (ablation of the "
                         "interaction term, issue 21)"))

__all__ = ["METHOD", "TrajOptConfig", "Trajectory", "fit", "frame_velocities", "reconstruct"]
