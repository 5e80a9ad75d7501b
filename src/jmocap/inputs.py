"""What a reconstruction method reads from one clip: :class:`ClipInputs` (arrays only).

A :class:`~jmocap.data.clip.Clip` (validated, any source format) becomes a ``ClipInputs`` padded
to a length bucket with a frame mask; a batch of clips is the same pytree with a leading axis,
so methods are ``jax.vmap``-ed over it.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap.camera import Camera, default_extrinsics

Array = jnp.ndarray


@struct.dataclass
class ClipInputs:
    """The arrays of one clip (a batch adds a leading axis to every field)."""

    keypoints: Array  # (T, J, 3) pixels x, y and confidence
    intrinsics: Array  # (4,) fx, fy, cx, cy
    image_size: Array  # (2,) width, height
    extrinsics: Array  # (4, 4) world -> camera (OpenCV axes)
    fps: Array  # () frames per second
    mask: Array  # (T,) bool, real frames

    @staticmethod
    def from_clip(clip, length: int | None = None) -> ClipInputs:
        """Inputs of a :class:`jmocap.data.clip.Clip`, optionally padded to ``length`` frames.
        A clip without extrinsics gets :func:`jmocap.camera.default_extrinsics`."""
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

    @property
    def camera(self) -> Camera:
        """The clip's camera as a :class:`jmocap.camera.Camera`."""
        return Camera(jnp.asarray(self.intrinsics), jnp.asarray(self.image_size), jnp.asarray(self.extrinsics))


__all__ = ["ClipInputs"]
