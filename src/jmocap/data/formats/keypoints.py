"""What every 2D reader returns: :class:`Keypoints2D`, and its conversion to a :class:`Clip`.

A reader keeps what its file says about the video (fps, image size, camera) and leaves the rest
``None``; :meth:`Keypoints2D.to_clip` fills the gaps from arguments, the camera sidecar
(:mod:`jmocap.data.formats.camera_file`) and the defaults (:data:`DEFAULT_FPS`, the default
intrinsics of :mod:`jmocap.camera`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from jmocap.camera import default_intrinsics
from jmocap.data.clip import MAX_IMAGE_SIDE, Clip, FormatError
from jmocap.data.formats.camera_file import (
    camera_track_of,
    read_camera_json,
    sidecar_path,
    undistort_points,
)
from jmocap.data.formats.common import _number, _type_name

DEFAULT_FPS = 30.0


@dataclass(frozen=True, eq=False)
class Keypoints2D:
    """2D keypoints read from a file, plus what the file says about the video.

    ``keypoints`` (T, J, 3) float32 ``x, y`` pixels and confidence in [0, 1] (0 = missing, then
    x = y = 0); ``frame_ids`` (T,) the source frame numbers (consecutive: gaps in the source are
    filled with missing frames); ``fps``, ``image_size``, ``intrinsics``, ``extrinsics`` are
    ``None`` when the file does not say.
    """

    keypoints: np.ndarray
    layout: str
    name: str
    frame_ids: np.ndarray
    fps: float | None = None
    image_size: tuple[int, int] | None = None
    intrinsics: np.ndarray | None = None
    extrinsics: np.ndarray | None = None
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.keypoints.shape[0])

    def replace(self, **changes) -> Keypoints2D:
        return dataclasses.replace(self, **changes)

    def to_clip(
        self,
        *,
        fps: float | None = None,
        image_size: Sequence[int] | None = None,
        intrinsics: Sequence[float] | None = None,
        extrinsics: np.ndarray | None = None,
        name: str | None = None,
        camera_json: str | os.PathLike | None = None,
    ) -> Clip:
        """A :class:`Clip`; arguments override the file's own values.

        Precedence for each of fps / image size / intrinsics / extrinsics: the argument, then
        ``camera_json`` (a sidecar, see :func:`read_camera_json`), then the file's own value,
        then the default: ``fps`` 30 (:data:`DEFAULT_FPS`), intrinsics
        :func:`jmocap.camera.default_intrinsics` (f = 1000 px, principal point at the image
        centre), no extrinsics. There is no default image size: without one a
        :class:`FormatError` asks for it. Defaults that were used are listed in
        ``clip.meta["assumed"]``. The subject's ``height_m`` / ``mass_kg`` come from the sidecar
        (none of the keypoint formats stores them).

        Checked: the image size is two positive integers (at most
        :data:`~jmocap.data.clip.MAX_IMAGE_SIDE`; ``"640"`` or ``True`` are refused, not
        converted) and everything :class:`Clip` checks; errors name the source file.
        """
        side = read_camera_json(camera_json) if camera_json is not None else {}
        where = self.source or self.name
        assumed = []

        def pick(arg, key, own):
            if arg is not None:
                return arg
            if side.get(key) is not None:
                return side[key]
            return own

        size = pick(image_size, "image_size", self.image_size)
        if size is None:
            raise FormatError(
                f"{where}: field 'image_size': no image size: the format does not store one; pass image_size=(width, "
                f"height) or write a sidecar camera file {sidecar_path(where).name if self.source else '<clip>.camera.json'}"
            )
        if isinstance(size, np.ndarray):
            size = size.tolist()
        if not isinstance(size, (tuple, list)) or len(size) != 2:
            raise FormatError(f"{where}: field 'image_size' must be (width, height), got {_type_name(size)}")
        size = tuple(
            _number(v, where, "image_size", integer=True, positive=True, maximum=MAX_IMAGE_SIDE)
            for v in size
        )
        intr = pick(intrinsics, "intrinsics", self.intrinsics)
        if intr is None:
            intr = default_intrinsics(*size)
            assumed.append("intrinsics")
        extr = pick(extrinsics, "extrinsics", self.extrinsics)
        track = camera_track_of(side, camera_json, len(self.keypoints)) if extrinsics is None else None
        f = pick(fps, "fps", self.fps)
        if f is None:
            f = DEFAULT_FPS
            assumed.append("fps")
        meta = dict(self.meta)
        meta.setdefault("source", self.source)
        meta["first_frame"] = int(self.frame_ids[0]) if len(self.frame_ids) else 0
        if assumed:
            meta["assumed"] = assumed
        clip_name = name if name is not None else self.name
        keypoints = self.keypoints
        if side.get("distortion") is not None:  # lens distortion: to the ideal pinhole's pixels
            keypoints = undistort_keypoints(keypoints, intr, side["distortion"])
            meta["undistorted"] = [float(v) for v in side["distortion"]]
        if side.get("convention"):
            meta["camera_convention"] = side["convention"]
        try:
            return Clip(
                name=clip_name,
                layout=self.layout,
                fps=f,
                keypoints=keypoints,
                intrinsics=intr,
                image_size=np.asarray(size),
                extrinsics=extr,
                camera_track=track,
                height_m=side.get("height_m"),
                mass_kg=side.get("mass_kg"),
                meta=meta,
            )
        except FormatError as e:  # name the source rather than the clip
            msg, prefix = str(e), f"clip {clip_name!r}: "
            raise type(e)(f"{where}: {msg.removeprefix(prefix)}") from None


def undistort_keypoints(keypoints: np.ndarray, intrinsics, distortion) -> np.ndarray:
    """Keypoints (T, J, 3) seen through a lens with OpenCV distortion -> the ideal pinhole
    camera's pixels (:func:`~jmocap.data.formats.camera_file.undistort_points`); confidences and
    missing points (confidence 0 or NaN) unchanged."""
    kp = np.array(keypoints, dtype=np.float64, copy=True)
    ok = np.isfinite(kp[..., :2]).all(-1) & (kp[..., 2] > 0)
    kp[ok, :2] = undistort_points(kp[ok, :2], intrinsics, distortion)
    return kp.astype(np.asarray(keypoints).dtype)


__all__ = ["DEFAULT_FPS", "Keypoints2D", "undistort_keypoints"]
