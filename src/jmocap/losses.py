"""The paper's training objectives (eqs. 8-12 and 17-25), as pure functions.

Every loss is a mean over its frames (and joints/points), with an optional frame mask, rather
than the paper's plain sums, so that the weights do not depend on clip length or joint count.
Forces are divided by the body weight ``m g`` and torques likewise, so that force losses are
O(1) like the pose losses (the paper's ``phi = 1e-6`` on raw torques plays the same role in
L_Dyn and is kept there).
"""

from __future__ import annotations

import jax.numpy as jnp

from jmocap.physics.contact import friction_cone_loss

Array = jnp.ndarray


def masked_mean(x: Array, mask: Array | None = None) -> Array:
    """Mean of x over its leading (frame) axis, counting only frames where mask is True; other
    axes are averaged too."""
    x = jnp.asarray(x)
    if mask is None:
        return jnp.mean(x)
    mask = jnp.asarray(mask)
    m = jnp.broadcast_to(mask.reshape(mask.shape + (1,) * (x.ndim - mask.ndim)), x.shape)
    m = m.astype(x.dtype)
    return jnp.sum(x * m) / jnp.maximum(jnp.sum(m), 1.0)


def loss_3d(pred: Array, gt: Array, mask: Array | None = None, weight: Array | None = None) -> Array:
    """L_3D (eq. 18): mean squared distance (m^2) of 3D joints (..., J, 3); ``weight`` (..., J)
    can switch joints off (missing ground truth)."""
    d = jnp.sum((pred - gt) ** 2, -1)
    if weight is not None:
        d = d * weight
    return masked_mean(d, mask)


def loss_2d(pred_px: Array, gt_px: Array, image_size: Array, conf: Array | None = None, mask=None) -> Array:
    """L_2D (eq. 19): squared reprojection error of keypoints normalised by the image size,
    weighted by the keypoints' confidence (0 for missing joints).

    The normalised error is clipped to +-2 image sizes, so that a joint projected from behind or
    next to the camera plane (an untrained pose) cannot dominate the loss with a huge gradient;
    its depth is corrected by the 3D and translation losses instead.
    """
    d = jnp.sum(jnp.clip((pred_px - gt_px) / image_size, -2.0, 2.0) ** 2, -1)
    if conf is not None:
        d = d * conf
    return masked_mean(d, mask)


def loss_ori(rot: Array, rot_gt: Array, mask: Array | None = None) -> Array:
    """L_ori (eq. 20): squared Frobenius distance of the root rotation matrices."""
    return masked_mean(jnp.sum((rot - rot_gt) ** 2, (-2, -1)), mask)


def loss_irr(angles: Array, lower: Array, upper: Array, mask: Array | None = None) -> Array:
    """L_irr (eqs. 21-22): squared excursion of joint angles outside [lower, upper], summed over
    joints (as the paper), averaged over frames."""
    excess = jnp.maximum(angles - upper, 0.0) + jnp.maximum(lower - angles, 0.0)
    return masked_mean(jnp.sum(excess**2, -1), mask)


def loss_contact(logits: Array, labels: Array, mask: Array | None = None) -> Array:
    """L_b (eq. 23): binary cross-entropy of the four contact probabilities (from logits, which
    is numerically stable), summed over the points, averaged over frames."""
    bce = jnp.maximum(logits, 0) - logits * labels + jnp.log1p(jnp.exp(-jnp.abs(logits)))
    return masked_mean(jnp.sum(bce, -1), mask)


def loss_translation(trans: Array, trans_gt: Array, mask: Array | None = None) -> Array:
    """L_CT (eq. 24): squared error of the root translation (m^2)."""
    return masked_mean(jnp.sum((trans - trans_gt) ** 2, -1), mask)


def loss_dyn(pose_error: Array, tau: Array, mask: Array | None = None, phi: float = 1e-6) -> Array:
    """L_Dyn (eq. 25): ||q - q_hat||^2 + phi ||tau||^2.

    ``pose_error`` is d(q_hat, q) in velocity coordinates (the quaternion part as a rotation
    vector, see :func:`jmocap.cycle.pd_error`), so that the root orientation is compared as a
    rotation rather than as four numbers.
    """
    return masked_mean(jnp.sum(pose_error**2, -1) + phi * jnp.sum(tau**2, -1), mask)


def loss_force(tau_star_root: Array, weight: Array, mask: Array | None = None) -> Array:
    """L_force (eq. 8): ||tau_root - (J^T G lambda)_root||^2 = ||tau*_root||^2, per body weight."""
    return masked_mean(jnp.sum((tau_star_root / weight) ** 2, -1), mask)


def loss_cone(grf: Array, normal: Array, mu: float = 0.8, mask: Array | None = None) -> Array:
    """L_cone (eq. 10) summed over contact points, averaged over frames."""
    return masked_mean(jnp.sum(friction_cone_loss(grf, normal, mu), -1), mask)


def loss_smooth(grf: Array, grf_prev: Array, weight: Array, mask: Array | None = None) -> Array:
    """L_smooth (eq. 11): ||lambda - lambda_prev||^2, per body weight."""
    return masked_mean(jnp.sum(((grf - grf_prev) / weight) ** 2, (-2, -1)), mask)


def loss_grf(tau_star_root, grf, grf_raw, grf_prev, weight, normal, mu=0.8, mask=None) -> Array:
    """L_GRF (eq. 12) = L_force + L_smooth + L_cone (the cone loss on GRFNet's raw output; the
    forces applied are projected onto the friction pyramid)."""
    return (
        loss_force(tau_star_root, weight, mask)
        + loss_smooth(grf, grf_prev, weight, mask)
        + loss_cone(grf_raw / weight, normal, mu, mask)
    )

