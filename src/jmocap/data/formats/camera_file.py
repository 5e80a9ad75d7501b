"""The camera sidecar: ``<clip>.camera.json`` next to a keypoint file or folder.

A JSON object with the image size ``"width"``, ``"height"`` (pixels) and the intrinsics, in
one of the common conventions (docs/formats.md, "Camera sidecar"), optionally ``"fps"`` and the
subject's ``"height_m"``, ``"mass_kg"``. It supplies what most detector formats do not store
(:meth:`~jmocap.data.formats.keypoints.Keypoints2D.to_clip`,
:func:`~jmocap.data.formats.read_clip`).

* intrinsics: ``"fx", "fy", "cx", "cy"``, or ``"K"`` (3x3, OpenCV: ``[[fx, 0, cx], [0, fy,
  cy], [0, 0, 1]]``); lens distortion ``"dist"`` (OpenCV's ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``):
  the keypoints are undistorted through it when the clip is read (:func:`undistort_points`);
* extrinsics, at most one of: ``"extrinsics"`` (4x4 world -> camera); ``"R"`` (3x3) or
  ``"rvec"`` (Rodrigues, 3) with ``"t"`` / ``"tvec"`` (OpenCV's world -> camera:
  ``x_cam = R X + t``); ``"R_world_to_cam"`` with ``"t_world_to_cam"``; ``"cam_to_world"``
  (4x4 camera pose); ``"camera_position"`` (3) with ``"camera_rotation"`` (3x3, camera ->
  world: its columns are the camera's x, y, z axes in the world). Camera axes are OpenCV's
  (x right, y down, z forward);
* the world: ``"world_up"`` ``"z"`` (jmocap's, the default) or ``"y"`` (a y-up world, as
  OpenSim, glTF, Unity: turned into jmocap's by ``(x, y, z) -> (x, -z, y)``), and
  ``"floor_height"`` (the floor's coordinate along the up axis, default 0).

Any other key, two forms of the same thing (``fx`` and ``K``, ``extrinsics`` and ``R``), or half
of a pair (``R`` without ``t``) is a :class:`FormatError` naming the file and the key: nothing
in a camera file is silently ignored.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data.clip import MAX_IMAGE_SIDE, Clip, _extrinsics_problem, _rigid_frames
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
    "intrinsics": "the sidecar gives the intrinsics as 'fx', 'fy', 'cx', 'cy' (or 'K')",
    "image_size": "the sidecar gives the image size as 'width', 'height'",
}
#: every key a sidecar may have (anything else is an error)
SIDECAR_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "K", "dist", "fps", "height_m", "mass_kg",
                "extrinsics", "R", "rvec", "t", "tvec", "R_world_to_cam", "t_world_to_cam", "cam_to_world",
                "camera_position", "camera_rotation", "world_up", "floor_height")
#: the forms of the extrinsics: (keys that must all be present, the form's name)
_EXTRINSIC_FORMS = (
    (("extrinsics",), "extrinsics"),
    (("R", "t"), "R/t"),
    (("R", "tvec"), "R/t"),
    (("rvec", "t"), "rvec/t"),
    (("rvec", "tvec"), "rvec/t"),
    (("R_world_to_cam", "t_world_to_cam"), "R_world_to_cam"),
    (("cam_to_world",), "cam_to_world"),
    (("camera_position", "camera_rotation"), "camera pose"),
)
_EXTRINSIC_KEYS = ("extrinsics", "R", "rvec", "t", "tvec", "R_world_to_cam", "t_world_to_cam", "cam_to_world",
                   "camera_position", "camera_rotation")
#: jmocap's world from a y-up world: (x, y, z) -> (x, -z, y), a rotation
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """The rotation matrix (3, 3) of a Rodrigues vector (axis times angle, radians)."""
    rvec = np.asarray(rvec, np.float64)
    theta = float(np.linalg.norm(rvec))
    if theta < 1e-12:
        return np.eye(3)
    k = rvec / theta
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * Kx + (1.0 - math.cos(theta)) * Kx @ Kx


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV's lens model on normalised image points (..., 2): radial ``k1 k2 k3`` (rational
    ``k4 k5 k6``) and tangential ``p1 p2`` (``dist`` with 4, 5 or 8 coefficients)."""
    d = np.zeros(8)
    d[: len(dist)] = dist
    k1, k2, p1, p2, k3, k4, k5, k6 = d
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    return np.stack([x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                     y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y], -1)


def undistort_points(uv: np.ndarray, intrinsics, dist, iterations: int = 30) -> np.ndarray:
    """Pixels (..., 2) seen through a lens with OpenCV distortion ``dist`` -> the pixels an ideal
    pinhole camera with the same ``intrinsics`` (fx, fy, cx, cy) sees: the inverse of
    :func:`distort_normalized` by fixed-point iteration (as OpenCV's ``undistortPoints`` with
    ``P = K``). Non-finite points stay non-finite."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    uv = np.asarray(uv, np.float64)
    xd = np.stack([(uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy], -1)
    x = xd.copy()
    for _ in range(iterations):
        x = x + (xd - distort_normalized(x, dist))
    return np.stack([x[..., 0] * fx + cx, x[..., 1] * fy + cy], -1)


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


def _depth(v) -> int:
    """How deeply ``v`` nests JSON arrays (along first elements): 0 for a number."""
    d = 0
    while isinstance(v, list) and v:
        v, d = v[0], d + 1
    return d


def _matrix(data, key, shape, path, frames: bool = False) -> np.ndarray:
    """``data[key]`` as finite numbers of ``shape``; with ``frames``, one per frame: (T, *shape)."""
    ndim = len(shape) + int(frames)
    if ndim == 1:
        a = np.asarray([_number(v, path, key) for v in _list(data[key], path, key)], np.float64)
    else:
        a = _nested_numbers(data[key], ndim, path, key)
    want = ", ".join(map(str, ("T",) * int(frames) + tuple(shape)))
    if a.shape[int(frames):] != tuple(shape) or (frames and a.shape[0] == 0) or a.ndim != ndim:
        raise _ferr(path, f"must have shape ({want}), got {a.shape}", field=key)
    bad = ~np.isfinite(a)
    if bad.any():
        if frames:
            f = int(np.argmax(bad.reshape(len(a), -1).any(-1)))
            raise _ferr(path, "must be finite numbers", frame=f, field=key)
        raise _ferr(path, "must be finite numbers", field=key)
    return a


def _list(v, path, key):
    if not isinstance(v, list):
        raise _ferr(path, f"must be a JSON array, got {_type_name(v)}", field=key)
    return v


def _check_rigid(E: np.ndarray, path, key, frames: bool) -> None:
    """A :class:`FormatError` naming the file, the key and (for a track) the first frame where
    ``E`` (4x4 or T x 4 x 4) is not a rigid transform."""
    if not frames:
        problem = _extrinsics_problem(E)
        if problem is not None:
            raise _ferr(path, problem, field=key)
        return
    bad = _rigid_frames(E)
    if bad.any():
        raise _ferr(path, "must be a rigid transform [R t; 0 0 0 1] with R a rotation (orthonormal, determinant +1)",
                    frame=int(np.argmax(bad)), field=key)


def _rotation(R: np.ndarray, path, key, frames: bool = False) -> np.ndarray:
    E = np.zeros(R.shape[:-2] + (4, 4))
    E[..., :3, :3] = R
    E[..., 3, 3] = 1.0
    if frames:
        bad = _rigid_frames(E)
        if bad.any():
            raise _ferr(path, "must be a rotation matrix (orthonormal, determinant +1)", frame=int(np.argmax(bad)),
                        field=key)
    elif _extrinsics_problem(E) is not None:
        raise _ferr(path, "must be a rotation matrix (orthonormal, determinant +1)", field=key)
    return R


# how deeply each extrinsics key nests for one camera (a track nests one level more)
_STATIC_DEPTH = {"extrinsics": 2, "cam_to_world": 2, "R": 2, "R_world_to_cam": 2, "camera_rotation": 2,
                 "rvec": 1, "t": 1, "tvec": 1, "t_world_to_cam": 1, "camera_position": 1}


def _world_to_camera(data, path) -> tuple[np.ndarray | None, str | None]:
    """The world -> camera transform of whichever extrinsics form ``data`` has: (4, 4) for one
    camera, (T, 4, 4) for a camera track (every key of the form with a leading frame axis)."""
    present = [k for k in _EXTRINSIC_KEYS if k in data]
    if not present:
        return None, None
    forms = [(keys, name) for keys, name in _EXTRINSIC_FORMS if all(k in data for k in keys)]
    covered = {k for keys, _ in forms for k in keys}
    for k in present:
        if k not in covered:
            partner = {"R": "'t' (or 'tvec')", "rvec": "'t' (or 'tvec')", "t": "'R' or 'rvec'", "tvec": "'R' or 'rvec'",
                       "R_world_to_cam": "'t_world_to_cam'", "t_world_to_cam": "'R_world_to_cam'",
                       "camera_position": "'camera_rotation'", "camera_rotation": "'camera_position'"}.get(k, "")
            raise _ferr(path, f"needs {partner} with it", field=k)
    if len(forms) > 1:  # two forms (or one form with both 't' and 'tvec')
        keys = sorted({k for keys, _ in forms for k in keys})
        raise _ferr(path, f"gives the extrinsics more than one way ({', '.join(keys)}): give one", field=keys[0])
    keys, name = forms[0]
    per_frame = [_depth(data[k]) > _STATIC_DEPTH[k] for k in keys]
    frames = per_frame[0]
    if any(p != frames for p in per_frame):
        raise _ferr(path, f"gives one camera in {keys[per_frame.index(False)]!r} but one per frame in "
                    f"{keys[per_frame.index(True)]!r}: give both for one camera, or both per frame", field=keys[0])
    if frames:
        lengths = {k: len(data[k]) for k in keys}
        if len(set(lengths.values())) > 1:
            raise _ferr(path, "the camera track's keys have different numbers of frames: "
                        + ", ".join(f"{k} {n}" for k, n in lengths.items()), field=keys[0])
    if name in ("extrinsics", "cam_to_world"):
        M = _matrix(data, name, (4, 4), path, frames)
        _check_rigid(M, path, name, frames)
        if name == "extrinsics":
            return M, name
        Rc, c = M[..., :3, :3], M[..., :3, 3]
    elif name == "camera pose":
        Rc = _rotation(_matrix(data, "camera_rotation", (3, 3), path, frames), path, "camera_rotation", frames)
        c = _matrix(data, "camera_position", (3,), path, frames)
    else:
        rkey, tkey = keys
        if rkey == "rvec":
            rv = _matrix(data, "rvec", (3,), path, frames)
            R = np.stack([rodrigues(r) for r in rv]) if frames else rodrigues(rv)
        else:
            R = _rotation(_matrix(data, rkey, (3, 3), path, frames), path, rkey, frames)
        E = np.zeros(R.shape[:-2] + (4, 4))
        E[..., :3, :3] = R
        E[..., :3, 3] = _matrix(data, tkey, (3,), path, frames)
        E[..., 3, 3] = 1.0
        return E, name
    # a camera pose (rotation camera -> world, centre): its inverse
    E = np.zeros(Rc.shape[:-2] + (4, 4))
    RcT = np.swapaxes(Rc, -1, -2)
    E[..., :3, :3] = RcT
    E[..., :3, 3] = -np.einsum("...ij,...j->...i", RcT, c)
    E[..., 3, 3] = 1.0
    return E, name


def read_camera_json(path: str | os.PathLike) -> dict[str, Any]:
    """Read a camera sidecar in any of the conventions of the module docstring.

    Returns ``{"intrinsics": (4,), "image_size": (w, h), "extrinsics": (4, 4) world -> camera
    in jmocap's z-up world | None, "camera_track": (T, 4, 4) | None (a moving camera: every
    extrinsics key given per frame; "extrinsics" is then its first frame), "distortion": (k,) | None, "fps": float | None, "height_m":
    float | None, "mass_kg": float | None, "convention": str}`` (``convention`` names the
    extrinsics form and world read, for the record).

    Checked (else a :class:`FormatError` naming the file and the field): the file is a JSON
    object of known keys only; ``fx``, ``fy``, ``cx``, ``cy`` (or ``K``) finite JSON numbers
    with ``fx``, ``fy`` > 0; ``width``, ``height`` positive integers (at most
    :data:`~jmocap.data.clip.MAX_IMAGE_SIDE`); ``fps`` a finite number > 0; rotations are
    rotations, transforms rigid; ``dist`` 4, 5 or 8 numbers. Numbers must be JSON numbers:
    ``"30"`` or ``true`` are refused, not converted.
    """
    path = Path(path)
    data = _load_json(path)
    if not isinstance(data, dict):
        raise _ferr(path, f"a camera file must be a JSON object, got {_type_name(data)}")
    for key, hint in _NOT_SIDECAR_KEYS.items():
        if key in data:
            raise _ferr(path, f"is not a camera sidecar key: {hint}", field=key)
    for key in data:
        if key not in SIDECAR_KEYS:
            raise _ferr(path, "unknown key (a camera file's keys are: " + ", ".join(SIDECAR_KEYS)
                        + "; docs/formats.md)", field=key)
    for key in ("width", "height"):
        if key not in data:
            raise _ferr(path, "missing", field=key)
    out: dict[str, Any] = {}
    if "K" in data:
        for k in ("fx", "fy", "cx", "cy"):
            if k in data:
                raise _ferr(path, "the intrinsics are given twice ('K' and 'fx'/'fy'/'cx'/'cy'): give one", field=k)
        K = _matrix(data, "K", (3, 3), path)
        if abs(K[0, 1]) > 1e-9 or not np.allclose(K[1, 0], 0) or not np.allclose(K[2], [0, 0, 1]):
            raise _ferr(path, "must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)", field="K")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise _ferr(path, "fx and fy (K[0][0], K[1][1]) must be positive", field="K")
        out["intrinsics"] = np.asarray([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float64)
    else:
        for key in ("fx", "fy", "cx", "cy"):
            if key not in data:
                raise _ferr(path, "missing (or give 'K')", field=key)
        intr = [_number(data[k], path, k, positive=k in ("fx", "fy")) for k in ("fx", "fy", "cx", "cy")]
        out["intrinsics"] = np.asarray(intr, np.float64)
    out["image_size"] = tuple(
        _number(data[k], path, k, integer=True, positive=True, maximum=MAX_IMAGE_SIDE)
        for k in ("width", "height")
    )
    out["distortion"] = None
    if "dist" in data:
        d = np.asarray([_number(v, path, "dist") for v in _list(data["dist"], path, "dist")], np.float64)
        if len(d) not in (4, 5, 8):
            raise _ferr(path, f"must have 4, 5 or 8 coefficients (OpenCV: k1 k2 p1 p2 [k3 [k4 k5 k6]]), got {len(d)}",
                        field="dist")
        out["distortion"] = d if np.any(d != 0) else None
    E, form = _world_to_camera(data, path)
    up = data.get("world_up", "z")
    if up not in ("z", "y"):
        raise _ferr(path, f"must be \"z\" or \"y\", got {up!r}", field="world_up")
    floor = _number(data["floor_height"], path, "floor_height") if "floor_height" in data else 0.0
    if E is not None:
        # world points of the file's world X_f = A^T (X_jmocap + floor up): x_cam = E [A^T (X + f e_z)]
        A = Y_UP_TO_Z_UP if up == "y" else np.eye(3)
        W = np.eye(4)
        W[:3, :3] = A.T
        W[:3, 3] = A.T @ np.array([0.0, 0.0, floor])
        E = E @ W
    elif up != "z" or floor != 0.0:
        raise _ferr(path, "given without extrinsics (it changes only where the camera is)",
                    field="world_up" if up != "z" else "floor_height")
    track = E is not None and E.ndim == 3
    out["extrinsics"] = E[0] if track else E
    out["camera_track"] = E if track else None
    out["convention"] = (f"{form or 'no extrinsics'}{' per frame (a camera track)' if track else ''}, {up}-up world"
                         + (f", floor at {floor}" if floor else ""))
    fps = data.get("fps")
    if fps is not None:
        fps = _number(fps, path, "fps", positive=True)
    out["fps"] = fps
    for key in ("height_m", "mass_kg"):  # the subject's, optional (jmocap.subject)
        v = data.get(key)
        out[key] = None if v is None else _number(v, path, key, positive=True)
    return out


def camera_track_of(side: dict, path, frames: int) -> np.ndarray | None:
    """The camera track (T, 4, 4) of a read sidecar ``side`` (:func:`read_camera_json`) for a
    clip of ``frames`` frames; None for a static camera. A track of another length is a
    :class:`FormatError` naming the sidecar ``path``."""
    track = side.get("camera_track")
    if track is not None and len(track) != frames:
        raise _ferr(path, f"the camera track has {len(track)} frames but the clip has {frames}: one camera per "
                    f"frame of the keypoints", field="extrinsics")
    return track


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
    if clip.camera_track is not None:  # a moving camera: one world -> camera per frame
        data["extrinsics"] = np.asarray(clip.camera_track, np.float64).tolist()
    elif clip.extrinsics is not None:
        data["extrinsics"] = np.asarray(clip.extrinsics, np.float64).tolist()
    for key in ("height_m", "mass_kg"):  # the subject, when the clip knows it
        if getattr(clip, key, None) is not None:
            data[key] = float(getattr(clip, key))
    path = Path(path)
    _atomic_write_text(path, json.dumps(data, indent=1))
    return path


__all__ = [
    "SIDECAR_KEYS",
    "camera_track_of",
    "Y_UP_TO_Z_UP",
    "distort_normalized",
    "find_sidecar",
    "read_camera_json",
    "rodrigues",
    "sidecar_path",
    "undistort_points",
    "write_camera_json",
]
