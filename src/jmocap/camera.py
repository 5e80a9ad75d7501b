"""Pinhole camera: projection, unprojection and the two keypoint normalisations of the paper.

Conventions (see ``docs/formats.md``):

* World frame: z-up, floor at z = 0, metres.
* Camera frame: OpenCV axes, x right, y down, z forward (along the optical axis); a point in
  front of the camera has depth Z > 0.
* ``extrinsics`` is the 4x4 rigid world->camera transform ``[R t; 0 1]``:
  ``X_cam = R @ X_world + t``.
* ``intrinsics`` is ``(fx, fy, cx, cy)`` in pixels, no skew, no lens distortion:
  ``u = fx X/Z + cx``, ``v = fy Y/Z + cy`` (paper eq. 3).
* ``image_size`` is ``(width, height)`` in pixels.

Batching. Every function is pure ``jax.numpy`` and works under ``jit``, ``vmap`` and ``grad``.
A :class:`Camera` may carry batch dimensions (``intrinsics (..., 4)``). Those camera batch
dimensions are matched against the *leading* dimensions of the point arrays: a camera with
batch shape ``(B,)`` projects points of shape ``(B, T, J, 3)`` (one camera per clip), and an
unbatched camera projects points of any shape ``(..., 3)``. The same rule applies to the
``intrinsics`` / ``image_size`` arguments of :func:`canonicalise` and :func:`root_relative`.
``jax.vmap`` over a batched camera works as well.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap.layouts import Layout, get_layout
from jmocap.numerics import safe_div, safe_normalize

Array = jnp.ndarray

# Default intrinsics when a clip does not come with a calibration. The paper's demo uses a
# focal length of 1000 px and the image centre as principal point; we do the same, whatever the
# resolution. (For a 1920x1080 video this is a ~88 degree horizontal field of view.)
DEFAULT_FOCAL_PX = 1000.0


def _float_dtype(dtype):
    """``dtype``, or the default float dtype (float32, float64 under ``jax_enable_x64``)."""
    return jax.dtypes.canonicalize_dtype(jnp.float64 if dtype is None else dtype)


def default_intrinsics(width: float, height: float, focal: float = DEFAULT_FOCAL_PX) -> np.ndarray:
    """The documented default ``(fx, fy, cx, cy)`` for an uncalibrated video.

    ``fx = fy = focal`` (1000 px, as in the paper's demo) and the principal point at the image
    centre ``(width / 2, height / 2)``. Returns a float64 numpy array of shape (4,).
    """
    if not (width > 0 and height > 0):
        raise ValueError(f"image size must be positive, got width={width}, height={height}")
    return np.array([focal, focal, width / 2.0, height / 2.0], dtype=np.float64)


def default_extrinsics(height: float = 1.0, distance: float = 4.0) -> np.ndarray:
    """The camera assumed when a clip has no extrinsics: level, at ``(0, -distance, height)``,
    looking along world +y at ``(0, 0, height)``; OpenCV axes (x right, y down, z forward).
    Returns the float64 4x4 world -> camera transform."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # world -> camera
    eye = np.array([0.0, -distance, height])
    E = np.eye(4)
    E[:3, :3] = R
    E[:3, 3] = -R @ eye
    return E


@struct.dataclass
class Camera:
    """A pinhole camera as a JAX pytree (all fields are arrays; batch dims allowed).

    Attributes:
      intrinsics: (..., 4) ``fx, fy, cx, cy`` in pixels.
      image_size: (..., 2) ``width, height`` in pixels (stored as floats).
      extrinsics: (..., 4, 4) world->camera rigid transform ``[R t; 0 1]`` (OpenCV axes).
    """

    intrinsics: Array
    image_size: Array
    extrinsics: Array

    @classmethod
    def from_intrinsics(cls, fx, fy, cx, cy, width, height, extrinsics=None, dtype=None) -> Camera:
        """Build a camera from scalars (or arrays of matching batch shape).

        ``extrinsics`` defaults to the identity: the world frame *is* the camera frame.
        """
        dtype = _float_dtype(dtype)
        scalars = [jnp.asarray(a, dtype) for a in (fx, fy, cx, cy, width, height)]
        extr = None if extrinsics is None else jnp.asarray(extrinsics, dtype)
        shapes = [a.shape for a in scalars] + ([] if extr is None else [extr.shape[:-2]])
        batch = jnp.broadcast_shapes(*shapes)  # all fields share one batch shape (for vmap)
        scalars = [jnp.broadcast_to(a, batch) for a in scalars]
        intr = jnp.stack(scalars[:4], -1)
        size = jnp.stack(scalars[4:], -1)
        if extr is None:
            extr = jnp.broadcast_to(jnp.eye(4, dtype=dtype), batch + (4, 4))
        else:
            extr = jnp.broadcast_to(extr, batch + (4, 4))
        return cls(intrinsics=intr, image_size=size, extrinsics=extr)

    @classmethod
    def default(cls, width, height, extrinsics=None, dtype=None) -> Camera:
        """A camera with :func:`default_intrinsics` for the given image size."""
        fx, fy, cx, cy = default_intrinsics(float(width), float(height))
        return cls.from_intrinsics(fx, fy, cx, cy, width, height, extrinsics, dtype)

    @classmethod
    def look_at(
        cls,
        eye,
        target,
        up=(0.0, 0.0, 1.0),
        *,
        fx=DEFAULT_FOCAL_PX,
        fy=None,
        cx=None,
        cy=None,
        width=1920,
        height=1080,
        dtype=None,
    ) -> Camera:
        """A camera at ``eye`` (world) looking at ``target``, with ``up`` the world up (z).

        The optical axis (camera +z) points from eye to target, camera +x is
        ``forward x up`` (image right) and camera +y is ``forward x right`` (image down), so a
        world z-up scene appears upright. ``fy`` defaults to ``fx``, the principal point to the
        image centre. ``up`` must not be parallel to the viewing direction.
        """
        dtype = _float_dtype(dtype)
        eye = jnp.asarray(eye, dtype)
        target = jnp.asarray(target, dtype)
        up = jnp.asarray(up, dtype)
        forward = safe_normalize(target - eye)
        right = safe_normalize(jnp.cross(forward, up))
        down = jnp.cross(forward, right)
        R = jnp.stack([right, down, forward], axis=-2)  # rows = camera axes in world coords
        t = -jnp.einsum("...ij,...j->...i", R, eye)
        top = jnp.concatenate([R, t[..., None]], axis=-1)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], dtype), top.shape[:-2] + (1, 4))
        extr = jnp.concatenate([top, bottom], axis=-2)
        fy = fx if fy is None else fy
        cx = width / 2.0 if cx is None else cx
        cy = height / 2.0 if cy is None else cy
        return cls.from_intrinsics(fx, fy, cx, cy, width, height, extr, dtype)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.intrinsics.shape[:-1])

    @property
    def rotation(self) -> Array:
        """(..., 3, 3) world->camera rotation R."""
        return self.extrinsics[..., :3, :3]

    @property
    def translation(self) -> Array:
        """(..., 3) world->camera translation t."""
        return self.extrinsics[..., :3, 3]

    @property
    def position(self) -> Array:
        """(..., 3) camera centre in world coordinates, ``-R^T t``."""
        return -jnp.einsum("...ji,...j->...i", self.rotation, self.translation)


def _expand(param: Array, core_ndim: int, x: Array, x_core_ndim: int) -> Array:
    """Insert axes so that ``param``'s batch dims align with the leading dims of ``x``.

    ``param`` has shape ``batch + core`` (core = its last ``core_ndim`` dims); ``x`` has shape
    ``lead + x_core``. The result has shape ``batch + (1,) * (len(lead) - len(batch)) + core``
    and broadcasts against ``x`` in the usual way.
    """
    batch_ndim = param.ndim - core_ndim
    x_batch_ndim = x.ndim - x_core_ndim
    extra = x_batch_ndim - batch_ndim
    if extra < 0:
        raise ValueError(
            f"camera/intrinsics batch shape {param.shape[:batch_ndim]} has more dims than the "
            f"points' batch shape {x.shape[:x_batch_ndim]}"
        )
    return param.reshape(param.shape[:batch_ndim] + (1,) * extra + param.shape[batch_ndim:])


def world_to_camera(camera: Camera, X: Array) -> Array:
    """World points (..., 3) -> camera-frame points (..., 3): ``R X + t``."""
    X = jnp.asarray(X)
    R = _expand(camera.rotation, 2, X, 1)
    t = _expand(camera.translation, 1, X, 1)
    return jnp.einsum("...ij,...j->...i", R, X) + t


def camera_to_world(camera: Camera, Xc: Array) -> Array:
    """Camera-frame points (..., 3) -> world points (..., 3): ``R^T (Xc - t)`` (rigid extrinsics)."""
    Xc = jnp.asarray(Xc)
    R = _expand(camera.rotation, 2, Xc, 1)
    t = _expand(camera.translation, 1, Xc, 1)
    return jnp.einsum("...ji,...j->...i", R, Xc - t)


def project(camera: Camera, X_world: Array, return_depth: bool = False):
    """Project world points (..., 3) to pixels (..., 2); with ``return_depth`` also Z (...,).

    ``u = fx X/Z + cx``, ``v = fy Y/Z + cy`` with ``[X, Y, Z]`` in the camera frame. A point at
    Z = 0 maps to the principal point (with finite gradients) rather than to infinity; points
    behind the camera (Z < 0) are projected by the same formula and are the caller's concern
    (check the returned depth).
    """
    Xc = world_to_camera(camera, X_world)
    z = Xc[..., 2]
    xy = safe_div(Xc[..., :2], z[..., None])
    K = _expand(camera.intrinsics, 1, xy, 1)
    uv = xy * K[..., 0:2] + K[..., 2:4]
    if return_depth:
        return uv, z
    return uv


def unproject(camera: Camera, uv: Array, depth: Array) -> Array:
    """Pixels (..., 2) at camera depth Z (...,) -> world points (..., 3). Inverse of :func:`project`."""
    uv = jnp.asarray(uv)
    depth = jnp.asarray(depth)
    K = _expand(camera.intrinsics, 1, uv, 1)
    xy = (uv - K[..., 2:4]) / K[..., 0:2]
    Xc = jnp.concatenate([xy * depth[..., None], depth[..., None]], axis=-1)
    return camera_to_world(camera, Xc)


def canonicalise(keypoints_px: Array, intrinsics: Array) -> Array:
    """Canonical keypoints K_c (paper eqs. 4-6): ``[(u - cx)/fx, (v - cy)/fy]``.

    This is the image of the joint on the plane Z = 1 of the camera frame, ``[X/Z, Y/Z]``,
    independent of the camera intrinsics.

    Args:
      keypoints_px: (..., J, 2) pixel keypoints, or (..., J, 3) with a confidence channel.
      intrinsics: (..., 4) ``fx, fy, cx, cy``; its batch dims match the *leading* dims of the
        keypoints (e.g. (4,) for one camera, (B, 4) for keypoints (B, T, J, 3)).

    Returns:
      Array of the same shape as ``keypoints_px``: the canonical coordinates, and the confidence
      channel unchanged when given. Joints with confidence 0 (missing) get coordinates 0.
    """
    kp = jnp.asarray(keypoints_px)
    K = _expand(jnp.asarray(intrinsics, kp.dtype), 1, kp, 1)
    xy = (kp[..., :2] - K[..., 2:4]) / K[..., 0:2]
    if kp.shape[-1] == 2:
        return xy
    if kp.shape[-1] != 3:
        raise ValueError(f"keypoints must be (..., J, 2) or (..., J, 3), got {kp.shape}")
    conf = kp[..., 2:3]
    return jnp.concatenate([jnp.where(conf > 0, xy, 0.0), conf], axis=-1)


def root_relative(keypoints_px: Array, image_size: Array, layout: str | Layout) -> Array:
    """Root-relative keypoints K_rr normalised by the image size (paper Sec. 3.1/3.2).

    ``K_rr = p / (w, h) - root / (w, h)`` with ``root`` the mean of the layout's root joints
    (``layout.root_indices``: MidHip for BODY_25, Hip for H36M, the two hips for COCO).

    Missing joints (confidence 0, only with (..., J, 3) input):

    * the root is the mean of the root joints that are *visible* (confidence > 0); for COCO, a
      frame with one hip missing uses the other hip alone;
    * a frame where no root joint is visible uses the mean of ``layout.root_fallback`` (the two
      hips for BODY_25's MidHip and Human3.6M's Hip) when all of those are visible; the root
      joint itself stays missing;
    * a frame with neither has no root: every joint of that frame gets coordinates 0 and
      confidence 0 (the whole frame is treated as missing);
    * a missing joint gets coordinates 0 (its confidence stays 0).

    Args:
      keypoints_px: (..., J, 2) or (..., J, 3) pixel keypoints (x, y[, confidence]).
      image_size: (..., 2) ``width, height``; batch dims match the leading dims of keypoints.
      layout: layout name or :class:`~jmocap.layouts.Layout` (J must equal its joint count).

    Returns:
      Array of the same shape as the input.
    """
    layout = get_layout(layout)
    kp = jnp.asarray(keypoints_px)
    if kp.ndim < 2 or kp.shape[-2] != layout.num_joints or kp.shape[-1] not in (2, 3):
        raise ValueError(
            f"keypoints must be (..., {layout.num_joints}, 2|3) for layout {layout.name!r}, "
            f"got {kp.shape}"
        )
    size = _expand(jnp.asarray(image_size, kp.dtype), 1, kp, 1)
    p = kp[..., :2] / size
    idx = np.asarray(layout.root_indices)
    if kp.shape[-1] == 2:
        root = jnp.mean(p[..., idx, :], axis=-2, keepdims=True)
        return p - root
    conf = kp[..., 2:3]
    w = (conf[..., idx, :] > 0).astype(kp.dtype)  # (..., R, 1)
    n = jnp.sum(w, axis=-2, keepdims=True)  # (..., 1, 1)
    root = safe_div(jnp.sum(p[..., idx, :] * w, axis=-2, keepdims=True), n)
    has_root = n > 0
    if layout.root_fallback:  # no root joint seen: the mean of the fallback joints, all of them seen
        fb = np.asarray(layout.root_fallback_indices)
        fb_seen = jnp.all(conf[..., fb, :] > 0, axis=-2, keepdims=True)
        use = ~has_root & fb_seen
        root = jnp.where(use, jnp.mean(p[..., fb, :], axis=-2, keepdims=True), root)
        has_root = has_root | use
    visible = (conf > 0) & has_root
    xy = jnp.where(visible, p - root, 0.0)
    conf = jnp.where(has_root, conf, 0.0)
    return jnp.concatenate([xy, conf], axis=-1)


__all__ = [
    "DEFAULT_FOCAL_PX",
    "Camera",
    "camera_to_world",
    "canonicalise",
    "default_intrinsics",
    "project",
    "root_relative",
    "unproject",
    "world_to_camera",
]
