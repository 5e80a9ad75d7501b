"""The camera sidecar: ``<clip>.camera.json`` next to a keypoint file or folder.

A JSON object ``{"fx", "fy", "cx", "cy", "width", "height"}`` (pixels) with optional
``"extrinsics"`` (4x4 nested list, world->camera, OpenCV axes) and ``"fps"``. It supplies what
most detector formats do not store (:meth:`~jmocap.data.formats.keypoints.Keypoints2D.to_clip`,
:func:`~jmocap.data.formats.read_clip`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data.clip import MAX_IMAGE_SIDE, Clip, _extrinsics_problem
from jmocap.data.formats.common import (
    _atomic_write_text,
    _ferr,
    _load_json,
    _nested_numbers,
    _number,
    _type_name,
)

# keys a sidecar does not have, though a clip does: refused rather than silently ignored
_NOT_SIDECAR_KEYS = {
    "intrinsics": "the sidecar gives the intrinsics as 'fx', 'fy', 'cx', 'cy'",
    "image_size": "the sidecar gives the image size as 'width', 'height'",
}


def sidecar_path(path: str | os.PathLike) -> Path:
    """The camera sidecar of a clip path: ``walk.npz`` / ``walk.json`` / ``walk/`` -> ``walk.camera.json``."""
    p = Path(path)
    stem = p.name if p.is_dir() or not p.suffix else p.stem
    return p.with_name(stem + ".camera.json")


def find_sidecar(path: str | os.PathLike) -> Path | None:
    """The camera sidecar of a clip path when one exists: :func:`sidecar_path`, and for a
    folder also ``<folder>/camera.json``. A name too long for the file system has none."""
    p = Path(path)
    for cand in (sidecar_path(p), p / "camera.json"):
        try:
            if cand.is_file():
                return cand
        except OSError:  # ENAMETOOLONG, EACCES: no readable sidecar of that name
            continue
    return None


def read_camera_json(path: str | os.PathLike) -> dict[str, Any]:
    """Read a camera sidecar: ``{"fx", "fy", "cx", "cy", "width", "height"}`` plus optional
    ``"extrinsics"`` (4x4 nested list, world->camera, OpenCV axes) and ``"fps"``.

    The subject's ``"height_m"`` and ``"mass_kg"`` may be given too (numbers > 0; their
    plausible ranges are checked with the clip, :mod:`jmocap.data.validate`).

    Returns ``{"intrinsics": (4,), "image_size": (w, h), "extrinsics": (4, 4) | None,
    "fps": float | None, "height_m": float | None, "mass_kg": float | None}``.

    Checked (else a :class:`FormatError` naming the file and the field): the file is a JSON
    object; ``fx``, ``fy``, ``cx``, ``cy`` are finite JSON numbers with ``fx``, ``fy`` > 0;
    ``width``, ``height`` positive integers (at most :data:`~jmocap.data.clip.MAX_IMAGE_SIDE`);
    ``fps`` a finite number > 0; ``extrinsics`` a 4x4 list of numbers that is a rigid transform
    ``[R t; 0 0 0 1]`` with R a rotation. Numbers must be JSON numbers: ``"30"`` or ``true``
    are refused, not converted. The clip's key names ``intrinsics`` and ``image_size`` are
    refused (a sidecar that has them means something the reader would otherwise ignore).
    """
    path = Path(path)
    data = _load_json(path)
    if not isinstance(data, dict):
        raise _ferr(path, f"a camera file must be a JSON object, got {_type_name(data)}")
    for key, hint in _NOT_SIDECAR_KEYS.items():
        if key in data:
            raise _ferr(path, f"is not a camera sidecar key: {hint}", field=key)
    for key in ("fx", "fy", "cx", "cy", "width", "height"):
        if key not in data:
            raise _ferr(path, "missing", field=key)
    out: dict[str, Any] = {}
    intr = [_number(data[k], path, k, positive=k in ("fx", "fy")) for k in ("fx", "fy", "cx", "cy")]
    out["intrinsics"] = np.asarray(intr, np.float64)
    out["image_size"] = tuple(
        _number(data[k], path, k, integer=True, positive=True, maximum=MAX_IMAGE_SIDE)
        for k in ("width", "height")
    )
    E = data.get("extrinsics")
    if E is not None:
        E = _nested_numbers(E, 2, path, "extrinsics")
        problem = _extrinsics_problem(E)
        if problem is not None:
            raise _ferr(path, problem, field="extrinsics")
    out["extrinsics"] = E
    fps = data.get("fps")
    if fps is not None:
        fps = _number(fps, path, "fps", positive=True)
    out["fps"] = fps
    for key in ("height_m", "mass_kg"):  # the subject's, optional (jmocap.subject)
        v = data.get(key)
        out[key] = None if v is None else _number(v, path, key, positive=True)
    return out


def write_camera_json(path: str | os.PathLike, clip: Clip) -> Path:
    """Write the camera, fps and subject (``height_m``, ``mass_kg`` when known) of ``clip`` as a
    sidecar JSON, atomically."""
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
    for key in ("height_m", "mass_kg"):  # the subject, when the clip knows it
        if getattr(clip, key, None) is not None:
            data[key] = float(getattr(clip, key))
    path = Path(path)
    _atomic_write_text(path, json.dumps(data, indent=1))
    return path


__all__ = ["find_sidecar", "read_camera_json", "sidecar_path", "write_camera_json"]
