"""Evaluation metrics of 3D human motion capture: pose, body orientations and travelled-distance
translation drift (sparse-IMU capture), smoothness, 2D reprojection, foot-floor contact, dynamics
and contact classification, each exactly as its source paper defines it.

Papers (full text in ``shared/papers/``): [000] Shimada et al. 2021, Neural PhysCap; [001]
Rempe et al. 2020, Contact and Human Dynamics from Monocular Video; [002] Yi et al. 2022, PIP.
``docs/evaluation.md`` restates every definition with its units and the choices made where a
paper is silent.

Conventions
-----------
* Every metric is pure ``jax.numpy`` wrapped in ``jax.jit`` (options that shape the computation,
  ``align``, ``root``, ``steps``, are static), so it composes with ``jit`` and ``vmap``
  and compiles once per shape. Arrays have any leading batch dimensions, then frames: joints
  ``(..., T, J, 3)`` in metres in the z-up world (floor z = 0), foot points ``(..., T, P, 3)``,
  contact labels ``(..., T, P)``; per-clip scalars (fps, weights) are () or the batch shape.
  The foot-floor metrics take an optional ``scene`` (:class:`jmocap.scene.Scene`): heights are
  then signed distances to the floor and its boxes.
* ``mask`` (``(..., T)`` bool, default all True) marks the real frames; a metric averages over
  real frames only. A finite difference is used only where every frame it reads is real.
* A metric whose selection is empty (no real frame, no in-contact frame, no flight frame, ...)
  returns NaN: it is undefined there, not zero. :func:`evaluate_arrays` validates that its inputs
  are finite first, so a NaN it sees can only mean "undefined", and it leaves that key out.
* Pose errors are reported in millimetres, as the papers do; other units are in the names of
  the keys of :func:`evaluate_arrays` (``_mm``, ``_pct``, ``_px``, ``_m``, ...).
* Wrong shapes raise ``ValueError`` naming the argument and its shape.

Physics helpers (:func:`motion_quantities`, :func:`zero_moment_point`) read a
:class:`jmocap.Model` and reuse :mod:`jmocap.physics`; they are jit/vmap-able as well.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jmocap import physics as P
from jmocap.camera import Camera, default_extrinsics, project, world_to_camera
from jmocap.constants import FRICTION_MU, GRAVITY  # the body weight is mass * GRAVITY
from jmocap.model import Model, character
from jmocap.numerics import safe_div, safe_norm, safe_normalize
from jmocap.physics.contact import sole_half_width
from jmocap.physics.linalg import det3
from jmocap.physics.rotations import quat_to_mat

Array = jnp.ndarray

PCK_THRESHOLD_MM = 150.0
AUC_MAX_MM = 150.0
AUC_STEPS = 31  # thresholds 0, 5, ..., 150 mm
FLOAT_THRESHOLD_M = 0.03  # Rempe et al. [001] Sec. 4.3: floating / penetration 3 cm, skate 2 cm
PENETRATION_THRESHOLD_M = 0.03
SKATE_THRESHOLD_M = 0.02
CONTACT_MAX_STEP_M = 0.02  # Rempe et al. [001] Sec. 3.2 contact labelling rule
CONTACT_MAX_HEIGHT_M = 0.05
PNP_TOLERANCE_M = 0.001  # PNP: penetration deeper than 1 mm (the paper gives no tolerance)
ZMP_MIN_NORMAL_FORCE = 0.1  # frames whose implied vertical force is below 10 % of body weight
#: a ground-truth frame's motion is explained by its contact forces while the ground truth's own
#: root residual (the virtual force of a simulated clip's rescue, ``gt tau[:3]``, docs/data.md)
#: is at most this share of body weight (%). Only such frames score the forces (net GRF error,
#: per-foot correlation) and count as ballistic: a "flight" held up by a force no person has is
#: not a free fall, and an estimate that puts that force on the feet is not wrong there
GT_MAX_RESIDUAL_PCT_BW = 1.0
ALIGNMENTS = ("none", "root", "procrustes")


# =========================================================================================
# validation and masked reductions
# =========================================================================================


def _points(x, name: str, dims: str = "T, J, 3") -> Array:
    """``x`` as an array of shape ``(..., <dims>)``, e.g. ``dims = "T, J, 3"``: at least that
    many dimensions, numeric entries checked; ValueError naming ``name`` otherwise."""
    x = jnp.asarray(x)
    parts = [d.strip() for d in dims.split(",")]
    tail = x.shape[x.ndim - len(parts):] if x.ndim >= len(parts) else None
    if tail is None or any(d.isdigit() and int(d) != n for d, n in zip(parts, tail, strict=True)):
        raise ValueError(f"{name} must have shape (..., {dims}), got {tuple(x.shape)}")
    return x


def _same(a: Array, b: Array, na: str, nb: str) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{na} and {nb} must have the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")


def _frame_mask(mask, lead: tuple[int, ...]) -> Array:
    """The (..., T) frame mask (all True when None), checked against the arrays' (..., T)."""
    if mask is None:
        return jnp.ones(lead, bool)
    m = jnp.asarray(mask)
    if m.shape != tuple(lead):
        raise ValueError(f"mask must have shape (..., T) = {tuple(lead)}, got {tuple(m.shape)}")
    return m.astype(bool)


def _joint_mask(mask, shape: tuple[int, ...]) -> Array:
    """A mask for per-joint values of shape (..., T, J): a frame mask (..., T) (all True when
    None) broadcast over the joints, or a per-joint mask (..., T, J) as it is (a joint missing in
    a frame, e.g. a ground truth that has only some joints, or a marker lost for a while)."""
    if mask is not None and jnp.ndim(mask) == len(shape):
        m = jnp.asarray(mask)
        if m.shape != tuple(shape):
            raise ValueError(f"mask must have shape (..., T) or (..., T, J) = {tuple(shape)}, got {tuple(m.shape)}")
        return m.astype(bool)
    return jnp.broadcast_to(_frame_mask(mask, shape[:-1])[..., None], shape)


def _diff_mask(mask: Array, n: int) -> Array:
    """(..., T) -> (..., T - n): True where frames t .. t + n are all real (an n-th difference)."""
    T = mask.shape[-1]
    out = mask[..., : T - n]
    for k in range(1, n + 1):
        out = out & mask[..., k : T - n + k]
    return out


def _central_mask(mask: Array) -> Array:
    """(..., T): True where frame t and both neighbours are real (a central difference)."""
    inner = _diff_mask(mask, 2)
    pad = jnp.zeros(mask.shape[:-1] + (1,), bool)
    return jnp.concatenate([pad, inner, pad], -1)


def _mean(x: Array, w: Array, nd: int) -> Array:
    """Weighted mean over the last ``nd`` axes of ``x``: ``sum(w x) / sum(w)``, NaN when
    ``sum(w) == 0`` (entries with zero weight never contribute, even if not finite)."""
    w = jnp.broadcast_to(w, x.shape).astype(x.dtype)
    axes = tuple(range(-nd, 0))
    s = jnp.sum(w, axis=axes)
    num = jnp.sum(jnp.where(w > 0, x, 0.0) * w, axis=axes)
    return jnp.where(s > 0, num / jnp.where(s > 0, s, 1.0), jnp.nan)


def _std(x: Array, w: Array, nd: int) -> Array:
    """Population standard deviation (ddof 0) over the last ``nd`` axes; NaN when empty."""
    mu = _mean(x, w, nd).reshape(x.shape[: x.ndim - nd] + (1,) * nd)
    return jnp.sqrt(_mean((x - mu) ** 2, w, nd))


def _pct(count: Array, total: Array) -> Array:
    """100 count / total, NaN when total == 0."""
    return jnp.where(total > 0, 100.0 * count / jnp.where(total > 0, total, 1), jnp.nan)


def _bcast(value, dtype, trailing: int) -> Array:
    """A per-clip scalar (fps, weight, mass: shape () or the batch shape (...,)) reshaped to
    broadcast against arrays with ``trailing`` more dimensions."""
    v = jnp.asarray(value, dtype)
    return v.reshape(v.shape + (1,) * trailing)


# =========================================================================================
# pose (3D joint positions)
# =========================================================================================


@partial(jax.jit, static_argnames=("root",))
def root_position(joints: Array, root=(0,)) -> Array:
    """(..., T, J, 3) -> (..., T, 3): the root, the mean of the joints ``root`` (a layout's
    ``root_indices``: MidHip for BODY_25, Hip for H36M, the two hips for COCO)."""
    joints = _points(joints, "joints")
    return jnp.mean(joints[..., np.asarray(root, int), :], axis=-2)


@partial(jax.jit, static_argnames=("root",))
def root_align(joints: Array, root=(0,)) -> Array:
    """Joints relative to their root, per frame: ``p_j - root``."""
    return joints - root_position(joints, root)[..., None, :]


@jax.jit
def procrustes_align(pred: Array, gt: Array, weights=None) -> Array:
    """``pred`` (..., J, 3) moved onto ``gt`` by the least-squares similarity transform per
    frame: ``s R p + t`` with scale s > 0, a *proper* rotation R (det R = +1: a mirrored pose is
    not a rotated pose) and translation t (Umeyama 1991, IEEE TPAMI 13(4), eqs. 38-42).

    With the centred point sets X (pred) and Y (gt), ``X^T Y = U S V^T``,
    ``R = V diag(1, 1, d) U^T`` with ``d = sign det(V U^T)``, ``s = tr(diag(1, 1, d) S) / |X|^2``.
    ``weights`` (..., J) (0/1: a joint mask) fit the transform to the weighted joints only
    (means and sums weighted; joints of weight 0 may hold NaN) and move every joint by it.
    """
    pred = _points(pred, "pred", "J, 3")
    gt = _points(gt, "gt", "J, 3")
    _same(pred, gt, "pred", "gt")
    if weights is None:
        w = jnp.ones(pred.shape[:-1], pred.dtype)
    else:
        w = jnp.broadcast_to(jnp.asarray(weights, pred.dtype), pred.shape[:-1])
    wn = (w / jnp.maximum(jnp.sum(w, -1, keepdims=True), 1e-12))[..., None]
    use = w[..., None] > 0
    pred0, gt0 = jnp.where(use, pred, 0.0), jnp.where(use, gt, 0.0)
    mp = jnp.sum(wn * pred0, -2, keepdims=True)
    mg = jnp.sum(wn * gt0, -2, keepdims=True)
    X, Y = (pred0 - mp) * jnp.sqrt(wn), (gt0 - mg) * jnp.sqrt(wn)
    H = jnp.swapaxes(X, -1, -2) @ Y  # sum_j x_j y_j^T
    U, S, Vt = jnp.linalg.svd(H)
    # det in closed form: one LAPACK call (the SVD) per program, never two at once (linalg docs)
    d = jnp.where(det3(U @ Vt) < 0, -1.0, 1.0).astype(pred.dtype)
    c = jnp.concatenate([jnp.ones(d.shape + (2,), pred.dtype), d[..., None]], -1)  # diag(1, 1, d)
    R = jnp.swapaxes(Vt, -1, -2) @ (c[..., :, None] * jnp.swapaxes(U, -1, -2))
    s = safe_div(jnp.sum(c * S, -1), jnp.sum(X * X, axis=(-1, -2)))
    return s[..., None, None] * ((pred - mp) @ jnp.swapaxes(R, -1, -2)) + mg


@partial(jax.jit, static_argnames=("align", "root"))
def joint_errors(pred: Array, gt: Array, align: str = "root", root=(0,), weights=None) -> Array:
    """Per-joint Euclidean errors (..., T, J) in metres after an alignment.

    ``align``: ``"none"`` (absolute: world coordinates as they are), ``"root"`` (each pose
    translated so that its root is at the origin: the standard "MPJPE without Procrustes" of
    [000] Table 1) or ``"procrustes"`` (per-frame similarity alignment, :func:`procrustes_align`,
    fitted to the joints of nonzero ``weights`` (..., T, J) when given).
    """
    pred = _points(pred, "pred")
    gt = _points(gt, "gt")
    _same(pred, gt, "pred", "gt")
    if align == "root":
        pred, gt = root_align(pred, root), root_align(gt, root)
    elif align == "procrustes":
        pred = procrustes_align(pred, gt, weights)
    elif align != "none":
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    return jnp.linalg.norm(pred - gt, axis=-1)


def _errors_mm(pred, gt, mask, align, root):
    """Per-joint errors (mm) and their weights. ``mask``: (..., T) frames or (..., T, J) joints
    (a frame counts for root alignment only where every root joint is present)."""
    shape = jnp.shape(pred)[:-1]
    m = _joint_mask(mask, shape)
    if align == "root":
        m = m & jnp.all(m[..., np.asarray(root, int)], -1, keepdims=True)
    err = joint_errors(pred, gt, align, root, m.astype(jnp.result_type(pred)) if align == "procrustes" else None)
    return err * 1000.0, m


@partial(jax.jit, static_argnames=("align", "root"))
def mpjpe(pred: Array, gt: Array, mask=None, *, align: str = "root", root=(0,)) -> Array:
    """Mean per-joint position error (mm): the mean over real frames and joints of
    ``|p_pred - p_gt|`` after ``align`` (root-aligned by default; ``"none"`` for the absolute,
    global error; ``"procrustes"`` for PA-MPJPE). [000] Table 1, Sec. 4.3. Root-aligned, it is
    TransPose's *positional error* as its paper defines it (the mean Euclidean error of all
    joints with the root joint aligned; there in cm, here in mm; its evaluation script also
    aligns the root orientation: :func:`mpjpe_root_frame`)."""
    err, w = _errors_mm(pred, gt, mask, align, root)
    return _mean(err, w, 2)


@jax.jit
def pa_mpjpe(pred: Array, gt: Array, mask=None) -> Array:
    """Procrustes-aligned MPJPE (mm): per-frame similarity alignment with scale and a proper
    rotation (reflections are not allowed), then MPJPE. [000] Table 1 ("Procrustes")."""
    return mpjpe(pred, gt, mask, align="procrustes")


def _pck_of(err_mm: Array, w: Array, threshold_mm: float) -> Array:
    return 100.0 * _mean((err_mm < threshold_mm).astype(err_mm.dtype), w, 2)


def _auc_of(err_mm: Array, w: Array, max_mm: float, steps: int) -> Array:
    th = jnp.linspace(0.0, max_mm, steps, dtype=err_mm.dtype)
    passed = (err_mm[..., None] < th).astype(err_mm.dtype).mean(-1)  # share of thresholds met
    return 100.0 * _mean(passed, w, 2)


@partial(jax.jit, static_argnames=("align", "root"))
def pck(pred: Array, gt: Array, mask=None, *, threshold_mm: float = PCK_THRESHOLD_MM,
        align: str = "root", root=(0,)) -> Array:
    """Percentage of correct keypoints (%): joints whose error is below ``threshold_mm``
    (150 mm, the MPI-INF-3DHP protocol used by [000] Table 1), after ``align``."""
    return _pck_of(*_errors_mm(pred, gt, mask, align, root), threshold_mm)


@partial(jax.jit, static_argnames=("steps", "align", "root"))
def auc(pred: Array, gt: Array, mask=None, *, max_mm: float = AUC_MAX_MM, steps: int = AUC_STEPS,
        align: str = "root", root=(0,)) -> Array:
    """Area under the PCK curve (%): the mean of PCK (error strictly below the threshold) at
    ``steps`` thresholds evenly spaced over 0..``max_mm`` (0, 5, ..., 150 mm: 31 thresholds),
    after ``align``. [000] Table 1 (MPI-INF-3DHP protocol). PCK at 0 mm is always 0, so a
    perfect estimate scores 30/31 = 96.8 %."""
    return _auc_of(*_errors_mm(pred, gt, mask, align, root), max_mm, steps)


@partial(jax.jit, static_argnames=("root",))
def root_translation_error(pred: Array, gt: Array, mask=None, *, root=(0,)) -> Array:
    """Global root translation error (mm): mean over real frames of ``|r_pred - r_gt|``, r the
    root joint (:func:`root_position`) in world coordinates. [000] Table 2. A per-joint ``mask``
    (..., T, J) counts the frames where every root joint is present."""
    pred = _points(pred, "pred")
    gt = _points(gt, "gt")
    _same(pred, gt, "pred", "gt")
    e = jnp.linalg.norm(root_position(pred, root) - root_position(gt, root), axis=-1) * 1000.0
    m = jnp.all(_joint_mask(mask, pred.shape[:-1])[..., np.asarray(root, int)], -1)
    return _mean(e, m, 1)


# =========================================================================================
# sparse-IMU pose and translation: body orientations, root-frame joints, travelled distance
# (PIP [002] Sec. 4 and Fig. 3, after TransPose, Yi et al. 2021, Sec. 5)
# =========================================================================================

#: The bodies whose global orientation the SIP error scores ("upper arms and legs", [002] Sec. 4),
#: in the order of SMPL's joints 1, 2, 16, 17 (L_Hip, R_Hip, L_Shoulder, R_Shoulder) that
#: TransPose's and PIP's evaluation (``joint_mask=[1, 2, 16, 17]``) reads. An SMPL joint's
#: global rotation is that of the bone below it; on jmocap's character (``assets/mjcf/humanoid.xml``)
#: the MuJoCo body that carries the hip joints and spans hip -> knee is ``left_hip`` /
#: ``right_hip`` (the thigh), and the body that carries the shoulder joints and spans shoulder ->
#: elbow is ``left_shoulder`` / ``right_shoulder`` (the upper arm). (As :data:`jmocap.data.imu.
#: SENSOR_BODIES` names the forearm ``left_elbow`` and the lower leg ``left_knee``.)
SIP_BODIES = ("left_hip", "right_hip", "left_shoulder", "right_shoulder")
#: the distances (m) of PIP's cumulative translation error curve (its evaluation script: 1..7 m)
TRANSLATION_DISTANCES_M = (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0)


def body_rotations(model: Model, q: Array, bodies: tuple[str, ...] | None = None) -> Array:
    """World orientations (..., T, B, 3, 3) of the MuJoCo ``bodies`` (names; default: every body
    but the world, in the model's order) along a trajectory ``q`` (..., T, nq), by forward
    kinematics (:func:`jmocap.physics.forward_kinematics`, ``xmat``: columns are the body's axes
    in the world). jit/vmap-able (the names are static). On jmocap's character every body frame
    is the world frame at the rest pose (a T-pose facing +x), so orientations of characters of
    different sizes compare directly. For the SIP error: ``body_rotations(model, q, SIP_BODIES)``;
    the root (pelvis) orientation: ``body_rotations(model, q, ("pelvis",))[..., 0, :, :]``."""
    return _body_rotations(model, q, None if bodies is None else tuple(bodies))


@partial(jax.jit, static_argnames=("bodies",))
def _body_rotations(model: Model, q: Array, bodies) -> Array:
    q = _points(q, "q", f"T, {model.nq}")
    ids = np.arange(1, model.topo.nbody) if bodies is None else np.array([model.body_id(b) for b in bodies], int)
    flat = q.reshape(-1, model.nq)
    R = jax.vmap(lambda x: P.forward_kinematics(model, x).xmat[ids])(flat)
    return R.reshape(q.shape[:-1] + (len(ids), 3, 3))


@jax.jit
def rotation_angle_deg(a: Array, b: Array) -> Array:
    """Geodesic distance (degrees, 0..180) between rotation matrices a, b (..., 3, 3): the angle
    of the relative rotation ``D = a^T b``, ``atan2(|vee(D - D^T)|, tr D - 1)`` (= arccos((tr D -
    1) / 2), without arccos's loss of precision near 0)."""
    d = jnp.swapaxes(a, -1, -2) @ b
    two_cos = d[..., 0, 0] + d[..., 1, 1] + d[..., 2, 2] - 1.0
    two_sin = jnp.stack([d[..., 2, 1] - d[..., 1, 2], d[..., 0, 2] - d[..., 2, 0], d[..., 1, 0] - d[..., 0, 1]], -1)
    return jnp.degrees(jnp.arctan2(safe_norm(two_sin), two_cos))


def _rotations(pred_rot, gt_rot, pred_root, gt_root):
    pred_rot = _points(pred_rot, "pred_rot", "T, B, 3, 3")
    gt_rot = _points(gt_rot, "gt_rot", "T, B, 3, 3")
    _same(pred_rot, gt_rot, "pred_rot", "gt_rot")
    if (pred_root is None) != (gt_root is None):
        raise ValueError("pred_root and gt_root must be given together (root orientation aligned) or not at all")
    if pred_root is not None:
        want = pred_rot.shape[:-3] + (3, 3)
        for name, r in (("pred_root", pred_root), ("gt_root", gt_root)):
            if jnp.shape(r) != want:
                raise ValueError(f"{name} must have shape (..., T, 3, 3) = {want}, got {tuple(jnp.shape(r))}")
        # each body's orientation in its own root's frame: R_root^T R_b
        pred_rot = jnp.swapaxes(jnp.asarray(pred_root), -1, -2)[..., None, :, :] @ pred_rot
        gt_rot = jnp.swapaxes(jnp.asarray(gt_root), -1, -2)[..., None, :, :] @ gt_rot
    return pred_rot, gt_rot


@jax.jit
def orientation_errors(pred_rot: Array, gt_rot: Array, pred_root=None, gt_root=None) -> Array:
    """Per-body orientation errors (..., T, B) in degrees: :func:`rotation_angle_deg` between the
    estimated and true world orientations (..., T, B, 3, 3) of each body (global: no alignment).
    With the root orientations ``pred_root``, ``gt_root`` (..., T, 3, 3) (both or neither) the
    root orientation is aligned: each body is compared in its own root's frame,
    ``angle((R̂_root^T R̂_b)^T (R_root^T R_b))``."""
    p, g = _rotations(pred_rot, gt_rot, pred_root, gt_root)
    return rotation_angle_deg(p, g)


@jax.jit
def angular_error(pred_rot: Array, gt_rot: Array, mask=None, *, pred_root=None, gt_root=None) -> Array:
    """Angular error (degrees), TransPose Sec. 5 (the mean global rotation error of all body
    joints): the mean over the B bodies given and the real frames of :func:`orientation_errors`
    of the world orientations (..., T, B, 3, 3), e.g. of every body of the character
    (:func:`body_rotations` with ``bodies=None``). Global by default; ``pred_root``/``gt_root``
    align the root orientation (see :func:`sip_error`). ``mask``: (..., T) frames or (..., T, B)
    bodies. jmocap's character has other bodies than SMPL's 24 joints, so the value is not
    comparable with the papers' numbers beyond its meaning."""
    e = orientation_errors(pred_rot, gt_rot, pred_root, gt_root)
    return _mean(e, _joint_mask(mask, e.shape), 2)


@jax.jit
def sip_error(pred_rot: Array, gt_rot: Array, mask=None, *, pred_root=None, gt_root=None) -> Array:
    """SIP error (degrees), PIP [002] Sec. 4: "the mean orientation error of the upper arms and
    legs in the global space": the mean over the four :data:`SIP_BODIES` and the real frames of
    the geodesic angle between estimated and true world orientations. ``pred_rot``, ``gt_rot``
    (..., T, 4, 3, 3) are those of :data:`SIP_BODIES` (``body_rotations(model, q, SIP_BODIES)``).

    **Global** by default, as the paper states: no alignment, so an error of the root (pelvis)
    orientation counts in every body. PIP's and TransPose's evaluation scripts set SMPL's root
    (pelvis) rotation to the identity in estimate and truth before forward kinematics, i.e. they
    compare the bodies in the pelvis frame; passing ``pred_root``, ``gt_root`` (..., T, 3, 3)
    (the pelvis orientations) reproduces that (root orientation aligned). With six IMUs the
    pelvis orientation is measured, so the two differ little there; for a monocular method they
    can differ by the whole heading error. ``mask``: (..., T) frames or (..., T, 4) bodies.
    """
    if jnp.ndim(pred_rot) >= 4 and jnp.shape(pred_rot)[-3] != len(SIP_BODIES):
        raise ValueError(f"pred_rot must hold the {len(SIP_BODIES)} SIP_BODIES {SIP_BODIES}: shape (..., T, 4, 3, 3), "
                         f"got {tuple(jnp.shape(pred_rot))}")
    return angular_error(pred_rot, gt_rot, mask, pred_root=pred_root, gt_root=gt_root)


@partial(jax.jit, static_argnames=("root",))
def mpjpe_root_frame(pred: Array, gt: Array, pred_root: Array, gt_root: Array, mask=None, *, root=(0,)) -> Array:
    """MPJPE (mm) with root position **and** orientation aligned: the mean over real frames and
    joints of ``|R̂^T (p̂ - r̂) - R^T (p - r)|``, each pose's joints (..., T, J, 3) relative to its
    root joint r (:func:`root_position`, the layout's ``root``) and expressed in its root body's
    frame (``pred_root``, ``gt_root`` (..., T, 3, 3): the pelvis orientations, e.g.
    ``quat_to_mat(q[..., 3:7])``); equivalently the estimate rotated about its root by
    ``R R̂^T`` onto the truth's root orientation.

    jmocap's mesh-free stand-in for PIP's *mesh error* ([002] Sec. 4: "the mean vertex distance
    between the reconstructed and ground-truth meshes with both root position and orientation
    aligned", cm): the same alignment on the layout's joints instead of SMPL's 6890 vertices
    (jmocap ships no SMPL mesh), in mm. It is also what TransPose's and PIP's scripts compute
    as "positional error" (their SMPL pelvis rotation set to the identity, root joint position
    aligned); TransPose's paper words it with the root position aligned only, which is
    :func:`mpjpe` (``align="root"``). ``mask``: (..., T) frames or (..., T, J) joints.
    """
    pred = _points(pred, "pred")
    gt = _points(gt, "gt")
    _same(pred, gt, "pred", "gt")
    want = pred.shape[:-2] + (3, 3)
    for name, r in (("pred_root", pred_root), ("gt_root", gt_root)):
        if jnp.shape(r) != want:
            raise ValueError(f"{name} must have shape (..., T, 3, 3) = {want}, got {tuple(jnp.shape(r))}")
    a = root_align(pred, root) @ jnp.asarray(pred_root, pred.dtype)  # rows: (R^T x)^T = x^T R
    b = root_align(gt, root) @ jnp.asarray(gt_root, gt.dtype)
    m = _joint_mask(mask, pred.shape[:-1])
    m = m & jnp.all(m[..., np.asarray(root, int)], -1, keepdims=True)
    return _mean(jnp.linalg.norm(a - b, axis=-1) * 1000.0, m, 2)


def _translation_curve(pred: Array, gt: Array, mask: Array, distances: Array, distinct_ends: bool) -> Array:
    """One clip: pred, gt (T, 3), mask (T,), distances (D,) -> (D,) metres."""
    T = gt.shape[0]
    step_ok = mask[1:] & mask[:-1]
    step = jnp.where(step_ok, jnp.linalg.norm(gt[1:] - gt[:-1], axis=-1), 0.0)
    s = jnp.concatenate([jnp.zeros(1, gt.dtype), jnp.cumsum(step)])  # ground-truth path length
    holes = jnp.cumsum(~mask)  # masked frames in 0..t
    before = holes - (~mask)  # masked frames in 0..t-1
    i = jnp.arange(T)

    def one(d):
        e = jnp.searchsorted(s, s + d, side="left")  # the first frame with s[e] >= s[i] + d
        ec = jnp.minimum(e, T - 1)
        valid = (e < T) & (holes[ec] - before == 0)  # every frame i..e real
        if distinct_ends:  # the first valid start of each end frame (ends are monotone in i)
            same = jnp.concatenate([jnp.zeros(1, bool), valid[:-1] & (ec[1:] == ec[:-1])])
            valid = valid & ~same
        travelled = s[ec] - s
        err = jnp.linalg.norm((pred[ec] - pred) - (gt[ec] - gt), axis=-1)
        err = safe_div(err * d, travelled)  # the error rescaled to exactly d metres travelled
        return _mean(err, valid & (i < ec), 1)

    return jax.vmap(one)(distances)


@partial(jax.jit, static_argnames=("distinct_ends",))
def cumulative_translation_error(pred: Array, gt: Array, mask=None, distances=TRANSLATION_DISTANCES_M, *,
                                 distinct_ends: bool = True) -> Array:
    """Cumulative translation error (m) against the real travelled distance, PIP [002] Fig. 3
    ("the global position error w.r.t. the real travelled distance"): (..., D), one value per
    distance d in ``distances`` (m, > 0; default 1, 2, ..., 7 m as PIP's evaluation script).

    ``pred``, ``gt`` (..., T, 3) are the global root positions (e.g. :func:`root_position` of the
    joints, or ``q[..., :3]``). With s(t) the path length of the true root up to frame t (the sum
    of its frame-to-frame displacements), a window starts at any frame i and ends at the first
    frame e with ``s(e) - s(i) >= d``; its error is the drift of the estimate over the window,
    each window's start aligned (the estimate translated so that it starts where the truth
    does), rescaled to exactly d metres:

        err(i, d) = |(p̂(e) - p̂(i)) - (p(e) - p(i))| * d / (s(e) - s(i)).

    The value at d is the mean of err(i, d) over the windows. As PIP's script, only the first
    start of each end frame counts (``distinct_ends``: starts during a standstill share an end
    frame and count once; ``False``: every start frame counts). A window counts only where all
    of its frames are real (``mask`` (..., T)); a distance no window reaches (the clip's path is
    shorter) is NaN. PIP averages each distance's value over the clips (a figure, not a table
    number); :func:`mean_translation_error` gives one number per clip.
    """
    pred = _points(pred, "pred", "T, 3")
    gt = _points(gt, "gt", "T, 3")
    _same(pred, gt, "pred", "gt")
    m = _frame_mask(mask, pred.shape[:-1])
    dist = jnp.asarray(distances, pred.dtype)
    if dist.ndim != 1:
        raise ValueError(f"distances must have shape (D,), got {tuple(dist.shape)}")
    lead, T = pred.shape[:-2], pred.shape[-2]
    out = jax.vmap(lambda p, g, mm: _translation_curve(p, g, mm, dist, distinct_ends))(
        pred.reshape(-1, T, 3), gt.reshape(-1, T, 3), m.reshape(-1, T))
    return out.reshape(lead + dist.shape)


@partial(jax.jit, static_argnames=("distinct_ends",))
def mean_translation_error(pred: Array, gt: Array, mask=None, distances=TRANSLATION_DISTANCES_M, *,
                           distinct_ends: bool = True) -> Array:
    """The mean (m) of :func:`cumulative_translation_error` over the distances the clip reaches
    (its defined values); NaN when it reaches none. The mean of a curve that grows with d: compare
    it only between methods on the same clips and distances."""
    c = cumulative_translation_error(pred, gt, mask, distances, distinct_ends=distinct_ends)
    return _mean(c, jnp.isfinite(c), 1)


# =========================================================================================
# smoothness
# =========================================================================================


def _diff(x: Array, n: int, mask, axis: int = -3):
    """n-th differences of joints (..., T, J, 3) over time and their (..., T - n, J) mask: a
    difference counts where its n + 1 frames are real (for a per-joint mask, for that joint)."""
    d = jnp.diff(x, n=n, axis=axis)
    m = jnp.swapaxes(_joint_mask(mask, x.shape[:-1]), -1, -2)  # (..., J, T)
    return d, jnp.swapaxes(_diff_mask(m, n), -1, -2)


@jax.jit
def smoothness_error(pred: Array, gt: Array, mask=None) -> tuple[Array, Array]:
    """``(e_smooth, sigma_smooth)`` in mm, [000] eq. 26 (after PhysCap, Shimada et al. 2020).

    ``Jit_X(s, t) = |p_X(s, t) - p_X(s, t - 1)|`` is the frame-to-frame displacement of joint s;
    ``e_smooth`` is the mean over joints and frame pairs of ``|Jit_GT - Jit_pred|`` and
    ``sigma_smooth`` its (population) standard deviation over the same terms. Positions are the
    world (absolute) joint positions. A pair counts when both of its frames are real (eq. 26's
    1/(Tk) runs over the T - 1 pairs of a T-frame clip).
    """
    pred = _points(pred, "pred")
    gt = _points(gt, "gt")
    _same(pred, gt, "pred", "gt")
    dp, w = _diff(pred, 1, mask)
    dg, _ = _diff(gt, 1, mask)
    term = jnp.abs(jnp.linalg.norm(dg, axis=-1) - jnp.linalg.norm(dp, axis=-1)) * 1000.0
    return _mean(term, w, 2), _std(term, w, 2)


@jax.jit
def acceleration_error(pred: Array, gt: Array, fps, mask=None) -> Array:
    """Acceleration error (m/s^2): mean over joints and frames of ``|a_pred - a_gt|`` with
    ``a = (p_{t+1} - 2 p_t + p_{t-1}) fps^2`` (second differences). HMMR/VIBE report the same
    second differences per frame^2 in "mm"; theirs = ours * 1000 / fps^2."""
    pred = _points(pred, "pred")
    gt = _points(gt, "gt")
    _same(pred, gt, "pred", "gt")
    ap, w = _diff(pred, 2, mask)
    ag, _ = _diff(gt, 2, mask)
    e = jnp.linalg.norm(ap - ag, axis=-1) * _bcast(fps, ap.dtype, 2) ** 2
    return _mean(e, w, 2)


@jax.jit
def jitter(joints: Array, fps, mask=None) -> Array:
    """Jitter (km/s^3), PIP [002] Sec. 4: the mean jerk magnitude of all joints in world
    coordinates, ``|p_{t+3} - 3 p_{t+2} + 3 p_{t+1} - p_t| fps^3 / 1000`` (third differences):
    the paper's "mean jerk ... of all body joints in the global space in km/s^3", on the layout's
    joints instead of SMPL's 24. (PIP's published evaluation script, by default, takes the jerk
    of the translation-free pose with the pelvis rotation set to the identity, and names the
    global one "absolute jitter"; this follows the paper's wording: global.)"""
    joints = _points(joints, "joints")
    d, w = _diff(joints, 3, mask)
    jerk = jnp.linalg.norm(d, axis=-1) * _bcast(fps, d.dtype, 2) ** 3 / 1000.0
    return _mean(jerk, w, 2)


# =========================================================================================
# 2D reprojection
# =========================================================================================


#: the side view scores only the ground-truth joints at least this far in front of the virtual
#: side camera: a subject who walks metres across the input view can pass beside or behind a
#: camera put at the input camera's distance from the mean root, where a pinhole projection's
#: pixels grow without bound (one held-out walk reached 63,554 px mean from a few such joints)
SIDE_VIEW_NEAR_M = 0.5


@jax.jit
def side_view_camera(camera: Camera, pivot: Array, angle: float = np.pi / 2) -> Camera:
    """The virtual evaluation camera of [000] Table 4: the input ``camera`` rotated by ``angle``
    (default +90 deg, counter-clockwise seen from above) about the vertical world axis through
    ``pivot`` (..., 3) (only its x, y matter), with the same intrinsics and image size.

    The camera pose moves by the world rigid motion G (that rotation), so its world->camera
    extrinsics become ``E G^-1``: it sees the subject from the side at the same distance.
    """
    c, s = jnp.cos(-angle), jnp.sin(-angle)
    pivot = jnp.asarray(pivot, camera.extrinsics.dtype)
    Rz = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], camera.extrinsics.dtype)  # G^-1
    p = pivot.at[..., 2].set(0.0)
    t = p - jnp.einsum("ij,...j->...i", Rz, p)
    G_inv = jnp.zeros(p.shape[:-1] + (4, 4), p.dtype).at[..., :3, :3].set(Rz)
    G_inv = G_inv.at[..., :3, 3].set(t).at[..., 3, 3].set(1.0)
    return camera.replace(extrinsics=camera.extrinsics @ G_inv)


@jax.jit
def reprojection_error(pred: Array, gt: Array, camera: Camera, mask=None) -> tuple[Array, Array]:
    """``(e_2D, sigma_2D)`` in pixels, [000] Table 4: the mean and (population) standard
    deviation over joints and real frames of ``|pi(p_pred) - pi(p_gt)|``, pi the pinhole
    projection of ``camera`` (:func:`jmocap.camera.project`). For the side view, pass
    :func:`side_view_camera`."""
    pred = _points(pred, "pred")
    gt = _points(gt, "gt")
    _same(pred, gt, "pred", "gt")
    e = jnp.linalg.norm(project(camera, pred) - project(camera, gt), axis=-1)
    w = _joint_mask(mask, e.shape)  # frames (..., T) or joints (..., T, J)
    return _mean(e, w, 2), _std(e, w, 2)


# =========================================================================================
# foot-floor contact
# =========================================================================================


def _feet(points, contacts=None):
    points = _points(points, "foot_points", "T, P, 3")
    if contacts is None:
        return points, None
    c = jnp.asarray(contacts)
    if c.shape != points.shape[:-1]:
        raise ValueError(f"contacts must have shape (..., T, P) = {tuple(points.shape[:-1])}, got {tuple(c.shape)}")
    return points, c > 0.5


def _height(points: Array, scene=None) -> Array:
    """Height (..., P) of foot points above what they stand on: ``z`` over the floor, or their
    signed distance to a :class:`jmocap.scene.Scene` (the floor and its boxes) when given."""
    if scene is None:
        return points[..., 2]
    from jmocap.scene import sdf

    return sdf(scene, points)


@jax.jit
def contact_labels(points: Array, max_step: float = CONTACT_MAX_STEP_M,
                   max_height: float = CONTACT_MAX_HEIGHT_M) -> Array:
    """Rempe et al.'s labelling rule [001] Sec. 3.2 on foot points (..., T, P, 3): a point is in
    contact at frame t when it moved less than ``max_step`` (2 cm) since frame t - 1 and is less
    than ``max_height`` (5 cm) above the floor; frame 0 uses its displacement to frame 1. (The
    rule that made the synthetic ``gt_contacts``.) Returns bool (..., T, P)."""
    points = _points(points, "foot_points", "T, P, 3")
    step = jnp.linalg.norm(jnp.diff(points, axis=-3), axis=-1)
    step = jnp.concatenate([step[..., :1, :], step], -2) if points.shape[-3] > 1 else jnp.zeros(points.shape[:-1])
    return (step < max_step) & (points[..., 2] < max_height)


@jax.jit
def mean_penetration_error(points: Array, contacts: Array, mask=None, scene=None) -> Array:
    """Mean Penetration Error, MPE (mm), [000] Table 5: the mean distance ``|z|`` between foot
    point and floor over the points and real frames where the foot is in contact (``contacts``,
    ground-truth labels). With a ``scene`` (:mod:`jmocap.scene`) every foot metric measures
    heights as the signed distance to the scene instead of ``z``."""
    points, c = _feet(points, contacts)
    w = c & _frame_mask(mask, points.shape[:-2])[..., None]
    return _mean(jnp.abs(_height(points, scene)) * 1000.0, w, 2)


@jax.jit
def non_penetration(points: Array, mask=None, scene=None, *, tolerance: float = PNP_TOLERANCE_M) -> Array:
    """Percentage of Non-Penetration, PNP (%), [000] Table 5: the share of real frames in which
    no foot point is below the floor, ``z >= -tolerance`` for every point. The paper states no
    tolerance; jmocap's 1 mm keeps float noise and the sub-millimetre sinking of soft (MuJoCo)
    contacts from counting as penetration."""
    points, _ = _feet(points)
    ok = jnp.all(_height(points, scene) >= -tolerance, axis=-1)
    m = _frame_mask(mask, ok.shape)
    return 100.0 * _mean(ok.astype(points.dtype), m, 1)


@jax.jit
def foot_floating(points: Array, contacts: Array, mask=None, scene=None, *,
                  threshold: float = FLOAT_THRESHOLD_M) -> Array:
    """Floating (%), [001] Table 2: among the (point, frame) pairs in contact by the labels, the
    share more than ``threshold`` (3 cm) above the floor."""
    points, c = _feet(points, contacts)
    w = c & _frame_mask(mask, points.shape[:-2])[..., None]
    return 100.0 * _mean((_height(points, scene) > threshold).astype(points.dtype), w, 2)


@jax.jit
def foot_penetration(points: Array, mask=None, scene=None, *, threshold: float = PENETRATION_THRESHOLD_M) -> Array:
    """Penetration (%), [001] Table 2: the share of all (point, frame) pairs more than
    ``threshold`` (3 cm) below the floor, at any time."""
    points, _ = _feet(points)
    w = jnp.broadcast_to(_frame_mask(mask, points.shape[:-2])[..., None], points.shape[:-1])
    return 100.0 * _mean((_height(points, scene) < -threshold).astype(points.dtype), w, 2)


@jax.jit
def foot_skate(points: Array, contacts: Array, mask=None, *, threshold: float = SKATE_THRESHOLD_M) -> Array:
    """Skate (%), [001] Table 2: among the (point, frame t >= 1) pairs in contact at t by the
    labels, the share that moved more than ``threshold`` (2 cm, 3D distance) since frame t - 1."""
    points, c = _feet(points, contacts)
    step = jnp.linalg.norm(jnp.diff(points, axis=-3), axis=-1)  # (..., T-1, P): t-1 -> t
    m = _diff_mask(_frame_mask(mask, points.shape[:-2]), 1)[..., None]
    w = c[..., 1:, :] & m
    return 100.0 * _mean((step > threshold).astype(points.dtype), w, 2)


# =========================================================================================
# dynamics
# =========================================================================================


def _forces(grf, name="grf") -> Array:
    return _points(grf, name, "T, P, 3")


@jax.jit
def net_force_percent(grf: Array, weight) -> Array:
    """(..., T, P, 3) contact forces -> (..., T) ``|sum_P f| / weight * 100`` (% body weight);
    [001] Sec. 4.3 (the net GRF ``f_GRF(t) = sum_i f_i(t)``)."""
    grf = _forces(grf)
    return jnp.linalg.norm(jnp.sum(grf, -2), axis=-1) / _bcast(weight, grf.dtype, 1) * 100.0


@jax.jit
def grf_mean(grf: Array, weight, mask=None) -> Array:
    """Mean GRF (% body weight), [001] Table 2: the mean over real frames of the net contact
    force magnitude over the body weight (``mass * GRAVITY``); about 100 % for any motion that
    starts and ends at rest."""
    f = net_force_percent(grf, weight)
    return _mean(f, _frame_mask(mask, f.shape), 1)


@jax.jit
def grf_max(grf: Array, weight, mask=None) -> Array:
    """Max GRF (% body weight), [001] Table 2: the largest net contact force over real frames."""
    f = net_force_percent(grf, weight)
    m = _frame_mask(mask, f.shape)
    return jnp.where(jnp.any(m, -1), jnp.max(jnp.where(m, f, -jnp.inf), -1), jnp.nan)


@jax.jit
def grf_ballistic(grf: Array, weight, flight: Array, mask=None) -> Array:
    """Ballistic GRF (% body weight), [001] Table 2: the *median* net contact force over the real
    frames of flight (``flight`` (..., T) True where no foot point is in contact); 0 for a
    physically valid motion, in which only gravity acts during flight."""
    f = net_force_percent(grf, weight)
    fl = jnp.asarray(flight, bool)
    if fl.shape != f.shape:
        raise ValueError(f"flight must have shape (..., T) = {tuple(f.shape)}, got {tuple(fl.shape)}")
    sel = fl & _frame_mask(mask, f.shape)
    return jnp.nanmedian(jnp.where(sel, f, jnp.nan), axis=-1)


@jax.jit
def root_residual(tau: Array, weight, mask=None) -> Array:
    """Residual root force (% body weight), [000] Fig. 4d: the mean over real frames of
    ``|tau_root| / w`` with ``tau_root = tau[:3]`` the virtual (non-physical) force that acts on
    the root directly and w the body weight."""
    tau = _points(tau, "tau", "T, nv")
    if tau.shape[-1] < 6:
        raise ValueError(f"tau must have shape (..., T, nv >= 6), got {tuple(tau.shape)}")
    r = jnp.linalg.norm(tau[..., :3], axis=-1) / _bcast(weight, tau.dtype, 1) * 100.0
    return _mean(r, _frame_mask(mask, r.shape), 1)


@jax.jit
def grf_error(grf: Array, gt_grf: Array, weight, gt_weight, mask=None) -> Array:
    """Net GRF error (% body weight): the mean over real frames of
    ``|sum_P f / w - sum_P f_gt / w_gt| * 100``, each force over the weight of its own model (the
    estimate's character may weigh other than the subject)."""
    grf, gt_grf = _forces(grf), _forces(gt_grf, "gt_grf")
    a = jnp.sum(grf, -2) / _bcast(weight, grf.dtype, 2)
    b = jnp.sum(gt_grf, -2) / _bcast(gt_weight, gt_grf.dtype, 2)
    _same(a, b, "grf (net)", "gt_grf (net)")
    e = jnp.linalg.norm(a - b, axis=-1) * 100.0
    return _mean(e, _frame_mask(mask, e.shape), 1)


@jax.jit
def foot_grf_correlation(grf: Array, gt_grf: Array, mask=None) -> Array:
    """Per-foot vertical GRF correlation with the ground truth: for each foot the Pearson
    correlation over real frames of its vertical force (heel + toe: contact points 0+1 are the
    left foot, 2+3 the right, :data:`jmocap.constants.CONTACT_SITES`) with the ground truth's,
    then the mean of the two feet. It measures timing and the share between the feet, not the
    magnitude (a foot whose estimated or true force is constant has no correlation: NaN, and the
    mean is over the defined feet). +1: the estimate's left/right loading follows the truth; a
    method that gives both feet the same force scores about 0 on a walk."""
    grf, gt_grf = _forces(grf), _forces(gt_grf, "gt_grf")
    _same(grf, gt_grf, "grf", "gt_grf")
    if grf.shape[-2] != 4:
        raise ValueError(f"grf must have the 4 contact points (..., T, 4, 3), got {tuple(grf.shape)}")

    def feet(f):
        return jnp.stack([f[..., 0, 2] + f[..., 1, 2], f[..., 2, 2] + f[..., 3, 2]], -1)  # (..., T, 2)

    a, b = feet(grf), feet(gt_grf)
    w = _frame_mask(mask, a.shape[:-1])[..., None].astype(a.dtype)
    n = jnp.sum(w, -2)
    ca = a - jnp.sum(w * a, -2, keepdims=True) / jnp.maximum(n, 1)[..., None, :]
    cb = b - jnp.sum(w * b, -2, keepdims=True) / jnp.maximum(n, 1)[..., None, :]
    va, vb = jnp.sum(w * ca * ca, -2), jnp.sum(w * cb * cb, -2)
    tiny = 1e-12 * jnp.maximum(jnp.max(jnp.abs(b), axis=-2) ** 2, 1.0) * jnp.maximum(n, 1)
    ok = (va > tiny) & (vb > tiny) & (n >= 3)
    r = jnp.sum(w * ca * cb, -2) / jnp.sqrt(jnp.where(ok, va * vb, 1.0))
    return jnp.sum(jnp.where(ok, r, 0.0), -1) / jnp.where(jnp.any(ok, -1), jnp.sum(ok, -1), jnp.nan)


@jax.jit
def torque_error(tau: Array, gt_tau: Array, mass, gt_mass, mask=None) -> Array:
    """Joint torque error (N m / kg): the mean over real frames and hinge dofs (``tau[6:]``) of
    ``|tau / m - tau_gt / m_gt|``, each torque over the mass of its own model."""
    tau = _points(tau, "tau", "T, nv")
    gt_tau = _points(gt_tau, "gt_tau", "T, nv")
    _same(tau, gt_tau, "tau", "gt_tau")
    e = jnp.abs(tau[..., 6:] / _bcast(mass, tau.dtype, 2) - gt_tau[..., 6:] / _bcast(gt_mass, tau.dtype, 2))
    return _mean(e, _frame_mask(mask, tau.shape[:-1])[..., None], 2)


@jax.jit
def zmp_from_wrench(force: Array, torque: Array, origin: Array) -> Array:
    """The zero-moment point (..., 2) on the floor z = 0 of an external wrench (force (..., 3),
    torque (..., 3) about ``origin`` (..., 3), world frame): the floor point about which the
    wrench has no horizontal moment,

        p_x = o_x - (n_y + o_z f_x) / f_z,    p_y = o_y + (n_x - o_z f_y) / f_z.

    Defined for ``f_z > 0`` (returns the origin's projection where ``f_z == 0``)."""
    f, n, o = force, torque, origin
    px = o[..., 0] - safe_div(n[..., 1] + o[..., 2] * f[..., 0], f[..., 2])
    py = o[..., 1] + safe_div(n[..., 0] - o[..., 2] * f[..., 1], f[..., 2])
    return jnp.stack([px, py], -1)


def _difference_velocities(model: Model, q: Array, fps) -> tuple[Array, Array]:
    """Central-difference velocity and acceleration (T, nv) of a pose sequence (edge frames
    replicate a neighbour's difference: mask them, see :func:`_central_mask`)."""
    back = P.finite_difference_velocity(model, q, fps)  # (q_t - q_{t-1}) fps, row 0 zero
    fwd = jnp.concatenate([back[1:], back[-1:]], 0)  # (q_{t+1} - q_t) fps
    return 0.5 * (back + fwd), (fwd - back) * jnp.asarray(fps, q.dtype)


def _cross2(a: Array, b: Array) -> Array:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _point_segment_distance(p: Array, a: Array, b: Array) -> Array:
    ab = b - a
    t = jnp.clip(safe_div(jnp.sum((p - a) * ab, -1), jnp.sum(ab * ab, -1)), 0.0, 1.0)
    return jnp.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


@jax.jit
def support_polygon_distance(point: Array, vertices: Array, active: Array) -> Array:
    """Distance (...,) in the floor plane from ``point`` (..., 2) to the convex hull of the
    ``active`` (..., V) ``vertices`` (..., V, 2|3; only x, y are used); 0 inside or on the hull,
    NaN when no vertex is active.

    Exact for any V (meant for a handful): the point is inside the hull iff it lies in a
    non-degenerate triangle of active vertices (Caratheodory); outside, the nearest hull point
    lies on a segment between two active vertices (one vertex: the distance to it; two: to the
    segment).
    """
    p = jnp.asarray(point)[..., :2]
    v = jnp.asarray(vertices)[..., :2]
    act = jnp.asarray(active, bool)
    V = v.shape[-2]
    if act.shape[-1] != V:
        raise ValueError(f"active must have shape (..., V) with V = {V}, got {tuple(act.shape)}")
    i, j = np.triu_indices(V)  # pairs with i <= j (i == j: a single vertex)
    d = _point_segment_distance(p[..., None, :], v[..., i, :], v[..., j, :])
    d = jnp.min(jnp.where(act[..., i] & act[..., j], d, jnp.inf), -1)
    inside = jnp.zeros(d.shape, bool)
    if V >= 3:
        ijk = np.array(list(itertools.combinations(range(V), 3)))
        a, b, c = (v[..., ijk[:, k], :] for k in range(3))
        q = p[..., None, :]
        c1, c2, c3 = _cross2(b - a, q - a), _cross2(c - b, q - b), _cross2(a - c, q - c)
        area = jnp.abs(_cross2(b - a, c - a))
        scale = jnp.max(jnp.abs(v), axis=(-1, -2))[..., None] + 1.0
        tri = ((c1 >= 0) & (c2 >= 0) & (c3 >= 0)) | ((c1 <= 0) & (c2 <= 0) & (c3 <= 0))
        ok = act[..., ijk[:, 0]] & act[..., ijk[:, 1]] & act[..., ijk[:, 2]]
        inside = jnp.any(tri & ok & (area > 1e-12 * scale * scale), -1)
    return jnp.where(jnp.any(act, -1), jnp.where(inside, 0.0, d), jnp.nan)


@jax.jit
def zmp_distance(zmp: Array, normal_force: Array, weight, support: Array, contacts: Array, mask=None,
                 *, min_normal: float = ZMP_MIN_NORMAL_FORCE) -> Array:
    """ZMP distance (m), PIP [002] Sec. 4: the mean over frames of the distance from the ZMP
    (..., T, 2) to the support polygon (base of support), the convex hull of the in-contact
    ``support`` points (..., T, V, 3) projected on the floor (:func:`support_polygon_distance`).

    A frame counts when it and both neighbours are real (the ZMP uses central differences), at
    least one support point is in contact (``contacts`` (..., T, V)) and the motion needs a
    vertical force of at least ``min_normal`` body weights (below that, in flight or nearly,
    the ZMP is undefined or arbitrarily far).
    """
    zmp = _points(zmp, "zmp", "T, 2")
    support, c = _feet(support, contacts)
    m = _central_mask(_frame_mask(mask, zmp.shape[:-1]))
    fz = jnp.asarray(normal_force, zmp.dtype)
    if fz.shape != zmp.shape[:-1]:
        raise ValueError(f"normal_force must have shape (..., T) = {tuple(zmp.shape[:-1])}, got {tuple(fz.shape)}")
    sel = m & jnp.any(c, -1) & (fz >= min_normal * _bcast(weight, fz.dtype, 1))
    d = support_polygon_distance(zmp, support, c)
    return _mean(jnp.where(sel, d, 0.0), sel, 1)


# =========================================================================================
# contact classification
# =========================================================================================


@jax.jit
def contact_classification(prob: Array, gt: Array, mask=None, *, threshold: float = 0.5) -> dict[str, Array]:
    """Accuracy, balanced accuracy, precision, recall and F1 (%) of the foot-contact labels,
    pooled over the four points (L heel, L toe, R heel, R toe) and the real frames: a point is
    predicted in contact when ``prob > threshold``; ``gt`` (..., T, P) holds the {0, 1} labels.
    Precision (recall) is NaN when nothing is predicted (labelled) in contact; F1 = 2 TP / (2 TP
    + FP + FN); balanced accuracy the mean of the recalls of "in contact" and "not in contact"
    (NaN when either class is absent: a majority-class guess scores 50)."""
    prob = _points(prob, "contact_prob", "T, P")
    gt = jnp.asarray(gt)
    _same(prob, gt, "contact_prob", "gt_contacts")
    m = jnp.broadcast_to(_frame_mask(mask, prob.shape[:-1])[..., None], prob.shape)
    pr, g = prob > threshold, gt > 0.5
    axes = (-1, -2)

    def count(x):
        return jnp.sum((x & m).astype(prob.dtype), axes)

    tp, fp, fn, tn = count(pr & g), count(pr & ~g), count(~pr & g), count(~pr & ~g)
    return {
        "accuracy": _pct(tp + tn, tp + tn + fp + fn),
        "balanced_accuracy": 0.5 * (_pct(tp, tp + fn) + _pct(tn, tn + fp)),
        "precision": _pct(tp, tp + fp),
        "recall": _pct(tp, tp + fn),
        "f1": _pct(2 * tp, 2 * tp + fp + fn),
    }


# =========================================================================================
# quantities of a motion the metrics read, and the flat evaluation of one clip
# =========================================================================================


def motion_quantities(model: Model, q: Array, fps, layout: str = "body25", half_width=0.0) -> dict[str, Array]:
    """What the metrics read of a motion ``q`` (T, nq), from the physics (jit/vmap-able; pass the
    layout as a static argument):

    * ``keypoints3d`` (T, J, 3): the layout's joints (:func:`jmocap.physics.keypoints`);
    * ``feet`` (T, 4, 3): the foot contact sites (L heel, L toe, R heel, R toe);
    * ``support`` (T, 8, 3): the sole corners used for the support polygon, each contact site
      moved by +-``half_width`` along its foot's horizontal lateral axis (the sole is as wide as
      the foot geoms, :func:`sole_half_width`; with 0 it is the four sites themselves), in the
      order (site 0 +, site 0 -, site 1 +, ...);
    * ``zmp`` (T, 2) and ``implied_force`` (T, 3): the zero-moment point and the external force
      the motion needs (:func:`zero_moment_point`; the latter is the "implied GRF" of [001]
      Sec. 4.3 for methods that estimate no forces).
    """
    q = jnp.asarray(q)
    sites = model.topo.contact_sites
    kin = jax.vmap(lambda x: P.forward_kinematics(model, x))(q)
    kp = jax.vmap(lambda x, k: P.keypoints(model, x, layout, kin=k))(q, kin)
    feet = jax.vmap(lambda x, k: P.site_positions(model, x, sites, kin=k))(q, kin)
    bodies = np.asarray(model.topo.site_body)[list(sites)]
    lateral = safe_normalize(kin.xmat[:, bodies][..., 1].at[..., 2].set(0.0))  # feet's y axes, floor plane
    hw = jnp.asarray(half_width, q.dtype)
    support = jnp.stack([feet + hw * lateral, feet - hw * lateral], -2).reshape(q.shape[0], -1, 3)
    zmp, force = zero_moment_point(model, q, fps, kin=kin)
    return dict(keypoints3d=kp, feet=feet, support=support, zmp=zmp, implied_force=force)


def friction_cone_violation(force: Array, weight, mask=None, *, mu: float = FRICTION_MU,
                            min_force: float = 0.05) -> Array:
    """% of frames whose motion needs an external force ``force`` (T, 3) (the motion's
    ``m (c'' - g)``, :func:`zero_moment_point`) that the floor cannot give: pulling
    (``f_z < 0``) or outside the Coulomb cone ``|f_h| > mu f_z``. Frames needing less than
    ``min_force`` body weights (flight) are admissible; the first and last frame (one-sided
    differences) are not counted."""
    f = jnp.asarray(force)
    w = _bcast(weight, f.dtype, 1)
    fz, fh = f[..., 2], jnp.sqrt(f[..., 0] ** 2 + f[..., 1] ** 2 + 1e-30)
    big = jnp.sqrt(fz * fz + fh * fh) > min_force * w
    bad = big & ((fz < 0) | (fh > mu * fz))
    wm = _central_mask(_frame_mask(mask, bad.shape))  # the edge frames' differences are one-sided
    return _pct(jnp.sum(bad * wm, -1), jnp.sum(wm, -1))


def zero_moment_point(model: Model, q: Array, fps, *, kin=None) -> tuple[Array, Array]:
    """The (fictitious) zero-moment point of a motion ``q`` (T, nq): ``(zmp (T, 2), force (T, 3))``.

    PIP [002] Sec. 4 after Vukobratovic & Borovac 2004. Computed from whole-body dynamics, not
    from the estimated contact forces: the root rows of the inverse dynamics without contact,
    ``tau = M qdd + h`` (:func:`jmocap.physics.mass_matrix`, :func:`~jmocap.physics.bias_forces`)
    of the central-difference velocities and accelerations, are the external wrench the motion
    needs (``tau[:3]``: world force, ``R tau[3:6]``: torque about the root); the ZMP is where that
    wrench has no horizontal moment (:func:`zmp_from_wrench`). This includes the rate of change
    of angular momentum, not only the centre-of-mass acceleration. The centre of pressure of
    *estimated* contact forces lies in the support polygon by construction whenever their normal
    components are non-negative, so it would measure nothing. ``force`` is the external force
    needed (``m (c'' - g)``); the ZMP means little where its vertical part is small (flight).
    Edge frames use one-sided differences: mask them. ``kin``: the frames' forward kinematics
    (batched over T), when already computed.
    """
    qd, qdd = _difference_velocities(model, q, fps)
    if kin is None:
        kin = jax.vmap(lambda x: P.forward_kinematics(model, x))(q)

    def root_wrench(qt, qdt, qddt, k):
        M = P.mass_matrix(model, qt, kin=k)
        return M[:6] @ qddt + P.bias_forces(model, qt, qdt, kin=k)[:6]

    tau = jax.vmap(root_wrench)(q, qd, qdd, kin)
    R = quat_to_mat(q[:, 3:7])
    torque = jnp.einsum("tij,tj->ti", R, tau[:, 3:6])
    return zmp_from_wrench(tau[:, :3], torque, q[:, :3]), tau[:, :3]


class MetricInfo(NamedTuple):
    """How to present one key of :func:`evaluate_arrays`."""

    label: str
    unit: str
    better: str  # "lower" | "higher" | "100" (closest to 100 % is best)
    source: str  # the paper / table that defines it
    aggregate: str = "mean"  # how per-clip values combine over clips: "mean" | "max"


METRICS: dict[str, MetricInfo] = {
    "mpjpe_mm": MetricInfo("MPJPE (root-aligned)", "mm", "lower", "[000] Tab. 1"),
    "pa_mpjpe_mm": MetricInfo("PA-MPJPE", "mm", "lower", "[000] Tab. 1"),
    "mpjpe_abs_mm": MetricInfo("MPJPE (absolute, world)", "mm", "lower", "[001] Tab. 3"),
    "pck150_pct": MetricInfo("PCK@150mm (root-aligned)", "%", "higher", "[000] Tab. 1"),
    "auc_pct": MetricInfo("AUC 0-150mm (root-aligned)", "%", "higher", "[000] Tab. 1"),
    "pa_pck150_pct": MetricInfo("PCK@150mm (Procrustes)", "%", "higher", "[000] Tab. 1"),
    "pa_auc_pct": MetricInfo("AUC 0-150mm (Procrustes)", "%", "higher", "[000] Tab. 1"),
    "mpjpe_cam_mm": MetricInfo("MPJPE (root-aligned), camera frame", "mm", "lower", "[003] Tab. 1"),
    "root_err_cam_mm": MetricInfo("root translation error, camera frame", "mm", "lower", "[003]"),
    "accel_err_cam_m_s2": MetricInfo("acceleration error, camera frame", "m/s^2", "lower", "[003] Tab. 1"),
    "root_err_mm": MetricInfo("global root translation error", "mm", "lower", "[000] Tab. 2"),
    "e_smooth_mm": MetricInfo("e_smooth", "mm", "lower", "[000] eq. 26, Tab. 3"),
    "sigma_smooth_mm": MetricInfo("sigma_smooth", "mm", "lower", "[000] Tab. 3"),
    "accel_err_m_s2": MetricInfo("acceleration error", "m/s^2", "lower", "HMMR/VIBE"),
    "jitter_km_s3": MetricInfo("jitter", "km/s^3", "lower", "[002] Sec. 4"),
    "reproj_input_px": MetricInfo("reprojection error, input view", "px", "lower", "[000] Tab. 4"),
    "reproj_input_std_px": MetricInfo("reprojection error std, input view", "px", "lower", "[000] Tab. 4"),
    "reproj_side_px": MetricInfo("reprojection error, side view", "px", "lower", "[000] Tab. 4"),
    "reproj_side_std_px": MetricInfo("reprojection error std, side view", "px", "lower", "[000] Tab. 4"),
    "mpe_mm": MetricInfo("Mean Penetration Error", "mm", "lower", "[000] Tab. 5"),
    "pnp_pct": MetricInfo("Percentage of Non-Penetration", "%", "higher", "[000] Tab. 5"),
    "float_pct": MetricInfo("foot floating (>3 cm in contact)", "%", "lower", "[001] Tab. 2"),
    "penetrate_pct": MetricInfo("foot penetration (>3 cm)", "%", "lower", "[001] Tab. 2"),
    "skate_pct": MetricInfo("foot skate (>2 cm in contact)", "%", "lower", "[001] Tab. 2"),
    "grf_mean_pct_bw": MetricInfo("mean GRF", "% BW", "100", "[001] Tab. 2"),
    "grf_max_pct_bw": MetricInfo("max GRF", "% BW", "lower", "[001] Tab. 2", "max"),
    "grf_ballistic_pct_bw": MetricInfo("ballistic GRF (median in flight)", "% BW", "lower", "[001] Tab. 2"),
    "root_residual_pct_bw": MetricInfo("residual root force", "% BW", "lower", "[000] Fig. 4d"),
    "zmp_dist_m": MetricInfo("ZMP distance to support polygon", "m", "lower", "[002] Sec. 4"),
    "cone_violation_pct": MetricInfo("motion needs force outside the friction cone", "%", "lower", "jmocap"),
    "grf_err_pct_bw": MetricInfo("net GRF error vs ground truth", "% BW", "lower", "jmocap"),
    "foot_grf_corr": MetricInfo("per-foot vertical GRF correlation with ground truth", "", "higher", "jmocap"),
    "torque_err_nm_kg": MetricInfo("joint torque error vs ground truth", "N m/kg", "lower", "jmocap"),
    "contact_acc_pct": MetricInfo("contact accuracy", "%", "higher", "[001] Fig. E1"),
    "contact_prec_pct": MetricInfo("contact precision", "%", "higher", "jmocap"),
    "contact_rec_pct": MetricInfo("contact recall", "%", "higher", "jmocap"),
    "contact_f1_pct": MetricInfo("contact F1", "%", "higher", "jmocap"),
}


def _finite(d: Mapping[str, Any], side: str, mask: np.ndarray) -> dict[str, np.ndarray]:
    """The non-None arrays of ``d`` as numpy, checked finite on the real frames."""
    out = {}
    for k, v in d.items():
        if v is None:
            continue
        a = np.asarray(v)
        if a.ndim and a.shape[0] != mask.shape[0]:
            raise ValueError(f"{side} {k!r} has {a.shape[0]} frames (shape {a.shape}), the mask {mask.shape[0]}")
        if side == "gt" and k == "keypoints3d" and a.ndim == 3:
            # a joint the ground truth lacks is NaN in x, y, z: left out by per-joint masks
            a = np.where(np.isnan(a).all(-1, keepdims=True), np.nan, a)
            bad = ~np.isfinite(np.where(np.isnan(a), 0.0, a)[mask])
            if bad.any():
                t = int(np.nonzero(mask)[0][np.argmax(bad.reshape(bad.shape[0], -1).any(1))])
                raise ValueError(f"{side} {k!r} has non-finite values (other than a whole missing joint), "
                                 f"first at frame {t}")
            out[k] = a
            continue
        bad = ~np.isfinite(a[mask]) if a.ndim else ~np.isfinite(a)
        if bad.any():
            t = int(np.nonzero(mask)[0][np.argmax(bad.reshape(bad.shape[0], -1).any(1))]) if a.ndim else 0
            raise ValueError(f"{side} {k!r} has non-finite values, first at frame {t}")
        out[k] = a
    return out


PRED_KEYS = ("keypoints3d", "feet", "support", "zmp", "implied_force", "grf", "tau", "contact_prob")
GT_KEYS = ("keypoints3d", "feet", "support", "zmp", "implied_force", "grf", "tau", "contacts")


def evaluate_arrays(
    pred: Mapping[str, Any],
    gt: Mapping[str, Any],
    *,
    fps: float,
    mask=None,
    camera: Camera | None = None,
    root: tuple[int, ...] = (0,),
    pred_mass: float | None = None,
    gt_mass: float | None = None,
    pred_camera: Camera | None = None,
    scene=None,
) -> dict[str, float]:
    """Every applicable metric of one clip as a flat ``{key: float}`` (keys: :data:`METRICS`).

    ``pred`` and ``gt`` map names to per-frame arrays (leading axis T), any of which may be
    missing or None: ``keypoints3d`` (T, J, 3), ``feet`` (T, 4, 3), ``support`` (T, V, 3),
    ``zmp`` (T, 2), ``implied_force`` (T, 3) (see :func:`motion_quantities`), ``grf`` (T, 4, 3),
    ``tau`` (T, nv), and ``contact_prob`` (T, 4) for the prediction / ``contacts`` (T, 4) {0, 1}
    for the ground truth. ``mask`` (T,) marks real frames; ``camera`` is the input view;
    ``root`` the root joint indices of the layout; the masses (kg) give the body weights of the
    estimate's character and of the subject.

    A moving ``camera`` (extrinsics (T, 4, 4), one per frame) adds the camera-frame metrics
    (``*_cam_*``): the ground truth seen by it, the estimate by ``pred_camera``, the camera the
    estimate was made with where that differs (a method that took the first frame's camera for
    all, ignoring the camera's motion; default ``camera``).

    A ``scene`` (:class:`jmocap.scene.Scene`, the clip's terrain) makes the foot metrics measure
    heights against it (signed distance) instead of against the floor ``z = 0``.

    A metric whose inputs are missing is absent from the result, and so is one that is
    undefined for this clip (e.g. ballistic GRF without flight frames); no value is NaN. Inputs
    must be finite on the real frames (ValueError naming the array and frame otherwise). Without
    estimated forces (``grf``), the GRF statistics use ``implied_force``, as [001] does for its
    kinematic baseline. Ballistic (flight) frames are those without any ground-truth contact
    whose ground-truth root residual (``gt["tau"][:3]``, when given) is at most
    :data:`GT_MAX_RESIDUAL_PCT_BW`, or, without ground-truth labels, those without
    any estimated contact; the net GRF error and the per-foot correlation are scored on the
    frames within that residual too (all frames without ``gt["tau"]``).

    The metrics run as one jitted function per combination of available inputs and shapes.
    """
    for side, d, keys in (("pred", pred, PRED_KEYS), ("gt", gt, GT_KEYS)):
        unknown = sorted(set(d) - set(keys))
        if unknown:
            raise ValueError(f"{side} has unknown arrays {unknown}; known: {', '.join(keys)}")
    arrays = [v for v in list(pred.values()) + list(gt.values()) if v is not None]
    if not arrays:
        return {}
    T = np.shape(arrays[0])[0]
    m = np.ones(T, bool) if mask is None else np.asarray(mask, bool)
    if m.shape != (T,):
        raise ValueError(f"mask must have shape (T,) = ({T},), got {m.shape}")
    p, g = _finite(pred, "pred", m), _finite(gt, "gt", m)
    values = _metric_values(p, g, m, np.float32(fps), camera, tuple(int(i) for i in root),
                            None if pred_mass is None else np.float32(pred_mass),
                            None if gt_mass is None else np.float32(gt_mass), pred_camera,
                            None if scene is None else jax.tree.map(lambda a: np.asarray(a, np.float32), scene))
    values = {k: float(v) for k, v in jax.device_get(values).items()}
    return {k: values[k] for k in METRICS if k in values and np.isfinite(values[k])}


@partial(jax.jit, static_argnames=("root",))
def _metric_values(p, g, m, fps, camera, root, pred_mass, gt_mass, pred_camera=None, scene=None) -> dict[str, Array]:
    """The metrics of :func:`evaluate_arrays` as arrays (NaN where undefined); the set of keys
    follows the (static) set of inputs."""
    out: dict[str, Array] = {}
    pw = None if pred_mass is None else pred_mass * GRAVITY
    gw = None if gt_mass is None else gt_mass * GRAVITY
    gt_contacts = g.get("contacts")
    # the frames whose ground-truth motion its contact forces explain (GT_MAX_RESIDUAL_PCT_BW)
    explained = m
    if g.get("tau") is not None and gw is not None:
        explained = m & (jnp.linalg.norm(g["tau"][:, :3], axis=-1) / gw * 100.0 <= GT_MAX_RESIDUAL_PCT_BW)

    kp, kg = p.get("keypoints3d"), g.get("keypoints3d")
    if kp is not None and kg is not None:
        # per-joint mask: the joints the ground truth has (NaN: missing) on the real frames
        jm = m[:, None] & jnp.all(jnp.isfinite(kg), -1)
        kg = jnp.where(jm[..., None], kg, 0.0)
        for name, align in (("", "root"), ("pa_", "procrustes")):
            out[f"{name}mpjpe_mm"] = mpjpe(kp, kg, jm, align=align, root=root)
            out[f"{name}pck150_pct"] = pck(kp, kg, jm, align=align, root=root)
            out[f"{name}auc_pct"] = auc(kp, kg, jm, align=align, root=root)
        out["mpjpe_abs_mm"] = mpjpe(kp, kg, jm, align="none")
        out["root_err_mm"] = root_translation_error(kp, kg, jm, root=root)
        out["e_smooth_mm"], out["sigma_smooth_mm"] = smoothness_error(kp, kg, jm)
        out["accel_err_m_s2"] = acceleration_error(kp, kg, fps, jm)
        if camera is not None:
            out["reproj_input_px"], out["reproj_input_std_px"] = reprojection_error(kp, kg, camera, jm)
            root_ok = jnp.all(jm[:, np.asarray(root, int)], -1)
            pivot = _mean(root_position(kg, root).T, root_ok[None], 1)  # the mean gt root (3,)
            side = side_view_camera(camera, pivot)
            seen = jm & (world_to_camera(side, kg)[..., 2] >= SIDE_VIEW_NEAR_M)
            out["reproj_side_px"], out["reproj_side_std_px"] = reprojection_error(kp, kg, side, seen)
            if camera.extrinsics.ndim == 3:  # a moving camera: the camera-frame metrics too
                kpc = world_to_camera(pred_camera if pred_camera is not None else camera, kp)
                kgc = world_to_camera(camera, kg)
                out["mpjpe_cam_mm"] = mpjpe(kpc, kgc, jm, align="root", root=root)
                out["root_err_cam_mm"] = root_translation_error(kpc, kgc, jm, root=root)
                out["accel_err_cam_m_s2"] = acceleration_error(kpc, kgc, fps, jm)
    if kp is not None:
        out["jitter_km_s3"] = jitter(kp, fps, m)

    feet = p.get("feet")
    if feet is not None:
        out["pnp_pct"] = non_penetration(feet, m, scene)
        out["penetrate_pct"] = foot_penetration(feet, m, scene)
        if gt_contacts is not None:
            out["mpe_mm"] = mean_penetration_error(feet, gt_contacts, m, scene)
            out["float_pct"] = foot_floating(feet, gt_contacts, m, scene)
            out["skate_pct"] = foot_skate(feet, gt_contacts, m)

    forces = p.get("grf")
    if forces is None and p.get("implied_force") is not None:
        forces = p["implied_force"][:, None, :]
    if forces is not None and pw is not None:
        out["grf_mean_pct_bw"] = grf_mean(forces, pw, m)
        out["grf_max_pct_bw"] = grf_max(forces, pw, m)
        labels = gt_contacts if gt_contacts is not None else p.get("contact_prob")
        if labels is not None:
            flight = ~jnp.any(labels > 0.5, -1)
            out["grf_ballistic_pct_bw"] = grf_ballistic(forces, pw, flight, explained if gt_contacts is not None else m)
    if p.get("tau") is not None and pw is not None:
        out["root_residual_pct_bw"] = root_residual(p["tau"], pw, m)
    if all(p.get(k) is not None for k in ("zmp", "implied_force", "support", "feet")) and pw is not None:
        on = jnp.repeat(contact_labels(p["feet"]), p["support"].shape[1] // p["feet"].shape[1], axis=-1)
        out["zmp_dist_m"] = zmp_distance(p["zmp"], p["implied_force"][:, 2], pw, p["support"], on, m)
    if p.get("implied_force") is not None and pw is not None:
        out["cone_violation_pct"] = friction_cone_violation(p["implied_force"], pw, m)
    if p.get("grf") is not None and g.get("grf") is not None and pw is not None and gw is not None:
        out["grf_err_pct_bw"] = grf_error(p["grf"], g["grf"], pw, gw, explained)
        if p["grf"].shape[-2] == 4 and g["grf"].shape[-2] == 4:
            out["foot_grf_corr"] = foot_grf_correlation(p["grf"], g["grf"], explained)
    if p.get("tau") is not None and g.get("tau") is not None and pred_mass is not None and gt_mass is not None:
        out["torque_err_nm_kg"] = torque_error(p["tau"], g["tau"], pred_mass, gt_mass, m)
    if p.get("contact_prob") is not None and gt_contacts is not None:
        c = contact_classification(p["contact_prob"], gt_contacts, m)
        out.update(contact_acc_pct=c["accuracy"], contact_prec_pct=c["precision"],
                   contact_rec_pct=c["recall"], contact_f1_pct=c["f1"])
    return out


_quantities = jax.jit(motion_quantities, static_argnames="layout")


def clip_camera(clip, length: int | None = None) -> Camera:
    """The input camera of a :class:`~jmocap.data.clip.Clip` (the default extrinsics,
    :func:`jmocap.camera.default_extrinsics`, when the clip has none, as the methods assume);
    a moving camera's extrinsics are its track (T, 4, 4), frame t seen by camera t, padded to
    ``length`` frames with its last."""
    ext = clip.extrinsics if clip.extrinsics is not None else default_extrinsics()
    if clip.camera_track is not None:
        ext = clip.camera_track
        if length is not None and length > len(ext):
            ext = np.concatenate([ext, np.broadcast_to(ext[-1], (length - len(ext), 4, 4))])
    f32 = np.float32
    return Camera(jnp.asarray(np.asarray(clip.intrinsics, f32)), jnp.asarray(np.asarray(clip.image_size, f32)),
                  jnp.asarray(np.asarray(ext, f32)))


def clip_ground_truth(clip, gt_model: Model | None = None) -> tuple[dict[str, Array], float | None]:
    """The ground truth of a clip as :func:`evaluate_arrays` reads it, and the subject's mass.

    Quantities that need the physics (feet, ZMP, ...) come from ``gt_q`` on ``gt_model``
    (default: the character scaled to the clip's height and mass)."""
    gt: dict[str, Any] = dict(keypoints3d=clip.gt_keypoints3d, grf=clip.gt_grf, tau=clip.gt_tau,
                              contacts=clip.gt_contacts)
    mass = clip.mass_kg
    if clip.gt_q is not None:
        gt_model = gt_model or character(clip.height_m, clip.mass_kg)
        mass = mass or gt_model.total_mass
        qty = _quantities(gt_model, jnp.asarray(clip.gt_q), clip.fps, clip.layout, sole_half_width(gt_model))
        gt = {**qty, **{k: v for k, v in gt.items() if v is not None}}
    return gt, mass


def evaluate_motion(
    clip,
    *,
    q=None,
    keypoints3d=None,
    grf=None,
    tau=None,
    contact_prob=None,
    model: Model | None = None,
    mask=None,
    gt_model: Model | None = None,
) -> dict[str, float]:
    """All applicable metrics (:data:`METRICS`) of an estimate of one clip against the clip's
    ground truth, as a flat ``{key: float}``; metrics whose inputs are missing are absent.

    The estimate is given by its arrays over the clip's T frames: ``q`` (T, nq) on ``model`` (the
    character it was reconstructed with; default: scaled to the clip's height, as
    :mod:`jmocap.evaluate` does), from which keypoints, feet and the ZMP follow, and/or
    ``keypoints3d`` (T, J, 3) (overrides those of ``q``), ``grf`` (T, 4, 3), ``tau`` (T, nv),
    ``contact_prob`` (T, 4). A :class:`~jmocap.motion.Motion` gives them all:
    ``evaluate_motion(clip, q=m.q, grf=m.grf, tau=m.tau, contact_prob=m.contact_prob, model=...)``.
    """
    pred: dict[str, Any] = dict(grf=grf, tau=tau, contact_prob=contact_prob)
    pred_mass = None
    if q is not None:
        model = model or character(clip.height_m, clip.mass_kg)
        q = _points(q, "q", f"T, {model.nq}")
        if q.shape[0] != clip.num_frames:
            raise ValueError(f"q has {q.shape[0]} frames, clip {clip.name!r} has {clip.num_frames}")
        pred.update(_quantities(model, q, clip.fps, clip.layout, sole_half_width(model)))
    if model is not None:
        pred_mass = model.total_mass
    if keypoints3d is not None:
        pred["keypoints3d"] = keypoints3d
    gt, gt_mass = clip_ground_truth(clip, gt_model)
    return evaluate_arrays(pred, gt, fps=clip.fps, mask=mask, camera=clip_camera(clip),
                           root=clip.layout_spec.root_indices, pred_mass=pred_mass, gt_mass=gt_mass,
                           scene=clip.scene)
