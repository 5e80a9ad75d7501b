"""Scenes: the terrain a subject moves on, beyond the floor (issue 21, item 1).

A :class:`Scene` is the floor (the plane ``z = 0`` of the z-up world, solid below) plus a set of
oriented boxes: steps, stairs (one box per step), platforms, ramps (a pitched box), walls. Boxes
cover what the terrain clips of Neural MoCon (Huang et al. 2022) need; a mesh or height field
would be approximated by boxes.

* :func:`sdf` is the scene's signed distance (m) at any points, in pure JAX (``jit``/``vmap``/
  ``grad``): negative inside the floor or a box. It is the interaction term's distance (MoCon eq.
  4) and the height that foot metrics measure against (penetration and floating relative to the
  scene, not to ``z = 0``). Tested against MuJoCo's own geometry distance (``mj_geomDistance``).
  The union is the minimum of the parts' distances: exact outside and in sign, but inside two
  overlapping solids it is the distance to the nearer of their surfaces, which may be hidden
  inside the other (a box's bottom face on the floor): model a box that stands on the floor as
  reaching below it, so that depths inside it are measured to its exposed faces.
* :func:`add_to_spec` puts the boxes into a MuJoCo model (:class:`mujoco.MjSpec`) beside the
  character, as static world geoms with the floor's friction, so that a simulation collides
  with them.
* A scene is a JSON document, ``{"format": "jmocap-scene-1", "boxes": [...]}`` (docs/formats.md),
  each box ``{"center": [x, y, z], "half_size": [hx, hy, hz]}`` in metres, optionally turned by
  ``"yaw_deg"`` (about z), ``"pitch_deg"`` (about the box's y, after the yaw: a ramp) and
  ``"roll_deg"`` (about its x, last), or by a full ``"rotation"`` (3 x 3, box -> world);
  :func:`parse_scene` validates one (errors name the source, the box and the key).

Boxes are stored padded (``centers`` (N, 3), ``half_sizes`` (N, 3), ``rotations`` (N, 3, 3)):
:func:`pad` adds empty boxes far below the floor (:data:`EMPTY_DEPTH_M`), which change no
distance, so scenes with different numbers of boxes batch, and a clip without a scene is the
empty scene (the floor alone).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap.data.limits import FormatError

Array = jnp.ndarray

FORMAT = "jmocap-scene-1"
#: the most boxes a scene may have (a flight of stairs is a box per step)
MAX_BOXES = 4096
#: the largest box half size and the farthest box centre accepted (m)
MAX_EXTENT_M = 1000.0
#: where padding boxes sit (m below the floor): far enough to change no distance that matters
EMPTY_DEPTH_M = 1.0e4


class SceneError(FormatError):
    """A scene that does not follow ``jmocap-scene-1`` (the message names the box and key)."""


@struct.dataclass
class Scene:
    """The floor ``z = 0`` and ``N`` oriented boxes (a batch adds a leading axis)."""

    centers: Array  # (N, 3) m
    half_sizes: Array  # (N, 3) m
    rotations: Array  # (N, 3, 3) box -> world

    @property
    def num_boxes(self) -> int:
        return int(self.centers.shape[-2])

    @staticmethod
    def empty(dtype=np.float64) -> Scene:
        """The floor alone."""
        return Scene(np.zeros((0, 3), dtype), np.zeros((0, 3), dtype), np.zeros((0, 3, 3), dtype))


def rotation_from_angles(yaw_deg: float = 0.0, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """(3, 3) box -> world: ``Rz(yaw) Ry(pitch) Rx(roll)`` (intrinsic z-y'-x'', degrees)."""
    y, p, r = (math.radians(a) for a in (yaw_deg, pitch_deg, roll_deg))
    cz, sz, cy, sy, cx, sx = math.cos(y), math.sin(y), math.cos(p), math.sin(p), math.cos(r), math.sin(r)
    Rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    return Rz @ Ry @ Rx


def box_sdf(points: Array, center: Array, half_size: Array, rotation: Array) -> Array:
    """Signed distance (...,) of ``points`` (..., 3) to one box: the Euclidean distance outside,
    minus the distance to the nearest face inside."""
    local = jnp.einsum("...ji,...j->...i", rotation, points - center)  # R^T (p - c)
    q = jnp.abs(local) - half_size
    outside = jnp.sqrt(jnp.sum(jnp.square(jnp.maximum(q, 0.0)), -1) + 1e-30) * jnp.any(q > 0.0, -1)
    inside = jnp.minimum(jnp.max(q, -1), 0.0)
    return outside + inside


def sdf(scene: Scene, points: Array) -> Array:
    """Signed distance (...,) of ``points`` (..., 3) to the scene (the floor and every box)."""
    d = points[..., 2]
    if scene.centers.shape[-2] == 0:
        return d
    boxes = box_sdf(points[..., None, :], scene.centers, scene.half_sizes, scene.rotations)  # (..., N)
    return jnp.minimum(d, jnp.min(boxes, -1))


def surface_height(scene: Scene, xy: np.ndarray) -> np.ndarray:
    """Height (...,) of the scene's highest surface above each point ``xy`` (..., 2) (numpy): the
    top of the floor or of the highest box that a vertical line through the point meets (the
    slab test in each box's frame; exact for pitched and rolled boxes too). A point's height
    above the terrain under it is ``z - surface_height(scene, p[..., :2])``."""
    xy = np.asarray(xy, np.float64)
    top = np.zeros(xy.shape[:-1])
    for c, h, R in boxes(scene):
        # the line (x, y, z) in box coordinates: o + z d, with d = R^T e_z
        o = np.einsum("ji,...j->...i", R, np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], -1) - c)
        d = R[2]
        lo = np.full(xy.shape[:-1], -np.inf)
        hi = np.full(xy.shape[:-1], np.inf)
        for k in range(3):
            if abs(d[k]) < 1e-12:
                out = np.abs(o[..., k]) > h[k]
                lo = np.where(out, np.inf, lo)
                continue
            a, b = (-h[k] - o[..., k]) / d[k], (h[k] - o[..., k]) / d[k]
            lo = np.maximum(lo, np.minimum(a, b))
            hi = np.minimum(hi, np.maximum(a, b))
        top = np.where(lo <= hi, np.maximum(top, hi), top)
    return top


def height_above(scene: Scene | None, points: np.ndarray) -> np.ndarray:
    """Height (...,) of points (..., 3) above the terrain under them (numpy; above ``z = 0``
    when ``scene`` is None): ``z - surface_height``."""
    points = np.asarray(points, np.float64)
    if scene is None:
        return points[..., 2]
    return points[..., 2] - surface_height(scene, points[..., :2])


def pad(scene: Scene, n: int) -> Scene:
    """The scene with empty boxes appended up to ``n`` boxes (numpy; for batching)."""
    k = scene.num_boxes
    if n < k:
        raise ValueError(f"cannot pad a scene of {k} boxes to {n}")
    extra = n - k
    dt = np.asarray(scene.centers).dtype
    centers = np.concatenate([np.asarray(scene.centers), np.tile(np.array([0.0, 0.0, -EMPTY_DEPTH_M], dt), (extra, 1))])
    halves = np.concatenate([np.asarray(scene.half_sizes), np.zeros((extra, 3), dt)])
    rots = np.concatenate([np.asarray(scene.rotations), np.broadcast_to(np.eye(3, dtype=dt), (extra, 3, 3))])
    return Scene(centers, halves, rots)


def boxes(scene: Scene) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``(center, half_size, rotation)`` (numpy float64) of every box of a scene that is not
    padding (:func:`pad`)."""
    return [
        (np.asarray(c, np.float64), np.asarray(h, np.float64), np.asarray(R, np.float64))
        for c, h, R in zip(scene.centers, scene.half_sizes, scene.rotations, strict=True)
        if float(np.asarray(c)[2]) > -EMPTY_DEPTH_M / 2
    ]


def parse_scene(obj: Any, where: str = "scene") -> Scene:
    """A validated :class:`Scene` from a ``jmocap-scene-1`` document (a dict, or JSON text)."""
    if isinstance(obj, str):
        try:
            obj = json.loads(obj)
        except json.JSONDecodeError as e:
            raise SceneError(f"{where}: not JSON ({e})") from None
    if not isinstance(obj, Mapping):
        raise SceneError(f"{where}: a scene is a JSON object, got {type(obj).__name__}")
    if obj.get("format", FORMAT) != FORMAT:
        raise SceneError(f"{where}: format {obj.get('format')!r} is not {FORMAT!r}")
    unknown = sorted(set(obj) - {"format", "boxes"})
    if unknown:
        raise SceneError(f"{where}: unknown keys {unknown} (known: format, boxes)")
    boxes = obj.get("boxes", [])
    if not isinstance(boxes, list):
        raise SceneError(f"{where}: 'boxes' must be a list")
    if len(boxes) > MAX_BOXES:
        raise SceneError(f"{where}: {len(boxes)} boxes, more than {MAX_BOXES}")
    centers, halves, rots = [], [], []
    for i, box in enumerate(boxes):
        at = f"{where}: box {i}"
        if not isinstance(box, Mapping):
            raise SceneError(f"{at}: a box is a JSON object")
        extra = sorted(set(box) - {"center", "half_size", "yaw_deg", "pitch_deg", "roll_deg", "rotation", "name"})
        if extra:
            raise SceneError(f"{at}: unknown keys {extra}")
        c = _vector(box, "center", at, (3,))
        h = _vector(box, "half_size", at, (3,))
        if np.any(np.abs(c) > MAX_EXTENT_M):
            raise SceneError(f"{at}: 'center' is more than {MAX_EXTENT_M:g} m from the origin")
        if np.any(h <= 0) or np.any(h > MAX_EXTENT_M):
            raise SceneError(f"{at}: every 'half_size' must be in (0, {MAX_EXTENT_M:g}] m, got {h.tolist()}")
        angles = [k for k in ("yaw_deg", "pitch_deg", "roll_deg") if k in box]
        if "rotation" in box:
            if angles:
                raise SceneError(f"{at}: give 'rotation' or angles ({', '.join(angles)}), not both")
            R = _vector(box, "rotation", at, (3, 3))
            if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                raise SceneError(f"{at}: 'rotation' is not a rotation matrix (orthonormal, det +1)")
        else:
            vals = {k: float(_vector(box, k, at, ())) for k in angles}
            R = rotation_from_angles(vals.get("yaw_deg", 0.0), vals.get("pitch_deg", 0.0), vals.get("roll_deg", 0.0))
        centers.append(c)
        halves.append(h)
        rots.append(R)
    if not centers:
        return Scene.empty()
    return Scene(np.stack(centers), np.stack(halves), np.stack(rots))


def _vector(box: Mapping, key: str, at: str, shape: tuple) -> np.ndarray:
    if key not in box:
        raise SceneError(f"{at}: missing {key!r}")
    v = box[key]
    if isinstance(v, bool) or (isinstance(v, list) and any(isinstance(x, bool | str) for x in np.ravel(np.asarray(v, object)))):
        raise SceneError(f"{at}: {key!r} must be numbers")
    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        raise SceneError(f"{at}: {key!r} must be numbers, got {v!r}") from None
    if a.shape != shape:
        raise SceneError(f"{at}: {key!r} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise SceneError(f"{at}: {key!r} is not finite")
    return a


def scene_document(scene: Scene) -> dict:
    """The ``jmocap-scene-1`` document of a scene (rotations written in full)."""
    return {"format": FORMAT, "boxes": [
        {"center": c.tolist(), "half_size": h.tolist(), "rotation": R.tolist()} for c, h, R in boxes(scene)
    ]}


def add_to_spec(spec, scene: Scene, friction: float | None = None, prefix: str = "scene_box") -> list[str]:
    """Add the scene's boxes to a :class:`mujoco.MjSpec`'s world body as static box geoms
    (``contype``/``conaffinity`` 1, like the floor; ``friction`` as the floor's when None).
    Returns the geoms' names."""
    import mujoco

    floor = next((g for g in spec.worldbody.geoms if g.type == mujoco.mjtGeom.mjGEOM_PLANE), None)
    names = []
    for i, (c, h, R) in enumerate(boxes(scene)):
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, R.ravel())
        g = spec.worldbody.add_geom()
        g.name = f"{prefix}{i}"
        g.type = mujoco.mjtGeom.mjGEOM_BOX
        g.size = h
        g.pos = c
        g.quat = quat
        g.contype, g.conaffinity = 1, 1
        if friction is not None:
            g.friction = [friction, g.friction[1], g.friction[2]]
        elif floor is not None:
            g.friction = floor.friction
        names.append(g.name)
    return names


__all__ = ["EMPTY_DEPTH_M", "FORMAT", "MAX_BOXES", "Scene", "SceneError", "add_to_spec", "box_sdf", "boxes", "pad",
           "parse_scene", "rotation_from_angles", "scene_document", "sdf",
           "surface_height", "height_above"]
