"""OpenSim export of a reconstruction: one result in, the files OpenSim opens out.

(Results are read with :func:`jmocap.results.load_result`.) :func:`write_opensim` writes, per
clip, into ``out_dir``:

=========================  ==========================================================================
file                       contents
=========================  ==========================================================================
``<name>.osim``            the result's own character (``jmocap.results.result_model``: a subject
                           scaled to its height and mass exports its own skeleton) as an OpenSim 4
                           model, generated from the MuJoCo model
``<name>_coordinates.mot`` the motion as OpenSim coordinates (Storage format, ``inDegrees=yes``)
``<name>_grf.mot``         ground reaction force, centre of pressure and free moment per foot
                           (only when the result has force estimates: ``forces_estimated`` and
                           ``grf``; the kinematic method's zeros are not exported)
``<name>_grf.xml``         the ExternalLoads that apply ``<name>_grf.mot`` to the feet
``<name>_markers.trc``     ``keypoints3d`` as markers (TRC), named as in the result's ``layout``
=========================  ==========================================================================

Nothing here imports ``opensim``: the files are written directly (XML with ElementTree, the
text formats by hand), atomically (:func:`jmocap.io.atomic_write`). The tests read every file
back with OpenSim's own classes (``opensim`` 4.6) and compare with MuJoCo C.

Conventions
-----------

* **Axes.** jmocap's world is z-up (x forward, y left, z up); OpenSim's ground is y-up (X
  forward, Y up, Z right). Every exported position, force and torque is
  ``(X, Y, Z)_opensim = (x, z, -y)_jmocap`` (:data:`AXES`, a proper rotation: -90 degrees about
  x), so gravity is ``0 -9.81 0`` and the floor is the plane ``Y = 0``.
* **Units.** Metres, kilograms, newtons, newton metres, seconds. Coordinates ``.mot``: degrees
  for rotations, metres for translations (``inDegrees=yes``); the ``.osim`` file stores ranges
  and functions in radians, as OpenSim does.
* **Bodies.** One OpenSim ``Body`` per MuJoCo body (same name), with MuJoCo's mass, centre of
  mass and inertia (MuJoCo's principal moments rotated from its inertial frame into the body
  frame: ``Ixx Iyy Izz Ixy Ixz Iyz`` about the centre of mass). Every body frame is MuJoCo's
  own body frame (z-up in the character's reference pose), so joint axes, centres of mass and
  marker locations are MuJoCo's numbers unchanged; the one change of axes sits in the root
  joint (below). For display, every MuJoCo geom of a body becomes OpenSim geometry on an
  offset frame of the body (``<body>_geom<k>``): sphere -> ``Sphere``, box -> ``Brick``,
  ellipsoid -> ``Ellipsoid``, cylinder -> ``Cylinder``, capsule -> ``Cylinder`` + two
  ``Sphere`` caps (OpenSim has no capsule); meshes, planes and height fields are left out.
* **Root.** The free joint of the root body ``<root>`` (``pelvis``) becomes the
  ``CustomJoint`` ``ground_<root>`` with six coordinates, named as in OpenSim's gait models:
  ``<root>_tilt``, ``<root>_list``, ``<root>_rotation`` (rotations about ground Z, X and Y,
  body-fixed, in that order: ``R = Rz(tilt) Rx(list) Ry(rotation)``, all OpenSim axes), then
  ``<root>_tx``, ``<root>_ty``, ``<root>_tz`` (the root body's origin in ground, OpenSim axes).
  Its child frame is an offset frame on the root body rotated +90 degrees about the body's x
  axis, which carries the z-up -> y-up change: at zero coordinates the character stands up
  along ground Y. The angles come from MuJoCo's root quaternion: ``Rz Rx Ry =
  AXES R_mujoco AXES^T``, unwrapped over time (continuous); ``list`` is in [-90, 90] degrees
  (the sequence's gimbal lock is a body lying on its side, ``list`` = +-90).
* **Joints.** Every other body is joined to its MuJoCo parent: with hinges, a ``CustomJoint``
  ``<parent>_<body>`` whose ``rotation1..3`` are the body's hinges in MuJoCo's order (axes in
  MuJoCo's body frame; the coordinates are named after, and equal to, MuJoCo's joints: a hinge's
  coordinate value is its ``qpos`` and the rotation angle ``qpos - ref`` (a ``LinearFunction``
  ``1 -ref``); ranges from MuJoCo's ``jnt_range`` (+-2 pi where unlimited); coordinates are not
  clamped, so a reconstruction slightly outside a range reproduces exactly). Unused rotation
  axes complete the set to three independent axes with a constant 0. OpenSim's ``CustomJoint``
  composes its rotations body-fixed, ``R = Rot(axis1, q1) Rot(axis2, q2) Rot(axis3, q3)``,
  exactly MuJoCo's order for the hinges of one body, so MuJoCo's pose is reproduced (the tests
  compare every body's position and orientation against MuJoCo C). The parent frame is an
  offset frame on the parent at MuJoCo's ``body_pos`` (+ the joint anchor) rotated by
  ``body_quat`` (written as OpenSim's body-fixed X-Y-Z ``orientation``); the child frame an
  offset frame at the joint anchor ``jnt_pos``. Bodies without joints get a ``WeldJoint``.
  A body attached to MuJoCo's world other than by a free joint is joined to ground the same
  way, its offset turned into OpenSim's axes.
  Ball and slide joints, and bodies whose hinges have different anchors or more than three
  hinges, are not supported (``ValueError``; jmocap's humanoid has none).
* **Markers.** The ``.osim`` model has one ``Marker`` per keypoint of the result's layout,
  named like the keypoint and fixed at the MuJoCo site that produces it
  (:mod:`jmocap.layouts`), so OpenSim's Inverse Kinematics can track the ``.trc`` directly.
  The ``.trc`` holds ``keypoints3d`` (OpenSim axes, metres; ``Frame#`` from 1, ``Time`` =
  frame / fps); a keypoint that is NaN is written as ``NaN``, which OpenSim reads as missing.
  A result without a ``layout`` gets markers ``kp0``, ``kp1``, ... in the ``.trc`` and none in
  the model; a result without ``keypoints3d`` gets no ``.trc``.
* **Ground reaction forces.** Per foot (left: the contact sites ``contact_left_heel`` and
  ``contact_left_toe``; right: the two right ones, ``model.topo.contact_sites``): force = the
  sum of the two site forces; centre of pressure = the vertical-force-weighted mean of the two
  site positions (MuJoCo kinematics of ``q``) projected onto the floor (``Y = 0``); when the
  foot's vertical force is at most :data:`COP_MIN_FORCE_N` (no contact), the plain mean of its
  two sites on the floor; free moment = the vertical component of
  ``sum_i (r_i - cop) x f_i`` over the two sites (``r_i`` projected on the floor). The torque
  about the centre of pressure of the two point forces has no horizontal component (it
  vanishes by the choice of the centre of pressure), so ``ground_torque_*_x`` and ``_z`` are 0
  (in contact; they are written as 0 always). Moving the site forces down to the floor drops
  the moment of their horizontal parts about the sites' small height above it (the contact
  sites sit on the sole).
  Columns, OpenSim's (its Moco walking examples') convention, ``s`` = ``l`` or ``r``:
  ``ground_force_s_vx vy vz`` (N), ``ground_force_s_px py pz`` (m),
  ``ground_torque_s_x y z`` (N m), all in ground, OpenSim axes; left foot first.
* **ExternalLoads.** ``<name>_grf.xml`` has two ``ExternalForce`` (``left``, ``right``) applied
  to the foot body that carries both contact sites of that foot (the deepest common ancestor:
  jmocap's ``left_ankle`` / ``right_ankle``, OpenSim's ``calcn``), force and point expressed
  in ground, identifiers ``ground_force_s_v``, ``ground_force_s_p``, ``ground_torque_s_``,
  ``data_source_name`` and ``datafile`` = the ``.mot`` file name (relative: keep the files
  together).

Using the files
---------------

In the OpenSim GUI: File > Open Model (``<name>.osim``), File > Load Motion
(``<name>_coordinates.mot``); to see the forces, right-click the motion > Associate Motion
Data (``<name>_grf.mot``). With the API::

    import opensim
    model = opensim.Model("clip.osim")
    motion = opensim.TimeSeriesTable("clip_coordinates.mot")     # degrees
    markers = opensim.TimeSeriesTableVec3("clip_markers.trc")   # or TRCFileAdapter().read
    loads = opensim.ExternalLoads("clip_grf.xml", True)

Inverse dynamics: the ``InverseDynamicsTool`` with ``setModelFileName("clip.osim")``,
``setCoordinatesFileName("clip_coordinates.mot")`` and
``setExternalLoadsFileName("clip_grf.xml")``; inverse kinematics: the ``InverseKinematicsTool``
with ``set_marker_file("clip_markers.trc")`` (the model's markers have the same names; the
tests run it). OpenSim's inverse dynamics splines the coordinates (GCV) and needs at least six
frames.
"""

from __future__ import annotations

import math
import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from jmocap.data.clip import FormatError
from jmocap.io import atomic_write
from jmocap.layouts import get_layout
from jmocap.model import Model, site_trajectory

__all__ = [
    "AXES",
    "COP_MIN_FORCE_N",
    "coordinates_table",
    "external_loads_xml",
    "foot_bodies",
    "grf_table",
    "marker_table",
    "osim_model_xml",
    "root_coordinates",
    "to_opensim",
    "write_opensim",
]

#: OpenSim axes from jmocap axes: ``v_opensim = AXES @ v_jmocap`` ((X, Y, Z) = (x, z, -y))
AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: a foot whose vertical force is at most this (N) is not in contact: its centre of pressure is
#: the mean of its contact sites on the floor
COP_MIN_FORCE_N = 1.0
#: the root's rotation coordinates (suffixes) and their axes in OpenSim ground, in order
ROOT_ROTATIONS = (("tilt", (0.0, 0.0, 1.0)), ("list", (1.0, 0.0, 0.0)), ("rotation", (0.0, 1.0, 0.0)))
ROOT_TRANSLATIONS = (("tx", (1.0, 0.0, 0.0)), ("ty", (0.0, 1.0, 0.0)), ("tz", (0.0, 0.0, 1.0)))
SIDES = ("l", "r")  # left foot = contact sites 0, 1; right = 2, 3
OSIM_DOCUMENT_VERSION = "40000"
_UNLIMITED_ROT = (-2 * math.pi, 2 * math.pi)
_UNLIMITED_TRANS = (-100.0, 100.0)
_NAME_BAD = re.compile(r"[^A-Za-z0-9_.\-]")

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_FREE = int(mujoco.mjtJoint.mjJNT_FREE)


# ======================================================================================
# rotations and axes
# ======================================================================================


def to_opensim(v) -> np.ndarray:
    """jmocap world vectors (..., 3) in OpenSim axes: ``(X, Y, Z) = (x, z, -y)``."""
    return np.asarray(v, np.float64) @ AXES.T


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions w, x, y, z (any norm) -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _euler_xyz(R: np.ndarray) -> tuple[float, float, float]:
    """Body-fixed X-Y-Z angles (OpenSim's frame ``orientation``): ``R = Rx(a) Ry(b) Rz(c)``."""
    b = math.asin(float(np.clip(R[0, 2], -1.0, 1.0)))
    if abs(R[0, 2]) < 1.0 - 1e-12:
        a = math.atan2(-R[1, 2], R[2, 2])
        c = math.atan2(-R[0, 1], R[0, 0])
    else:  # gimbal lock: put everything in a
        a = math.atan2(R[2, 1], R[1, 1])
        c = 0.0
    return a, b, c


def root_coordinates(root_q) -> np.ndarray:
    """The root's six OpenSim coordinates from MuJoCo free-joint ``qpos`` (T, 7).

    Returns (T, 6): ``tilt, list, rotation`` (radians, unwrapped over time: continuous) with
    ``AXES R AXES^T = Rz(tilt) Rx(list) Ry(rotation)`` (OpenSim axes, body-fixed), then
    ``tx, ty, tz`` (metres, OpenSim axes).
    """
    root_q = np.asarray(root_q, np.float64)
    R = AXES @ _quat_to_mat(root_q[:, 3:7]) @ AXES.T  # (T, 3, 3) in OpenSim axes
    # Rz(a) Rx(b) Ry(c): M[2,1] = sin b, M[2,0] = -cos b sin c, M[2,2] = cos b cos c,
    # M[0,1] = -sin a cos b, M[1,1] = cos a cos b
    tilt = np.arctan2(-R[:, 0, 1], R[:, 1, 1])
    lst = np.arcsin(np.clip(R[:, 2, 1], -1.0, 1.0))
    rot = np.arctan2(-R[:, 2, 0], R[:, 2, 2])
    angles = np.unwrap(np.stack([tilt, lst, rot], 1), axis=0)
    return np.concatenate([angles, to_opensim(root_q[:, 0:3])], 1)


def _fmt(x: float) -> str:
    x = float(x)
    if x == 0.0:
        return "0"
    return f"{x:.12g}"


def _vec(v) -> str:
    return " ".join(_fmt(x) for x in np.asarray(v, np.float64).ravel())


# ======================================================================================
# model structure
# ======================================================================================


def _clean(name: str) -> str:
    return _NAME_BAD.sub("_", name)


def _names(mj: mujoco.MjModel) -> tuple[list[str], list[str]]:
    """Unique OpenSim-safe body and joint names (MuJoCo's where it has them)."""
    bodies = []
    for b in range(mj.nbody):
        n = "ground" if b == 0 else _clean(mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}")
        bodies.append(n)
    joints = [_clean(mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}") for j in range(mj.njnt)]
    for lst in (bodies, joints):
        seen: dict[str, int] = {}
        for i, n in enumerate(lst):
            if n in seen:
                lst[i] = f"{n}_{i}"
            seen[lst[i]] = i
    return bodies, joints


def _body_joints(mj: mujoco.MjModel, b: int) -> list[int]:
    return [j for j in range(mj.njnt) if int(mj.jnt_bodyid[j]) == b]


def _coordinate_spec(mj: mujoco.MjModel) -> list[tuple[str, str, int, int]]:
    """Every OpenSim coordinate in ``.mot`` order: (name, kind, qpos address, root slot).

    kind: ``root_rot`` / ``root_trans`` (slot 0..2 of the root's six) or ``hinge``.
    """
    bnames, jnames = _names(mj)
    out = []
    for j in range(mj.njnt):
        t = int(mj.jnt_type[j])
        adr = int(mj.jnt_qposadr[j])
        if t == _FREE:
            root = bnames[int(mj.jnt_bodyid[j])]
            out += [(f"{root}_{s}", "root_rot", adr, k) for k, (s, _) in enumerate(ROOT_ROTATIONS)]
            out += [(f"{root}_{s}", "root_trans", adr, k) for k, (s, _) in enumerate(ROOT_TRANSLATIONS)]
        elif t == _HINGE:
            out.append((jnames[j], "hinge", adr, -1))
        else:
            kind = {int(mujoco.mjtJoint.mjJNT_BALL): "ball", int(mujoco.mjtJoint.mjJNT_SLIDE): "slide"}[t]
            raise ValueError(f"OpenSim export: joint {jnames[j]!r} is a {kind} joint; only hinges and "
                             "a free root are supported")
    names = [n for n, *_ in out]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"OpenSim export: coordinate names are not unique: {dup}")
    return out


def foot_bodies(model: Model) -> tuple[int, int]:
    """Body ids that receive the left and right ground reaction force: for each foot, the
    deepest body carrying both of its contact sites (jmocap: ``left_ankle``, ``right_ankle``)."""
    sites = model.topo.contact_sites
    if len(sites) != 4:
        raise ValueError(f"OpenSim export: the model has {len(sites)} foot contact sites, expected 4")
    parent = model.topo.body_parent
    out = []
    for a, b in ((sites[0], sites[1]), (sites[2], sites[3])):
        chain = []
        x = model.topo.site_body[a]
        while True:
            chain.append(x)
            if x == 0:
                break
            x = parent[x]
        y = model.topo.site_body[b]
        while y not in chain:
            y = parent[y]
        out.append(int(y))
    return out[0], out[1]


# ======================================================================================
# validation
# ======================================================================================


def _check(result: dict[str, Any], model: Model) -> tuple[np.ndarray, float]:
    if not isinstance(result, dict):
        raise FormatError(f"OpenSim export: expected a result dict, got {type(result).__name__}")
    if result.get("q") is None:
        raise FormatError("OpenSim export: field 'q' is missing")
    q = np.asarray(result["q"])
    if q.dtype.kind not in "fiu":
        raise FormatError(f"OpenSim export: field 'q': expected numbers, got dtype {q.dtype}")
    q = q.astype(np.float64)
    if q.ndim != 2 or q.shape[1] != model.nq or q.shape[0] == 0:
        raise FormatError(f"OpenSim export: field 'q': expected shape (T>0, nq={model.nq}), got {q.shape}")
    bad = ~np.isfinite(q)
    if bad.any():
        t, i = np.argwhere(bad)[0]
        raise FormatError(f"OpenSim export: field 'q': frame {t}, coordinate {i} is {q[t, i]}")
    for a in model.topo.free_qadr:
        n = np.linalg.norm(q[:, a + 3 : a + 7], axis=1)
        if (n < 1e-9).any():
            raise FormatError(f"OpenSim export: field 'q': frame {int(np.argmax(n < 1e-9))}: the root "
                              "quaternion is zero")
    fps = result.get("fps")
    try:
        fps = float(fps)
    except (TypeError, ValueError):
        raise FormatError(f"OpenSim export: field 'fps': expected a number, got {fps!r}") from None
    if not (math.isfinite(fps) and fps > 0):
        raise FormatError(f"OpenSim export: field 'fps': expected a positive number, got {fps}")
    return q, fps


def _has_forces(result: dict[str, Any]) -> bool:
    return bool(result.get("forces_estimated")) and result.get("grf") is not None


def _check_grf(result: dict[str, Any], T: int) -> np.ndarray:
    grf = np.asarray(result["grf"])
    if grf.dtype.kind not in "fiu" or grf.shape != (T, 4, 3):
        raise FormatError(f"OpenSim export: field 'grf': expected shape ({T}, 4, 3) numbers, got "
                          f"{grf.shape} {grf.dtype}")
    grf = grf.astype(np.float64)
    bad = ~np.isfinite(grf.reshape(T, -1)).all(1)
    if bad.any():
        raise FormatError(f"OpenSim export: field 'grf': frame {int(np.argmax(bad))} is not finite")
    return grf


def _check_keypoints(result: dict[str, Any], T: int) -> tuple[np.ndarray, tuple[str, ...]]:
    kp = np.asarray(result["keypoints3d"])
    if kp.dtype.kind not in "fiu" or kp.ndim != 3 or kp.shape[0] != T or kp.shape[2] != 3:
        raise FormatError(f"OpenSim export: field 'keypoints3d': expected shape ({T}, J, 3) numbers, got "
                          f"{kp.shape} {kp.dtype}")
    kp = kp.astype(np.float64)
    if np.isinf(kp).any():
        raise FormatError("OpenSim export: field 'keypoints3d' has infinite values")
    names = _marker_names(result, kp.shape[1])
    return kp, names


def _marker_names(result: dict[str, Any], J: int) -> tuple[str, ...]:
    layout = result.get("layout")
    if layout:
        try:
            joints = get_layout(str(layout)).joints
        except ValueError as e:
            raise FormatError(f"OpenSim export: field 'layout': {e}") from None
        if len(joints) != J:
            raise FormatError(f"OpenSim export: field 'layout': {layout!r} has {len(joints)} keypoints, "
                              f"'keypoints3d' has {J}")
        return tuple(_clean(n) for n in joints)
    return tuple(f"kp{i}" for i in range(J))


# ======================================================================================
# tables
# ======================================================================================


def coordinates_table(result: dict[str, Any], model: Model | None = None) -> tuple[list[str], np.ndarray]:
    """The result's motion as OpenSim coordinates: (names, values (T, n)), in the ``.mot``'s
    units (degrees for rotations, metres for translations); see the module docstring."""
    model = _model(result, model)
    q, _ = _check(result, model)
    return _coordinates(model.mj, q)


def _coordinates(mj: mujoco.MjModel, q: np.ndarray) -> tuple[list[str], np.ndarray]:
    spec = _coordinate_spec(mj)
    cols = []
    roots: dict[int, np.ndarray] = {}
    for _, kind, adr, k in spec:
        if kind == "hinge":
            cols.append(np.degrees(q[:, adr]))
            continue
        if adr not in roots:
            roots[adr] = root_coordinates(q[:, adr : adr + 7])
        rc = roots[adr]
        cols.append(np.degrees(rc[:, k]) if kind == "root_rot" else rc[:, 3 + k])
    return [n for n, *_ in spec], np.stack(cols, 1)


def grf_table(result: dict[str, Any], model: Model | None = None) -> tuple[list[str], np.ndarray]:
    """The ground reaction forces per foot in OpenSim's columns: (names, values (T, 18)).

    Requires ``grf``; see the module docstring for the centre of pressure and free moment.
    """
    model = _model(result, model)
    q, _ = _check(result, model)
    if result.get("grf") is None:
        raise FormatError("OpenSim export: field 'grf' is missing")
    grf = _check_grf(result, q.shape[0])
    sites = model.topo.contact_sites
    if len(sites) != 4:
        raise ValueError(f"OpenSim export: the model has {len(sites)} foot contact sites, expected 4")
    pos = to_opensim(site_trajectory(model.mj, q, sites))  # (T, 4, 3)
    f = to_opensim(grf)
    return _grf_columns(pos, f)


def _grf_columns(pos: np.ndarray, f: np.ndarray) -> tuple[list[str], np.ndarray]:
    """Per-foot force, centre of pressure and free moment from four site positions and forces
    (T, 4, 3), both in OpenSim axes (Y up)."""
    names, cols = [], []
    torques = []
    for k, s in enumerate(SIDES):
        p = pos[:, 2 * k : 2 * k + 2].copy()
        p[..., 1] = 0.0  # on the floor
        fi = f[:, 2 * k : 2 * k + 2]
        force = fi.sum(1)
        fy = fi[..., 1]
        fy_sum = fy.sum(1)
        contact = fy_sum > COP_MIN_FORCE_N
        w = np.where(contact[:, None], fy / np.where(contact, fy_sum, 1.0)[:, None], 0.5)
        cop = (w[..., None] * p).sum(1)
        moment = np.cross(p - cop[:, None], fi).sum(1)
        torque = np.zeros_like(moment)
        torque[:, 1] = moment[:, 1]
        names += [f"ground_force_{s}_v{a}" for a in "xyz"] + [f"ground_force_{s}_p{a}" for a in "xyz"]
        cols += [force, cop]
        torques.append((s, torque))
    for s, torque in torques:
        names += [f"ground_torque_{s}_{a}" for a in "xyz"]
        cols.append(torque)
    return names, np.concatenate(cols, 1)


def marker_table(result: dict[str, Any], model: Model | None = None) -> tuple[list[str], np.ndarray]:
    """``keypoints3d`` as markers: (names, positions (T, J, 3) in OpenSim axes, NaN kept)."""
    model = _model(result, model)
    q, _ = _check(result, model)
    if result.get("keypoints3d") is None:
        raise FormatError("OpenSim export: field 'keypoints3d' is missing")
    kp, names = _check_keypoints(result, q.shape[0])
    return list(names), to_opensim(kp)


# ======================================================================================
# file formats
# ======================================================================================


def _storage_text(name: str, labels: Sequence[str], time: np.ndarray, values: np.ndarray, in_degrees: bool) -> str:
    """OpenSim Storage (``.mot``/``.sto``) text: header, ``endheader``, labels, rows."""
    n, m = values.shape
    lines = [
        name,
        "version=1",
        f"nRows={n}",
        f"nColumns={m + 1}",
        f"inDegrees={'yes' if in_degrees else 'no'}",
        "endheader",
        "\t".join(["time", *labels]),
    ]
    for t in range(n):
        lines.append("\t".join([_fmt(time[t]), *(_fmt(v) for v in values[t])]))
    return "\n".join(lines) + "\n"


def _trc_text(file_name: str, names: Sequence[str], fps: float, xyz: np.ndarray) -> str:
    """OpenSim TRC text (``PathFileType 4``), the layout OpenSim's own ``TRCFileAdapter`` writes."""
    T, J, _ = xyz.shape
    rate = _fmt(fps)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{file_name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{rate}\t{T}\t{J}\tm\t{rate}\t1\t{T}",
        "\t".join(["Frame#", "Time", *(f"{n}\t\t" for n in names)]).rstrip("\t"),
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, J + 1)),
        "",
    ]
    for t in range(T):
        vals = ("NaN" if not math.isfinite(v) else _fmt(v) for v in xyz[t].ravel())
        lines.append("\t".join([str(t + 1), _fmt(t / fps), *vals]))
    return "\n".join(lines) + "\n"


def _xml_bytes(root: ET.Element) -> bytes:
    ET.indent(root, space="\t")
    return ('<?xml version="1.0" encoding="UTF-8" ?>\n' + ET.tostring(root, encoding="unicode") + "\n").encode()


def _sub(parent: ET.Element, tag: str, text: str | None = None, **attrib: str) -> ET.Element:
    e = ET.SubElement(parent, tag, attrib)
    if text is not None:
        e.text = text
    return e


def _offset_frame(parent: ET.Element, name: str, socket_parent: str, translation, orientation) -> None:
    f = _sub(parent, "PhysicalOffsetFrame", name=name)
    _sub(f, "socket_parent", socket_parent)
    _sub(f, "translation", _vec(translation))
    _sub(f, "orientation", _vec(orientation))


def _transform_axis(st: ET.Element, name: str, axis, coord: str | None, intercept: float = 0.0) -> None:
    ta = _sub(st, "TransformAxis", name=name)
    _sub(ta, "coordinates", coord or "")
    _sub(ta, "axis", _vec(axis))
    if coord is None:
        fn = _sub(ta, "Constant", name="function")
        _sub(fn, "value", "0")
    else:
        fn = _sub(ta, "LinearFunction", name="function")
        _sub(fn, "coefficients", f"1 {_fmt(intercept)}")


def _coordinate(parent: ET.Element, name: str, default: float, rng: tuple[float, float]) -> None:
    c = _sub(parent, "Coordinate", name=name)
    _sub(c, "default_value", _fmt(default))
    _sub(c, "default_speed_value", "0")
    _sub(c, "range", f"{_fmt(rng[0])} {_fmt(rng[1])}")
    _sub(c, "clamped", "false")
    _sub(c, "locked", "false")


def _complete_axes(axes: list[np.ndarray]) -> list[np.ndarray]:
    """Three independent rotation axes starting with ``axes`` (1..3 of them)."""
    out = [a / np.linalg.norm(a) for a in axes]
    if len(out) == 1:
        a = out[0]
        e = np.eye(3)[int(np.argmin(np.abs(a)))]
        b = e - a * (a @ e)
        out.append(b / np.linalg.norm(b))
    if len(out) == 2:
        c = np.cross(out[0], out[1])
        out.append(c / np.linalg.norm(c))
    return out


def osim_model_xml(model: Model, markers: Sequence[tuple[str, str]] = (), name: str = "jmocap") -> bytes:
    """The ``.osim`` XML (bytes) of a jmocap character; ``markers`` = (marker name, MuJoCo site
    name) pairs. See the module docstring for the bodies, joints and coordinates."""
    mj = model.mj
    bnames, jnames = _names(mj)
    _coordinate_spec(mj)  # raises for unsupported joints
    doc = ET.Element("OpenSimDocument", Version=OSIM_DOCUMENT_VERSION)
    m = _sub(doc, "Model", name=_clean(name))
    _sub(m, "credits", "jmocap: generated from the MuJoCo character of a reconstruction")
    _sub(m, "length_units", "meters")
    _sub(m, "force_units", "N")
    _sub(m, "gravity", _vec(AXES @ np.asarray(mj.opt.gravity)))
    _sub(m, "Ground", name="ground")

    bodyset = _sub(m, "BodySet", name="bodyset")
    bobj = _sub(bodyset, "objects")
    for b in range(1, mj.nbody):
        e = _sub(bobj, "Body", name=bnames[b])
        _sub(e, "mass", _fmt(mj.body_mass[b]))
        _sub(e, "mass_center", _vec(mj.body_ipos[b]))
        R = _quat_to_mat(mj.body_iquat[b])
        inertia = R @ np.diag(mj.body_inertia[b]) @ R.T
        _sub(e, "inertia", _vec([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2],
                                 inertia[1, 2]]))
        geoms = [g for g in range(mj.ngeom) if int(mj.geom_bodyid[g]) == b]
        if geoms:
            comps = _sub(e, "components")
            for k, g in enumerate(geoms):
                _geometry(comps, mj, g, f"/bodyset/{bnames[b]}", f"{bnames[b]}_geom{k}")
    _sub(bodyset, "groups")

    jointset = _sub(m, "JointSet", name="jointset")
    jobj = _sub(jointset, "objects")
    for b in range(1, mj.nbody):
        _joint_xml(jobj, mj, b, bnames, jnames)
    _sub(jointset, "groups")

    if markers:
        markerset = _sub(m, "MarkerSet", name="markerset")
        mobj = _sub(markerset, "objects")
        for mname, site in markers:
            s = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, site)
            if s < 0:
                raise ValueError(f"OpenSim export: the model has no site {site!r} for marker {mname!r}")
            mk = _sub(mobj, "Marker", name=mname)
            _sub(mk, "socket_parent_frame", f"/bodyset/{bnames[int(mj.site_bodyid[s])]}")
            _sub(mk, "location", _vec(mj.site_pos[s]))
            _sub(mk, "fixed", "false")
        _sub(markerset, "groups")
    return _xml_bytes(doc)


def _geometry(comps: ET.Element, mj: mujoco.MjModel, g: int, body_path: str, name: str) -> None:
    """Display geometry of MuJoCo geom ``g`` on offset frame(s) of its body."""
    t = int(mj.geom_type[g])
    size = np.asarray(mj.geom_size[g], np.float64)
    R = _quat_to_mat(mj.geom_quat[g])
    pos = np.asarray(mj.geom_pos[g], np.float64)
    G = mujoco.mjtGeom
    shapes: list[tuple[str, np.ndarray, np.ndarray, str, dict[str, str]]] = []
    if t == G.mjGEOM_SPHERE:
        shapes.append(("", pos, R, "Sphere", {"radius": _fmt(size[0])}))
    elif t == G.mjGEOM_BOX:
        shapes.append(("", pos, R, "Brick", {"half_lengths": _vec(size)}))
    elif t == G.mjGEOM_ELLIPSOID:
        shapes.append(("", pos, R, "Ellipsoid", {"radii": _vec(size)}))
    elif t in (G.mjGEOM_CYLINDER, G.mjGEOM_CAPSULE):
        # MuJoCo's axis is the geom's z, OpenSim's cylinder's is its y: turn by +90 deg about x
        Ry = R @ AXES.T
        shapes.append(("", pos, Ry, "Cylinder", {"radius": _fmt(size[0]), "half_height": _fmt(size[1])}))
        if t == G.mjGEOM_CAPSULE:
            for end, sign in (("_a", 1.0), ("_b", -1.0)):
                shapes.append((end, pos + sign * size[1] * R[:, 2], R, "Sphere", {"radius": _fmt(size[0])}))
    for suffix, p, Rf, kind, props in shapes:
        f = _sub(comps, "PhysicalOffsetFrame", name=name + suffix)
        _sub(f, "socket_parent", body_path)
        _sub(f, "translation", _vec(p))
        _sub(f, "orientation", _vec(_euler_xyz(Rf)))
        ag = _sub(f, "attached_geometry")
        shape = _sub(ag, kind, name=f"{name}{suffix}_shape")
        _sub(shape, "socket_frame", "..")
        for k, v in props.items():
            _sub(shape, k, v)


def _joint_xml(jobj: ET.Element, mj: mujoco.MjModel, b: int, bnames: list[str], jnames: list[str]) -> None:
    p = int(mj.body_parentid[b])
    pname = bnames[p]
    ppath = "/ground" if p == 0 else f"/bodyset/{pname}"
    cpath = f"/bodyset/{bnames[b]}"
    joints = _body_joints(mj, b)
    types = [int(mj.jnt_type[j]) for j in joints]
    jname = f"{pname}_{bnames[b]}"
    body_R = _quat_to_mat(mj.body_quat[b])
    body_pos = np.asarray(mj.body_pos[b], np.float64)
    # MuJoCo's world is z-up: a body attached to it (other than through the free joint) has
    # its offset in jmocap axes, turned into OpenSim's ground here
    to_parent = AXES if p == 0 else np.eye(3)
    if _FREE in types:
        if len(joints) != 1:
            raise ValueError(f"OpenSim export: body {bnames[b]!r} has a free joint and other joints")
        root = bnames[b]
        j = _sub(jobj, "CustomJoint", name=jname)
        _sub(j, "socket_parent_frame", "ground_offset")
        _sub(j, "socket_child_frame", f"{root}_offset")
        coords = _sub(j, "coordinates")
        for s, _ in ROOT_ROTATIONS:
            _coordinate(coords, f"{root}_{s}", 0.0, _UNLIMITED_ROT)
        q0 = np.asarray(mj.qpos0[int(mj.jnt_qposadr[joints[0]]) : int(mj.jnt_qposadr[joints[0]]) + 7])
        t0 = to_opensim(q0[:3])
        for k, (s, _) in enumerate(ROOT_TRANSLATIONS):
            _coordinate(coords, f"{root}_{s}", float(t0[k]), _UNLIMITED_TRANS)
        frames = _sub(j, "frames")
        _offset_frame(frames, "ground_offset", "/ground", (0, 0, 0), (0, 0, 0))
        # the child frame's axes in the body frame are AXES^T = Rx(+90 deg): y-up on the body
        _offset_frame(frames, f"{root}_offset", cpath, (0, 0, 0), _euler_xyz(AXES.T))
        st = _sub(j, "SpatialTransform")
        for k, (s, axis) in enumerate(ROOT_ROTATIONS):
            _transform_axis(st, f"rotation{k + 1}", axis, f"{root}_{s}")
        for k, (s, axis) in enumerate(ROOT_TRANSLATIONS):
            _transform_axis(st, f"translation{k + 1}", axis, f"{root}_{s}")
        return
    if not joints:
        j = _sub(jobj, "WeldJoint", name=jname)
        _sub(j, "socket_parent_frame", f"{pname}_offset")
        _sub(j, "socket_child_frame", f"{bnames[b]}_offset")
        frames = _sub(j, "frames")
        _offset_frame(frames, f"{pname}_offset", ppath, to_parent @ body_pos, _euler_xyz(to_parent @ body_R))
        _offset_frame(frames, f"{bnames[b]}_offset", cpath, (0, 0, 0), (0, 0, 0))
        return
    if len(joints) > 3:
        raise ValueError(f"OpenSim export: body {bnames[b]!r} has {len(joints)} hinges; at most 3 are supported")
    anchors = np.asarray([mj.jnt_pos[j] for j in joints], np.float64)
    if np.abs(anchors - anchors[0]).max() > 1e-12:
        raise ValueError(f"OpenSim export: the hinges of body {bnames[b]!r} have different anchors")
    anchor = anchors[0]
    axes = [np.asarray(mj.jnt_axis[j], np.float64) for j in joints]
    full = _complete_axes(axes)
    if abs(np.linalg.det(np.stack(full))) < 1e-6:
        raise ValueError(f"OpenSim export: the hinge axes of body {bnames[b]!r} are not independent")
    j = _sub(jobj, "CustomJoint", name=jname)
    _sub(j, "socket_parent_frame", f"{pname}_offset")
    _sub(j, "socket_child_frame", f"{bnames[b]}_offset")
    coords = _sub(j, "coordinates")
    for jj in joints:
        lo, hi = (float(x) for x in mj.jnt_range[jj])
        rng = (lo, hi) if bool(mj.jnt_limited[jj]) and hi > lo else _UNLIMITED_ROT
        _coordinate(coords, jnames[jj], float(mj.qpos0[int(mj.jnt_qposadr[jj])]), rng)
    frames = _sub(j, "frames")
    _offset_frame(frames, f"{pname}_offset", ppath, to_parent @ (body_pos + body_R @ anchor),
                  _euler_xyz(to_parent @ body_R))
    _offset_frame(frames, f"{bnames[b]}_offset", cpath, anchor, (0, 0, 0))
    st = _sub(j, "SpatialTransform")
    for k in range(3):
        if k < len(joints):
            jj = joints[k]
            ref = float(mj.qpos0[int(mj.jnt_qposadr[jj])])
            _transform_axis(st, f"rotation{k + 1}", full[k], jnames[jj], -ref)
        else:
            _transform_axis(st, f"rotation{k + 1}", full[k], None)
    for k in range(3):
        _transform_axis(st, f"translation{k + 1}", np.eye(3)[k], None)


def external_loads_xml(model: Model, grf_file: str, name: str = "jmocap") -> bytes:
    """The ExternalLoads XML that applies ``grf_file`` (columns of :func:`grf_table`) to the
    feet (:func:`foot_bodies`)."""
    bnames, _ = _names(model.mj)
    feet = foot_bodies(model)
    doc = ET.Element("OpenSimDocument", Version=OSIM_DOCUMENT_VERSION)
    el = _sub(doc, "ExternalLoads", name=_clean(name))
    objs = _sub(el, "objects")
    for s, body, label in zip(SIDES, feet, ("left", "right"), strict=True):
        f = _sub(objs, "ExternalForce", name=label)
        _sub(f, "applied_to_body", bnames[body])
        _sub(f, "force_expressed_in_body", "ground")
        _sub(f, "point_expressed_in_body", "ground")
        _sub(f, "force_identifier", f"ground_force_{s}_v")
        _sub(f, "point_identifier", f"ground_force_{s}_p")
        _sub(f, "torque_identifier", f"ground_torque_{s}_")
        _sub(f, "data_source_name", grf_file)
    _sub(el, "groups")
    _sub(el, "datafile", grf_file)
    return _xml_bytes(doc)


# ======================================================================================
# writer
# ======================================================================================


def _model(result: dict[str, Any], model: Model | None) -> Model:
    if model is not None:
        return model
    from jmocap.results import result_model

    if not isinstance(result, dict):
        raise FormatError(f"OpenSim export: expected a result dict, got {type(result).__name__}")
    return result_model(result)


def _clip_name(result: dict[str, Any], name: str | None) -> str:
    if name is None:
        name = str(result.get("name") or "") or "motion"
    name = _clean(Path(str(name)).name)
    if not name.strip("._"):
        raise ValueError(f"OpenSim export: unusable file name {name!r}")
    return name


def write_opensim(
    result: dict[str, Any],
    out_dir: str | os.PathLike,
    name: str | None = None,
    *,
    model: Model | None = None,
) -> dict[str, Path]:
    """Write a result's OpenSim files into ``out_dir`` (created); returns their paths.

    Keys: ``model`` (``<name>.osim``), ``coordinates`` (``<name>_coordinates.mot``), ``markers``
    (``<name>_markers.trc``, when the result has ``keypoints3d``), and ``grf``
    (``<name>_grf.mot``) and ``external_loads`` (``<name>_grf.xml``) only when the result has
    force estimates (``forces_estimated`` and ``grf``): a result without them (the kinematic
    method) has no ``grf`` / ``external_loads`` key and no such files are written.

    Args:
      result: a result dict (:func:`jmocap.results.load_result`).
      out_dir: the folder.
      name: file stem; default the result's ``name`` (else ``motion``).
      model: the character; default :func:`jmocap.results.result_model` of the result.

    Raises :class:`jmocap.data.clip.FormatError` naming the field for a malformed result, and
    ``ValueError`` for a character OpenSim cannot represent (see the module docstring).
    """
    model = _model(result, model)
    q, fps = _check(result, model)
    T = q.shape[0]
    stem = _clip_name(result, name)
    time = np.arange(T) / fps

    coord_names, coord_values = _coordinates(model.mj, q)
    marker_names: tuple[str, ...] = ()
    kp = None
    if result.get("keypoints3d") is not None:
        kp, marker_names = _check_keypoints(result, T)
    grf = None
    if _has_forces(result):
        grf = _check_grf(result, T)

    markers: list[tuple[str, str]] = []
    layout = result.get("layout")
    if kp is not None and layout:
        sites = get_layout(str(layout)).sites
        site_names = set(model.topo.site_names)
        markers = [(m, s) for m, s in zip(marker_names, sites, strict=True) if s in site_names]

    # every file's bytes first: a malformed result or an unsupported character writes nothing
    files: dict[str, tuple[str, bytes | str]] = {
        "model": (f"{stem}.osim", osim_model_xml(model, markers, stem)),
        "coordinates": (f"{stem}_coordinates.mot",
                        _storage_text(f"{stem}_coordinates.mot", coord_names, time, coord_values, in_degrees=True)),
    }
    if kp is not None:
        trc = f"{stem}_markers.trc"
        files["markers"] = (trc, _trc_text(trc, marker_names, fps, to_opensim(kp)))
    if grf is not None:
        sites = model.topo.contact_sites
        if len(sites) != 4:
            raise ValueError(f"OpenSim export: the model has {len(sites)} foot contact sites, expected 4")
        grf_names, grf_values = _grf_columns(to_opensim(site_trajectory(model.mj, q, sites)), to_opensim(grf))
        grf_file = f"{stem}_grf.mot"
        files["grf"] = (grf_file, _storage_text(grf_file, grf_names, time, grf_values, in_degrees=False))
        files["external_loads"] = (f"{stem}_grf.xml", external_loads_xml(model, grf_file, stem))

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return {key: atomic_write(out / fname, data) for key, (fname, data) in files.items()}
