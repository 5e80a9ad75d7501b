"""MuJoCo C simulation of a character: the model set up for simulation, PD servos on its hinges,
and the feet's contact forces read out at the four contact sites.

Shared by the synthetic ground truth (:mod:`jmocap.data.synthetic.physics` and its sampling
controller) and the ``mocon`` method (:mod:`jmocap.methods.mocon`), so that both simulate the
same character with the same contact model and report forces the same way:

* :func:`simulation_model` -- timestep, ``implicitfast``, jmocap's friction pyramid, contact
  stiffness; :func:`add_servos` -- a position servo on every hinge, its gains from the standing
  pose's joint-space inertia (a critically damped second-order response at ``freq_hz``);
* :func:`foot_contacts`, :func:`contact_forces`, :func:`record_foot_forces` -- the foot-ground
  contacts of a step (the ground: every geom of the world body, floor and terrain boxes), their
  world-frame forces, split between each foot's heel and toe sites (:func:`floor_split`);
* :func:`tent_average` -- frame values of substep values that match central differences of the
  frame positions (Newton's law at the frames).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import mujoco
import numpy as np

from jmocap.constants import FRICTION_CONE, FRICTION_MU


def simulation_model(mj: mujoco.MjModel, dt: float, contact_timeconst: float) -> mujoco.MjModel:
    """A copy of ``mj`` set up for the tracking simulation: timestep ``dt``, ``implicitfast``,
    jmocap's one friction model (``FRICTION_MU``, pyramidal cone) on every geom, no passive
    damping, contact time constant ``contact_timeconst`` (stiffer than MuJoCo's 0.02 s)."""
    if FRICTION_CONE != "pyramidal":
        raise ValueError(f"unsupported friction cone {FRICTION_CONE!r}")
    mj = copy.deepcopy(mj)
    mj.opt.timestep = dt
    mj.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    mj.opt.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
    mj.geom_friction[:, 0] = FRICTION_MU
    mj.dof_damping[:] = 0.0
    mj.geom_solref[:, 0] = max(contact_timeconst, 2 * dt)
    mj.geom_solref[:, 1] = 1.0
    return mj



def tent_weights(n: int) -> np.ndarray:
    """Weights (2n - 1,) of substeps ``kn - n + 1 .. kn + n - 1`` in frame k's value.

    With MuJoCo's semi-implicit step (``v' = v + h a``, ``x' = x + h v'``) the central second
    difference of the positions at substeps ``(k-1)n, kn, (k+1)n`` is exactly
    ``sum_m (n - |m|) a[kn + m] / n^2`` (``a[s]``: the acceleration of step s); so a force
    sampled with these weights is the one Newton's law gives from central differences of the
    frame positions."""
    m = np.arange(-n + 1, n)
    return (n - np.abs(m)) / float(n * n)


def tent_average(x: np.ndarray, n: int) -> np.ndarray:
    """Frame values (T, ...) of substep values (T n, ...) by :func:`tent_weights`; frame 0 (no
    substeps before it) is the renormalised half tent."""
    T = len(x) // n
    w = tent_weights(n)
    out = np.zeros((T,) + x.shape[1:])
    for j, m in enumerate(range(-n + 1, n)):
        idx = np.arange(T) * n + m
        ok = (idx >= 0) & (idx < len(x))
        out[ok] += w[j] * x[idx[ok]]
    if T:
        out[0] /= w[n - 1:].sum()
    return out


def lever_split(points: np.ndarray, forces: np.ndarray, heel: np.ndarray, toe: np.ndarray) -> np.ndarray:
    """Split contact forces (k, 3) at points (k, 3) between a foot's heel and toe sites (3,):
    the lever rule along the heel-toe axis (clipped to the segment). Returns (2, 3): heel, toe.

    Each share is a non-negative multiple of its force (so stays in the friction cone); the sum
    is the foot's force, and its moment is kept except for the contacts' offsets across the
    heel-toe axis and beyond its ends."""
    axis = toe - heel
    s = np.clip((points - heel) @ axis / max(float(axis @ axis), 1e-12), 0.0, 1.0)
    return np.stack([((1 - s)[:, None] * forces).sum(0), (s[:, None] * forces).sum(0)])


def floor_split(points: np.ndarray, forces: np.ndarray, heel: np.ndarray, toe: np.ndarray,
                floor_m: float, heights: np.ndarray | None = None) -> np.ndarray:
    """Split contact forces (k, 3) at points (k, 3) between a foot's heel and toe sites (3,) that
    are on the floor: :func:`lever_split` when both sites are within ``floor_m`` of the floor
    (z = 0), everything to the one that is when only one is, and to the lower site when neither
    is. Returns (2, 3): heel, toe.

    The foot's force is always kept; its moment as :func:`lever_split` keeps it when both sites
    are down. A raised site never takes a share: on the ball of the foot (heel up) the whole
    force goes to the toe site, where the lever rule would give the raised heel 5-15 % of it
    (a point in the air "in contact"). ``heights`` (2,): the sites' heights above the surface
    under them (terrain, :func:`jmocap.scene.height_above`); their ``z`` when None."""
    hh, ht = (heel[2], toe[2]) if heights is None else heights
    down = np.array([hh <= floor_m, ht <= floor_m])
    if down.all():
        return lever_split(points, forces, heel, toe)
    take = int(down[1]) if down.any() else int(ht < hh)  # 0 heel, 1 toe
    out = np.zeros((2, 3))
    out[take] = forces.sum(0)
    return out



@dataclass
class FootContacts:
    """The foot-floor contacts of the current state (MuJoCo's ``d.contact`` after ``mj_step1``)."""

    index: np.ndarray  # (k,) indices into d.contact
    foot: np.ndarray  # (k,) 0 left, 1 right
    body: np.ndarray  # (k,) body id of the foot geom
    pos: np.ndarray  # (k, 3) contact points
    sign: np.ndarray  # (k,) +1 when geom2 is the foot (the force MuJoCo reports acts on geom2)


def foot_contacts(d, is_floor, geom_foot, geom_body) -> tuple[FootContacts, int]:
    """Foot-floor contacts and the number of other floor contacts."""
    nc = d.ncon
    g1 = d.contact.geom1[:nc]
    g2 = d.contact.geom2[:nc]
    f1, f2 = is_floor[g1], is_floor[g2]
    other = np.where(f1, g2, g1)
    on_floor = f1 | f2
    foot = geom_foot[other]
    use = on_floor & (foot >= 0)
    idx = np.nonzero(use)[0]
    return FootContacts(index=idx, foot=foot[idx], body=geom_body[other[idx]],
                     pos=d.contact.pos[:nc][idx].copy(),
                     sign=np.where(f1[idx], 1.0, -1.0)), int(np.sum(on_floor & (foot < 0)))


def contact_forces(mj, d, con: FootContacts) -> np.ndarray:
    """World-frame forces (k, 3) on the feet of the contacts ``con`` (after the step)."""
    out = np.zeros((len(con.index), 3))
    f6 = np.zeros(6)
    for i, c in enumerate(con.index):
        mujoco.mj_contactForce(mj, d, int(c), f6)
        out[i] = con.sign[i] * (d.contact.frame[c].reshape(3, 3).T @ f6[:3])
    return out



def substep_records(S: int, nv: int) -> dict:
    """Zeroed per-substep records of a simulation (:func:`frames_from_substeps`'s ``sub``):
    ``tau`` (S, nv), ``grf`` (S, 4, 3), ``foot`` (S, 2, 3), ``moment`` (S, 2, 3), ``mid`` (S, 2, 3)
    and ``rescue`` (S,) bool."""
    return dict(tau=np.zeros((S, nv)), grf=np.zeros((S, 4, 3)), foot=np.zeros((S, 2, 3)),
                moment=np.zeros((S, 2, 3)), mid=np.zeros((S, 2, 3)), rescue=np.zeros(S, bool))


def record_foot_forces(mj, d, con: FootContacts, sites_xpos: np.ndarray, sub: dict, s: int, floor_m: float,
                       site_h: np.ndarray | None = None) -> None:
    """Substep ``s``'s foot forces into ``sub`` (:func:`substep_records`), after ``mj_step2``: each
    foot's contact forces split between its heel and toe sites on the floor (:func:`floor_split`;
    ``sites_xpos`` (4, 3) the sites at ``mj_step1``, ``site_h`` (4,) their heights above the
    terrain, their ``z`` when None), its total force, its moment about the world origin and its
    heel-toe midpoint. A foot without contacts gets zeros."""
    fw = contact_forces(mj, d, con)
    for f in range(2):
        on = con.foot == f
        heel, toe = sites_xpos[2 * f], sites_xpos[2 * f + 1]
        sub["mid"][s, f] = (heel + toe) / 2
        if on.any():
            hts = None if site_h is None else site_h[2 * f: 2 * f + 2]
            sub["grf"][s, 2 * f: 2 * f + 2] = floor_split(con.pos[on], fw[on], heel, toe, floor_m, hts)
            sub["foot"][s, f] = fw[on].sum(0)
            sub["moment"][s, f] = np.cross(con.pos[on], fw[on]).sum(0)
        else:
            sub["grf"][s, 2 * f: 2 * f + 2] = 0.0
            sub["foot"][s, f] = 0.0
            sub["moment"][s, f] = 0.0


def add_servos(spec: mujoco.MjSpec, base: mujoco.MjModel, q_stand: np.ndarray, freq_hz: float):
    """Add a position servo on every hinge of ``base`` to ``spec`` (the spec ``base`` was compiled
    from, or one with the same joints), compile it and copy ``base``'s simulation settings
    (:func:`simulation_model`) onto the result. Each servo's stiffness is ``I (2 pi f)^2`` and
    its damping ``2 I (2 pi f)``, ``I`` the hinge's diagonal entry of the joint-space inertia at
    ``q_stand``: every hinge alone responds as a critically damped oscillator at ``freq_hz``.
    Returns ``(model, kv)``, ``kv`` (nv,) each dof's servo damping (0 on the root)."""
    d = mujoco.MjData(base)
    d.qpos[:] = q_stand
    mujoco.mj_forward(base, d)
    M = np.zeros((base.nv, base.nv))
    mujoco.mj_fullM(base, d, M)
    w = 2 * math.pi * freq_hz
    kv = np.zeros(base.nv)
    for j in range(base.njnt):
        if base.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
            continue
        dof = int(base.jnt_dofadr[j])
        inertia = M[dof, dof]
        act = spec.add_actuator()
        act.name = "servo_" + mujoco.mj_id2name(base, mujoco.mjtObj.mjOBJ_JOINT, j)
        act.target = mujoco.mj_id2name(base, mujoco.mjtObj.mjOBJ_JOINT, j)
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.set_to_position(kp=inertia * w * w, kv=2 * inertia * w)
        act.ctrllimited = False
        act.forcelimited = False
        kv[dof] = 2 * inertia * w
    mj = spec.compile()
    if mj.nq != base.nq or mj.nv != base.nv or not np.allclose(mj.body_mass, base.body_mass) \
            or not np.allclose(mj.body_pos, base.body_pos) or not np.allclose(mj.geom_size, base.geom_size):
        raise ValueError("the servo model does not reproduce the character's model")
    mj.opt.timestep = base.opt.timestep
    mj.opt.integrator = base.opt.integrator
    mj.opt.cone = base.opt.cone
    mj.geom_friction[:] = base.geom_friction
    mj.dof_damping[:] = base.dof_damping
    mj.geom_solref[:] = base.geom_solref
    return mj, kv


def foot_geom_map(mj: mujoco.MjModel, feet: tuple[tuple[int, ...], tuple[int, ...]]):
    """``(ground, geom_foot, geom_body)`` (ngeom,): the ground (the floor plane and any terrain
    boxes: every geom of the world body), each geom's foot (0 left, 1 right, -1 none; ``feet``
    the body ids of each foot) and its body."""
    if not any(mj.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE for g in range(mj.ngeom)):
        raise ValueError("the model has no floor plane")
    ground = np.asarray(mj.geom_bodyid) == 0
    geom_foot = np.full(mj.ngeom, -1)
    for f, bodies in enumerate(feet):
        geom_foot[np.isin(mj.geom_bodyid, list(bodies))] = f
    return ground, geom_foot, np.array(mj.geom_bodyid)


def snapshot(mj: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """``d``'s ``mjSTATE_INTEGRATION`` state: what :func:`rewind` restores."""
    keep = np.zeros(mujoco.mj_stateSize(mj, mujoco.mjtState.mjSTATE_INTEGRATION))
    mujoco.mj_getState(mj, d, keep, mujoco.mjtState.mjSTATE_INTEGRATION)
    return keep


def tilt(quat_a: np.ndarray, quat_b: np.ndarray) -> float:
    """Angle (rad) between the body z axes of two orientations (wxyz quaternions)."""
    Ra, Rb = np.zeros(9), np.zeros(9)
    mujoco.mju_quat2Mat(Ra, quat_a / np.linalg.norm(quat_a))
    mujoco.mju_quat2Mat(Rb, quat_b / np.linalg.norm(quat_b))
    za, zb = Ra.reshape(3, 3)[:, 2], Rb.reshape(3, 3)[:, 2]
    return float(np.arccos(np.clip(za @ zb, -1.0, 1.0)))


def rewind(mj: mujoco.MjModel, d: mujoco.MjData, snapshots: dict[int, tuple[np.ndarray, np.ndarray]], k0: int,
           windows: int, window: int) -> tuple[int, np.ndarray]:
    """A sampling controller's backtrack: restore ``d`` to the latest snapshot at or before
    ``windows - 1`` windows (of ``window`` frames) before frame ``k0`` (``snapshots``: frame ->
    (:func:`snapshot`, the correction in force)). Returns that frame and its
    correction."""
    back = max(0, k0 - (windows - 1) * window)
    back = max(k for k in snapshots if k <= back)
    keep, prev = snapshots[back]
    mujoco.mj_setState(mj, d, keep, mujoco.mjtState.mjSTATE_INTEGRATION)
    return back, prev


__all__ = [
    "FootContacts",
    "add_servos",
    "contact_forces",
    "floor_split",
    "foot_contacts",
    "foot_geom_map",
    "lever_split",
    "record_foot_forces",
    "rewind",
    "simulation_model",
    "snapshot",
    "substep_records",
    "tent_average",
    "tent_weights",
    "tilt",
]
