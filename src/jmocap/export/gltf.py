"""glTF 2.0 export of reconstructions: result files in, one animated binary glTF (``.glb``) out.

(Result files are read with :func:`jmocap.results.load_result`.)

:func:`write_glb` writes the character's rigid skeleton, with its MuJoCo collision geometry
(capsules, spheres, ellipsoids, cylinders, boxes, meshes) as triangle meshes, and one
animation per clip; optionally the ground reaction forces as animated arrows and the contact
states as animated markers. No skin: every body is a rigid node carrying its own mesh, so any
glTF viewer plays it without skinning support.

Conventions:

* Axes: glTF's own, y-up, right-handed, the character's forward along +Z:
  ``(X, Y, Z)_gltf = (y, z, x)_jmocap`` (jmocap's world is x forward, y left, z up), a proper
  rotation (a cyclic permutation, the same y-up choice as the BVH exporter). The change of
  axes is applied to the nodes that hang from the scene root only (the skeleton's root body
  and the arrow / marker nodes, which hold glTF world coordinates); every other body node keeps
  MuJoCo's local frame (translation ``body_pos``, rotation ``body_quat`` times its joints'
  rotations), because a rotation applied at the root leaves the local frames below it
  unchanged. Mapping a world point back: ``p_jmocap = (Z, X, Y)``.
* Units: metres, seconds; rotations as unit quaternions ``(x, y, z, w)`` (glTF's order).
* Nodes: one per MuJoCo body, named after the body (``pelvis``, ``left_knee``, ...), children
  following MuJoCo's body tree; a body's mesh is attached to its own node (its geoms placed by
  ``geom_pos`` / ``geom_quat``; the world's geoms, e.g. the floor plane, and fully transparent
  geoms are left out). Materials: ``jmocap_center``, ``jmocap_left`` (bluish) and
  ``jmocap_right`` (reddish), from the body name's ``left`` / ``right`` prefix. Identical
  meshes and accessors are stored once. The nodes' own (rest) transforms are the model's
  reference pose ``qpos0``.
* Animations: one per result, named after the clip (``name``; made unique with ``_2``, ...).
  Keyframes at every frame, times ``frame / fps`` seconds (one input accessor per clip).
  ``LINEAR`` samplers: ``translation`` of the root (the free joint's position) and of any
  body whose joints move its origin (slide joints, hinges off the body origin), ``rotation``
  of the root and of every body with joints. Quaternions are sign-continuous over time (the
  short way for a viewer's slerp).
* Ground reaction forces (``forces=True`` and a result with ``forces_estimated`` and ``grf``):
  one node per foot contact site at the scene root, ``grf_left_heel``, ``grf_left_toe``,
  ``grf_right_heel``, ``grf_right_toe``, each an arrow mesh of unit length along its local +Y
  (shaft + cone). Animated: ``translation`` = the site's world position (MuJoCo kinematics,
  ``site_xpos``), ``rotation`` turns +Y onto the force's direction, ``scale`` =
  ``(1, |F| / (m g), 1)``: the arrow's length in metres is the force in body weights (one body
  weight, the character's mass times |gravity|, is 1 m) at a constant thickness; a force under
  1e-6 body weights (no contact) scales the arrow to ``(0, 0, 0)``. Clips without estimated
  forces keep the arrows at scale 0.
* Contacts (``contacts=True`` and ``contact_prob``): a sphere node per contact site,
  ``contact_left_heel``, ..., at the site (``translation``, LINEAR) with ``scale`` 1 while
  ``contact_prob > 0.5`` and 0 otherwise (``STEP`` interpolation).
* The arrows' and markers' rest scale is 0 (hidden outside the animations). ``scene.extras``
  holds ``jmocap``: the axis mapping, the arrow scale (``grf_metres_per_newton``) and each
  clip's fps and frame count.

Opening it:

* Blender: *File > Import > glTF 2.0 (.glb/.gltf)*. Blender turns the y-up file into its
  z-up world (the character stands up, facing -Y); every body becomes a mesh object (rigid,
  parented like the skeleton) and every clip an action (see the *Nonlinear Animation*
  editor or the importer's animation option to switch clips).
* three.js: ``new GLTFLoader().load(url, (gltf) => { scene.add(gltf.scene); const mixer = new
  THREE.AnimationMixer(gltf.scene); mixer.clipAction(gltf.animations[0]).play(); })`` and
  ``mixer.update(dt)`` per frame; ``THREE.AnimationClip.findByName(gltf.animations, name)``
  picks a clip by name.
"""

from __future__ import annotations

import hashlib
import math
import os
import struct
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pygltflib as G

from jmocap.export.bvh import _check_fps, check_q
from jmocap.io import atomic_write
from jmocap.model import Model, site_trajectory

__all__ = ["TO_GLTF", "write_glb"]

#: jmocap world -> glTF: (X, Y, Z) = (y, z, x), a proper rotation (det +1)
TO_GLTF = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])

_FLOAT, _U16, _U32 = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_TRIANGLES = 4
_SEGMENTS = 16  # around the axis of capsules, spheres, cylinders
_RINGS = 4  # per quarter circle (hemisphere of a capsule / sphere: 4 rings)
_ARROW = {"shaft_radius": 0.012, "head_radius": 0.035, "head_length": 0.2}
_MARKER_RADIUS = 0.03
_CONTACT_THRESHOLD = 0.5
_ZERO_FORCE_BW = 1e-6
_MATERIALS = {  # name: base colour (linear RGBA)
    "jmocap_center": (0.80, 0.62, 0.48, 1.0),
    "jmocap_left": (0.30, 0.50, 0.85, 1.0),
    "jmocap_right": (0.85, 0.35, 0.30, 1.0),
    "jmocap_grf": (0.95, 0.80, 0.10, 1.0),
    "jmocap_contact": (0.90, 0.10, 0.10, 1.0),
}


# ======================================================================================
# quaternions (w, x, y, z), vectorised over leading axes
# ======================================================================================


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _qrot(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors ``v`` (..., 3) by unit quaternions ``q`` (..., 4)."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    axis = np.asarray(axis, np.float64)
    axis = axis / np.linalg.norm(axis)
    h = 0.5 * np.asarray(angle, np.float64)[..., None]
    return np.concatenate([np.cos(h), np.sin(h) * axis], axis=-1)


def _mat2quat(R: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, np.float64).reshape(9))
    return q


def _normalize(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _continuous(q: np.ndarray) -> np.ndarray:
    """Flip quaternion signs along axis 0 so consecutive ones are on the same hemisphere (the
    first one with w >= 0)."""
    first = np.where(q[:1, ..., :1] < 0, -1.0, 1.0)
    step = np.where(np.sum(q[1:] * q[:-1], axis=-1, keepdims=True) < 0, -1.0, 1.0)
    return q * np.cumprod(np.concatenate([first, step], axis=0), axis=0)


def _from_y(d: np.ndarray) -> np.ndarray:
    """(T, 4) unit quaternions (w, x, y, z) rotating +Y onto the unit directions ``d`` (T, 3)."""
    y = np.array([0.0, 1.0, 0.0])
    c = d @ y
    w = 1.0 + c
    q = np.concatenate([w[:, None], np.cross(y, d)], axis=1)
    anti = w < 1e-9  # d = -Y: half a turn about X
    q[anti] = [0.0, 1.0, 0.0, 0.0]
    return _normalize(q)


_Q_TO_GLTF = _mat2quat(TO_GLTF)


# ======================================================================================
# kinematics: each body's transform relative to its parent, per frame
# ======================================================================================


def _local_transforms(mj: mujoco.MjModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, nbody, 3) translations and (T, nbody, 4) rotations (w, x, y, z) of every body in its
    parent's frame, MuJoCo's ``mj_kinematics`` rules; the world's children also get the change
    of axes to glTF (their parent is the glTF scene)."""
    T = q.shape[0]
    pos = np.zeros((T, mj.nbody, 3))
    quat = np.zeros((T, mj.nbody, 4))
    quat[:, 0, 0] = 1.0
    J = mujoco.mjtJoint
    for b in range(1, mj.nbody):
        p = np.broadcast_to(np.asarray(mj.body_pos[b], np.float64), (T, 3)).copy()
        Q = np.broadcast_to(_normalize(np.asarray(mj.body_quat[b], np.float64)), (T, 4)).copy()
        for j in range(mj.body_jntadr[b], mj.body_jntadr[b] + mj.body_jntnum[b]):
            a = int(mj.jnt_qposadr[j])
            typ = int(mj.jnt_type[j])
            if typ == J.mjJNT_FREE:
                p = q[:, a : a + 3].copy()
                Q = _normalize(q[:, a + 3 : a + 7])
                continue
            anchor_local = np.asarray(mj.jnt_pos[j], np.float64)
            if typ == J.mjJNT_SLIDE:
                p = p + _qrot(Q, np.asarray(mj.jnt_axis[j], np.float64)) * (q[:, a] - mj.qpos0[a])[:, None]
                continue
            anchor = p + _qrot(Q, anchor_local)
            if typ == J.mjJNT_HINGE:
                Q = _qmul(Q, _axis_angle(mj.jnt_axis[j], q[:, a] - mj.qpos0[a]))
            else:  # ball
                Q = _qmul(Q, _normalize(q[:, a : a + 4]))
            p = anchor - _qrot(Q, anchor_local)
        if int(mj.body_parentid[b]) == 0:
            p = p @ TO_GLTF.T
            Q = _qmul(_Q_TO_GLTF, Q)
        pos[:, b] = p
        quat[:, b] = _normalize(Q)
    return pos, quat


def _animated(mj: mujoco.MjModel, b: int) -> tuple[bool, bool]:
    """Whether body ``b``'s translation / rotation change with ``q``."""
    J = mujoco.mjtJoint
    trans = rot = False
    for j in range(mj.body_jntadr[b], mj.body_jntadr[b] + mj.body_jntnum[b]):
        typ = int(mj.jnt_type[j])
        if typ == J.mjJNT_FREE:
            trans = rot = True
        elif typ == J.mjJNT_SLIDE:
            trans = True
        else:
            rot = True
            trans = trans or bool(np.linalg.norm(mj.jnt_pos[j]) > 0)
    return trans, rot


def _site_positions(mj: mujoco.MjModel, q: np.ndarray, sites: Sequence[int]) -> np.ndarray:
    """(T, len(sites), 3) world positions of ``sites`` (MuJoCo kinematics), glTF axes."""
    return site_trajectory(mj, q, sites) @ TO_GLTF.T


# ======================================================================================
# triangle meshes: (positions (N, 3), normals (N, 3), triangles (M, 3)), outward CCW
# ======================================================================================


def _lathe(sections: list[list[tuple[float, float, float, float]]], n: int = _SEGMENTS):
    """Surfaces of revolution about z. Each section is a list of rows ``(radius, z, normal_r,
    normal_z)`` from top to bottom; consecutive rows of a section are joined by quads (or fans
    where a row has radius 0, a single vertex)."""
    theta = 2.0 * np.pi * np.arange(n) / n
    c, s = np.cos(theta), np.sin(theta)
    P: list[np.ndarray] = []
    N: list[np.ndarray] = []
    F: list[np.ndarray] = []
    count = 0
    for rows in sections:
        ids = []
        for r, z, nr, nz in rows:
            if r == 0.0:
                P.append(np.array([[0.0, 0.0, z]]))
                N.append(np.array([[0.0, 0.0, math.copysign(1.0, nz)]]))  # a pole: along the axis
                ids.append(np.full(n, count))
                count += 1
            else:
                P.append(np.stack([r * c, r * s, np.full(n, z)], axis=1))
                nrm = np.stack([nr * c, nr * s, np.full(n, nz)], axis=1)
                N.append(nrm / np.linalg.norm(nrm, axis=1, keepdims=True))
                ids.append(count + np.arange(n))
                count += n
        for top, bot in zip(ids[:-1], ids[1:], strict=True):
            a, b = top, np.roll(top, -1)
            d, cc = bot, np.roll(bot, -1)
            if not (top[0] == top[-1]):  # (a, d, b) unless the top row is a point
                F.append(np.stack([a, d, b], axis=1))
            if not (bot[0] == bot[-1]):  # (b, d, c) unless the bottom row is a point
                F.append(np.stack([b, d, cc], axis=1))
    return np.concatenate(P), np.concatenate(N), np.concatenate(F)


def _capsule(radius: float, half: float):
    k = np.arange(_RINGS + 1) * (0.5 * np.pi / _RINGS)  # polar angle 0 .. pi/2
    top = [(radius * math.sin(a), half + radius * math.cos(a), math.sin(a), math.cos(a)) for a in k]
    bot = [(radius * math.sin(a), -half - radius * math.cos(a), math.sin(a), -math.cos(a)) for a in k[::-1]]
    if half == 0.0:
        bot = bot[1:]  # a sphere: one equator
    return _lathe([top + bot])


def _ellipsoid(radii):
    P, N, F = _capsule(1.0, 0.0)
    radii = np.asarray(radii, np.float64)
    N = N / radii
    return P * radii, N / np.linalg.norm(N, axis=1, keepdims=True), F


def _cylinder(radius: float, half: float, top_cap: bool = True):
    sections = [
        [(radius, half, 1.0, 0.0), (radius, -half, 1.0, 0.0)],
        [(radius, -half, 0.0, -1.0), (0.0, -half, 0.0, -1.0)],
    ]
    if top_cap:
        sections.insert(0, [(0.0, half, 0.0, 1.0), (radius, half, 0.0, 1.0)])
    return _lathe(sections)


def _box(half):
    half = np.asarray(half, np.float64)
    P, N, F = [], [], []
    for ax in range(3):
        u, v = (ax + 1) % 3, (ax + 2) % 3
        for sign in (1.0, -1.0):
            base = len(P) * 4
            quad = []
            for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[ax], p[u], p[v] = sign * half[ax], su * half[u], sv * half[v]
                quad.append(p)
            P.append(np.array(quad))
            n = np.zeros(3)
            n[ax] = sign
            N.append(np.tile(n, (4, 1)))
            tri = [[0, 1, 2], [0, 2, 3]] if sign > 0 else [[0, 2, 1], [0, 3, 2]]
            F.append(base + np.array(tri))
    return np.concatenate(P), np.concatenate(N), np.concatenate(F)


def _mujoco_mesh(mj: mujoco.MjModel, mesh: int):
    """A MuJoCo mesh asset, flat shaded (unshared vertices, face normals)."""
    v0, nv = int(mj.mesh_vertadr[mesh]), int(mj.mesh_vertnum[mesh])
    f0, nf = int(mj.mesh_faceadr[mesh]), int(mj.mesh_facenum[mesh])
    V = np.asarray(mj.mesh_vert[v0 : v0 + nv], np.float64)
    tri = np.asarray(mj.mesh_face[f0 : f0 + nf], np.int64)
    P = V[tri].reshape(-1, 3)
    n = np.cross(P[1::3] - P[0::3], P[2::3] - P[0::3])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    keep = length[:, 0] > 1e-15
    n = n[keep] / length[keep]
    P = P.reshape(-1, 3, 3)[keep].reshape(-1, 3)
    return P, np.repeat(n, 3, axis=0), np.arange(len(P)).reshape(-1, 3)


def _geom_mesh(mj: mujoco.MjModel, g: int):
    """The triangle mesh of geom ``g`` in its body's frame, or None (planes, height fields...)."""
    G_ = mujoco.mjtGeom
    typ, size = int(mj.geom_type[g]), np.asarray(mj.geom_size[g], np.float64)
    if typ == G_.mjGEOM_SPHERE:
        m = _capsule(size[0], 0.0)
    elif typ == G_.mjGEOM_CAPSULE:
        m = _capsule(size[0], size[1])
    elif typ == G_.mjGEOM_ELLIPSOID:
        m = _ellipsoid(size)
    elif typ == G_.mjGEOM_CYLINDER:
        m = _cylinder(size[0], size[1])
    elif typ == G_.mjGEOM_BOX:
        m = _box(size)
    elif typ == G_.mjGEOM_MESH and int(mj.geom_dataid[g]) >= 0:
        m = _mujoco_mesh(mj, int(mj.geom_dataid[g]))
    else:
        return None
    P, N, F = m
    quat = _normalize(np.asarray(mj.geom_quat[g], np.float64))
    return _qrot(quat, P) + np.asarray(mj.geom_pos[g], np.float64), _qrot(quat, N), F


def _arrow():
    """Unit arrow along +Y from the origin: a shaft and a cone head."""
    r, R, h = _ARROW["shaft_radius"], _ARROW["head_radius"], _ARROW["head_length"]
    L = 1.0 - h
    slant = math.hypot(R, h)
    nr, nz = h / slant, R / slant  # the cone's outward normal (radial, axial)
    P, N, F = _lathe([
        [(0.0, 1.0, 0.0, 1.0), (R, L, nr, nz)],  # cone side (apex normal: +axis)
        [(R, L, 0.0, -1.0), (0.0, L, 0.0, -1.0)],  # cone base
        [(r, L, 1.0, 0.0), (r, 0.0, 1.0, 0.0)],  # shaft
        [(r, 0.0, 0.0, -1.0), (0.0, 0.0, 0.0, -1.0)],  # shaft bottom
    ])
    C = TO_GLTF  # the lathe's z -> +Y (a proper rotation keeps the winding)
    return P @ C.T, N @ C.T, F


# ======================================================================================
# glTF document builder
# ======================================================================================


class _Doc:
    """Accumulates a glTF document and its binary buffer; identical data is stored once."""

    def __init__(self) -> None:
        self.gltf = G.GLTF2(
            asset=G.Asset(version="2.0", generator=f"jmocap {_version()} (jmocap.export.gltf)"),
            scene=0,
        )
        self.blob = bytearray()
        self._views: dict[tuple, int] = {}
        self._accessors: dict[tuple, int] = {}

    def view(self, data: bytes, target: int | None) -> int:
        key = (hashlib.sha256(data).digest(), target)
        if key not in self._views:
            offset = len(self.blob)
            self.blob += data
            self.blob += b"\0" * (-len(self.blob) % 4)
            self.gltf.bufferViews.append(G.BufferView(buffer=0, byteOffset=offset, byteLength=len(data), target=target))
            self._views[key] = len(self.gltf.bufferViews) - 1
        return self._views[key]

    def accessor(self, array: np.ndarray, *, kind: str, target: int | None = None, bounds: bool = False) -> int:
        """Add ``array`` (count, n) or (count,) as an accessor of ``kind`` (SCALAR, VEC3, VEC4)."""
        a = np.ascontiguousarray(array)
        if a.dtype == np.float32:
            ctype = _FLOAT
        elif a.dtype == np.uint16:
            ctype = _U16
        elif a.dtype == np.uint32:
            ctype = _U32
        else:
            raise TypeError(a.dtype)
        data = a.tobytes()
        key = (hashlib.sha256(data).digest(), kind, ctype, target, bounds)
        if key not in self._accessors:
            acc = G.Accessor(bufferView=self.view(data, target), byteOffset=0, componentType=ctype,
                             count=int(a.shape[0]), type=kind)
            if bounds:
                flat = a.reshape(a.shape[0], -1)
                cast = float if ctype == _FLOAT else int
                acc.min = [cast(x) for x in flat.min(axis=0)]
                acc.max = [cast(x) for x in flat.max(axis=0)]
            self.gltf.accessors.append(acc)
            self._accessors[key] = len(self.gltf.accessors) - 1
        return self._accessors[key]

    def primitive(self, P: np.ndarray, N: np.ndarray, F: np.ndarray, material: int) -> G.Primitive:
        idx = F.reshape(-1)
        idx = idx.astype(np.uint16 if len(P) < 65535 else np.uint32)
        return G.Primitive(
            attributes=G.Attributes(
                POSITION=self.accessor(P.astype(np.float32), kind="VEC3", target=_ARRAY_BUFFER, bounds=True),
                NORMAL=self.accessor(_normalize(N).astype(np.float32), kind="VEC3", target=_ARRAY_BUFFER),
            ),
            indices=self.accessor(idx, kind="SCALAR", target=_ELEMENT_ARRAY_BUFFER),
            material=material,
            mode=_TRIANGLES,
        )

    def mesh(self, name: str, primitives: list[G.Primitive], cache: dict) -> int:
        key = tuple((p.attributes.POSITION, p.attributes.NORMAL, p.indices, p.material) for p in primitives)
        if key not in cache:
            self.gltf.meshes.append(G.Mesh(name=name, primitives=primitives))
            cache[key] = len(self.gltf.meshes) - 1
        return cache[key]

    def glb(self) -> bytes:
        self.gltf.buffers = [G.Buffer(byteLength=len(self.blob))]
        self.gltf.set_binary_blob(bytes(self.blob))
        return b"".join(self.gltf.save_to_bytes())


def _version() -> str:
    try:
        from jmocap import __version__

        return str(__version__)
    except ImportError:  # pragma: no cover
        return "?"


def _xyzw(q: np.ndarray) -> np.ndarray:
    return q[..., [1, 2, 3, 0]]


# ======================================================================================
# input
# ======================================================================================


def _series(result: Mapping[str, Any], key: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    a = np.asarray(result[key])
    if a.dtype.kind not in "fiub":
        raise ValueError(f"{where}: field {key!r}: expected numbers, got dtype {a.dtype}")
    a = a.astype(np.float64)
    if a.shape != shape:
        raise ValueError(f"{where}: field {key!r}: expected shape {shape}, got {a.shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        t = int(np.argwhere(bad)[0][0])
        raise ValueError(f"{where}: field {key!r}: frame {t} has a non-finite value")
    return a


def _same_character(a: Model, b: Model) -> bool:
    ma, mb = a.mj, b.mj
    if (ma.nbody, ma.njnt, ma.ngeom, ma.nq) != (mb.nbody, mb.njnt, mb.ngeom, mb.nq):
        return False
    return all(
        np.allclose(getattr(ma, f), getattr(mb, f), atol=1e-9)
        for f in ("body_pos", "body_quat", "body_parentid", "jnt_axis", "jnt_pos", "geom_size", "geom_pos",
                  "site_pos", "body_mass")
    )


# ======================================================================================
# writer
# ======================================================================================


def write_glb(
    result: Mapping[str, Any] | Sequence[Mapping[str, Any]],
    path: str | os.PathLike,
    *,
    forces: bool = True,
    contacts: bool = True,
    model: Model | None = None,
) -> Path:
    """Write one or more reconstruction results of one character as an animated glTF binary.

    Args:
      result: a result dict (:func:`jmocap.results.load_result`; ``q`` and ``fps`` are
        required, ``name``, ``grf``, ``forces_estimated``, ``contact_prob``, ``height_m``,
        ``mass_kg`` and ``assumed`` are used when present) or a list of them: one animation
        per result, all sharing one skeleton, so they must be of the same character (same
        height and mass); ``ValueError`` otherwise.
      path: the ``.glb`` file (parent folders are created); written atomically.
      forces: add the ground reaction force arrows (for results with estimated forces).
      contacts: add the contact markers (for results with ``contact_prob``).
      model: the character; default :func:`jmocap.results.result_model` of the first result.

    See the module docstring for axes, units, node names, animation layout and the arrows'
    scale. Raises ``ValueError`` naming the result and field for bad input (``q`` shape or
    non-finite values, ``fps`` not positive, ``grf`` / ``contact_prob`` of the wrong shape or
    non-finite). Returns the path.
    """
    from jmocap.results import result_model

    path = Path(path)
    where = f"write_glb({path})"
    results = [result] if isinstance(result, Mapping) else list(result)
    if not results:
        raise ValueError(f"{where}: no results")
    for i, r in enumerate(results):
        if not isinstance(r, Mapping):
            raise ValueError(f"{where}: result {i} is a {type(r).__name__}, expected a result dict")
        for key in ("q", "fps"):
            if r.get(key) is None:
                raise ValueError(f"{where}: result {i}: missing field {key!r}")
    if model is None:
        model = result_model(results[0])
        for i, r in enumerate(results[1:], 1):
            if not _same_character(model, result_model(r)):
                raise ValueError(
                    f"{where}: result {i} is of another character (height_m {r.get('height_m')}, mass_kg "
                    f"{r.get('mass_kg')}) than result 0 (height_m {results[0].get('height_m')}, mass_kg "
                    f"{results[0].get('mass_kg')}); one file holds clips of one character"
                )
    mj = model.mj
    sites = tuple(model.topo.contact_sites)
    weight = float(np.sum(mj.body_mass)) * float(np.linalg.norm(mj.opt.gravity))

    # ---- validate and prepare every clip --------------------------------------------------
    clips = []
    used_names: set[str] = set()
    for i, r in enumerate(results):
        name = str(r.get("name") or f"clip{i}")
        here = f"{where}: result {i} ({name})"
        q = check_q(model, r["q"], f"{here}: field 'q'")
        fps = _check_fps(r["fps"], here)
        T = len(q)
        grf = None
        if forces and sites and bool(r.get("forces_estimated")) and r.get("grf") is not None:
            grf = _series(r, "grf", (T, len(sites), 3), here)
        prob = None
        if contacts and sites and r.get("contact_prob") is not None:
            prob = _series(r, "contact_prob", (T, len(sites)), here)
        times = (np.arange(T, dtype=np.float64) / fps).astype(np.float32)
        if T > 1 and not (np.diff(times) > 0).all():
            raise ValueError(f"{here}: fps {fps} too high for {T} frames (float32 key times collide)")
        unique, k = name, 2
        while unique in used_names:
            unique, k = f"{name}_{k}", k + 1
        used_names.add(unique)
        clips.append({"name": unique, "q": q, "fps": fps, "times": times, "grf": grf, "prob": prob})
    with_arrows = any(c["grf"] is not None for c in clips)
    with_markers = any(c["prob"] is not None for c in clips)

    doc = _Doc()
    g = doc.gltf
    for mname, rgba in _MATERIALS.items():
        g.materials.append(G.Material(
            name=mname,
            pbrMetallicRoughness=G.PbrMetallicRoughness(baseColorFactor=list(rgba), metallicFactor=0.0,
                                                       roughnessFactor=0.8),
        ))
    material = {m: i for i, m in enumerate(_MATERIALS)}

    # ---- skeleton: one node per body, rest pose qpos0 ---------------------------------------
    names = [model.topo.body_names[b] or f"body{b}" for b in range(mj.nbody)]
    rest_p, rest_q = _local_transforms(mj, np.asarray(mj.qpos0, np.float64)[None])
    rest_q = _continuous(rest_q)
    mesh_cache: dict = {}
    body_node = {}
    for b in range(1, mj.nbody):
        lower = names[b].lower()
        side = "jmocap_left" if lower.startswith("left") else "jmocap_right" if lower.startswith("right") else (
            "jmocap_center")
        prims = []
        for geom in range(mj.ngeom):
            if int(mj.geom_bodyid[geom]) != b or float(mj.geom_rgba[geom][3]) == 0.0:
                continue
            m = _geom_mesh(mj, geom)
            if m is not None:
                prims.append(doc.primitive(*m, material[side]))
        node = G.Node(name=names[b], translation=[float(x) for x in rest_p[0, b]],
                      rotation=[float(x) for x in _xyzw(rest_q[0, b])])
        if prims:
            node.mesh = doc.mesh(names[b], prims, mesh_cache)
        g.nodes.append(node)
        body_node[b] = len(g.nodes) - 1
    roots = []
    for b in range(1, mj.nbody):
        parent = int(mj.body_parentid[b])
        if parent == 0:
            roots.append(body_node[b])
        else:
            g.nodes[body_node[parent]].children.append(body_node[b])

    # ---- arrows and markers at the scene root -------------------------------------------
    site_label = [model.topo.site_names[s].removeprefix("contact_") for s in sites]
    rest_sites = _site_positions(mj, np.asarray(mj.qpos0, np.float64)[None], sites)[0]
    arrow_nodes: list[int] = []
    marker_nodes: list[int] = []
    if with_arrows:
        mesh = doc.mesh("grf_arrow", [doc.primitive(*_arrow(), material["jmocap_grf"])], mesh_cache)
        for k, label in enumerate(site_label):
            g.nodes.append(G.Node(name=f"grf_{label}", mesh=mesh, translation=[float(x) for x in rest_sites[k]],
                                  scale=[0.0, 0.0, 0.0]))
            arrow_nodes.append(len(g.nodes) - 1)
    if with_markers:
        P, N, F = _capsule(_MARKER_RADIUS, 0.0)
        mesh = doc.mesh("contact_marker", [doc.primitive(P, N, F, material["jmocap_contact"])], mesh_cache)
        for k, label in enumerate(site_label):
            g.nodes.append(G.Node(name=f"contact_{label}", mesh=mesh,
                                  translation=[float(x) for x in rest_sites[k]], scale=[0.0, 0.0, 0.0]))
            marker_nodes.append(len(g.nodes) - 1)
    g.scenes.append(G.Scene(name="jmocap", nodes=roots + arrow_nodes + marker_nodes))

    # ---- animations ------------------------------------------------------------------------
    animated = {b: _animated(mj, b) for b in range(1, mj.nbody)}
    for clip in clips:
        q, times = clip["q"], clip["times"]
        T = len(q)
        anim = G.Animation(name=clip["name"])
        t_acc = doc.accessor(times, kind="SCALAR", bounds=True)

        def channel(node: int, path_: str, values: np.ndarray, interpolation: str = "LINEAR",
                    anim=anim, t_acc=t_acc) -> None:
            kind = {"translation": "VEC3", "scale": "VEC3", "rotation": "VEC4"}[path_]
            out = doc.accessor(np.asarray(values, np.float32), kind=kind)
            anim.samplers.append(G.AnimationSampler(input=t_acc, output=out, interpolation=interpolation))
            anim.channels.append(G.AnimationChannel(
                sampler=len(anim.samplers) - 1, target=G.AnimationChannelTarget(node=node, path=path_)))

        pos, quat = _local_transforms(mj, q)
        for b in range(1, mj.nbody):
            trans, rot = animated[b]
            if trans:
                channel(body_node[b], "translation", pos[:, b])
            if rot:
                channel(body_node[b], "rotation", _xyzw(_continuous(quat[:, b])))
        if arrow_nodes or marker_nodes:
            site_pos = _site_positions(mj, q, sites)
        for k, node in enumerate(arrow_nodes):
            channel(node, "translation", site_pos[:, k])
            rotation = np.tile([0.0, 0.0, 0.0, 1.0], (T, 1))
            scale = np.zeros((T, 3))
            if clip["grf"] is not None:
                f = clip["grf"][:, k] @ TO_GLTF.T
                mag = np.linalg.norm(f, axis=1)
                on = mag > _ZERO_FORCE_BW * weight
                if on.any():
                    rotation[on] = _xyzw(_from_y(f[on] / mag[on, None]))
                    # between forces, hold the last direction (no spurious swing of the arrow)
                    last = np.maximum.accumulate(np.where(on, np.arange(T), -1))
                    first = int(np.argmax(on))
                    rotation = rotation[np.where(last >= 0, last, first)]
                scale[on] = np.stack([np.ones(on.sum()), mag[on] / weight, np.ones(on.sum())], axis=1)
            channel(node, "rotation", _xyzw(_continuous(rotation[:, [3, 0, 1, 2]])))
            channel(node, "scale", scale)
        for k, node in enumerate(marker_nodes):
            channel(node, "translation", site_pos[:, k])
            on = np.zeros(T) if clip["prob"] is None else (clip["prob"][:, k] > _CONTACT_THRESHOLD).astype(float)
            channel(node, "scale", np.repeat(on[:, None], 3, axis=1), "STEP")
        g.animations.append(anim)

    g.scenes[0].extras = {
        "jmocap": {
            "axes": "(X, Y, Z)_gltf = (y, z, x)_jmocap; y up, +Z forward, metres",
            "grf_metres_per_newton": 1.0 / weight,
            "body_weight_N": weight,
            "contact_threshold": _CONTACT_THRESHOLD,
            "clips": [{"name": c["name"], "fps": c["fps"], "frames": len(c["q"])} for c in clips],
        }
    }
    data = doc.glb()
    _check_header(data)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, data)
    return path


def _check_header(data: bytes) -> None:
    """Sanity of the GLB container pygltflib produced (lengths, alignment)."""
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    ok = magic == b"glTF" and version == 2 and length == len(data) and json_type == b"JSON" and json_len % 4 == 0
    bin_at = 20 + json_len
    bin_len, bin_type = struct.unpack_from("<I4s", data, bin_at)
    ok = ok and bin_type == b"BIN\0" and bin_len % 4 == 0 and bin_at + 8 + bin_len == length
    if not ok:  # pragma: no cover - a pygltflib regression
        raise RuntimeError("write_glb: pygltflib produced a malformed GLB container")
