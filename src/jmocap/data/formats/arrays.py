"""Plain keypoint arrays: ``.npy`` / ``.npz`` of (T, J, 2|3) pixels (Human3.6M-17 by default).

:func:`read_keypoint_array`; read without pickle, within :mod:`jmocap.data.limits`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from jmocap.data import limits
from jmocap.data.clip import MAX_IMAGE_SIDE, FormatError
from jmocap.data.formats.common import _READ_ERRORS, _check_nonempty, _ferr, clean_keypoints
from jmocap.data.formats.keypoints import Keypoints2D
from jmocap.layouts import get_layout

_ARRAY_KEYS = ("keypoints", "keypoints_2d", "kp2d", "joints_2d", "poses_2d", "pose_2d")


def read_keypoint_array(
    path: str | os.PathLike,
    *,
    layout: str = "h36m17",
    key: str | None = None,
    name: str | None = None,
) -> Keypoints2D:
    """Read a (T, J, 2) or (T, J, 3) pixel array from ``.npy`` or ``.npz`` (no pickle).

    The joint order is ``layout`` (default ``h36m17``: Hip, RHip, RKnee, RFoot, LHip, LKnee,
    LFoot, Spine, Thorax, Neck/Nose, Head, LShoulder, LElbow, LWrist, RShoulder, RElbow,
    RWrist). (T, J, 2) arrays get confidence 1; NaN or (0, 0) joints are missing. In an .npz,
    the array is ``key``, else the first of ``keypoints``, ``keypoints_2d``, ``kp2d``,
    ``joints_2d``, ``poses_2d``, ``pose_2d`` present, else the file's only array. Optional
    scalar entries ``fps`` and ``image_size`` (2,) / ``intrinsics`` (4,) are used when present.
    """
    path = Path(path)
    lay = get_layout(layout)
    extras: dict[str, np.ndarray] = {}
    try:
        if path.suffix == ".npy":
            fieldname = "<array>"
            a = limits.load_npy(path, f"{path}: field {fieldname!r}")
        else:
            npz = limits.load_npz(path, str(path))
            files = list(npz)
            if key is None:
                key = next((k for k in _ARRAY_KEYS if k in files), None)
                if key is None:
                    if len(files) != 1:
                        raise _ferr(path, f"has arrays {files} and none of the keypoint names {list(_ARRAY_KEYS)}: "
                                           "name the keypoint array so (read_arrays(key=...) in Python)")
                    key = files[0]
            if key not in files:
                raise _ferr(path, f"has no array {key!r} (arrays: {files})", field=key)
            a = npz[key]
            fieldname = key
            extras = {k: npz[k] for k in ("fps", "image_size", "intrinsics") if k in files}
    except FormatError:
        raise
    except (*_READ_ERRORS, MemoryError) as e:
        raise _ferr(path, f"not a readable numpy file: {e}") from None
    if (
        a.ndim != 3
        or a.shape[1] != lay.num_joints
        or a.shape[2] not in (2, 3)
        or a.dtype.kind not in "fiu"
    ):
        raise _ferr(
            path,
            f"has shape {a.shape} ({a.dtype}), expected (T, {lay.num_joints}, 2|3) for layout "
            f"{lay.name!r}",
            field=fieldname,
        )
    _check_nonempty(path, a.shape[0])
    limits.check_frames(a.shape[0], f"{path}: field {fieldname!r}")
    if a.shape[2] == 3:
        conf = a[..., 2]
        with np.errstate(invalid="ignore"):
            bad = np.isfinite(conf) & ((conf < 0) | (conf > 1.5))
        if bad.any():
            f = int(np.argmax(bad.any(axis=1)))
            raise _ferr(
                path, f"confidence {conf[f][bad[f]][0]} is far outside [0, 1]", f, fieldname
            )
    fps, size, intr = _extras(path, extras)
    return Keypoints2D(
        keypoints=clean_keypoints(a),
        layout=lay.name,
        name=name or path.stem,
        frame_ids=np.arange(a.shape[0]),
        fps=fps,
        image_size=size,
        intrinsics=intr,
        source=str(path),
        meta={"format": "array"},
    )


def _extras(path, extras: dict[str, np.ndarray]):
    """``(fps, image_size, intrinsics)`` from an array ``.npz``'s optional entries (None when
    absent). Checked: each holds numbers (not strings, booleans or objects); ``fps`` a finite
    scalar > 0, ``image_size`` two positive integers (at most
    :data:`~jmocap.data.clip.MAX_IMAGE_SIDE`), ``intrinsics`` four finite numbers."""
    shapes = {"fps": (), "image_size": (2,), "intrinsics": (4,)}
    for k, v in extras.items():
        if v.dtype.kind not in "iuf" or v.shape != shapes[k]:
            raise _ferr(
                path, f"has shape {v.shape} ({v.dtype}), expected {shapes[k]} numbers", field=k
            )
        if not np.isfinite(v).all():
            raise _ferr(path, f"has non-finite values {v.tolist()}", field=k)
    fps = size = intr = None
    if "fps" in extras:
        fps = float(extras["fps"])
        if not fps > 0:
            raise _ferr(path, f"must be > 0, got {fps}", field="fps")
    if "image_size" in extras:
        s = extras["image_size"].astype(np.float64)
        if not (np.all(s > 0) and np.all(s == np.round(s)) and np.all(s <= MAX_IMAGE_SIDE)):
            raise _ferr(
                path, f"must be positive integers up to {MAX_IMAGE_SIDE}, got {s.tolist()}",
                field="image_size",
            )
        size = (int(s[0]), int(s[1]))
    if "intrinsics" in extras:
        intr = np.asarray(extras["intrinsics"], np.float64)
    return fps, size, intr


__all__ = ["read_keypoint_array"]
