"""Static cameras of the synthetic clips: configuration, look-at placement, sampling.

:func:`look_at_extrinsics` is the package's :meth:`jmocap.camera.Camera.look_at` called on
numpy arrays in float64 (:func:`~.bridge.np64`); :func:`project_points` is the numpy form of
:func:`jmocap.camera.project` (its docstring says why it stays numpy); :func:`sample_camera` places a
camera that keeps the subject in view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jmocap.camera import Camera
from jmocap.data.synthetic.bridge import np64
from jmocap.data.synthetic.errors import GenerationError


@dataclass(frozen=True)
class CameraConfig:
    """Static pinhole cameras looking at the subject (OpenCV axes, no distortion).

    The focal length is log-uniform in ``focal_px``, or, when ``focal_equiv_mm`` is set, in
    35 mm-equivalent millimetres (``f_px = f_mm / 36 * the image's long side``: 13 mm is a
    phone's ultra-wide lens, 24-28 mm its main one, 50-120 mm telephoto). The camera looks at
    a point 35-60 % up the subject (so a high or low camera is pitched), then rolls about its
    optical axis by up to ``roll_deg`` (a hand-held phone). :meth:`extended` is the extended
    generator's wider distribution."""

    focal_px: tuple[float, float] = (500.0, 2000.0)
    image_sizes: tuple[tuple[int, int], ...] = ((1920, 1080), (1280, 720), (1080, 1920), (1000, 1000))
    distance_m: tuple[float, float] = (3.0, 8.0)
    height_m: tuple[float, float] = (0.3, 2.0)
    principal_jitter: float = 0.02  # principal point offset, fraction of the image size
    min_visible: float = 0.95  # fraction of joint-frames that must project inside the image
    min_depth_m: float = 1.0  # closest any joint may come to the camera
    tries: int = 30
    focal_equiv_mm: tuple[float, float] | None = None
    roll_deg: float = 0.0

    @classmethod
    def extended(cls) -> CameraConfig:
        """Phones to telephoto (13-120 mm equivalent), 2-10 m away, 0.3-3 m high, rolled by up
        to 5 degrees."""
        return cls(distance_m=(2.0, 10.0), height_m=(0.3, 3.0), focal_equiv_mm=(13.0, 120.0),
                   roll_deg=5.0, tries=60)


def _look_at(eye, target, up):
    return Camera.look_at(eye, target, up, dtype=jnp.float64).extrinsics


_look_at_jit = jax.jit(_look_at)  # fixed (3,) shapes: compiled once per process (~1 s), then ~1 ms


def look_at_extrinsics(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World->camera [R t; 0 1] (OpenCV axes), float64 (4, 4), of a camera at ``eye`` looking
    at ``target``: the extrinsics of :meth:`jmocap.camera.Camera.look_at`."""
    return np64(_look_at_jit, eye, target, up)


def project_points(intrinsics, extrinsics, X):
    """Pinhole projection of world points (..., 3): pixels (..., 2) and depth (...,).

    The maths of :func:`jmocap.camera.project` (``u = fx X/Z + cx``, ``v = fy Y/Z + cy``; that
    one maps Z = 0 to the principal point), kept in numpy: it projects every joint-frame of a
    clip (T x J points, T different for every clip) up to ~70 times per clip in
    :func:`sample_camera`, and JAX would compile again for every new T (0.5 s per shape
    measured, against ~1 ms per call here)."""
    fx, fy, cx, cy = intrinsics
    Xc = X @ extrinsics[:3, :3].T + extrinsics[:3, 3]
    z = Xc[..., 2]
    uv = np.stack([fx * Xc[..., 0] / z + cx, fy * Xc[..., 1] / z + cy], axis=-1)
    return uv, z


def sample_camera(rng: np.random.Generator, points: np.ndarray, cfg: CameraConfig = CameraConfig()):
    """A static camera looking at the subject whose world joints over the clip are ``points``
    (T, J, 3). Resamples until ``min_visible`` of the joint-frames project inside the image and
    nothing comes closer than ``min_depth_m``; the last resort shortens the focal length until
    the subject fits. Returns (intrinsics (4,), image_size (2,), extrinsics (4, 4), info)."""
    flat = points.reshape(-1, 3)
    centre = (flat.min(axis=0) + flat.max(axis=0)) / 2
    best = None
    for attempt in range(cfg.tries):
        W, H = cfg.image_sizes[int(rng.integers(len(cfg.image_sizes)))]
        if cfg.focal_equiv_mm is None:
            f = float(np.exp(rng.uniform(np.log(cfg.focal_px[0]), np.log(cfg.focal_px[1]))))
        else:
            f_mm = float(np.exp(rng.uniform(np.log(cfg.focal_equiv_mm[0]), np.log(cfg.focal_equiv_mm[1]))))
            f = f_mm / 36.0 * max(W, H)
        dist = float(rng.uniform(*cfg.distance_m))
        cam_h = float(rng.uniform(*cfg.height_m))
        az = float(rng.uniform(-np.pi, np.pi))
        eye = np.array([centre[0] + dist * math.cos(az), centre[1] + dist * math.sin(az), cam_h])
        target = np.array([centre[0], centre[1], float(rng.uniform(0.35, 0.6)) * (flat[:, 2].max())])
        if abs(np.dot((target - eye) / np.linalg.norm(target - eye), [0, 0, 1])) > 0.98:
            continue
        E = look_at_extrinsics(eye, target)
        extra = {}
        if cfg.roll_deg > 0:  # roll about the optical axis (camera z): E <- Rz(roll) E
            r = math.radians(float(rng.uniform(-cfg.roll_deg, cfg.roll_deg)))
            Rz = np.array([[math.cos(r), -math.sin(r), 0.0], [math.sin(r), math.cos(r), 0.0], [0.0, 0.0, 1.0]])
            E = E.copy()
            E[:3, :] = Rz @ E[:3, :]
            extra["roll_deg"] = math.degrees(r)
        cx = W / 2 + float(rng.uniform(-1, 1)) * cfg.principal_jitter * W
        cy = H / 2 + float(rng.uniform(-1, 1)) * cfg.principal_jitter * H
        K = np.array([f, f, cx, cy])
        uv, z = project_points(K, E, flat)
        if z.min() < cfg.min_depth_m:
            continue
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        frac = float(inside.mean())
        cand = (K, np.array([W, H]), E, dict(distance_m=dist, height_m=cam_h, azimuth=az, attempts=attempt + 1,
                                                 **extra))
        if frac >= cfg.min_visible:
            return cand
        if best is None or frac > best[0]:
            best = (frac, cand)
    if best is None:
        raise GenerationError("no camera placement keeps the subject in front of the camera")
    K, size, E, info = best[1]
    # shrink the focal length around the principal point until the subject fits
    for _ in range(40):
        uv, _z = project_points(K, E, flat)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < size[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < size[1])
        if inside.mean() >= cfg.min_visible:
            break
        K = K.copy()
        K[:2] *= 0.9
    info["focal_shrunk"] = True
    return K, size, E, info
