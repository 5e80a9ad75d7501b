"""Cameras of the synthetic clips: configuration, look-at placement, sampling.

:func:`look_at_extrinsics` is the package's :meth:`jmocap.camera.Camera.look_at` called on
numpy arrays in float64 (:func:`~.bridge.np64`); :func:`project_points` is the numpy form of
:func:`jmocap.camera.project` (its docstring says why it stays numpy); :func:`sample_camera` places a
static camera that keeps the subject in view, :func:`sample_moving_camera` a moving one
(:data:`MOVING_KINDS`: hand-held, panning tripod, dolly, orbiting drone) with its per-frame track.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from scipy.ndimage import gaussian_filter1d

from jmocap.camera import Camera
from jmocap.data.synthetic.bridge import np64
from jmocap.data.synthetic.errors import GenerationError
from jmocap.data.synthetic.rotations import _rx, _ry, _rz


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
    """Pinhole projection of world points (..., 3): pixels (..., 2) and depth (...,). With a
    camera track ``extrinsics`` (T, 4, 4), ``X`` is (T, ..., 3) and frame t is seen by camera t.

    The maths of :func:`jmocap.camera.project` (``u = fx X/Z + cx``, ``v = fy Y/Z + cy``; that
    one maps Z = 0 to the principal point), kept in numpy: it projects every joint-frame of a
    clip (T x J points, T different for every clip) up to ~70 times per clip in
    :func:`sample_camera`, and JAX would compile again for every new T (0.5 s per shape
    measured, against ~1 ms per call here)."""
    fx, fy, cx, cy = intrinsics
    extrinsics = np.asarray(extrinsics)
    if extrinsics.ndim == 3:  # one camera per frame
        X = np.asarray(X)
        R = extrinsics[:, :3, :3].reshape((len(X),) + (1,) * (X.ndim - 2) + (3, 3))
        t = extrinsics[:, :3, 3].reshape((len(X),) + (1,) * (X.ndim - 2) + (3,))
        Xc = np.einsum("...ij,...j->...i", R, X) + t
    else:
        Xc = X @ extrinsics[:3, :3].T + extrinsics[:3, 3]
    z = Xc[..., 2]
    uv = np.stack([fx * Xc[..., 0] / z + cx, fy * Xc[..., 1] / z + cy], axis=-1)
    return uv, z


def _draw_image(rng: np.random.Generator, cfg: CameraConfig) -> tuple[int, int, float]:
    """One draw of the image size (W, H) and the focal length f (pixels) of ``cfg``."""
    W, H = cfg.image_sizes[int(rng.integers(len(cfg.image_sizes)))]
    if cfg.focal_equiv_mm is None:
        f = float(np.exp(rng.uniform(np.log(cfg.focal_px[0]), np.log(cfg.focal_px[1]))))
    else:
        f_mm = float(np.exp(rng.uniform(np.log(cfg.focal_equiv_mm[0]), np.log(cfg.focal_equiv_mm[1]))))
        f = f_mm / 36.0 * max(W, H)
    return W, H, f


def _inside_share(K, E, points, W, H) -> tuple[float, float]:
    """The share of ``points`` projecting inside the W x H image of camera (K, E) (one camera, or
    a track with points (T, ..., 3)) and their smallest depth."""
    uv, z = project_points(K, E, points)
    inside = (uv[..., 0] >= 0) & (uv[..., 0] < W) & (uv[..., 1] >= 0) & (uv[..., 1] < H)
    return float(inside.mean()), float(z.min())


def _shrink_focal(K, size, E, points, cfg: CameraConfig):
    """The last resort of the samplers: the focal length shortened around the principal point
    (by 10 % at a time, at most 40 times) until ``min_visible`` of ``points`` fit the image."""
    for _ in range(40):
        if _inside_share(K, E, points, size[0], size[1])[0] >= cfg.min_visible:
            break
        K = K.copy()
        K[:2] *= 0.9
    return K


def sample_camera(rng: np.random.Generator, points: np.ndarray, cfg: CameraConfig = CameraConfig()):
    """A static camera looking at the subject whose world joints over the clip are ``points``
    (T, J, 3). Resamples until ``min_visible`` of the joint-frames project inside the image and
    nothing comes closer than ``min_depth_m``; the last resort shortens the focal length until
    the subject fits. Returns (intrinsics (4,), image_size (2,), extrinsics (4, 4), info)."""
    flat = points.reshape(-1, 3)
    centre = (flat.min(axis=0) + flat.max(axis=0)) / 2
    best = None
    for attempt in range(cfg.tries):
        W, H, f = _draw_image(rng, cfg)
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
        frac, zmin = _inside_share(K, E, flat, W, H)
        if zmin < cfg.min_depth_m:
            continue
        cand = (K, np.array([W, H]), E, dict(distance_m=dist, height_m=cam_h, azimuth=az, attempts=attempt + 1,
                                                 **extra))
        if frac >= cfg.min_visible:
            return cand
        if best is None or frac > best[0]:
            best = (frac, cand)
    if best is None:
        raise GenerationError("no camera placement keeps the subject in front of the camera")
    K, size, E, info = best[1]
    info["focal_shrunk"] = True
    return _shrink_focal(K, size, E, flat, cfg), size, E, info


#: the moving cameras of :func:`sample_moving_camera`
MOVING_KINDS = ("handheld", "pan", "dolly", "orbit")


def _smooth(x: np.ndarray, sigma_frames: float) -> np.ndarray:
    """Gaussian smoothing along axis 0 (3 standard deviations either side, edges mirrored; a
    series shorter than that repeats its end frames): a camera operator's lag."""
    if sigma_frames <= 0:
        return x
    r = int(np.ceil(3 * sigma_frames))
    return gaussian_filter1d(np.asarray(x, float), sigma_frames, axis=0, radius=r,
                             mode="mirror" if len(x) > r else "nearest")


def _smooth_noise(rng, T: int, dims: int, sigma_frames: float) -> np.ndarray:
    """Unit-variance Gaussian noise (T, dims) smoothed over ``sigma_frames`` (hand tremor, drift)."""
    n = _smooth(rng.standard_normal((T + 1, dims)), sigma_frames)[:T]
    return n / max(float(n.std()), 1e-9)


def _track_path(rng, kind: str, points: np.ndarray, fps: float, cfg: CameraConfig):
    """The eye and target paths (T, 3) of one draw of a moving camera of ``kind`` around the
    subject whose joints are ``points`` (T, J, 3), with a per-frame roll/tremor (T, 3) in the
    camera's axes (radians) and the draw's description."""
    T = len(points)
    centre = 0.5 * (points.min(axis=1) + points.max(axis=1))  # (T, 3) the subject's box centre
    top = float(points[..., 2].max())
    dist = float(rng.uniform(*cfg.distance_m))
    cam_h = float(rng.uniform(*cfg.height_m))
    az = float(rng.uniform(-np.pi, np.pi))
    aim = float(rng.uniform(0.35, 0.6)) * top
    shake = np.zeros((T, 3))
    info: dict = dict(kind=kind, distance_m=dist, height_m=cam_h, azimuth=az)
    if kind == "pan":  # a tripod turning to follow the subject (with an operator's lag)
        lag = float(rng.uniform(0.1, 0.4))
        c0 = centre.mean(0)
        eye = np.broadcast_to(np.array([c0[0] + dist * np.cos(az), c0[1] + dist * np.sin(az), cam_h]), (T, 3)).copy()
        target = _smooth(centre, lag * fps)
        target[:, 2] = aim
        # the operator reframes: the aim sweeps sideways and up and down over a few seconds
        period = float(rng.uniform(3.0, 8.0))
        sweep = float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.05, 0.25))
        ph = 2 * np.pi * np.arange(T) / (period * fps) + float(rng.uniform(0, 2 * np.pi))
        lateral = np.array([-np.sin(az), np.cos(az), 0.0])
        target = target + sweep[0] * np.sin(ph)[:, None] * lateral + np.outer(sweep[1] * np.sin(0.7 * ph), [0, 0, 1.0])
        info.update(lag_s=lag, sweep_m=sweep[0], sweep_period_s=period)
    elif kind == "dolly":  # a camera on a straight track beside the subject's path, keeping level with it
        c0 = centre.mean(0)
        direction = centre[-1, :2] - centre[0, :2]
        if np.linalg.norm(direction) < 0.3:  # a subject in place: the dolly moves along a random line
            direction = np.array([np.cos(az + np.pi / 2), np.sin(az + np.pi / 2)])
        direction = direction / np.linalg.norm(direction)
        side = np.array([-direction[1], direction[0]]) * (1.0 if rng.uniform() < 0.5 else -1.0)
        lag = float(rng.uniform(0.2, 0.6))
        slide = float(rng.uniform(0.2, 0.8)) * (1.0 if rng.uniform() < 0.5 else -1.0)  # the dolly's own move
        along = _smooth(centre[:, :2] @ direction, lag * fps) + slide * np.arange(T) / fps
        base = c0[:2] - (c0[:2] @ direction) * direction + side * dist
        eye = np.concatenate([base + along[:, None] * direction, np.full((T, 1), cam_h)], -1)
        target = _smooth(centre, 0.5 * lag * fps)
        target[:, 2] = aim
        info.update(lag_s=lag, slide_mps=slide)
    elif kind == "orbit":  # a drone circling the subject
        rate = np.radians(float(rng.uniform(10.0, 40.0))) * (1.0 if rng.uniform() < 0.5 else -1.0)
        height = float(rng.uniform(max(cam_h, 1.5), max(cam_h, 1.5) + 3.0))
        follow = _smooth(centre, 0.5 * fps)
        ang = az + rate * np.arange(T) / fps
        eye = np.stack([follow[:, 0] + dist * np.cos(ang), follow[:, 1] + dist * np.sin(ang),
                        np.full(T, height)], -1)
        target = follow.copy()
        target[:, 2] = aim
        shake = np.radians(0.3) * _smooth_noise(rng, T, 3, 0.3 * fps)  # wind on the gimbal
        info.update(rate_dps=float(np.degrees(rate)), height_m=height)
    elif kind == "handheld":  # an operator walking with the subject: bob and sway at the step rate, tremor
        lag = float(rng.uniform(0.3, 0.8))
        follow = _smooth(centre, lag * fps)
        offset = np.array([dist * np.cos(az), dist * np.sin(az)])
        step_hz = float(rng.uniform(1.6, 2.2))
        phase = 2 * np.pi * step_hz * np.arange(T) / fps + float(rng.uniform(0, 2 * np.pi))
        bob = float(rng.uniform(0.01, 0.04)) * np.cos(phase)  # the walk's vertical bob (twice per stride)
        sway_dir = np.array([-offset[1], offset[0]]) / dist
        sway = float(rng.uniform(0.01, 0.03)) * np.cos(0.5 * phase)  # side to side, once per stride
        moving = np.linalg.norm(np.diff(follow[:, :2], axis=0), axis=-1).sum() > 0.2 * T / fps
        gait = 1.0 if moving else float(rng.uniform(0.0, 0.3))  # a standing operator barely bobs
        wander = float(rng.uniform(0.1, 0.4)) * _smooth_noise(rng, T, 2, 1.0 * fps)  # the operator's feet
        eye = np.concatenate([follow[:, :2] + offset + gait * sway[:, None] * sway_dir + wander,
                              (cam_h + gait * bob)[:, None]], -1)
        target = _smooth(centre, 0.5 * lag * fps)
        target[:, 2] = aim
        tremor_deg = float(rng.uniform(0.3, 1.5))
        shake = np.radians(tremor_deg) * _smooth_noise(rng, T, 3, 0.15 * fps)
        info.update(lag_s=lag, step_hz=step_hz, tremor_deg=tremor_deg, walking_operator=bool(moving))
    else:
        raise ValueError(f"unknown moving camera {kind!r} (one of {', '.join(MOVING_KINDS)})")
    return eye, target, shake, info


def sample_moving_camera(rng: np.random.Generator, points: np.ndarray, fps: float, kind: str,
                         cfg: CameraConfig = CameraConfig()):
    """A moving camera of ``kind`` (:data:`MOVING_KINDS`) filming the subject whose world joints
    are ``points`` (T, J, 3) at ``fps``:

    * ``handheld``: an operator following the subject at a distance with a lag of 0.3-0.8 s,
      the walk's bob (1-4 cm at the step rate) and sway (1-3 cm) while the subject moves, and a
      hand's tremor of 0.3-1.5 degrees;
    * ``pan``: a tripod that pans and tilts to keep the subject in frame (lag 0.1-0.4 s);
    * ``dolly``: a camera on a straight track beside the subject's path, following it along;
    * ``orbit``: a drone circling the subject at 10-40 degrees per second, 1.5-5 m up.

    The intrinsics and image are drawn as :func:`sample_camera`'s (``cfg``); each draw must keep
    ``min_visible`` of the joint-frames in the image and every joint ``min_depth_m`` ahead, else
    it is redrawn, and the last resort shortens the focal length until the subject fits.
    Returns (intrinsics (4,), image_size (2,), camera track (T, 4, 4) world -> camera, info)."""
    best = None
    for attempt in range(cfg.tries):
        W, H, f = _draw_image(rng, cfg)
        eye, target, shake, info = _track_path(rng, kind, points, fps, cfg)
        view = (target - eye) / np.linalg.norm(target - eye, axis=-1, keepdims=True)
        if np.abs(view[:, 2]).max() > 0.98:
            continue
        track = np.stack([look_at_extrinsics(e, g) for e, g in zip(eye, target, strict=True)])
        roll = math.radians(float(rng.uniform(-cfg.roll_deg, cfg.roll_deg))) if cfg.roll_deg > 0 else 0.0
        shake = shake + np.array([0.0, 0.0, roll])
        if np.any(shake != 0):  # the camera turned about its own axes: E <- R_shake E
            turn = _rz(shake[:, 2]) @ _ry(shake[:, 1]) @ _rx(shake[:, 0])  # about x, then y, then z
            track[:, :3, :] = np.einsum("tij,tjk->tik", turn, track[:, :3, :])
        cx = W / 2 + float(rng.uniform(-1, 1)) * cfg.principal_jitter * W
        cy = H / 2 + float(rng.uniform(-1, 1)) * cfg.principal_jitter * H
        K = np.array([f, f, cx, cy])
        frac, zmin = _inside_share(K, track, points, W, H)
        if zmin < cfg.min_depth_m:
            continue
        cand = (K, np.array([W, H]), track, dict(info, attempts=attempt + 1, roll_deg=math.degrees(roll)))
        if frac >= cfg.min_visible:
            return cand
        if best is None or frac > best[0]:
            best = (frac, cand)
    if best is None:
        raise GenerationError(f"no {kind} camera keeps the subject in front of the camera")
    K, size, track, info = best[1]
    info["focal_shrunk"] = True
    return _shrink_focal(K, size, track, points, cfg), size, track, info
