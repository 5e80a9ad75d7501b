"""What a reconstruction method reads from one clip: :class:`ClipInputs` (arrays only).

A :class:`~jmocap.data.clip.Clip` (validated, any source format) becomes a ``ClipInputs`` padded
to a length bucket with a frame mask; a batch of clips is the same pytree with a leading axis,
so methods are ``jax.vmap``-ed over it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap.camera import Camera, default_extrinsics
from jmocap.scene import Scene, pad

#: a scene's boxes are padded to at least this many, and beyond it to the next power of two, so
#: that clips of different terrains share compiled code (a clip without a scene has none)
SCENE_SLOTS = 8


def scene_slots(n: int) -> int:
    """The padded number of boxes of a scene with ``n`` boxes (:data:`SCENE_SLOTS`)."""
    return 0 if n == 0 else max(SCENE_SLOTS, 1 << (int(n) - 1).bit_length())

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
    # (T, 4, 4) world -> camera of every frame (a moving camera's track; padding repeats the
    # last frame), or None: the static ``extrinsics`` for every frame (:meth:`world_to_camera`)
    camera_track: Array | None = None
    # the terrain (jmocap.scene.Scene, boxes padded to scene_slots; no boxes: the floor alone),
    # or None (the floor alone)
    scene: Scene | None = None

    @staticmethod
    def from_clip(clip, length: int | None = None) -> ClipInputs:
        """Inputs of a :class:`jmocap.data.clip.Clip`, optionally padded to ``length`` frames.
        A clip without extrinsics gets :func:`jmocap.camera.default_extrinsics`; a clip with a
        moving camera its track, padded with its last frame (``camera_track``); every other
        clip a ``camera_track`` of its static extrinsics, so that clips of both kinds batch. The
        clip's scene (``scene``) has its boxes padded to :func:`scene_slots`; a clip without one
        gets the empty scene (:func:`stack` pads the scenes of a batch to one size)."""
        kp = np.asarray(clip.keypoints, np.float32)
        T = kp.shape[0]
        L = T if length is None else int(length)
        if L < T:
            raise ValueError(f"clip {clip.name!r} has {T} frames, more than the padded length {L}")
        pad = np.zeros((L - T, *kp.shape[1:]), np.float32)
        ext = clip.extrinsics if clip.extrinsics is not None else default_extrinsics()
        track = np.broadcast_to(ext, (T, 4, 4)) if clip.camera_track is None else clip.camera_track
        track = np.concatenate([track, np.broadcast_to(track[-1], (L - T, 4, 4))])
        return ClipInputs(
            keypoints=np.concatenate([kp, pad]),
            intrinsics=np.asarray(clip.intrinsics, np.float32),
            image_size=np.asarray(clip.image_size, np.float32),
            extrinsics=np.asarray(ext, np.float32),
            fps=np.float32(clip.fps),
            mask=np.arange(L) < T,
            camera_track=track.astype(np.float32),
            scene=_padded_scene(getattr(clip, "scene", None)),
        )

    def world_to_camera(self) -> Array:
        """(..., T, 4, 4) world -> camera of every frame: ``camera_track``, or the static
        ``extrinsics`` repeated."""
        if self.camera_track is not None:
            return jnp.asarray(self.camera_track)
        E = jnp.asarray(self.extrinsics)
        T = self.keypoints.shape[-3]
        return jnp.broadcast_to(E[..., None, :, :], (*E.shape[:-2], T, 4, 4))

    def with_static_camera(self, extrinsics) -> ClipInputs:
        """These inputs seen by one static camera ``extrinsics`` (4, 4) (or (B, 4, 4))."""
        return self.replace(extrinsics=extrinsics, camera_track=None)

    @property
    def camera(self) -> Camera:
        """The clip's camera as a :class:`jmocap.camera.Camera`."""
        return Camera(jnp.asarray(self.intrinsics), jnp.asarray(self.image_size), jnp.asarray(self.extrinsics))


def _padded_scene(scene: Scene | None) -> Scene:
    if scene is None:
        return Scene.empty(np.float32)
    scene = jax.tree.map(lambda a: np.asarray(a, np.float32), scene)
    return pad(scene, scene_slots(scene.num_boxes))


def stack(inputs: list[ClipInputs]) -> ClipInputs:
    """A batch (leading axis) of clips' inputs, their scenes padded to the largest."""
    n = max((i.scene.num_boxes for i in inputs if i.scene is not None), default=0)
    if any(i.scene is not None for i in inputs):
        inputs = [i.replace(scene=pad(i.scene if i.scene is not None else Scene.empty(np.float32), n)) for i in inputs]
    return jax.tree.map(lambda *xs: np.stack(xs), *inputs)


__all__ = ["SCENE_SLOTS", "ClipInputs", "scene_slots", "stack"]
