"""The camera sidecar: ``<clip>.camera.json`` next to a keypoint file or folder.

A JSON object ``{"fx", "fy", "cx", "cy", "width", "height"}`` (pixels) with optional
``"extrinsics"`` (4x4 nested list, world->camera, OpenCV axes) and ``"fps"``. It supplies what
most detector formats do not store (:meth:`~jmocap.data.formats.keypoints.Keypoints2D.to_clip`,
:func:`~jmocap.data.formats.read_clip`).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data.clip import Clip
from jmocap.data.formats.common import _atomic_write_text, _ferr, _load_json


def sidecar_path(path: str | os.PathLike) -> Path:
    """The camera sidecar of a clip path: ``walk.npz`` / ``walk.json`` / ``walk/`` -> ``walk.camera.json``."""
    p = Path(path)
    stem = p.name if p.is_dir() or not p.suffix else p.stem
    return p.with_name(stem + ".camera.json")


def read_camera_json(path: str | os.PathLike) -> dict[str, Any]:
    """Read a camera sidecar: ``{"fx", "fy", "cx", "cy", "width", "height"}`` plus optional
    ``"extrinsics"`` (4x4 nested list, world->camera, OpenCV axes) and ``"fps"``.

    Returns ``{"intrinsics": (4,), "image_size": (w, h), "extrinsics": (4, 4) | None,
    "fps": float | None}``.
    """
    path = Path(path)
    data = _load_json(path)
    if not isinstance(data, dict):
        raise _ferr(path, "a camera file must be a JSON object")
    out: dict[str, Any] = {}
    try:
        intr = [float(data[k]) for k in ("fx", "fy", "cx", "cy")]
    except KeyError as e:
        raise _ferr(path, "missing", field=e.args[0]) from None
    except (TypeError, ValueError):
        raise _ferr(path, "fx, fy, cx, cy must be numbers", field="fx") from None
    if not all(math.isfinite(v) for v in intr) or intr[0] <= 0 or intr[1] <= 0:
        raise _ferr(path, f"intrinsics {intr} must be finite with fx, fy > 0", field="fx")
    out["intrinsics"] = np.asarray(intr, np.float64)
    try:
        w, h = data["width"], data["height"]
    except KeyError as e:
        raise _ferr(path, "missing", field=e.args[0]) from None
    if not (
        isinstance(w, (int, float))
        and isinstance(h, (int, float))
        and w > 0
        and h > 0
        and w == int(w)
        and h == int(h)
    ):
        raise _ferr(path, f"image size ({w!r}, {h!r}) must be positive integers", field="width")
    out["image_size"] = (int(w), int(h))
    E = data.get("extrinsics")
    if E is not None:
        try:
            E = np.asarray(E, np.float64)
        except (TypeError, ValueError):
            raise _ferr(path, "must be a 4x4 list of numbers", field="extrinsics") from None
        if E.shape != (4, 4) or not np.isfinite(E).all():
            raise _ferr(
                path, f"must be a finite 4x4 matrix, got shape {E.shape}", field="extrinsics"
            )
    out["extrinsics"] = E
    fps = data.get("fps")
    if fps is not None:
        if not isinstance(fps, (int, float)) or not fps > 0:
            raise _ferr(path, f"must be a positive number, got {fps!r}", field="fps")
        fps = float(fps)
    out["fps"] = fps
    return out


def write_camera_json(path: str | os.PathLike, clip: Clip) -> Path:
    """Write the camera (and fps) of ``clip`` as a sidecar JSON, atomically."""
    fx, fy, cx, cy = (float(v) for v in clip.intrinsics)
    w, h = (int(v) for v in clip.image_size)
    data: dict[str, Any] = {
        "fx": fx,
        "fy": fy,
        "cx": cx,
        "cy": cy,
        "width": w,
        "height": h,
        "fps": float(clip.fps),
    }
    if clip.extrinsics is not None:
        data["extrinsics"] = np.asarray(clip.extrinsics, np.float64).tolist()
    path = Path(path)
    _atomic_write_text(path, json.dumps(data, indent=1))
    return path


__all__ = ["read_camera_json", "sidecar_path", "write_camera_json"]
