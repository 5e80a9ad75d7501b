"""From a plan to joint angles: the realisation of a :class:`~.plan.Plan` as a :class:`Motion`.

:func:`_realize` samples the plan's segment tracks, fixes the pelvis height (a ``g``
parabola in every flight, C1 joins), solves the horizontal centre of mass with a
least-squares "dynamics filter" (:func:`_com_filter`: the zero-moment point of a linear
inverted pendulum on the loaded feet, ballistic in flight), places the feet
(:func:`_foot_targets`, :func:`_rel_swings`), keeps the ankles within reach, and solves the
legs (:func:`~.character._solve_all`), iterating with heel-raise and swing-lift feedback.
:func:`motion_report` / :func:`check_motion` measure and enforce the kinematic quality.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.ndimage import gaussian_filter1d

from jmocap.constants import GRAVITY
from jmocap.data.synthetic.character import Character, _solve_all, site_trajectories
from jmocap.data.synthetic.curves import (
    _bump,
    _ease,
    _interp_rows,
    _runs,
    _smooth_upper,
    _smoothstep,
    _Track,
)
from jmocap.data.synthetic.errors import GenerationError
from jmocap.data.synthetic.plan import MOTION_KINDS, Plan, Stance
from jmocap.data.synthetic.rotations import (
    _continuous_quats,
    _mat2quat,
    _rx,
    _ry,
    _rz,
    _slerp_R,
)
from jmocap.scene import Scene, height_above


@dataclass
class Motion:
    """A kinematic motion: joint angles and its plan-level annotations (frame-aligned)."""

    q: np.ndarray  # (T, nq)
    fps: float
    planted: np.ndarray  # (T, 4) bool: planned contact of each contact site (CONTACT_SITES order)
    flight: np.ndarray  # (T,) bool: no foot on the floor
    kind: np.ndarray  # (T,) int index into MOTION_KINDS (the segment kind of each frame)
    character: Character
    com: np.ndarray  # (T, 3) whole-body centre of mass
    zmp_ref: np.ndarray  # (T, 2) planned zero-moment point (NaN in flight)
    info: dict = field(default_factory=dict)
    scene: Scene | None = None  # the terrain (:mod:`~.terrain`); None: the flat floor

    @property
    def num_frames(self) -> int:
        return int(self.q.shape[0])

    def slice(self, a: int, b: int) -> Motion:
        return dataclasses.replace(
            self, q=self.q[a:b], planted=self.planted[a:b], flight=self.flight[a:b],
            kind=self.kind[a:b], com=self.com[a:b], zmp_ref=self.zmp_ref[a:b],
        )


def on_surface(s: Stance, R: np.ndarray, p: np.ndarray):
    """A foot pose (``R`` (..., 3, 3), ``p`` (..., 3)) planted on level ground at the stance's
    ground frame, moved onto the stance's surface: raised by ``s.h`` and, on a ramp, turned by
    ``s.tilt`` about the ground frame's origin at that height. ``p`` is changed in place."""
    p[..., 2] += s.h
    if s.tilt is None:
        return R, p
    pivot = np.array([s.G[0], s.G[1], s.h])
    return s.tilt @ R, pivot + (p - pivot) @ s.tilt.T


def _flights(plan: Plan, t_end: float):
    """Continuous-time intervals with no foot on the floor."""
    iv = sorted((s.t_on, s.t_off) for f in (0, 1) for s in plan.stances[f])
    out = []
    cur_end = -math.inf
    for a, b in iv:
        if a > cur_end and cur_end > -math.inf:
            out.append((cur_end, a))
        cur_end = max(cur_end, b)
    if cur_end < t_end:
        raise GenerationError("plan ends with a foot in the air")
    return out


def _seg_eval(plan: Plan, t: float, key: str) -> float:
    for seg in plan.segments:
        if seg.t0 <= t <= seg.t1:
            return float(np.asarray(seg.fn(np.array([t]))[key])[0])
    raise GenerationError(f"no segment covers t = {t}")


def _z_profile(plan: Plan, t: np.ndarray, z_des: np.ndarray, flights, ground: np.ndarray) -> np.ndarray:
    """Pelvis height: the segments' desired height (``z_des``, raised by the terrain height
    under the support ``ground`` (T,)), a g-parabola in every flight, and C1 corrections of the
    support phases next to a flight."""
    z = z_des.copy()
    eps = 1e-4

    def zf(tq):
        return _seg_eval(plan, tq, "z") + float(np.interp(tq, t, ground))

    bc = []  # (time, dv, side) velocity mismatches to fix at support-interval ends
    for a, b in flights:
        z0, z1 = zf(a), zf(b)
        Tf = b - a
        v0 = (z1 - z0) / Tf + GRAVITY * Tf / 2
        v1 = v0 - GRAVITY * Tf
        m = (t > a) & (t < b)
        u = t[m] - a
        z[m] = z0 + v0 * u - 0.5 * GRAVITY * u * u
        d_before = (zf(a) - zf(a - eps)) / eps
        d_after = (zf(b + eps) - zf(b)) / eps
        bc.append((a, v0 - d_before, "end"))
        bc.append((b, v1 - d_after, "start"))
    # support intervals
    edges = [0.0] + [x for ab in flights for x in ab] + [max(t[-1], plan.t)]
    for s0, s1 in zip(edges[0::2], edges[1::2], strict=True):
        dv0 = next((dv for tt, dv, side in bc if side == "start" and abs(tt - s0) < 1e-9), 0.0)
        dv1 = next((dv for tt, dv, side in bc if side == "end" and abs(tt - s1) < 1e-9), 0.0)
        if dv0 == 0.0 and dv1 == 0.0:
            continue
        m = (t >= s0) & (t <= s1)
        tt = t[m]
        L = s1 - s0
        if L < 0.5:
            u = (tt - s0) / L
            z[m] += (u**3 - 2 * u**2 + u) * dv0 * L + (u**3 - u**2) * dv1 * L
        else:
            w = 0.25
            z[m] += dv0 * (tt - s0) * (1.0 - _ease(tt, s0, s0 + w))
            z[m] += dv1 * (tt - s1) * _ease(tt, s1 - w, s1)
    return z


def _load_share(plan: Plan, t, st_idx):
    """Share of the body weight on the left foot (NaN while no foot is loaded)."""
    N = len(t)
    loaded = np.zeros((2, N), bool)
    for f in (0, 1):
        for j, s in enumerate(plan.stances[f]):
            if s.load:
                loaded[f] |= st_idx[f] == j
    lam = np.full(N, np.nan)
    lam[loaded[0] & ~loaded[1]] = 1.0
    lam[~loaded[0] & loaded[1]] = 0.0
    pins = sorted(plan.lam_pins)
    r = 0.3
    for k0, k1 in _runs(loaded[0] & loaded[1]):
        a = t[k0 - 1] if k0 > 0 else t[k0]
        b = t[k1] if k1 < N else t[k1 - 1]
        va = lam[k0 - 1] if k0 > 0 and not np.isnan(lam[k0 - 1]) else 0.5
        vb = lam[k1] if k1 < N and not np.isnan(lam[k1]) else 0.5
        inner = [(pt, pv) for pt, pv in pins if a < pt < b]
        knots = [(a, va)] + inner + [(b, vb)]
        if not inner and b - a > 2 * r:
            knots = [(a, va), (a + r, 0.5), (b - r, 0.5), (b, vb)]
        lam[k0:k1] = _Track(knots)(t[k0:k1])
    return lam, loaded


def _com_filter(p_ref, support, z_com, intent, fps, c_start, c_end, ground):
    """Horizontal COM trajectory (T, 2): its zero-moment point follows ``p_ref`` on support
    frames (linear inverted pendulum with the given COM height above the support's surface,
    ``z_com - ground``), ``c'' = 0`` in flight, least squares with small jerk and intent terms,
    at rest at both ends."""
    N = len(p_ref)
    dt = 1.0 / fps
    zdd = np.zeros(N)
    zdd[1:-1] = (z_com[:-2] - 2 * z_com[1:-1] + z_com[2:]) / dt**2
    beta = (z_com - ground) / np.maximum(zdd + GRAVITY, 0.5)
    rows, cols, vals = [], [], []
    rhs = []
    r = 0

    def add(cs, vs, b):
        nonlocal r
        rows.extend([r] * len(cs))
        cols.extend(cs)
        vals.extend(vs)
        rhs.append(b)
        r += 1

    w_z, w_f, w_j, w_i, w_b = 1.0, 1.0 * dt**2, 2e-3 * dt**3, 0.03, 100.0
    for k in range(1, N - 1):
        if support[k] and not np.isnan(p_ref[k, 0]):
            bk = beta[k] / dt**2
            add([k - 1, k, k + 1], [-w_z * bk, w_z * (1 + 2 * bk), -w_z * bk], w_z * p_ref[k])
        else:
            add([k - 1, k, k + 1], [w_f / dt**2, -2 * w_f / dt**2, w_f / dt**2], np.zeros(2))
    for k in range(1, N - 2):
        add([k - 1, k, k + 1, k + 2], [-w_j / dt**3, 3 * w_j / dt**3, -3 * w_j / dt**3, w_j / dt**3],
            np.zeros(2))
    for k in range(N):
        add([k], [w_i], w_i * intent[k])
    add([0], [w_b], w_b * c_start)
    add([N - 1], [w_b], w_b * c_end)
    if N > 2:
        add([0, 1], [-w_b / dt, w_b / dt], np.zeros(2))
        add([N - 2, N - 1], [-w_b / dt, w_b / dt], np.zeros(2))
    A = sp.csr_matrix((vals, (rows, cols)), shape=(r, N))
    B = np.array(rhs)
    AtA = (A.T @ A).tocsc()
    return np.column_stack([spla.spsolve(AtA, A.T @ B[:, i]) for i in range(2)])


def _foot_targets(plan: Plan, t, st_idx, fb, lift):
    """Ankle targets of every stance and world-frame swing frame, with the extra heel raise
    ``fb`` (2, T) added to the planned rocker angles. Returns (R_t, p_t, toe_t, planted,
    P_zmp, rel_swings)."""
    ch = plan.ch
    N = len(t)
    R_t = np.tile(np.eye(3), (2, N, 1, 1))
    p_t = np.zeros((2, N, 3))
    toe_t = np.zeros((2, N))
    planted = np.zeros((N, 4), bool)
    P_zmp = np.zeros((2, N, 2))

    phi_max = min(1.1, -min(ch.lower[L.toe_qadr] for L in ch.legs) - 0.05)

    def phi_of(f, s, tq):
        return np.clip(s.phi_at(tq) + np.interp(tq, t, fb[f]), -0.6, phi_max)

    for f in (0, 1):
        for j, s in enumerate(plan.stances[f]):
            m = st_idx[f] == j
            if not m.any():
                continue
            ph = phi_of(f, s, t[m])
            R, p, toe = ch.stance_pose(f, s.G, ph)
            R, p = on_surface(s, R, p)
            R_t[f, m], p_t[f, m], toe_t[f, m] = R, p, toe
            planted[m, 2 * f] = ph <= 0
            planted[m, 2 * f + 1] = ph >= 0
            pts = ch.contact_points_G(f, s.G)
            a = s.alpha_at(t[m])
            a = np.where(ph > 0.02, np.maximum(a, np.clip(ph / 0.1, 0, 1)), a)
            P_zmp[f, m] = (pts[0, :2] + a[:, None] * (pts[1, :2] - pts[0, :2]))
    rel = []
    for f in (0, 1):
        S = plan.stances[f]
        for j in range(len(S) - 1):
            a, b = S[j], S[j + 1]
            if a.swing.get("mode", "world") != "world":
                rel.append((f, j))
                continue
            m = (t > a.t_off) & (t < b.t_on) & (st_idx[f] < 0)
            if not m.any():
                continue
            R0, p0, k0 = ch.stance_pose(f, a.G, phi_of(f, a, np.array(a.t_off)))
            R1, p1, k1 = ch.stance_pose(f, b.G, phi_of(f, b, np.array(b.t_on)))
            R0, p0 = on_surface(a, R0, p0)
            R1, p1 = on_surface(b, R1, p1)
            s = (t[m] - a.t_off) / (b.t_on - a.t_off)
            h = _smoothstep(s)
            p = p0 + h[:, None] * (p1 - p0)
            p[:, 2] += _step_profile(s, b.h - a.h) - h * (b.h - a.h)
            p[:, 2] += a.swing.get("clear", 0.05) * _bump(s)
            R = _slerp_R(np.broadcast_to(R0, (len(s), 3, 3)), np.broadcast_to(R1, (len(s), 3, 3)), h)
            toe = k0 + _smoothstep(s / 0.5) * (k1 - k0)
            minz = height_above(plan.swing_scene, ch.foot_points(f, R, p, toe)).min(axis=-1)
            p[:, 2] += np.maximum(0.0, 0.002 * _bump(s) - minz) + lift[f, m]
            R_t[f, m], p_t[f, m], toe_t[f, m] = R, p, toe
    return R_t, p_t, toe_t, planted, P_zmp, rel


def _step_profile(s: np.ndarray, dh: float) -> np.ndarray:
    """A swing's change of surface height ``dh`` over its phase ``s`` in [0, 1]: up early (done
    by 60 % of the swing, before the foot is over the higher surface's edge), down late (from
    40 %)."""
    if dh > 0:
        return dh * _smoothstep(np.clip(s / 0.6, 0.0, 1.0))
    if dh < 0:
        return dh * _smoothstep(np.clip((s - 0.4) / 0.6, 0.0, 1.0))
    return np.zeros_like(s)


def _support_height(plan: Plan, t, st_idx, lam, fps) -> np.ndarray:
    """The terrain height under the support (T,): the stance heights weighted by the load share,
    interpolated through flights and smoothed over 0.15 s (the pelvis rises with the weight
    transfer onto a higher step, not at the footfall). Zero on the flat floor."""
    N = len(t)
    if plan.scene is None:
        return np.zeros(N)
    hs = np.zeros((2, N))
    for f in (0, 1):
        for j, s in enumerate(plan.stances[f]):
            hs[f, st_idx[f] == j] = s.h
    g = np.where(np.isnan(lam), np.nan, np.nan_to_num(lam) * hs[0] + (1 - np.nan_to_num(lam)) * hs[1])
    ok = ~np.isnan(g)
    g = np.interp(t, t[ok], g[ok])
    return gaussian_filter1d(g, sigma=0.15 * fps, mode="nearest")


def _realize(plan: Plan, fps: float, n_pass: int = 8) -> Motion:
    ch = plan.ch
    T_end = plan.t
    N = int(math.floor(T_end * fps + 1e-9)) + 1
    t = np.arange(N) / fps
    names = plan.upper_names
    nu = len(names)
    upper_qadr = np.array([ch.qadr[n] for n in names])

    # ---- segment tracks ----
    z_des = np.zeros(N)
    yaw = np.zeros(N)
    pitch = np.zeros(N)
    roll = np.zeros(N)
    upper = np.zeros((N, nu))
    kind = np.zeros(N, int)
    for i, seg in enumerate(plan.segments):
        last = i == len(plan.segments) - 1
        m = (t >= seg.t0) & ((t < seg.t1) if not last else (t <= seg.t1 + 1e-9))
        if not m.any():
            continue
        out = seg.fn(t[m])
        z_des[m] = out["z"]
        yaw[m] = out["yaw"]
        pitch[m] = out.get("pitch", 0.0)
        roll[m] = out.get("roll", 0.0)
        upper[m] = out["upper"]
        kind[m] = MOTION_KINDS.index(seg.kind)
    yaw = np.unwrap(yaw)
    upper = np.clip(upper, ch.lower[upper_qadr], ch.upper[upper_qadr])
    R_pel = _rz(yaw) @ _ry(pitch) @ _rx(roll)

    # ---- stances, flights, pelvis height ----
    st_idx = -np.ones((2, N), int)
    for f in (0, 1):
        for j, s in enumerate(plan.stances[f]):
            st_idx[f, (t >= s.t_on - 1e-9) & (t <= s.t_off + 1e-9)] = j
    flights = _flights(plan, T_end)
    flight = (st_idx[0] < 0) & (st_idx[1] < 0)
    lam, loaded = _load_share(plan, t, st_idx)
    support = ~np.isnan(lam)
    ground = _support_height(plan, t, st_idx, lam, fps)
    z0 = _z_profile(plan, t, z_des + ground, flights, ground)

    q = np.tile(ch.q_stand, (N, 1))
    q[:, upper_qadr] = upper
    q[:, 3:7] = _continuous_quats(_mat2quat(R_pel))
    off = np.einsum("tij,j->ti", R_pel, ch.com0)
    fb = np.zeros((2, N))  # extra heel raise where the ankle cannot dorsiflex enough
    lift = np.zeros((2, N))  # extra swing-foot lift where the solved foot dips below the floor
    swing_w = np.zeros((2, N))  # 0 at the ends of each swing, 1 inside
    for f in (0, 1):
        for a, b in _runs(st_idx[f] < 0):
            ta, tb = (t[a - 1] if a > 0 else t[a]), (t[b] if b < N else t[b - 1])
            u = (t[a:b] - ta) / max(tb - ta, 1e-9)
            swing_w[f, a:b] = _smoothstep(u / 0.2) * _smoothstep((1 - u) / 0.2)
    relaxed = ch.lower.copy()
    for L in ch.legs:
        relaxed[L.ik_qadr[4]] = -1.2  # ankle_y (dorsiflexion) relaxed while measuring the need
    info = {"flights": flights}
    intent = None
    for it in range(n_pass):
        R_t, p_t, toe_t, planted, P_zmp, rel = _foot_targets(plan, t, st_idx, fb, lift)
        world = np.ones((2, N), bool)  # legs with world-frame targets (stances and world swings)
        for f, j in rel:
            S_ = plan.stances[f]
            world[f] &= ~((t > S_[j].t_off) & (t < S_[j + 1].t_on))
        world |= st_idx >= 0
        p_ref = np.full((N, 2), np.nan)
        p_ref[support] = (lam[support, None] * P_zmp[0, support]
                          + (1 - lam[support, None]) * P_zmp[1, support])
        if intent is None:
            intent = p_ref.copy()
            for i in range(2):
                ok = ~np.isnan(intent[:, i])
                intent[:, i] = np.interp(t, t[ok], intent[ok, i])
            intent = gaussian_filter1d(intent, sigma=0.25 * fps, axis=0, mode="nearest")
        z_com = z0 + off[:, 2]
        c = _com_filter(p_ref, support, z_com, intent, fps, intent[0], intent[-1], ground)
        pel = np.column_stack([c - off[:, :2], z0])
        _rel_swings(plan, ch, t, pel, yaw, rel, st_idx, R_t, p_t, toe_t, lift)
        dz = _reach_fix(ch, pel, R_pel, p_t, world, flights, t, fps)
        pel[:, 2] = _limit_fall(t, pel[:, 2] - dz, flights, 0.6 * GRAVITY)
        _rel_swings(plan, ch, t, pel, yaw, rel, st_idx, R_t, p_t, toe_t, lift)
        for f, L in enumerate(ch.legs):
            q[:, L.toe_qadr] = toe_t[f]
        q[:, 0:3] = pel
        com, err = _solve_all(ch, q, R_t, p_t, planted, first=(it == 0), lower=relaxed)
        # feedback: heel raise where the ankle would dorsiflex beyond its range, swing-foot lift
        # where the solved foot dips below the floor
        clean = True
        for f, L in enumerate(ch.legs):
            a = L.ik_qadr[4]
            excess = np.maximum(ch.lower[a] + 0.02 - q[:, a], 0.0)
            excess[st_idx[f] < 0] = 0.0
            if np.any(q[:, a] < ch.lower[a] - 1e-9):
                clean = False
            if np.any(excess > 0):
                fb[f] += 1.5 * _smooth_upper(excess, fps)
            R_a, p_a, _ = ch.leg_fk(f, R_pel, q[:, 0:3], q[:, L.ik_qadr])
            minz = height_above(plan.swing_scene, ch.foot_points(f, R_a, p_a, q[:, L.toe_qadr])).min(axis=-1)
            need = np.where(st_idx[f] < 0, np.maximum(0.004 - minz, 0.0), 0.0)
            if np.any(np.where(st_idx[f] < 0, minz, 1.0) < 0.0):
                clean = False
            if np.any(need > 0):
                lift[f] += _smooth_upper(need, fps, 0.08) * swing_w[f]
        new_off = com - pel
        info["com_change"] = float(np.max(np.abs(new_off[:, :2] - off[:, :2])))
        off = new_off
        info["ik_err"] = err
        info["passes"] = it + 1
        if clean and it >= 2:
            break
        if it >= 3 and err > 0.01:
            raise GenerationError(f"leg IK cannot place the planted feet (residual {err:.3f} m)")
    for L in ch.legs:
        q[:, L.ik_qadr] = np.clip(q[:, L.ik_qadr], ch.lower[L.ik_qadr], ch.upper[L.ik_qadr])
    info["zmp_com"] = c
    info["heel_raise_fb"] = float(fb.max())
    info["swing_lift_fb"] = float(lift.max())
    return Motion(q=q, fps=fps, planted=planted, flight=flight, kind=kind, character=ch,
                  com=com, zmp_ref=p_ref, info=info, scene=plan.scene)


def _rel_swings(plan, ch, t, pel, yaw, swings, st_idx, R_t, p_t, toe_t, lift):
    for f, j in swings:
        S = plan.stances[f]
        a, b = S[j], S[j + 1]
        m = (t > a.t_off) & (t < b.t_on) & (st_idx[f] < 0)
        if not m.any():
            continue
        sw = a.swing

        def H(tq):
            pp = _interp_rows(t, np.atleast_1d(tq), pel)
            yy = np.interp(np.atleast_1d(tq), t, yaw)
            return _rz(yy), pp

        R0, p0, k0 = ch.stance_pose(f, a.G, a.phi_at(a.t_off))
        R1, p1, k1 = ch.stance_pose(f, b.G, b.phi_at(b.t_on))
        R0, p0 = on_surface(a, R0, p0)
        R1, p1 = on_surface(b, R1, p1)
        HR0, Hp0 = H(a.t_off)
        HR1, Hp1 = H(b.t_on)
        rel0 = (HR0[0].T @ R0, HR0[0].T @ (p0 - Hp0[0]), k0)
        rel1 = (HR1[0].T @ R1, HR1[0].T @ (p1 - Hp1[0]), k1)
        keys = [(0.0, rel0)] + [(k["s"], (k["R"], k["p"], k["toe"])) for k in sw.get("keys", [])] + [(1.0, rel1)]
        s = (t[m] - a.t_off) / (b.t_on - a.t_off)
        Rr = np.zeros((len(s), 3, 3))
        pr = np.zeros((len(s), 3))
        kr = np.zeros(len(s))
        for (sa, (Ra, pa, ka)), (sb, (Rb, pb, kb)) in zip(keys[:-1], keys[1:], strict=True):
            mm = (s >= sa) & (s <= sb)
            if not mm.any():
                continue
            h = _smoothstep((s[mm] - sa) / (sb - sa))
            Rr[mm] = _slerp_R(np.broadcast_to(Ra, (mm.sum(), 3, 3)), np.broadcast_to(Rb, (mm.sum(), 3, 3)), h)
            pr[mm] = pa + h[:, None] * (pb - pa)
            kr[mm] = ka + h * (kb - ka)
        pr[:, 2] += sw.get("tuck", 0.0) * _bump(s)
        HR, Hp = H(t[m])
        R = HR @ Rr
        p = Hp + np.einsum("tij,tj->ti", HR, pr)
        minz = height_above(plan.swing_scene, ch.foot_points(f, R, p, kr)).min(axis=-1)
        p[:, 2] += np.maximum(0.0, 0.002 * _bump(s) - minz) + lift[f, m]
        R_t[f, m], p_t[f, m], toe_t[f, m] = R, p, kr


def _reach_fix(ch, pel, R_pel, p_t, world, flights, t, fps):
    """How much to lower the pelvis (T,) so both ankles are within 99.5% of the leg length;
    smooth, >= the need at every frame, and affine (parabola-preserving) inside flights."""
    r = 0.995 * ch.reach
    need = np.zeros(len(t))
    for f, L in enumerate(ch.legs):
        hip = pel + np.einsum("tij,j->ti", R_pel, L.hip_offset)
        v = hip - p_t[f]
        h2 = v[:, 0] ** 2 + v[:, 1] ** 2
        dist = np.sqrt(h2 + v[:, 2] ** 2)
        bad = (dist > r) & world[f]
        if np.any(bad & (h2 >= r * r)):
            raise GenerationError("a foot target is out of reach horizontally")
        nd = np.where(bad, v[:, 2] - np.sqrt(np.maximum(r * r - h2, 0.0)), 0.0)
        need = np.maximum(need, nd)
    if not np.any(need > 0):
        return need
    for a, b in flights:  # a flight's need moves to its ends (the correction is affine inside)
        m = (t > a) & (t < b)
        if m.any() and need[m].max() > 0:
            top = need[m].max()
            need[m] = 0.0
            ia = int(np.nonzero(t <= a)[0][-1]) if np.any(t <= a) else 0
            ib = int(np.nonzero(t >= b)[0][0]) if np.any(t >= b) else len(t) - 1
            need[ia] = max(need[ia], top)
            need[ib] = max(need[ib], top)
    S = _smooth_upper(need, fps, 0.06)
    for a, b in flights:
        m = (t > a) & (t < b)
        if m.any():
            ia = max(np.nonzero(t <= a)[0][-1], 0) if np.any(t <= a) else 0
            ib = np.nonzero(t >= b)[0][0] if np.any(t >= b) else len(t) - 1
            S[m] = np.interp(t[m], [t[ia], t[ib]], [S[ia], S[ib]])
    return S


def _semiconvex_minorant(t, z, a):
    """The largest function <= z (sampled at t) whose second derivative is >= -a: the lower
    convex hull of z + a t^2 / 2, minus a t^2 / 2. Keeps a height profile from accelerating
    downwards faster than ``a`` (the floor can push, not pull)."""
    y = z + 0.5 * a * t * t
    hull = []
    for i in range(len(t)):
        while len(hull) >= 2:
            i0, i1 = hull[-2], hull[-1]
            # drop i1 if it lies above the segment i0 -> i
            if (y[i1] - y[i0]) * (t[i] - t[i0]) >= (y[i] - y[i0]) * (t[i1] - t[i0]):
                hull.pop()
            else:
                break
        hull.append(i)
    yh = np.interp(t, t[hull], y[hull])
    return yh - 0.5 * a * t * t


def _limit_fall(t, z, flights, a):
    """Apply :func:`_semiconvex_minorant` on every support interval (flights stay ballistic)."""
    z = z.copy()
    edges = [t[0] - 1.0] + [x for ab in flights for x in ab] + [t[-1] + 1.0]
    for s0, s1 in zip(edges[0::2], edges[1::2], strict=True):
        m = np.nonzero((t >= s0) & (t <= s1))[0]
        if len(m) > 2:
            z[m] = _semiconvex_minorant(t[m], z[m], a)
    return z


def motion_report(m: Motion) -> dict:
    """Kinematic quality numbers of a motion (what :func:`check_motion` bounds)."""
    ch = m.character
    q = m.q
    hinge = np.arange(7, ch.nq)
    viol = np.maximum(q[:, hinge] - ch.upper[hinge], 0) + np.maximum(ch.lower[hinge] - q[:, hinge], 0)
    pos = site_trajectories(ch, q, ch.check_sites)
    csite = pos[:, -4:]  # check_sites ends with the four contact sites
    drift = 0.0
    for i in range(4):
        for a, b in _runs(m.planted[:, i]):
            drift = max(drift, float(np.max(np.abs(csite[a:b, i] - csite[a, i]))))
    return dict(
        limit_violation=float(viol.max()) if viol.size else 0.0,
        min_height=float(height_above(m.scene, pos).min()),
        planted_drift=drift,
        ik_err=float(m.info.get("ik_err", 0.0)),
        root_speed_max=float(np.max(np.linalg.norm(np.diff(q[:, :3], axis=0), axis=1)) * m.fps) if len(q) > 1 else 0.0,
    )


def check_motion(m: Motion) -> dict:
    """Raise :class:`GenerationError` unless the motion is kinematically clean."""
    r = motion_report(m)
    if r["limit_violation"] > 1e-9:
        raise GenerationError(f"joint limit violated by {r['limit_violation']:.2e} rad")
    if r["min_height"] < -1e-6:
        raise GenerationError(f"floor penetration {r['min_height']:.2e} m" if m.scene is None
                              else f"terrain penetration {r['min_height']:.2e} m")
    if r["planted_drift"] > 1e-4:
        raise GenerationError(f"planted foot moved {r['planted_drift']:.2e} m")
    return r
