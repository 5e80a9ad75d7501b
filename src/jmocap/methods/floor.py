"""The floor seen from an uncalibrated static camera: its extrinsics estimated from the clip.

A video without a calibration gives jmocap neither the camera's tilt nor its height, yet every
method needs the floor (gravity's direction, where feet touch, what counts as penetration). The
documented default (:func:`jmocap.camera.default_extrinsics`: a level camera 1 m above the floor)
is wrong for almost every real video, and a method that holds labelled feet on a wrong floor
bends the whole reconstruction to it. Here the floor is estimated from the person instead
(pure JAX; ``jax.vmap`` over clips, ``jax.jit`` once per shape):

1. **The person in the camera frame**: TPNet's pose (:func:`jmocap.methods.stages.target_pose`;
   its camera-frame outputs do not depend on the extrinsics), then every frame fitted to its 2D
   keypoints by ``trajopt``'s per-frame stage without any floor or contact term
   (:func:`fitted_frames`), hence the sole points of both feet
   (:func:`jmocap.methods.stages.sole_points`) per frame. (TPNet's own depth alone put the floor
   about as far from the truth as a level camera; docs/evaluation.md.)
2. **Up from the body**: the pelvis's vertical axis in the camera frame, averaged over the real
   frames with robust weights (a frame whose pelvis leans more than about
   :attr:`FloorConfig.lean_scale_deg` from the mean counts less: bending, lying). People stand
   and move upright on average, so this is the world's up as the camera sees it, up to the
   clip's mean lean.
3. **The floor plane through the standing foot**: in every frame some point of the feet touches
   the floor (flights are short), so the lowest sole point along the up direction is a point of
   the floor. A plane is fitted to those points by iteratively reweighted least squares
   (Geman-McClure, scale :attr:`FloorConfig.height_scale_m`), its normal kept near the body's up
   by a prior of :attr:`FloorConfig.tilt_sigma_deg`: where the person walks about, the points
   span the floor and correct the up estimate; where the person stays on one spot, the prior
   decides. The plane's offset is the camera's height above the floor.
4. **Extrinsics** (:func:`extrinsics_from_floor`): world z along the fitted up, world y along the
   camera's optical axis projected onto the floor (the camera looks along +y, as the default
   camera), the world origin on the floor under the person's median position, the camera above
   it at the fitted height.

What it cannot know: the scene's scale beyond the subject's height (the person is the ruler: a
character 10 % too tall puts the camera 10 % too high and the person 10 % too far), and the
camera's yaw and horizontal position (any choice gives the same reconstruction, moved).

:func:`estimate_floor` returns a :class:`FloorEstimate`; ``usable`` says whether the fit is
trustworthy (enough real frames, the camera above the floor within :attr:`FloorConfig.max_height_m`,
most standing points on the fitted plane); callers fall back to the default camera otherwise.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from jmocap import physics as P
from jmocap.inputs import ClipInputs
from jmocap.methods import stages as S
from jmocap.model import Model
from jmocap.numerics import safe_normalize
from jmocap.physics.linalg import solve_spd3
from jmocap.physics.rotations import mat_to_quat, quat_mul, quat_to_mat

Array = jnp.ndarray


@struct.dataclass
class FloorConfig:
    """Settings of the floor estimate (every field traced; none is a jit cache key)."""

    #: robust scale of the pelvis's lean from the clip's mean up direction (degrees)
    lean_scale_deg: float = 20.0
    #: robust scale of the standing points' distances from the fitted plane (m)
    height_scale_m: float = 0.05
    #: the prior that holds the plane's normal near the body's mean up (degrees, 1 sigma)
    tilt_sigma_deg: float = 5.0
    #: a usable estimate puts the camera at most this high above the floor (m)
    max_height_m: float = 30.0
    #: ... and at least this share of the real frames' standing points within 3 height scales
    min_support: float = 0.5
    #: ... from at least this many real frames
    min_frames: int = 10


@struct.dataclass
class FloorEstimate:
    """The estimated floor of one clip (a batch adds a leading axis)."""

    extrinsics: Array  # (4, 4) world -> camera, OpenCV axes, floor z = 0
    up: Array  # (3,) the world's up direction in the camera frame (the floor's normal)
    height_m: Array  # () the camera's height above the floor
    pitch_deg: Array  # () the optical axis below the horizon (positive: looking down)
    roll_deg: Array  # () the world's up seen tilted towards the image's +x (right) by this angle
    support: Array  # () share of real frames whose lowest sole point lies within 3 scales of the floor
    frames: Array  # () real frames used
    usable: Array  # () bool: see the module docstring


# the per-frame fit's pull towards TPNet's pose in :func:`fitted_frames` (trajopt's w_pose until
# stop 56, with which the floor's accuracy was measured)
FIT_W_POSE = 2.0


def _geman_mcclure_weight(r: Array, scale) -> Array:
    """IRLS weight of the Geman-McClure loss ``r^2 / (r^2 + s^2)``: ``s^4 / (r^2 + s^2)^2``."""
    s2 = jnp.square(scale)
    return jnp.square(s2 / (jnp.square(r) + s2))


def body_frame_points(model: Model, tp: S.TargetPose) -> tuple[Array, Array]:
    """Camera-frame sole points (T, 8, 3) and pelvis up axes (T, 3) of a camera-frame pose
    (TPNet's, or the per-frame fit's: :func:`fitted_frames`)."""
    q_cam = tp.q_hat.at[:, 0:3].set(tp.trans_cam).at[:, 3:7].set(mat_to_quat(tp.rot_cam))

    def soles(q):
        return S.sole_points(model, P.forward_kinematics(model, q))[0]

    return jax.vmap(soles)(q_cam), tp.rot_cam[:, :, 2]


def fit_floor(points: Array, body_up: Array, mask: Array, config: FloorConfig | None = None,
              iterations: int = 8) -> tuple[Array, Array, Array]:
    """The floor plane ``up . X + height = 0`` (camera frame) from per-frame foot points and body
    up axes.

    ``points`` (T, P, 3): candidate floor points per frame (the sole points; the lowest along the
    current up direction is taken); ``body_up`` (T, 3) unit vectors; ``mask`` (T,) real frames.
    Returns ``(up (3,), height (), support ())``; see the module docstring for the method.
    """
    config = config or FloorConfig()
    dtype = points.dtype
    m = jnp.asarray(mask, dtype)
    ok = jnp.all(jnp.isfinite(points), (-1, -2)) & jnp.all(jnp.isfinite(body_up), -1)
    m = m * ok
    points = jnp.where(ok[:, None, None], points, 0.0)
    body_up = jnp.where(ok[:, None], body_up, 0.0)

    # 2. the body's up, robustly averaged
    lean = jnp.deg2rad(jnp.asarray(config.lean_scale_deg, dtype))
    u = safe_normalize(jnp.sum(m[:, None] * body_up, 0) + jnp.array([0.0, -1e-9, 0.0], dtype))
    for _ in range(3):
        ang = jnp.arccos(jnp.clip(body_up @ u, -1.0, 1.0))
        w = m * _geman_mcclure_weight(ang, lean)
        u = safe_normalize(jnp.sum(w[:, None] * body_up, 0) + jnp.array([0.0, -1e-9, 0.0], dtype))
    u_body = u

    # 3. the plane through the lowest points, normal near u_body
    sigma_h = jnp.asarray(config.height_scale_m, dtype)
    sigma_t = jnp.deg2rad(jnp.asarray(config.tilt_sigma_deg, dtype))
    n = u_body
    s = jnp.min(points @ n, -1)  # (T,) the lowest point's coordinate along n
    height = -_masked_median(s, m)
    scale = 4.0 * sigma_h
    for it in range(iterations):
        low = jnp.take_along_axis(points, jnp.argmin(points @ n, -1)[:, None, None], 1)[:, 0]  # (T, 3)
        # tangent basis at n
        a1 = safe_normalize(jnp.cross(n, jnp.where(jnp.abs(n[0]) < 0.9, jnp.array([1.0, 0, 0], dtype),
                                          jnp.array([0, 0, 1.0], dtype))))
        a2 = jnp.cross(n, a1)
        r = low @ n + height
        w = m * _geman_mcclure_weight(r, scale) / jnp.square(scale)
        A = jnp.stack([low @ a1, low @ a2, jnp.ones_like(r)], -1)  # d r / d (alpha, beta, height)
        # the prior pulls n towards u_body: residual (n + alpha a1 + beta a2 - u_body) . a_i / sigma_t
        pr = jnp.stack([(n - u_body) @ a1, (n - u_body) @ a2])
        H = (A * w[:, None]).T @ A + jnp.diag(jnp.concatenate([jnp.full(2, 1.0, dtype) / jnp.square(sigma_t),
                                                                 jnp.zeros(1, dtype)]))
        g = (A * w[:, None]).T @ r + jnp.concatenate([pr / jnp.square(sigma_t), jnp.zeros(1, dtype)])
        step = -solve_spd3(H + 1e-9 * jnp.eye(3, dtype=dtype), g)
        n = safe_normalize(n + step[0] * a1 + step[1] * a2)
        height = height + step[2]
        # graduated non-convexity: the robust scale shrinks from 4 sigma_h to sigma_h
        scale = jnp.maximum(sigma_h, scale * 0.5) if it < iterations - 1 else sigma_h
    low = jnp.min(points @ n, -1)
    r = low + height
    support = jnp.sum(m * (jnp.abs(r) < 3.0 * sigma_h)) / jnp.maximum(jnp.sum(m), 1.0)
    return n, height, support


def _masked_median(x: Array, m: Array) -> Array:
    """Median of ``x`` over ``m > 0`` (lower median; 0 without any)."""
    n = jnp.sum(m > 0)
    xs = jnp.sort(jnp.where(m > 0, x, jnp.inf))
    return jnp.where(n > 0, xs[jnp.maximum((n - 1) // 2, 0)], 0.0)


def extrinsics_from_floor(up: Array, height: Array, centre_cam: Array) -> Array:
    """World -> camera (4, 4) of a camera ``height`` above the floor whose up direction it sees as
    ``up`` (camera frame), with world y along the optical axis projected on the floor and the
    world origin on the floor under ``centre_cam`` (a camera-frame point, e.g. the person)."""
    dtype = up.dtype
    z = safe_normalize(up)
    fwd = jnp.array([0.0, 0.0, 1.0], dtype)
    y = fwd - (fwd @ z) * z
    # a camera looking straight down: the image's up direction instead
    alt = jnp.array([0.0, -1.0, 0.0], dtype)
    y = jnp.where(jnp.linalg.norm(y) > 1e-6, y, alt - (alt @ z) * z)
    y = safe_normalize(y)
    x = jnp.cross(y, z)
    R = jnp.stack([x, y, z], 1)  # columns: world axes in the camera frame -> X_c = R X_w + t
    # world coordinates of the centre with the camera at (0, 0, height): R^T X_c + (0, 0, height)
    c_w = centre_cam @ R + jnp.array([0.0, 0.0, 1.0], dtype) * height
    cam_w = jnp.array([0.0, 0.0, 1.0], dtype) * height - c_w.at[2].set(0.0)
    t = -R @ cam_w
    E = jnp.eye(4, dtype=dtype).at[:3, :3].set(R).at[:3, 3].set(t)
    return E


def camera_angles(up: Array) -> tuple[Array, Array]:
    """``(pitch, roll)`` in degrees of a camera that sees the world's up as ``up`` (OpenCV axes:
    a level camera sees up as (0, -1, 0)); pitch > 0 looks down; roll > 0 when the world's up
    appears tilted towards the image's +x (right)."""
    pitch = jnp.rad2deg(jnp.arcsin(jnp.clip(-up[2], -1.0, 1.0)))
    roll = jnp.rad2deg(jnp.arctan2(up[0], -up[1]))
    return pitch, roll


def camera_angles_inverse(pitch_deg, roll_deg) -> Array:
    """The up direction (camera frame) of a camera with these angles (:func:`camera_angles`)."""
    dtype = jnp.result_type(float)
    p, r = jnp.deg2rad(jnp.asarray(pitch_deg, dtype)), jnp.deg2rad(jnp.asarray(roll_deg, dtype))
    return jnp.stack([jnp.cos(p) * jnp.sin(r), -jnp.cos(p) * jnp.cos(r), -jnp.sin(p)])


def floor_from_target(model: Model, tp: S.TargetPose, mask: Array, config: FloorConfig | None = None) -> FloorEstimate:
    """The floor estimate from a camera-frame pose ``tp`` of a clip (TPNet's or the per-frame
    fit's; ``mask``: real frames)."""
    config = config or FloorConfig()
    pts, body_up = body_frame_points(model, tp)
    m = jnp.asarray(mask) & (tp.trans_cam[:, 2] > 0.1)  # a root behind the camera says nothing
    up, height, support = fit_floor(pts, body_up, m, config)
    mf = m.astype(pts.dtype)
    centre = jnp.sum(mf[:, None] * tp.trans_cam, 0) / jnp.maximum(jnp.sum(mf), 1.0)
    E = extrinsics_from_floor(up, height, centre)
    pitch, roll = camera_angles(up)
    frames = jnp.sum(m)
    usable = ((frames >= config.min_frames) & (height > 0.0) & (height < config.max_height_m)
              & (support >= config.min_support) & jnp.all(jnp.isfinite(E)))
    return FloorEstimate(E, up, height, pitch, roll, support, frames, usable)


def estimate_floor(params: dict, model: Model, inputs: ClipInputs, config: Any,
                   floor: FloorConfig | None = None) -> FloorEstimate:
    """The floor of one clip from its 2D keypoints: TPNet (``params["tpnet"]``; ``config``, a
    video method's config, gives the layout and network sizes) in the camera frame, every frame
    fitted to its keypoints (:func:`fitted_frames`), then :func:`floor_from_target`. The clip's
    own ``inputs.extrinsics`` are not read."""
    tp = S.target_pose(params, model, inputs, config)
    return floor_from_target(model, fitted_frames(model, tp, inputs, config), inputs.mask, floor)


def fitted_frames(model: Model, tp: S.TargetPose, inputs: ClipInputs, config: Any) -> S.TargetPose:
    """``tp`` with every frame fitted to its 2D keypoints, in the camera frame.

    TPNet's camera-frame depth is too coarse to find the floor by itself (docs/evaluation.md,
    "The floor of an uncalibrated camera"): every frame is fitted to its keypoints first, by
    ``trajopt``'s per-frame stage (:func:`jmocap.methods.trajopt.per_frame_fit`: robust
    reprojection, TPNet's pose as prior, joint limits, the root-depth track) *without* any
    floor or contact term, so the fitted camera-frame poses do not depend on any camera
    placement (the fit runs in the default camera's world and is moved back). ``config``: the
    per-frame stage's settings, a :class:`jmocap.methods.trajopt.TrajOptConfig` or any video
    method's config (then trajopt's defaults with its learned-stage fields)."""
    from jmocap.camera import default_extrinsics
    from jmocap.methods import trajopt as TO

    if not isinstance(config, TO.TrajOptConfig):
        config = TO.TrajOptConfig(layout=config.layout, canonicalise=config.canonicalise, nets=config.nets)
    dtype = tp.q_hat.dtype
    E = jnp.asarray(default_extrinsics(), dtype)
    inputs = inputs.with_static_camera(E)
    R, t = E[:3, :3], E[:3, 3]
    q_hat = S.root_in_world(tp.q_hat, tp.rot_cam, tp.trans_cam, E)
    # The floor is read off the fitted bodies' stance relative to the camera, and in this fit
    # nothing else holds it (no floor, contact or smoothness term; the world's vertical is the
    # default camera's guess): the prior keeps TPNet's orientation of the body and the weight it
    # was measured with (trajopt's own fit turns the prior and weighs it 4 since stop 57), and the
    # limits on the Euler angles as written (trajopt judges either triple since stop 58; not
    # measured here).
    no_floor = config.replace(w_floor=0.0, w_accel=0.0, w_contact_vel=0.0, prior_rotation="tpnet",
                              w_pose=FIT_W_POSE, limit_branches=False)
    prob = TO.problem(model, inputs, q_hat, jnp.zeros(tp.contact_logits.shape, dtype), no_floor)
    q1 = TO.per_frame_fit(model, q_hat, prob, no_floor, config.frame_iterations, config.gm_scale_initial,
                          config.gm_scale, TO.depth_track(q_hat, prob, no_floor), None, tile=config.frame_tile)
    return tp.replace(q_hat=q1, trans_cam=q1[:, 0:3] @ R.T + t,
                      rot_cam=jnp.einsum("ij,tjk->tik", R, jax.vmap(quat_to_mat)(q1[:, 3:7])))


def change_world(E_from: Array, E_to: Array) -> tuple[Array, Array]:
    """``(R, t)`` taking world points of a camera with extrinsics ``E_from`` to the world of the
    same camera with extrinsics ``E_to``: ``X_to = R X_from + t`` (``E_to^-1 E_from``, with the
    rigid transform's closed-form inverse: no LAPACK on the batch path)."""
    R_to, t_to = E_to[:3, :3], E_to[:3, 3]
    return R_to.T @ E_from[:3, :3], R_to.T @ (E_from[:3, 3] - t_to)


def move_motion(motion, R: Array, t: Array):
    """A :class:`jmocap.motion.Motion` (one clip, (T, ...)) moved rigidly, ``X -> R X + t``: the
    root's position and orientation (``q``, ``target_q``), its world-frame linear velocity and
    residual force (``qd[:, :3]``, ``tau[:, :3]``; the angular parts are in the root's own frame
    and stay), the contact forces and an estimated camera track (each camera sees the moved
    world as it saw the old one). Hinges, probabilities and diagnostics are unchanged."""
    qR = mat_to_quat(R)
    track = motion.camera_track
    if track is not None:  # E' = E [R t; 0 1]^-1: camera' X' = camera X
        rot = track[..., :3, :3] @ R.T
        track = track.at[..., :3, :3].set(rot).at[..., :3, 3].set(track[..., :3, 3] - rot @ t)

    def move_q(q):
        pos = q[:, 0:3] @ R.T + t
        quat = quat_mul(qR, q[:, 3:7])  # (broadcasts over frames)
        return q.at[:, 0:3].set(pos).at[:, 3:7].set(quat)

    return motion.replace(
        q=move_q(motion.q), target_q=move_q(motion.target_q), qd=motion.qd.at[:, 0:3].set(motion.qd[:, 0:3] @ R.T),
        tau=motion.tau.at[:, 0:3].set(motion.tau[:, 0:3] @ R.T), grf=motion.grf @ R.T, camera_track=track,
    )


__all__ = [
    "FloorConfig",
    "FloorEstimate",
    "body_frame_points",
    "camera_angles",
    "camera_angles_inverse",
    "change_world",
    "estimate_floor",
    "extrinsics_from_floor",
    "fit_floor",
    "fitted_frames",
    "floor_from_target",
    "move_motion",
]
