"""BVH export of a reconstruction: result files in, Biovision hierarchy (BVH) motion out.

(Result files are read with :func:`jmocap.results.load_result`.)

* :func:`write_bvh` writes a motion ``q`` (T, nq) of a jmocap character as BVH: one BVH joint
  per MuJoCo body, offsets from the model's ``body_pos`` (so a model scaled to a subject's
  height exports its own skeleton), the root's position and orientation, and every hinge
  angle as a rotation channel. Written atomically (temp file + ``os.replace``).
* :func:`read_bvh` parses any BVH file (not only jmocap's) and :func:`bvh_joint_positions`
  runs its forward kinematics, following the published format; the round-trip test uses them
  against MuJoCo C, independently of the writer.

The BVH conventions (``docs/formats.md``, section "BVH output"):

* Axes: ``up="y"`` (default) writes BVH's customary y-up frame, with the character's forward
  (+x in jmocap) along +Z and its left (+y) along +X: ``(X, Y, Z)_bvh = (y, z, x)_jmocap``,
  a proper rotation (a cyclic permutation), so every rotation stays right-handed. Blender's
  importer (forward -Z, up Y, its defaults) turns this into its z-up world with the character
  facing -Y (Blender's front view) and its left along +X. ``up="z"`` keeps jmocap's axes.
* Units: centimetres (default; ``units="m"`` for metres); angles in degrees.
* Channels: the root has ``Xposition Yposition Zposition`` and three rotations in yaw, pitch,
  roll order about (up, left, forward): ``Yrotation Xrotation Zrotation`` (y-up) or
  ``Zrotation Yrotation Xrotation`` (z-up). Every other joint has exactly three rotation
  channels: its hinges in MuJoCo's order (which is their composition order, the BVH rule:
  the rotation is the product of the channels' rotations in the order listed), then the axes
  it has no hinge about, which are always 0 (a knee: ``Xrotation Yrotation Zrotation`` in
  y-up, Y and Z fixed at 0; rigid bodies such as spine2, head, hands: three zeros). Three
  rotation channels everywhere keep importers that expect them (most do) happy; a zero
  rotation is the identity wherever it sits in the order, so the fixed channels change
  nothing.
* Skeleton: the root's OFFSET is 0 (its position channels are its world position, read the
  same way by importers that add the offset and those that do not); each End Site sits at the
  leaf body's farthest site (toe tip, head top) or, without sites, at twice its centre of
  mass offset (the fingertips).
"""

from __future__ import annotations

import math
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from jmocap.data.clip import FormatError
from jmocap.io import atomic_write
from jmocap.model import Model

__all__ = [
    "Bvh",
    "bvh_joint_positions",
    "check_q",
    "read_bvh",
    "write_bvh",
]

# ======================================================================================
# validation
# ======================================================================================


def check_q(model: Model, q, where: str = "q") -> np.ndarray:
    """Validate a motion ``q`` (T, nq) for ``model``; return it as float64 numpy.

    Raises ``ValueError`` naming ``where``, the frame and the coordinate for a wrong shape, a
    non-finite value or a zero root quaternion.
    """
    q = np.asarray(q)
    if q.dtype.kind not in "fiu":
        raise ValueError(f"{where}: expected numbers, got dtype {q.dtype}")
    q = q.astype(np.float64)
    if q.ndim != 2 or q.shape[1] != model.nq:
        raise ValueError(f"{where}: expected shape (T, nq={model.nq}), got {q.shape}")
    if q.shape[0] == 0:
        raise ValueError(f"{where}: no frames")
    bad = ~np.isfinite(q)
    if bad.any():
        t, i = np.argwhere(bad)[0]
        raise ValueError(
            f"{where}: frame {t}: coordinate {i} ({_qpos_name(model, i)}) is {q[t, i]}; "
            f"{int(bad.any(1).sum())} frame(s) have non-finite values"
        )
    for a in model.topo.free_qadr:
        n = np.linalg.norm(q[:, a + 3 : a + 7], axis=1)
        if (n < 1e-9).any():
            t = int(np.argmax(n < 1e-9))
            raise ValueError(f"{where}: frame {t}: root quaternion q[{a + 3}:{a + 7}] is zero")
    return q


def _qpos_name(model: Model, i: int) -> str:
    mj = model.mj
    for j in range(mj.njnt):
        a = int(mj.jnt_qposadr[j])
        n = {0: 7, 1: 4}.get(int(mj.jnt_type[j]), 1)  # free, ball, hinge/slide
        if a <= i < a + n:
            name = mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint {j}"
            if n == 7:
                return f"{name} {'position' if i - a < 3 else 'quaternion'}"
            return name
    return "?"


def _check_fps(fps, where: str) -> float:
    try:
        fps = float(fps)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: fps must be a number, got {fps!r}") from None
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"{where}: fps must be positive and finite, got {fps}")
    return fps


# ======================================================================================
# BVH writing
# ======================================================================================

_AXES = "XYZ"
# jmocap world -> BVH frame
_TO_BVH = {
    "y": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),  # (X,Y,Z) = (y,z,x)
    "z": np.eye(3),
}
_UNITS = {"cm": 100.0, "m": 1.0}
_ROOT_ORDER_WORLD = (2, 1, 0)  # yaw (up), pitch (left), roll (forward) in jmocap axes


@dataclass(frozen=True)
class _Joint:
    body: int
    name: str
    parent: int  # index into the joint list, -1 for the root
    offset: np.ndarray  # (3,) BVH frame and units
    channels: tuple[str, ...]
    # rotation channel k of this joint = sign[k] * (q[qadr[k]] - qpos0[qadr[k]]); qadr -1: 0
    qadr: tuple[int, ...]
    sign: tuple[float, ...]
    end_site: np.ndarray | None  # (3,) BVH frame and units, for leaves


def _skeleton(model: Model, C: np.ndarray, scale: float) -> list[_Joint]:
    """The BVH joints of ``model`` in hierarchy (depth-first) order; ValueError if not exportable."""
    mj = model.mj
    topo = model.topo
    free = [
        j for j in range(mj.njnt) if int(mj.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)
    ]
    if len(free) != 1:
        raise ValueError(f"BVH export needs exactly one free (root) joint, the model has {len(free)}")
    root = int(mj.jnt_bodyid[free[0]])
    children: list[list[int]] = [[] for _ in range(mj.nbody)]
    for b in range(1, mj.nbody):
        children[int(mj.body_parentid[b])].append(b)

    def name(b):
        return topo.body_names[b] or f"body{b}"

    joints: list[_Joint] = []

    def visit(b: int, parent: int) -> None:
        is_root = b == root
        if not is_root:
            quat = np.asarray(mj.body_quat[b])
            if not np.allclose(np.abs(quat), [1, 0, 0, 0], atol=1e-9):
                raise ValueError(
                    f"BVH export: body {name(b)!r} has a rest rotation (quat {quat}); jmocap's BVH "
                    "writer needs body frames aligned with their parents"
                )
        chans: list[str] = []
        qadr: list[int] = []
        sign: list[float] = []
        if is_root:
            chans += ["Xposition", "Yposition", "Zposition"]
            for a in _ROOT_ORDER_WORLD:
                k = int(np.argmax(np.abs(C[:, a])))
                chans.append(f"{_AXES[k]}rotation")
            qadr += [-1, -1, -1]
            sign += [0.0, 0.0, 0.0]  # the root's channels are filled from q's free joint
        else:
            for j in range(mj.body_jntadr[b], mj.body_jntadr[b] + mj.body_jntnum[b]):
                jname = topo.joint_names[j]
                if int(mj.jnt_type[j]) != int(mujoco.mjtJoint.mjJNT_HINGE):
                    raise ValueError(f"BVH export: joint {jname!r} is not a hinge")
                if np.linalg.norm(mj.jnt_pos[j]) > 1e-9:
                    raise ValueError(f"BVH export: hinge {jname!r} is not at its body's origin")
                axis = C @ np.asarray(mj.jnt_axis[j])
                k = int(np.argmax(np.abs(axis)))
                if abs(abs(axis[k]) - 1.0) > 1e-9:
                    raise ValueError(
                        f"BVH export: hinge {jname!r} axis {mj.jnt_axis[j]} is not a coordinate axis"
                    )
                ch = f"{_AXES[k]}rotation"
                if ch in chans:
                    raise ValueError(f"BVH export: body {name(b)!r} has two hinges about {_AXES[k]}")
                chans.append(ch)
                qadr.append(int(mj.jnt_qposadr[j]))
                sign.append(float(np.sign(axis[k])))
            if len(chans) > 3:
                raise ValueError(f"BVH export: body {name(b)!r} has more than three hinges")
            for k in range(3):  # fixed zero channels for the axes without a hinge
                ch = f"{_AXES[k]}rotation"
                if ch not in chans:
                    chans.append(ch)
                    qadr.append(-1)
                    sign.append(0.0)
        offset = np.zeros(3) if is_root else C @ np.asarray(mj.body_pos[b]) * scale
        end = None
        if not children[b]:
            sites = [s for s in range(mj.nsite) if int(mj.site_bodyid[s]) == b]
            if sites:
                pos = np.asarray(mj.site_pos[sites])
                tip = pos[int(np.argmax(np.linalg.norm(pos, axis=1)))]
            else:
                tip = 2.0 * np.asarray(mj.body_ipos[b])
            end = C @ tip * scale
        index = len(joints)
        joints.append(_Joint(b, name(b), parent, offset, tuple(chans), tuple(qadr), tuple(sign), end))
        for c in children[b]:
            visit(c, index)

    visit(root, -1)
    return joints


def _fmt(v, decimals: int = 6) -> str:
    return " ".join(f"{x:.{decimals}f}" for x in v)


def _hierarchy_text(joints: list[_Joint], decimals: int) -> str:
    lines = ["HIERARCHY"]
    kids: list[list[int]] = [[] for _ in joints]
    for i, jt in enumerate(joints):
        if jt.parent >= 0:
            kids[jt.parent].append(i)

    def emit(i: int, depth: int) -> None:
        jt = joints[i]
        pad = "\t" * depth
        lines.append(f"{pad}{'ROOT' if jt.parent < 0 else 'JOINT'} {jt.name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}\tOFFSET {_fmt(jt.offset, decimals)}")
        lines.append(f"{pad}\tCHANNELS {len(jt.channels)} {' '.join(jt.channels)}")
        for c in kids[i]:
            emit(c, depth + 1)
        if jt.end_site is not None:
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {_fmt(jt.end_site, decimals)}", f"{pad}\t}}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    return "\n".join(lines) + "\n"


def _root_channels(q: np.ndarray, qadr: int, C: np.ndarray, scale: float, order: str) -> np.ndarray:
    """(T, 6) root position (BVH units) and Euler angles (degrees, unwrapped over time)."""
    from scipy.spatial.transform import Rotation

    pos = q[:, qadr : qadr + 3] @ C.T * scale
    quat = q[:, qadr + 3 : qadr + 7]
    quat = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    R = Rotation.from_quat(quat[:, [1, 2, 3, 0]]).as_matrix()  # scipy: x, y, z, w
    R_bvh = C @ R @ C.T
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gimbal lock: any valid decomposition will do
        ang = Rotation.from_matrix(R_bvh).as_euler(order.upper(), degrees=False)  # intrinsic
    ang = np.unwrap(ang, axis=0)  # +-2 pi per angle leaves each frame's rotation unchanged
    return np.concatenate([pos, np.degrees(ang)], axis=1)


def write_bvh(
    path: str | os.PathLike,
    model: Model,
    q,
    fps: float,
    *,
    units: str = "cm",
    up: str = "y",
) -> Path:
    """Write the motion ``q`` (T, nq) of ``model`` at ``fps`` as a BVH file, atomically.

    Args:
      path: output ``.bvh`` file (parent folders are created).
      model: the character the motion belongs to (e.g. ``load_model(height_m=...)``): its body
        offsets make the skeleton.
      q: (T, nq) MuJoCo configurations (root position, root quaternion wxyz, hinge angles).
      fps: frame rate; the file's ``Frame Time`` is ``1 / fps``.
      units: ``"cm"`` (default) or ``"m"`` for offsets and root positions.
      up: ``"y"`` (default; BVH/Blender convention, ``(X, Y, Z) = (y, z, x)`` of jmocap's
        world) or ``"z"`` (jmocap's axes unchanged).

    The model must have one free root joint, body frames aligned with their parents, and
    hinges at body origins about coordinate axes, at most three (distinct) per body, which
    jmocap's humanoid has by construction; otherwise ``ValueError``. See the module docstring
    and ``docs/formats.md`` for the channel layout. Returns the path.
    """
    path = Path(path)
    where = f"write_bvh({path})"
    if units not in _UNITS:
        raise ValueError(f"{where}: units must be one of {sorted(_UNITS)}, got {units!r}")
    if up not in _TO_BVH:
        raise ValueError(f"{where}: up must be 'y' or 'z', got {up!r}")
    q = check_q(model, q, f"{where}: field 'q'")
    fps = _check_fps(fps, where)
    C, scale = _TO_BVH[up], _UNITS[units]
    joints = _skeleton(model, C, scale)

    qpos0 = np.asarray(model.mj.qpos0)
    cols = []
    for jt in joints:
        if jt.parent < 0:
            order = "".join(c[0] for c in jt.channels[3:])
            cols.append(_root_channels(q, int(model.topo.free_qadr[0]), C, scale, order))
            continue
        for a, s in zip(jt.qadr, jt.sign, strict=True):
            col = np.zeros(len(q)) if a < 0 else s * np.degrees(q[:, a] - qpos0[a])
            cols.append(col[:, None])
    motion = np.concatenate(cols, axis=1)

    # lengths to 1e-8 m (6 decimals in cm, 8 in m), angles to 1e-6 degree
    decimals = 6 + round(math.log10(100.0 / scale))
    fmt = " ".join([f"%.{decimals}f"] * 3 + ["%.6f"] * (motion.shape[1] - 3)) + "\n"
    text = [_hierarchy_text(joints, decimals), "MOTION\n", f"Frames: {len(q)}\n", f"Frame Time: {1.0 / fps:.8f}\n"]
    text += [fmt % tuple(row) for row in motion]
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, "".join(text).encode("ascii"))
    return path


# ======================================================================================
# BVH reading (any BVH file) and its forward kinematics
# ======================================================================================


@dataclass(frozen=True)
class Bvh:
    """A parsed BVH file (in the file's own axes and units).

    Attributes:
      names: joint names in hierarchy order (``End Site``s are not joints).
      parents: parent index of each joint, -1 for roots.
      offsets: (J, 3) OFFSET of each joint in its parent's frame.
      channels: channel names of each joint, as listed (``Xposition``, ``Zrotation``, ...).
      end_sites: (joint index, (3,) offset) of each End Site.
      frames: (T, total channels) the MOTION values, joints' channels in hierarchy order.
      frame_time: seconds per frame.
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_sites: tuple[tuple[int, np.ndarray], ...]
    frames: np.ndarray
    frame_time: float

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def channel_slice(self, joint: int | str) -> slice:
        """Columns of ``frames`` holding the channels of a joint (index or name)."""
        i = self.names.index(joint) if isinstance(joint, str) else joint
        start = sum(len(c) for c in self.channels[:i])
        return slice(start, start + len(self.channels[i]))


_CHANNELS = {f"{a}{kind}" for a in "xyz" for kind in ("position", "rotation")}


def read_bvh(path: str | os.PathLike) -> Bvh:
    """Parse a BVH file. Raises :class:`jmocap.data.FormatError` naming the file and line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise
    except OSError as e:
        raise FormatError(f"{path}: cannot read ({e})") from None
    # tokens with line numbers ('{' and '}' may touch other tokens)
    toks: list[tuple[str, int]] = []
    for n, line in enumerate(text.splitlines(), 1):
        toks += [(t, n) for t in re.findall(r"[{}]|[^\s{}]+", line)]
    pos = 0

    def err(msg: str, at: int | None = None) -> FormatError:
        line = toks[min(at if at is not None else pos, len(toks) - 1)][1] if toks else 0
        return FormatError(f"{path}: line {line}: {msg}")

    def take(expect: str | None = None) -> str:
        nonlocal pos
        if pos >= len(toks):
            raise err(f"unexpected end of file{'' if expect is None else f', expected {expect!r}'}")
        t = toks[pos][0]
        if expect is not None and t.upper() != expect.upper():
            raise err(f"expected {expect!r}, got {t!r}")
        pos += 1
        return t

    def number(what: str) -> float:
        t = take()
        try:
            v = float(t)
        except ValueError:
            raise err(f"{what}: expected a number, got {t!r}", pos - 1) from None
        if not math.isfinite(v):
            raise err(f"{what}: {t!r} is not finite", pos - 1)
        return v

    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    end_sites: list[tuple[int, np.ndarray]] = []

    def joint_body(parent: int) -> None:
        index = len(names)
        names.append(take())
        parents.append(parent)
        take("{")
        take("OFFSET")
        offsets.append([number(f"OFFSET of {names[index]!r}") for _ in range(3)])
        take("CHANNELS")
        nch = number(f"CHANNELS of {names[index]!r}")
        if nch != int(nch) or nch < 0:
            raise err(f"CHANNELS of {names[index]!r}: bad count {nch}", pos - 1)
        chans = tuple(take() for _ in range(int(nch)))
        for c in chans:
            if c.lower() not in _CHANNELS:
                raise err(f"joint {names[index]!r}: unknown channel {c!r}")
        channels.append(chans)
        while True:
            t = take().upper()
            if t == "JOINT":
                joint_body(index)
            elif t == "END":
                take("Site")
                take("{")
                take("OFFSET")
                end_sites.append((index, np.array([number("End Site OFFSET") for _ in range(3)])))
                take("}")
            elif t == "}":
                return
            else:
                raise err(f"expected JOINT, End Site or '}}', got {toks[pos - 1][0]!r}", pos - 1)

    take("HIERARCHY")
    while pos < len(toks) and toks[pos][0].upper() == "ROOT":
        take("ROOT")
        joint_body(-1)
    if not names:
        raise err("no ROOT joint")
    take("MOTION")
    take("Frames:")
    nframes = number("Frames")
    if nframes != int(nframes) or nframes < 0:
        raise err(f"bad frame count {nframes}", pos - 1)
    take("Frame")
    take("Time:")
    frame_time = number("Frame Time")
    if frame_time <= 0:
        raise err(f"Frame Time must be positive, got {frame_time}", pos - 1)
    nch = sum(len(c) for c in channels)
    values = toks[pos:]
    nframes = int(nframes)
    if len(values) != nframes * nch:
        raise err(f"MOTION has {len(values)} values, expected {nframes} frames x {nch} channels")
    try:
        frames = np.array([float(v) for v, _ in values], dtype=np.float64).reshape(nframes, nch)
    except ValueError:
        bad = next(i for i, (v, _) in enumerate(values) if not _is_float(v))
        raise err(f"frame {bad // max(nch, 1)}: expected a number, got {values[bad][0]!r}", pos + bad) from None
    if not np.isfinite(frames).all():
        t = int(np.argwhere(~np.isfinite(frames))[0, 0])
        raise err(f"frame {t} has a non-finite value", pos + t * nch)
    return Bvh(
        names=tuple(names),
        parents=tuple(parents),
        offsets=np.asarray(offsets, dtype=np.float64).reshape(-1, 3),
        channels=tuple(channels),
        end_sites=tuple(end_sites),
        frames=frames,
        frame_time=frame_time,
    )


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _axis_rotation(axis: int, angle: np.ndarray) -> np.ndarray:
    """(T, 3, 3) right-handed rotations by ``angle`` (radians) about coordinate axis 0/1/2."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    i, j = (axis + 1) % 3, (axis + 2) % 3
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def bvh_joint_positions(bvh: Bvh, *, with_rotations: bool = False):
    """Forward kinematics of a BVH: world positions (T, J, 3) of every joint, in the file's
    axes and units (and, with ``with_rotations``, the world rotations (T, J, 3, 3)).

    The published BVH rule: a joint's local transform is a translation by its OFFSET (plus
    its position channels, if any) and a rotation that is the product of its rotation
    channels' rotations in the order listed; ``world_j = world_parent @ local_j``.
    """
    T = bvh.frames.shape[0]
    J = len(bvh.names)
    pos = np.zeros((T, J, 3))
    rot = np.zeros((T, J, 3, 3))
    col = 0
    for j in range(J):
        R = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
        t = np.broadcast_to(bvh.offsets[j], (T, 3)).copy()
        for c in bvh.channels[j]:
            v = bvh.frames[:, col]
            col += 1
            axis = "xyz".index(c[0].lower())
            if c[1:].lower() == "position":
                t[:, axis] += v
            else:
                R = R @ _axis_rotation(axis, np.radians(v))
        p = bvh.parents[j]
        if p < 0:
            pos[:, j], rot[:, j] = t, R
        else:
            pos[:, j] = pos[:, p] + np.einsum("tij,tj->ti", rot[:, p], t)
            rot[:, j] = rot[:, p] @ R
    return (pos, rot) if with_rotations else pos
