"""The character: a MuJoCo model as a JAX pytree.

:func:`load_model` compiles an MJCF file (by default ``models/mjcf/humanoid.xml``, optionally
rescaled to a subject's height and mass) and returns a :class:`Model`:

* ``topo`` — the static kinematic tree (a hashable :class:`Topology` of Python ints and
  tuples, plus numpy masks derived from it). Python control flow may depend on it; it is part
  of the jit cache key, so two models with the same tree share compiled code.
* array fields — the numeric parameters the physics reads (body offsets, inertias, joint
  axes, site offsets, ...). They are numpy float64 arrays: JAX turns them into float32 or
  float64 device arrays depending on ``jax_enable_x64``, so one ``Model`` serves both.
  Being pytree leaves, they can be differentiated (system identification) or vmapped.
* ``mj`` — the underlying ``mujoco.MjModel`` (for MuJoCo C reference calls, rendering,
  simulation; carried as static data that does not enter jit's cache key, so rescaled
  subjects share compiled code) and ``mjx`` — the ``mjx.Model`` built from it (a pytree
  child; ``model.replace(mjx=None)`` drops it, e.g. to vmap over subjects).

Supported joints: a free joint on a child of the world (the floating root), and any number of
hinge and slide joints per body (MuJoCo applies them in order). Ball joints are rejected with a
clear error (jmocap parametrises spherical joints as hinge triplets, as the paper does).
"""

from __future__ import annotations

import functools
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from flax import struct

from jmocap.layouts import CONTACT_SITES

DEFAULT_MODEL_PATH = Path(__file__).resolve().parents[2] / "models" / "mjcf" / "humanoid.xml"

# joint slot types
SLOT_NONE, SLOT_HINGE, SLOT_SLIDE = 0, 1, 2


def _import_mjx():
    # mujoco.mjx prints (not warns) that the optional `warp` backend is missing; it is harmless.
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from mujoco import mjx
    return mjx


class _Handle:
    """Carries a Python object (the MjModel) through a pytree without entering jit's cache key.

    All handles compare equal, so models that differ only in their numbers (a subject scaled
    to another height) share compiled code. Traced code must therefore never read the
    object it holds; jmocap's physics reads only the Model's arrays.
    """

    __slots__ = ("obj",)

    def __init__(self, obj):
        self.obj = obj

    def __eq__(self, other) -> bool:
        return isinstance(other, _Handle)

    def __hash__(self) -> int:
        return 0


@dataclass(frozen=True)
class Topology:
    """Static structure of the kinematic tree (hashable: part of the jit cache key)."""

    nq: int
    nv: int
    nbody: int
    nsite: int
    nslot: int  # max number of hinge/slide joints in one body
    body_parent: tuple[int, ...]
    body_depth: tuple[int, ...]
    slot_type: tuple[tuple[int, ...], ...]  # (nbody, nslot): SLOT_NONE / SLOT_HINGE / SLOT_SLIDE
    slot_qadr: tuple[tuple[int, ...], ...]  # qpos address, -1 if none
    slot_dof: tuple[tuple[int, ...], ...]  # dof address, -1 if none
    slot_jnt: tuple[tuple[int, ...], ...]  # joint id, -1 if none
    free_body: tuple[int, ...]  # bodies with a free joint
    free_qadr: tuple[int, ...]
    free_dof: tuple[int, ...]
    dof_body: tuple[int, ...]
    dof_jnt: tuple[int, ...]
    dof_is_rot: tuple[bool, ...]
    site_body: tuple[int, ...]
    body_names: tuple[str, ...]
    site_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    contact_sites: tuple[int, ...]  # the four foot contact sites, if the model has them

    # ---- derived static masks (numpy; computed once per topology) -------------------------

    @functools.cached_property
    def levels(self) -> tuple[np.ndarray, ...]:
        """Body ids grouped by depth (1 = children of the world), for level-by-level passes."""
        depth = np.asarray(self.body_depth)
        return tuple(np.nonzero(depth == d)[0] for d in range(1, int(depth.max()) + 1))

    @functools.cached_property
    def body_ancestor(self) -> np.ndarray:
        """(nbody, nbody) bool: ``[b, a]`` is True when a is b or one of its ancestors (not world)."""
        anc = np.zeros((self.nbody, self.nbody), bool)
        for b in range(1, self.nbody):
            a = b
            while a > 0:
                anc[b, a] = True
                a = self.body_parent[a]
        return anc

    @functools.cached_property
    def dof_moves_body(self) -> np.ndarray:
        """(nbody, nv) bool: dof d moves body b (its body is b or an ancestor of b)."""
        return self.body_ancestor[:, np.asarray(self.dof_body, int)] if self.nv else np.zeros(
            (self.nbody, 0), bool
        )

    @functools.cached_property
    def dof_ancestor(self) -> np.ndarray:
        """(nv, nv) bool: ``[d, k]``: the body of dof d is the body of dof k or an ancestor of it.

        These are the non-zero pattern of the upper part of the mass matrix (CRBA).
        """
        db = np.asarray(self.dof_body, int)
        return self.body_ancestor[db][:, db].T

    @functools.cached_property
    def velocity_before(self) -> np.ndarray:
        """(nv, nv) bool: ``[d, k]``: dof k contributes to the velocity of the frame that carries
        the axis of dof d *before* d moves (MuJoCo's mj_comVel ordering).

        Dofs of strict ancestor bodies, and earlier dofs of the same body; except that the three
        rotational dofs of a free joint all use the velocity before any of them (their axes are
        the child's axes, and the three cross terms cancel).
        """
        nv = self.nv
        db = np.asarray(self.dof_body, int)
        dj = np.asarray(self.dof_jnt, int)
        rot = np.asarray(self.dof_is_rot, bool)
        strict = self.body_ancestor[db][:, db] & (db[:, None] != db[None, :])
        same_body_earlier = (db[:, None] == db[None, :]) & (np.arange(nv)[None, :] < np.arange(nv)[:, None])
        free_dof = np.zeros(nv, bool)
        for adr in self.free_dof:
            free_dof[adr : adr + 6] = True
        same_free_rot = (dj[:, None] == dj[None, :]) & free_dof[:, None] & rot[:, None] & rot[None, :]
        return strict | (same_body_earlier & ~same_free_rot)

    @functools.cached_property
    def hinge_qadr(self) -> np.ndarray:
        """qpos addresses of all hinge/slide joints, in qpos order."""
        t = np.asarray(self.slot_type)
        a = np.asarray(self.slot_qadr)
        return np.sort(a[t != SLOT_NONE])


@struct.dataclass
class Model:
    """A MuJoCo character as a pytree: see the module docstring."""

    topo: Topology = struct.field(pytree_node=False)
    mj_handle: _Handle = struct.field(pytree_node=False)
    mjx: Any
    # numeric parameters (numpy float64; see module docstring)
    body_pos: np.ndarray  # (nbody, 3) offset from the parent frame
    body_rot: np.ndarray  # (nbody, 3, 3) rotation relative to the parent frame
    body_ipos: np.ndarray  # (nbody, 3) centre of mass in the body frame
    body_irot: np.ndarray  # (nbody, 3, 3) principal inertia frame in the body frame
    body_mass: np.ndarray  # (nbody,)
    body_inertia: np.ndarray  # (nbody, 3) principal moments
    slot_axis: np.ndarray  # (nbody, nslot, 3) joint axis in the body frame
    slot_pos: np.ndarray  # (nbody, nslot, 3) joint anchor in the body frame
    slot_qpos0: np.ndarray  # (nbody, nslot) reference angle (MuJoCo qpos0)
    dof_armature: np.ndarray  # (nv,)
    site_pos: np.ndarray  # (nsite, 3) site offset in its body frame
    gravity: np.ndarray  # (3,)
    qpos0: np.ndarray  # (nq,) reference configuration
    q_lower: np.ndarray  # (nq,) joint lower limits (-inf where unlimited / root)
    q_upper: np.ndarray  # (nq,)
    timestep: float = struct.field(pytree_node=False, default=0.01)

    # ---- convenience -------------------------------------------------------------------

    @property
    def mj(self) -> mujoco.MjModel:
        """The compiled ``mujoco.MjModel`` (MuJoCo C reference, simulation, rendering)."""
        return self.mj_handle.obj

    @property
    def nq(self) -> int:
        return self.topo.nq

    @property
    def nv(self) -> int:
        return self.topo.nv

    @property
    def total_mass(self) -> float:
        return float(np.sum(self.body_mass))

    def body_id(self, name: str) -> int:
        return _index(self.topo.body_names, name, "body")

    def site_id(self, name: str) -> int:
        return _index(self.topo.site_names, name, "site")

    def site_ids(self, names) -> tuple[int, ...]:
        return tuple(self.site_id(n) for n in names)

    def keyframe(self, name: str) -> np.ndarray:
        """qpos of a named keyframe of the MJCF."""
        kid = mujoco.mj_name2id(self.mj, mujoco.mjtObj.mjOBJ_KEY, name)
        if kid < 0:
            raise KeyError(f"model has no keyframe {name!r}")
        return np.array(self.mj.key_qpos[kid])

    def __repr__(self) -> str:  # the default would print every array
        t = self.topo
        return (
            f"Model(nq={t.nq}, nv={t.nv}, nbody={t.nbody}, nsite={t.nsite}, "
            f"mass={self.total_mass:.2f} kg)"
        )


def _index(names: tuple[str, ...], name: str, kind: str) -> int:
    try:
        return names.index(name)
    except ValueError:
        raise KeyError(f"model has no {kind} named {name!r}") from None


# ---------------------------------------------------------------------------------------
# loading and scaling
# ---------------------------------------------------------------------------------------


def load_model(
    path: str | os.PathLike | None = None,
    *,
    height_m: float | None = None,
    mass_kg: float | None = None,
    with_mjx: bool = True,
) -> Model:
    """Load a character from MJCF (default: jmocap's humanoid), optionally rescaled.

    Args:
      path: MJCF file; ``None`` for ``models/mjcf/humanoid.xml``.
      height_m: standing height of the subject. All lengths (body offsets, joint anchors,
        geoms, sites, centres of mass, keyframe root positions) are multiplied by
        ``height_m / nominal_height`` and rotational inertias by its square. The nominal
        height is the height of site ``kp_head_top`` in keyframe ``stand``.
      mass_kg: total mass of the subject; masses and inertias are multiplied by
        ``mass_kg / total_mass``.
      with_mjx: also build the ``mjx.Model`` (``model.mjx``); ``False`` leaves it ``None``.
    """
    path = Path(path) if path is not None else DEFAULT_MODEL_PATH
    if not path.is_file():
        raise FileNotFoundError(f"MJCF model not found: {path}")
    if height_m is None and mass_kg is None:
        mj = mujoco.MjModel.from_xml_path(str(path))
    else:
        mj = _scaled_model(path, height_m, mass_kg)
    return from_mjmodel(mj, with_mjx=with_mjx)


def nominal_height(mj: mujoco.MjModel) -> float:
    """Height of site ``kp_head_top`` above the floor in keyframe ``stand``."""
    kid = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_KEY, "stand")
    sid = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, "kp_head_top")
    if kid < 0 or sid < 0:
        raise ValueError("height scaling needs a keyframe 'stand' and a site 'kp_head_top'")
    d = mujoco.MjData(mj)
    mujoco.mj_resetDataKeyframe(mj, d, kid)
    mujoco.mj_kinematics(mj, d)
    return float(d.site_xpos[sid, 2])


def _scaled_model(path: Path, height_m: float | None, mass_kg: float | None) -> mujoco.MjModel:
    spec = mujoco.MjSpec.from_file(str(path))
    base = spec.compile()
    s = 1.0
    if height_m is not None:
        if not (math.isfinite(height_m) and 0.5 <= height_m <= 2.5):
            raise ValueError(f"height_m must be a plausible standing height in metres, got {height_m}")
        s = height_m / nominal_height(base)
    m = 1.0
    if mass_kg is not None:
        if not (math.isfinite(mass_kg) and 10.0 <= mass_kg <= 300.0):
            raise ValueError(f"mass_kg must be a plausible body mass in kilograms, got {mass_kg}")
        m = mass_kg / float(np.sum(base.body_mass))

    for body in spec.bodies:
        if body.name == "world" or body is spec.worldbody:
            continue
        body.pos = np.asarray(body.pos) * s
        body.ipos = np.asarray(body.ipos) * s
        body.mass = body.mass * m
        body.inertia = np.asarray(body.inertia) * m * s * s
        fi = np.asarray(body.fullinertia)
        if np.all(np.isfinite(fi)):
            body.fullinertia = fi * m * s * s
    for joint in spec.joints:
        joint.pos = np.asarray(joint.pos) * s
        if joint.type == mujoco.mjtJoint.mjJNT_SLIDE:
            joint.range = np.asarray(joint.range) * s
    for geom in spec.geoms:
        if geom.type == mujoco.mjtGeom.mjGEOM_PLANE:
            continue  # the floor is infinite; keep it
        geom.size = np.asarray(geom.size) * s
        geom.pos = np.asarray(geom.pos) * s
        fromto = np.asarray(geom.fromto)
        if np.all(np.isfinite(fromto)):
            geom.fromto = fromto * s
        if geom.mass > 0:
            geom.mass = geom.mass * m
    for site in spec.sites:
        site.pos = np.asarray(site.pos) * s
        site.size = np.asarray(site.size) * s
        fromto = np.asarray(site.fromto)
        if np.all(np.isfinite(fromto)):
            site.fromto = fromto * s
    free_qadr = [
        base.jnt_qposadr[j] for j in range(base.njnt) if int(base.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)
    ]
    for key in spec.keys:
        qpos = np.array(key.qpos)
        if qpos.size == base.nq:
            for a in free_qadr:
                qpos[a : a + 3] *= s
            key.qpos = qpos
    return spec.compile()


def from_mjmodel(mj: mujoco.MjModel, *, with_mjx: bool = True) -> Model:
    """Build a :class:`Model` from a compiled ``mujoco.MjModel``."""
    J = mujoco.mjtJoint
    nbody = mj.nbody
    parent = tuple(int(p) for p in mj.body_parentid)
    depth = [0] * nbody
    for b in range(1, nbody):
        depth[b] = depth[parent[b]] + 1

    per_body: list[list[int]] = [[] for _ in range(nbody)]
    free_body, free_qadr, free_dof = [], [], []
    for j in range(mj.njnt):
        b, t = int(mj.jnt_bodyid[j]), int(mj.jnt_type[j])
        name = mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"
        if t == J.mjJNT_FREE:
            if parent[b] != 0:
                raise ValueError(f"free joint {name!r} must belong to a child of the world body")
            if mj.body_jntnum[b] != 1:
                raise ValueError(f"body of free joint {name!r} must have no other joint")
            free_body.append(b)
            free_qadr.append(int(mj.jnt_qposadr[j]))
            free_dof.append(int(mj.jnt_dofadr[j]))
        elif t in (J.mjJNT_HINGE, J.mjJNT_SLIDE):
            per_body[b].append(j)
        else:
            raise ValueError(
                f"joint {name!r} is a ball joint; jmocap supports free, hinge and slide joints "
                "(parametrise spherical joints as hinge triplets)"
            )
    nslot = max([len(js) for js in per_body] + [1])

    slot_type = np.zeros((nbody, nslot), int)
    slot_qadr = -np.ones((nbody, nslot), int)
    slot_dof = -np.ones((nbody, nslot), int)
    slot_jnt = -np.ones((nbody, nslot), int)
    slot_axis = np.zeros((nbody, nslot, 3))
    slot_axis[..., 2] = 1.0  # unused slots: any unit axis, angle 0
    slot_pos = np.zeros((nbody, nslot, 3))
    slot_qpos0 = np.zeros((nbody, nslot))
    for b, js in enumerate(per_body):
        for s, j in enumerate(js):
            slot_type[b, s] = SLOT_HINGE if int(mj.jnt_type[j]) == int(J.mjJNT_HINGE) else SLOT_SLIDE
            slot_qadr[b, s] = mj.jnt_qposadr[j]
            slot_dof[b, s] = mj.jnt_dofadr[j]
            slot_jnt[b, s] = j
            slot_axis[b, s] = mj.jnt_axis[j]
            slot_pos[b, s] = mj.jnt_pos[j]
            slot_qpos0[b, s] = mj.qpos0[mj.jnt_qposadr[j]]

    dof_is_rot = []
    for d in range(mj.nv):
        j = int(mj.dof_jntid[d])
        t = int(mj.jnt_type[j])
        if t == J.mjJNT_FREE:
            dof_is_rot.append(d - int(mj.jnt_dofadr[j]) >= 3)
        else:
            dof_is_rot.append(t == J.mjJNT_HINGE)

    q_lower = np.full(mj.nq, -np.inf)
    q_upper = np.full(mj.nq, np.inf)
    for j in range(mj.njnt):
        if mj.jnt_limited[j] and int(mj.jnt_type[j]) in (int(J.mjJNT_HINGE), int(J.mjJNT_SLIDE)):
            a = mj.jnt_qposadr[j]
            q_lower[a], q_upper[a] = mj.jnt_range[j]

    def names(obj, n):
        return tuple(mujoco.mj_id2name(mj, obj, i) or "" for i in range(n))

    site_names = names(mujoco.mjtObj.mjOBJ_SITE, mj.nsite)
    contact = tuple(site_names.index(s) for s in CONTACT_SITES) if all(
        s in site_names for s in CONTACT_SITES
    ) else ()
    joint_names = names(mujoco.mjtObj.mjOBJ_JOINT, mj.njnt)

    topo = Topology(
        nq=int(mj.nq),
        nv=int(mj.nv),
        nbody=nbody,
        nsite=int(mj.nsite),
        nslot=nslot,
        body_parent=parent,
        body_depth=tuple(depth),
        slot_type=_tup2(slot_type),
        slot_qadr=_tup2(slot_qadr),
        slot_dof=_tup2(slot_dof),
        slot_jnt=_tup2(slot_jnt),
        free_body=tuple(free_body),
        free_qadr=tuple(free_qadr),
        free_dof=tuple(free_dof),
        dof_body=tuple(int(b) for b in mj.dof_bodyid),
        dof_jnt=tuple(int(j) for j in mj.dof_jntid),
        dof_is_rot=tuple(dof_is_rot),
        site_body=tuple(int(b) for b in mj.site_bodyid),
        body_names=names(mujoco.mjtObj.mjOBJ_BODY, nbody),
        site_names=site_names,
        joint_names=joint_names,
        contact_sites=contact,
    )

    mjx_model = None
    if with_mjx:
        mjx_model = _import_mjx().put_model(mj)

    return Model(
        topo=topo,
        mj_handle=_Handle(mj),
        mjx=mjx_model,
        body_pos=np.array(mj.body_pos, np.float64),
        body_rot=_quat2mat_np(np.array(mj.body_quat)),
        body_ipos=np.array(mj.body_ipos, np.float64),
        body_irot=_quat2mat_np(np.array(mj.body_iquat)),
        body_mass=np.array(mj.body_mass, np.float64),
        body_inertia=np.array(mj.body_inertia, np.float64),
        slot_axis=slot_axis,
        slot_pos=slot_pos,
        slot_qpos0=slot_qpos0,
        dof_armature=np.array(mj.dof_armature, np.float64),
        site_pos=np.array(mj.site_pos, np.float64),
        gravity=np.array(mj.opt.gravity, np.float64),
        qpos0=np.array(mj.qpos0, np.float64),
        q_lower=q_lower,
        q_upper=q_upper,
        timestep=float(mj.opt.timestep),
    )


def _tup2(a: np.ndarray) -> tuple[tuple[int, ...], ...]:
    return tuple(tuple(int(x) for x in row) for row in a)


def _quat2mat_np(q: np.ndarray) -> np.ndarray:
    out = np.zeros((q.shape[0], 3, 3))
    for i, qi in enumerate(q):
        mujoco.mju_quat2Mat(out[i].reshape(9), qi / np.linalg.norm(qi))
    return out
