"""The motion repertoire: per-clip style, gestures and the motion segments.

Each ``seg_*`` function appends one segment to a :class:`~.plan.Plan`, starting and ending
standing on both feet: standing with gestures, walking (forwards / backwards) and running with
turns and speed ramps, jumps, squats, lunges, kicks and dance-like stepping. :data:`SEGMENTS`
maps the motion kinds to them; :func:`generate_motion` plans a random sequence of segments
for a character and realises it (:func:`~.motion._realize`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from jmocap.constants import GRAVITY
from jmocap.data.synthetic.character import SIDES, Character, character
from jmocap.data.synthetic.curves import (
    _const,
    _hermite,
    _interp_extrap,
    _keys,
    _Piecewise,
    _ramp,
    _smoothstep,
    _window,
    _wrap,
)
from jmocap.data.synthetic.motion import Motion, _realize
from jmocap.data.synthetic.plan import Plan, Pose, _neutral, _upper_names
from jmocap.data.synthetic.rotations import _rx, _ry
from jmocap.data.synthetic.terrain import place_terrain


def _style(rng: np.random.Generator, ch: Character) -> dict:
    """Per-clip personal style: neutral posture, stance width, ..."""
    s = ch.scale
    return dict(
        arm_down=rng.uniform(1.30, 1.50),
        arm_fwd=rng.uniform(-0.05, 0.15),
        arm_twist=rng.uniform(-0.2, 0.2),
        elbow=rng.uniform(0.08, 0.35),
        spine_flex=rng.uniform(-0.04, 0.10),
        neck_flex=rng.uniform(-0.08, 0.12),
        width=rng.uniform(0.14, 0.22) * s,
        toe_out=rng.uniform(0.0, 0.18),
        alpha=rng.uniform(0.15, 0.4),
        z_rest_drop=rng.uniform(0.002, 0.008) * s,
        arm_swing=rng.uniform(0.6, 1.3),
    )


def _heading_of(feet) -> float:
    a, b = feet
    # mean facing of the two feet (toe-out cancels)
    return math.atan2(math.sin(a[2]) + math.sin(b[2]), math.cos(a[2]) + math.cos(b[2]))


def _place(mid, facing, side_sign, width, toe_out, forward=0.0):
    """Ground frame of a foot beside a point ``mid`` (on a line facing ``facing``)."""
    c, s = math.cos(facing), math.sin(facing)
    lat = side_sign * width / 2
    return np.array([mid[0] + c * forward - s * lat, mid[1] + s * forward + c * lat,
                     facing + side_sign * toe_out])


def _sgn(foot):
    return 1.0 if foot == 0 else -1.0


def _gesture(plan: Plan, P: Pose, u, dur, name, side, rng_vals):
    """Add an arm/head gesture to pose P over local times u in [0, dur]."""
    st = plan.style
    ramp = min(0.6, dur / 3)
    w = _window(u, 0.0, dur, ramp)
    a = rng_vals
    nd = st["arm_down"]
    if name == "wave":
        P.arm(side, down=w * (-a[0] - nd), twist=w * (-1.35 - st["arm_twist"]),
              elbow=w * (a[1] - st["elbow"]))
        P.add_sym(side, "elbow", "z", -w * 0.35 * np.sin(2 * np.pi * a[2] * u))
        P.neck(turn=w * _sgn(0 if side == "left" else 1) * 0.3)
    elif name == "reach":
        sides = SIDES if a[3] > 0.5 else (side,)
        for sd in sides:
            P.arm(sd, fwd=w * (a[0] * 1.2 + 0.8 - st["arm_fwd"]), elbow=w * (0.05 - st["elbow"]))
        P.spine(flex=w * 0.15 * a[1])
    elif name == "arms_up":
        for sd in SIDES:
            P.arm(sd, down=w * (-1.15 - 0.3 * a[0] - nd), elbow=w * (0.1 - st["elbow"]))
        P.spine(flex=-w * 0.1)
        P.neck(flex=-w * 0.2 * a[1])
    elif name == "cross":
        for sd in SIDES:
            P.arm(sd, fwd=w * (1.2 + 0.3 * a[0] - st["arm_fwd"]), elbow=w * (1.7 + 0.3 * a[1] - st["elbow"]),
                  twist=w * 0.3)
    elif name == "hips":
        for sd in SIDES:
            P.arm(sd, down=w * (0.95 - nd), fwd=w * (-0.35 - st["arm_fwd"]), twist=w * 0.9,
                  elbow=w * (1.6 - st["elbow"]))
    elif name == "look":
        P.neck(turn=w * (a[0] - 0.5) * 1.6 * np.sin(np.pi * u / dur), flex=w * (a[1] - 0.5) * 0.4)
        P.spine(twist=w * (a[0] - 0.5) * 0.6 * np.sin(np.pi * u / dur))
    elif name == "stretch":
        for sd in SIDES:
            P.arm(sd, down=w * (-1.3 - nd), elbow=w * (0.05 - st["elbow"]))
        P.spine(lat=w * (a[0] - 0.5) * 0.6 * np.sin(2 * np.pi * u / dur))
    elif name == "circles":
        f = 0.6 + 0.6 * a[1]
        for sd in SIDES:
            P.arm(sd, down=w * (0.1 * np.sin(2 * np.pi * f * u) - nd + 0.2 * a[0]),
                  fwd=w * 0.35 * np.cos(2 * np.pi * f * u), elbow=w * (0.05 - st["elbow"]))
    elif name == "clap":
        f = 1.2 + 1.2 * a[1]
        osc = 0.5 - 0.5 * np.cos(2 * np.pi * f * u)
        for sd in SIDES:
            P.arm(sd, fwd=w * (1.25 - st["arm_fwd"] + 0.25 * osc), elbow=w * (0.5 - st["elbow"] + 0.4 * osc),
                  twist=w * 0.8)
    elif name == "point":
        P.arm(side, down=w * (1.45 - 0.5 * a[0] - nd), fwd=w * (1.45 - st["arm_fwd"]), elbow=-w * st["elbow"])
        P.neck(turn=w * 0.2 * (1 if side == "left" else -1))


GESTURES = ("wave", "reach", "arms_up", "cross", "hips", "look", "stretch", "circles", "clap", "point")


def seg_stand(plan: Plan, dur: float | None = None, gestures: bool = True, kind: str = "stand"):
    """Standing: weight shifts, small knee bends, arm gestures."""
    rng = plan.rng
    dur = float(rng.uniform(2.0, 4.5) if dur is None else dur)
    t0, t1 = plan.t, plan.t + dur
    heading = _heading_of(plan.feet())
    plan.heading = heading
    if gestures:
        for _ in range(int(rng.integers(0, 3))):
            plan.lam_pins.append((t0 + float(rng.uniform(0.35, max(0.4, dur - 0.35))),
                                  float(rng.uniform(0.3, 0.7))))
    plan.lam_pins.append((t1, 0.5))
    gs = []
    if gestures and dur > 1.2:
        n = 1 if dur < 3.0 else int(rng.integers(1, 3))
        edges = np.sort(rng.uniform(0, dur, n - 1)) if n > 1 else np.array([])
        bounds = np.concatenate([[0.0], edges, [dur]])
        for i in range(n):
            if bounds[i + 1] - bounds[i] > 1.0:
                gs.append((bounds[i], bounds[i + 1], GESTURES[int(rng.integers(len(GESTURES)))],
                           SIDES[int(rng.integers(2))], rng.uniform(0, 1, 4)))
    bend = float(rng.uniform(0.0, 0.04)) * plan.ch.scale if gestures else 0.0
    z_rest = plan.z_rest

    def fn(t):
        u = t - t0
        P = _neutral(plan, len(t))
        for a, b, name, side, vals in gs:
            m = (u >= a) & (u <= b)
            if m.any():
                sub = Pose(P.names, len(t))
                _gesture(plan, sub, np.where(m, u - a, 0.0), b - a, name, side, vals)
                for k in P.v:
                    P.v[k] = P.v[k] + np.where(m, sub.v[k], 0.0)
        z = z_rest - bend * np.sin(np.pi * np.clip(u / dur, 0, 1)) ** 2
        return dict(z=z, yaw=np.full(len(t), heading), upper=P.array())

    plan.add_segment(kind, t0, t1, fn, gestures=[g[2] for g in gs])


def _gait_timing(v, run=False):
    """(step period, stance duration, swing time) of a walking or running step at speed v."""
    if not run:
        cad = float(np.clip(1.05 + 0.6 * v, 1.3, 2.3))
        Ts = 1.0 / cad
        ds = float(np.clip(0.12 + 0.14 * (1.3 - v), 0.07, 0.22))
        return Ts, Ts + ds, Ts - ds
    cad = float(np.clip(2.45 + 0.12 * v, 2.6, 3.1))
    Ts = 1.0 / cad
    tc = float(np.clip(0.36 - 0.04 * v, 0.17, 0.29))
    return Ts, tc, 2 * Ts - tc


def seg_locomotion(plan: Plan, run: bool = False, backward: bool = False):
    """Walking (forwards or backwards) or running, with speed ramps and turns, from standing
    to standing."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    if run:
        v = float(rng.uniform(2.0, 4.2))
        n = int(rng.integers(8, 15))
    elif backward:
        v = float(rng.uniform(0.4, 0.95))
        n = int(rng.integers(4, 9))
    else:
        v = float(rng.uniform(0.6, 1.7))
        n = int(rng.integers(4, 12))
    v *= math.sqrt(s)
    turn = 0.0
    if rng.uniform() < 0.5:
        turn = float(rng.uniform(-1.0, 1.0) * (0.6 if backward else (1.2 if run else 1.8)))
    width = st["width"] * (0.8 if run else 1.0) + float(rng.uniform(-0.02, 0.02)) * s
    toe_out = st["toe_out"]
    facing0 = _heading_of(plan.feet())
    path_dir0 = facing0 + (math.pi if backward else 0.0)
    f1 = int(rng.integers(2))
    # per-step speeds: ramp up over the first steps, down over the last ones
    n_ramp = max(2, int(math.ceil(v / (0.75 * math.sqrt(s)))))
    n = max(n, 2 * n_ramp + 2)
    v_late, k_change = v, n + 1
    if plan.extended and rng.uniform() < 0.4:  # a change of speed half-way
        v_late = v * float(rng.uniform(0.5, 1.6))
        k_change = n // 2
    speeds = []
    for k in range(1, n + 1):
        up = min(1.0, k / (n_ramp + 1))
        down = min(1.0, (n - k + 0.5) / (n_ramp + 0.5))
        vt = v + (v_late - v) * float(_smoothstep(np.array((k - k_change) / 3.0)))
        vk = max(0.45 * math.sqrt(s), vt * min(up, down))
        speeds.append(vk)
    mid = plan.mid()
    P_prev = np.array(mid)
    t_lift = t0 + float(rng.uniform(0.3, 0.5))
    prev_land = None
    heel = -float(rng.uniform(0.12, 0.22)) * (0.6 if run else 1.0)
    toe_off = float(rng.uniform(0.25, 0.4)) if not run else float(rng.uniform(0.35, 0.55))
    back_land = float(rng.uniform(0.12, 0.22))
    back_lift = -float(rng.uniform(0.08, 0.18))
    psi = path_dir0
    steps = []
    for k in range(1, n + 1):
        vk = speeds[k - 1]
        is_run = run and vk > 1.9 * math.sqrt(s)
        Ts, Tc, Tsw = _gait_timing(vk / math.sqrt(s), is_run)
        Tsw = min(Tsw, 0.6)
        if prev_land is not None:
            # the other foot landed at prev_land; this foot lifts Tc - Ts later (< 0: flight),
            # with the gait timing of the previous step
            pTc, pTs = steps[-1]["Tc"], steps[-1]["Ts"]
            t_lift = prev_land + (pTc - pTs)
            t_lift = max(t_lift, steps[-2]["land"] + 0.12 if len(steps) >= 2 else t_lift)
        last = k == n
        frac = (k - 1) / max(n - 2, 1)
        psi = path_dir0 + turn * float(_smoothstep(np.array(min(frac, 1.0))))
        Lk = 0.0 if last else vk * Ts
        if k == 1:
            Lk *= 0.6
        psi_bar = psi
        P = P_prev + Lk * np.array([math.cos(psi_bar), math.sin(psi_bar)])
        foot = f1 if k % 2 == 1 else 1 - f1
        facing = psi + (math.pi if backward else 0.0)
        G = _place(P, facing, _sgn(foot), width, toe_out)
        if last:
            Tsw = max(Tsw, 0.35)
        t_land = t_lift + Tsw
        steps.append(dict(foot=foot, G=G, lift=t_lift, land=t_land, Tc=Tc, Ts=Ts, run=is_run, v=vk))
        P_prev = P
        prev_land = t_land
    # emit stances
    for i, sd in enumerate(steps):
        foot = sd["foot"]
        prev = plan.stance(foot)
        stance_len = sd["lift"] - (prev.t_on if prev.t_on > -math.inf else sd["lift"] - 1.0)
        is_run = sd["run"]
        if backward:
            phi_off, r_off = back_lift, min(0.3 * stance_len, 0.2)
            phi_on, r_on = back_land, min(0.22, 0.5 * sd["Tc"])
            a_off, a_on = 0.25, 0.75
        else:
            phi_off = toe_off * (0.5 if i == 0 else 1.0)
            r_off = min((0.55 if is_run else 0.4) * stance_len, 0.3)
            phi_on = heel if i < len(steps) - 1 else heel * 0.5
            if is_run and rng.uniform() < 0.5:
                phi_on = 0.0  # mid-foot strike
            r_on = min(0.1, 0.3 * sd["Tc"]) if phi_on != 0.0 else 0.0
            a_off, a_on = 0.8, 0.3
        clear = ((0.05 + 0.025 * sd["v"]) if not is_run else (0.08 + 0.04 * sd["v"])) * s
        swing = {"mode": "world", "clear": clear}
        plan.step(foot, sd["G"], sd["lift"], sd["land"], phi_off=phi_off, r_off=r_off,
                  phi_on=phi_on, r_on=r_on, swing=swing, alpha_flat_off=a_off, alpha_flat_on=a_on)
    t_end = steps[-1]["land"] + float(rng.uniform(0.35, 0.6))
    plan.lam_pins.append((t_end, 0.5))
    facing_end = _heading_of(plan.feet())
    # gait phase: 0 at a left landing, pi at a right landing (linear between landings)
    land_t = np.array([sd["land"] for sd in steps])
    ph = (0.0 if steps[0]["foot"] == 0 else math.pi) + math.pi * np.arange(len(steps))
    facing_knots = [(t0, facing0)]
    f_prev = facing0
    for sd in steps:
        f_now = sd["G"][2] - _sgn(sd["foot"]) * toe_out
        f_now = f_prev + _wrap(f_now - f_prev)
        facing_knots.append((sd["land"], (f_now + f_prev) / 2 if sd is not steps[0] else f_prev))
        f_prev = f_now
    facing_knots.append((t_end, f_prev + _wrap(facing_end - f_prev)))
    env_a, env_b = steps[0]["lift"] - 0.1, steps[-1]["land"] + 0.1
    vmax = max(sd["v"] for sd in steps)
    A_rot = (0.04 + 0.04 * min(vmax, 2.0)) * (0.6 if backward else 1.0)
    A_roll = 0.02 + 0.02 * min(vmax, 2.0)
    A_arm = st["arm_swing"] * (0.12 + 0.14 * min(vmax, 2.0)) * (0.5 if backward else 1.0)
    lean = (float(rng.uniform(0.02, 0.08)) + (0.04 * min(vmax, 4.0) if run else 0.0)) * (-0.5 if backward else 1.0)
    tilt = float(rng.uniform(0.08, 0.16))  # anterior pelvic tilt while walking, undone by the spine
    z_rest = plan.z_rest
    z_loco = z_rest - 0.015 * s if not run else z_rest - 0.03 * s
    run_elbow = float(rng.uniform(1.2, 1.6))
    carry = None  # the extended generator: an arm task independent of the gait
    if plan.extended and rng.uniform() < 0.5:
        dur = steps[-1]["land"] - steps[0]["lift"]
        ga = steps[0]["lift"] + float(rng.uniform(0.0, 0.4)) * dur
        gb = ga + float(rng.uniform(0.3, 0.7)) * dur
        carry = (ga, gb, str(rng.choice(["phone", "carry", "wave", "point", "look", "cross", "hips"])),
                 SIDES[int(rng.integers(2))], rng.uniform(0, 1, 4))

    def fn(t):
        env = _window(t, env_a, env_b, 0.5)
        phase = _interp_extrap(t, land_t, ph)
        c = np.cos(phase)
        yaw = _keys(t, facing_knots) - env * A_rot * c
        roll = env * A_roll * np.sin(phase)
        pitch = env * (lean + tilt)
        P = _neutral(plan, len(t))
        keep = {"left": 1.0, "right": 1.0}  # how much of each arm's swing is left
        if carry is not None:
            ga, gb, name, side, vals = carry
            w = _window(t, ga, gb, min(0.5, (gb - ga) / 3))
            arms = SIDES if name in ("carry", "cross", "hips") else (side,)
            for sd in arms:
                keep[sd] = 1.0 - w
            if name == "phone":  # hand at the ear
                P.arm(side, down=w * (0.9 - st["arm_down"]), fwd=w * (0.5 - st["arm_fwd"]),
                      elbow=w * (2.3 - st["elbow"]), twist=-w * 0.4)
            elif name == "carry":  # a box held in front
                for sd in SIDES:
                    P.arm(sd, down=w * (1.2 - st["arm_down"]), fwd=w * (0.45 - st["arm_fwd"]),
                          elbow=w * (1.4 - st["elbow"]), twist=w * 0.5)
            elif name in ("wave", "point", "look", "cross", "hips"):
                sub = Pose(P.names, len(t))
                m = (t >= ga) & (t <= gb)
                _gesture(plan, sub, np.where(m, t - ga, 0.0), gb - ga, name, side, vals)
                for k in P.v:
                    P.v[k] = P.v[k] + np.where(m, sub.v[k], 0.0)
        kl, kr = keep["left"], keep["right"]
        P.arm("left", fwd=-env * A_arm * c * kl)
        P.arm("right", fwd=env * A_arm * c * kr)
        if run:
            P.arm("left", elbow=kl * env * (run_elbow - st["elbow"] + 0.25 * c), down=-kl * env * 0.15)
            P.arm("right", elbow=kr * env * (run_elbow - st["elbow"] - 0.25 * c), down=-kr * env * 0.15)
        else:
            P.arm("left", elbow=kl * env * 0.15 * A_arm * (1 + c))
            P.arm("right", elbow=kr * env * 0.15 * A_arm * (1 - c))
        P.spine(twist=env * 0.8 * A_rot * c, flex=env * (lean * 0.5 - tilt))
        P.neck(turn=-env * 0.2 * A_rot * c, flex=-env * lean)
        z = z_rest + (z_loco - z_rest) * _window(t, t0, t_end, 0.4)
        return dict(z=z, yaw=yaw, pitch=pitch, roll=roll, upper=P.array())

    kind = "run" if run else "walk"
    plan.add_segment(kind, t0, t_end, fn, speed=v, backward=backward, turn=turn, steps=n)
    plan.heading = facing_end


def _moved_feet(feet, mid, heading, dx, dy, dpsi):
    """Both feet translated by (dx, dy) in the heading frame and turned by dpsi about mid."""
    c, s_ = math.cos(heading), math.sin(heading)
    shift = np.array([c * dx - s_ * dy, s_ * dx + c * dy])
    cr, sr = math.cos(dpsi), math.sin(dpsi)
    out = []
    for G in feet:
        r = G[:2] - mid
        p = mid + np.array([cr * r[0] - sr * r[1], sr * r[0] + cr * r[1]]) + shift
        out.append(np.array([p[0], p[1], G[2] + dpsi]))
    return out


def seg_jump(plan: Plan):
    """Jumps on both feet: vertical, broad, lateral, turning; single or repeated hops. The
    pelvis follows a g-parabola in flight."""
    ch, rng = plan.ch, plan.rng
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    n = 1 if rng.uniform() < 0.6 else int(rng.integers(2, 4))
    hop = n > 1
    phi_to = float(rng.uniform(0.5, 0.8))
    phi_land = float(rng.uniform(0.25, 0.45))
    # pelvis heights at take-off / landing from the leg geometry (legs nearly straight)
    ank_to = ch.stance_pose(0, np.zeros(3), phi_to)[1][2]
    ank_land = ch.stance_pose(0, np.zeros(3), phi_land)[1][2]
    hip_drop = -ch.legs[0].hip_offset[2]
    z_to = ank_to + 0.93 * ch.reach + hip_drop
    z_land = ank_land + 0.92 * ch.reach + hip_drop
    z_rest = plan.z_rest
    Z = _Piecewise()
    t = t0 + float(rng.uniform(0.2, 0.4))
    Z.add(t0, t, _const(z_rest))
    d_c = float(rng.uniform(0.10, 0.22)) * s
    T_cm = float(rng.uniform(0.45, 0.7))
    t = Z.add(t, t + T_cm, _ramp(t, t + T_cm, z_rest, z_rest - d_c))
    z_low = z_rest - d_c
    arm_keys = [(t0, 0.0), (t - 0.05, -0.8)]  # arm swing (fwd) knots
    lean_keys = [(t0, 0.0), (t, float(rng.uniform(0.2, 0.45)))]
    jumps = []
    cur_feet = feet
    for i in range(n):
        T_po = float(rng.uniform(0.2, 0.3))
        T_f = float(rng.uniform(0.22, 0.35) if hop else rng.uniform(0.3, 0.5))
        v0 = (z_land - z_to) / T_f + GRAVITY * T_f / 2
        v1 = v0 - GRAVITY * T_f
        t_to = t + T_po
        Z.add(t, t_to, lambda tt, a=t, b=t_to, zl=z_low, v=v0: _hermite(tt, a, b, zl, 0.0, z_to, v))
        t_land = t_to + T_f
        Z.add(t_to, t_land, lambda tt, a=t_to, v=v0: z_to + v * (tt - a) - 0.5 * GRAVITY * (tt - a) ** 2)
        kind = rng.choice(["up", "broad", "side", "turn"], p=[0.3, 0.35, 0.15, 0.2])
        dx = dy = dpsi = 0.0
        if kind == "broad":
            dx = float(rng.uniform(0.2, 0.7 if not hop else 0.4)) * s
        elif kind == "side":
            dy = float(rng.choice([-1, 1]) * rng.uniform(0.15, 0.4)) * s
        elif kind == "turn":
            dpsi = float(rng.choice([-1, 1]) * rng.uniform(0.3, 1.2))
        mid = (cur_feet[0][:2] + cur_feet[1][:2]) / 2
        new_feet = _moved_feet(cur_feet, mid, heading, dx, dy, dpsi)
        tuck = float(rng.uniform(0.0, 0.12 if hop else 0.25)) * s
        for f in (0, 1):
            plan.step(f, new_feet[f], t_to, t_land, phi_off=phi_to, r_off=T_po, phi_on=phi_land,
                      r_on=float(rng.uniform(0.08, 0.14)), swing={"mode": "rel", "tuck": tuck},
                      alpha_flat_off=0.7, alpha_flat_on=0.5)
        heading_new = heading + dpsi
        jumps.append(dict(t_to=t_to, t_land=t_land, kind=str(kind), dx=dx, dy=dy, dpsi=dpsi,
                          h_old=heading, h_new=heading_new))
        heading = heading_new
        cur_feet = new_feet
        arm_keys += [(t_to, 1.6), (t_land, 1.0)]
        lean_keys += [(t_to, 0.05), (t_land, 0.05)]
        last = i == n - 1
        d_a = float(rng.uniform(0.08, 0.2 if last else 0.12)) * s
        T_ab = float(rng.uniform(0.25, 0.4) if last else rng.uniform(0.15, 0.22))
        t = Z.add(t_land, t_land + T_ab, lambda tt, a=t_land, b=t_land + T_ab, zz=z_rest - d_a, v=v1:
                  _hermite(tt, a, b, z_land, v, zz, 0.0))
        z_low = z_rest - d_a
        lean_keys.append((t, float(rng.uniform(0.15, 0.35))))
        arm_keys.append((t, 0.6 if not last else 0.3))
    T_rise = float(rng.uniform(0.5, 0.8))
    t_end = Z.add(t, t + T_rise, _ramp(t, t + T_rise, z_low, z_rest))
    t_end = Z.add(t_end, t_end + float(rng.uniform(0.2, 0.4)), _const(z_rest))
    arm_keys += [(t_end - 0.2, 0.0), (t_end, 0.0)]
    lean_keys += [(t_end - 0.2, 0.0), (t_end, 0.0)]
    plan.lam_pins.append((t_end, 0.5))
    yaw_keys = [(t0, jumps[0]["h_old"])]
    for j in jumps:
        yaw_keys += [(j["t_to"], j["h_old"]), (j["t_land"], j["h_new"])]
    yaw_keys.append((t_end, heading))
    arms_up = rng.uniform() < 0.5

    def fn(tt):
        P = _neutral(plan, len(tt))
        fwd = _keys(tt, arm_keys)
        for sd in SIDES:
            P.arm(sd, fwd=np.clip(fwd, -0.9, 1.6) * (1.0 if not arms_up else 0.6),
                  down=-(np.clip(fwd, 0, 2) * 0.6 if arms_up else 0.0),
                  elbow=0.2 * np.abs(fwd))
        lean = _keys(tt, lean_keys)
        P.spine(flex=0.5 * lean)
        P.neck(flex=-0.6 * lean)
        return dict(z=Z(tt), yaw=_keys(tt, yaw_keys), pitch=lean, upper=P.array())

    plan.add_segment("jump", t0, t_end, fn, jumps=len(jumps))
    plan.heading = heading


def _step_to(plan: Plan, foot, G, t_lift, dur=0.45, clear=0.05, phi_off=0.15, r_off=0.15):
    return plan.step(foot, G, t_lift, t_lift + dur, phi_off=phi_off, r_off=r_off,
                     swing={"mode": "world", "clear": clear * plan.ch.scale})


def seg_squat(plan: Plan):
    """Squats (1-4 repetitions) on a widened stance, arms forward / crossed / behind the head."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    mid = plan.mid()
    width = float(rng.uniform(0.25, 0.42)) * s
    toe = float(rng.uniform(0.1, 0.4))
    first = int(rng.integers(2))
    t = t0 + 0.5
    for f in (first, 1 - first):
        _step_to(plan, f, _place(mid, heading, _sgn(f), width, toe), t)
        t += 0.45 + 0.45
    reps = int(rng.integers(1, 5))
    depth = float(rng.uniform(0.15, 0.36)) * s
    T_rep = float(rng.uniform(1.6, 3.0))
    t_sq0 = t + 0.2
    knots = [(t0, 0.0), (t_sq0, 0.0)]
    for r in range(reps):
        a = t_sq0 + r * T_rep
        knots += [(a + 0.45 * T_rep, 1.0), (a + 0.55 * T_rep, 1.0), (a + T_rep, 0.0)]
    t_sq1 = t_sq0 + reps * T_rep
    t = t_sq1 + 0.3
    for f in (first, 1 - first):
        _step_to(plan, f, _place(mid, heading, _sgn(f), st["width"], st["toe_out"]), t)
        t += 0.9
    t_end = t + 0.3
    plan.lam_pins.append((t_end, 0.5))
    style = rng.choice(["forward", "cross", "head", "free"])
    lean = float(rng.uniform(0.5, 0.9))
    z_rest = plan.z_rest

    def fn(tt):
        prof = np.clip(_keys(tt, knots), 0, 1)
        P = _neutral(plan, len(tt))
        for sd in SIDES:
            if style == "forward":
                P.arm(sd, fwd=prof * (1.45 - st["arm_fwd"]), elbow=-prof * st["elbow"])
            elif style == "cross":
                P.arm(sd, fwd=prof * (1.3 - st["arm_fwd"]), elbow=prof * (1.8 - st["elbow"]), twist=0.3 * prof)
            elif style == "head":
                P.arm(sd, down=prof * (-0.1 - st["arm_down"]), elbow=prof * (2.2 - st["elbow"]),
                      fwd=prof * 0.3, twist=-prof * 0.8)
            else:
                P.arm(sd, fwd=prof * 0.5, elbow=prof * 0.4)
        P.spine(flex=prof * 0.25 * lean)
        P.neck(flex=-prof * 0.5 * lean)
        return dict(z=z_rest - depth * prof, yaw=np.full(len(tt), heading),
                    pitch=prof * lean * 0.8, upper=P.array())

    plan.add_segment("squat", t0, t_end, fn, reps=reps, depth=depth)


def seg_lunge(plan: Plan):
    """Forward or reverse lunges with either leg."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    A = int(rng.integers(2))  # the stepping foot
    B = 1 - A
    reverse = rng.uniform() < 0.4
    L = float(rng.uniform(0.4, 0.6) if reverse else rng.uniform(0.5, 0.75)) * s
    depth = float(rng.uniform(0.12, 0.24)) * s
    GA = feet[A].copy()
    c, sn = math.cos(heading), math.sin(heading)
    sign = -1.0 if reverse else 1.0
    G_new = GA + np.array([sign * L * c, sign * L * sn, 0.0])
    G_new[2] = heading + _sgn(A) * 0.05
    t_lift = t0 + float(rng.uniform(0.35, 0.55))
    T_sw = float(rng.uniform(0.4, 0.55))
    t_land = t_lift + T_sw
    if reverse:
        sA = plan.step(A, G_new, t_lift, t_land, phi_off=0.1, r_off=0.15, phi_on=0.6, r_on=0.1,
                       swing={"mode": "world", "clear": 0.06 * s})
    else:
        sA = plan.step(A, G_new, t_lift, t_land, phi_off=0.25, r_off=0.2, phi_on=-0.15, r_on=0.1,
                       swing={"mode": "world", "clear": 0.06 * s})
    T_down = float(rng.uniform(0.6, 1.0))
    T_hold = float(rng.uniform(0.1, 0.6))
    T_up = float(rng.uniform(0.6, 1.0))
    a = t_land + 0.15
    b = a + T_down
    c_ = b + T_hold
    d = c_ + T_up
    heel = float(rng.uniform(0.6, 0.9))
    if reverse:
        sA.phi = [(t_land, 0.6), (a, 0.6), (b, heel), (c_, heel), (d, 0.6)]
    else:
        sB = plan.stance(B)
        sB.phi += [(a - 0.1, 0.0), (b, heel), (c_, heel), (d, 0.5)]
    t_back = d + 0.1
    T_sw2 = float(rng.uniform(0.4, 0.55))
    if reverse:
        plan.step(A, GA, t_back, t_back + T_sw2, phi_off=0.0, r_off=0.0, phi_on=0.0,
                  swing={"mode": "world", "clear": 0.06 * s})
        sA.phi.append((t_back, 0.75))
    else:
        plan.step(A, GA, t_back, t_back + T_sw2, phi_off=0.25, r_off=0.15, phi_on=0.2, r_on=0.1,
                  swing={"mode": "world", "clear": 0.05 * s})
        sB = plan.stance(B)
        sB.phi += [(t_back + T_sw2 + 0.1, 0.0)]
    t_end = t_back + T_sw2 + float(rng.uniform(0.4, 0.7))
    front = B if reverse else A
    share = float(rng.uniform(0.6, 0.7))
    lamL = share if front == 0 else 1 - share
    plan.lam_pins += [(b, lamL), (c_, lamL), (t_end, 0.5)]
    if reverse:  # sink on the front leg while reaching back, pelvis tilted forward
        prof_knots = [(t0, 0.0), (t_lift, 0.0), (t_land, 0.35), (b, 1.0), (c_, 1.0), (d, 0.0),
                      (t_back + T_sw2, 0.0), (t_end, 0.0)]
        tilt_knots = [(t0, 0.0), (t_lift - 0.2, 0.0), (t_land, 1.0), (t_back + T_sw2, 1.0), (t_end, 0.0)]
    else:
        prof_knots = [(t0, 0.0), (a, 0.0), (b, 1.0), (c_, 1.0), (d, 0.0), (t_end, 0.0)]
        tilt_knots = [(t0, 0.0), (t_end, 0.0)]
    tilt = float(rng.uniform(0.25, 0.35))
    style = rng.choice(["hips", "free", "forward"])
    z_rest = plan.z_rest

    def fn(tt):
        prof = np.clip(_keys(tt, prof_knots), 0, 1)
        P = _neutral(plan, len(tt))
        for sd in SIDES:
            if style == "hips":
                P.arm(sd, down=prof * (0.95 - st["arm_down"]), fwd=prof * (-0.35 - st["arm_fwd"]),
                      twist=prof * 0.9, elbow=prof * (1.6 - st["elbow"]))
            elif style == "forward":
                P.arm(sd, fwd=prof * 1.2, elbow=prof * 0.2)
        tl = tilt * np.clip(_keys(tt, tilt_knots), 0, 1)
        P.spine(flex=-0.05 * prof - 0.9 * tl)
        return dict(z=z_rest - depth * prof, yaw=np.full(len(tt), heading), pitch=0.05 * prof + tl,
                    upper=P.array())

    plan.add_segment("lunge", t0, t_end, fn, reverse=bool(reverse))


def seg_kick(plan: Plan):
    """Front, side or back kicks from a single-leg stance."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    A = int(rng.integers(2))
    sg = _sgn(A)
    kind = str(rng.choice(["front", "side", "back"], p=[0.5, 0.3, 0.2]))
    L = ch.reach
    hip = np.array([0.0, ch.legs[A].hip_offset[1], ch.legs[A].hip_offset[2]])
    chamber_p = hip + np.array([0.36, 0.0, -0.5]) * s
    chamber_R = _ry(np.array(-0.3))
    pf = float(rng.uniform(0.2, 0.6))
    if kind == "front":
        e = float(rng.uniform(-0.6, 0.0))
        d = np.array([math.cos(e), 0.0, math.sin(e)])
        ext_R = _ry(np.array(-(math.pi / 2 + e) + pf))
        pitch_k, roll_k = -float(rng.uniform(0.05, 0.2)), 0.0
    elif kind == "side":
        a = float(rng.uniform(0.5, 0.8))
        d = np.array([0.1, sg * math.sin(a), -math.cos(a)])
        d /= np.linalg.norm(d)
        ext_R = _rx(np.array(-sg * a))
        pitch_k, roll_k = 0.0, sg * float(rng.uniform(0.1, 0.22))
        chamber_p = hip + np.array([0.25, sg * 0.15, -0.5]) * s
    else:
        b = float(rng.uniform(0.5, 0.8))
        d = np.array([-math.sin(b), 0.0, -math.cos(b)])
        ext_R = _ry(np.array(b + 0.3))
        pitch_k, roll_k = float(rng.uniform(0.25, 0.4)), 0.0
        chamber_p = hip + np.array([-0.1, 0.0, -0.45]) * s
        chamber_R = _ry(np.array(0.6))
    ext_p = hip + 0.94 * L * d
    t_lift = t0 + float(rng.uniform(0.7, 1.0))
    T = float(rng.uniform(0.9, 1.4))
    keys = [dict(s=0.3, R=chamber_R, p=chamber_p, toe=0.0),
            dict(s=0.5, R=ext_R, p=ext_p, toe=0.0),
            dict(s=0.62, R=ext_R, p=ext_p, toe=0.0),
            dict(s=0.8, R=chamber_R, p=chamber_p, toe=0.0)]
    plan.step(A, feet[A], t_lift, t_lift + T, phi_off=0.3, r_off=0.2, phi_on=0.2, r_on=0.1,
              swing={"mode": "rel", "keys": keys})
    t_end = t_lift + T + float(rng.uniform(0.5, 0.8))
    plan.lam_pins.append((t_end, 0.5))
    prof_knots = [(t0, 0.0), (t_lift - 0.3, 0.0), (t_lift + 0.45 * T, 1.0), (t_lift + 0.65 * T, 1.0),
                  (t_lift + T, 0.0), (t_end, 0.0)]
    guard = rng.uniform() < 0.5
    bend = float(rng.uniform(0.02, 0.05)) * s
    z_rest = plan.z_rest
    kick_window = [(t0, 0.0), (t_lift - 0.2, 0.0), (t_lift, 1.0), (t_lift + T, 1.0), (t_end - 0.1, 0.0)]

    def fn(tt):
        prof = np.clip(_keys(tt, prof_knots), 0, 1)
        win = np.clip(_keys(tt, kick_window), 0, 1)
        P = _neutral(plan, len(tt))
        for sd in SIDES:
            if guard:
                P.arm(sd, down=win * (0.9 - st["arm_down"]), fwd=win * 1.0, elbow=win * (2.0 - st["elbow"]))
            else:
                P.arm(sd, down=win * (0.4 - st["arm_down"]), elbow=win * 0.2)
        P.spine(flex=-0.5 * pitch_k * prof, lat=0.0)
        P.neck(flex=-0.5 * pitch_k * prof)
        return dict(z=z_rest - bend * win, yaw=np.full(len(tt), heading), pitch=pitch_k * prof,
                    roll=roll_k * prof, upper=P.array())

    plan.add_segment("kick", t0, t_end, fn, kick=kind)


def seg_dance(plan: Plan):
    """Dance-like stepping to a beat: side steps, marching, forward/back steps and turning
    steps, with a knee bounce and rhythmic arm patterns."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    Tb = float(rng.uniform(0.45, 0.65))
    n_moves = int(rng.integers(3, 7))
    feet = plan.feet()
    heading = _heading_of(feet)
    width = st["width"]
    t = t0 + Tb
    yaw_keys = [(t0, heading)]
    for _ in range(n_moves):
        move = str(rng.choice(["side", "march", "fwd_back", "turn"]))
        feet = plan.feet()
        heading = _heading_of(feet)
        mid = plan.mid()
        A = int(rng.integers(2))
        B = 1 - A
        clear = float(rng.uniform(0.05, 0.1))
        if move == "side":
            d = float(rng.uniform(0.2, 0.4)) * s * _sgn(A)
            G_A = _place(mid, heading, _sgn(A), width, st["toe_out"])
            c, sn = math.cos(heading), math.sin(heading)
            G_A[:2] += d * np.array([-sn, c])
            mid2 = mid + d * np.array([-sn, c])
            G_B = _place(mid2, heading, _sgn(B), width, st["toe_out"])
            seq = [(A, G_A), (B, G_B)]
        elif move == "march":
            clear = float(rng.uniform(0.12, 0.25))
            seq = [(A, feet[A]), (B, feet[B]), (A, feet[A]), (B, feet[B])]
        elif move == "fwd_back":
            L = float(rng.uniform(0.2, 0.35)) * s
            c, sn = math.cos(heading), math.sin(heading)
            G_f = feet[A] + np.array([L * c, L * sn, 0.0])
            seq = [(A, G_f), (A, feet[A])]
        else:
            dpsi = float(rng.choice([-1, 1]) * rng.uniform(0.4, 0.9))
            new = _moved_feet(feet, mid, heading, 0.0, 0.0, dpsi)
            first = 0 if dpsi > 0 else 1  # turn left: the left foot leads
            seq = [(first, new[first]), (1 - first, new[1 - first])]
        for foot, G in seq:
            plan.step(foot, G, t + 0.05 * Tb, t + 0.6 * Tb, phi_off=0.15, r_off=0.12,
                      phi_on=0.1 if move == "march" else 0.0, r_on=0.08 if move == "march" else 0.0,
                      swing={"mode": "world", "clear": clear * s})
            t += Tb
        yaw_keys.append((t, _heading_of(plan.feet()) + 0.0))
    t_end = t + Tb
    for i in range(1, len(yaw_keys)):
        prev = yaw_keys[i - 1][1]
        yaw_keys[i] = (yaw_keys[i][0], prev + _wrap(yaw_keys[i][1] - prev))
    yaw_keys.append((t_end, yaw_keys[-1][1]))
    plan.lam_pins.append((t_end, 0.5))
    bounce = float(rng.uniform(0.015, 0.05)) * s
    pattern = str(rng.choice(["pump", "updown", "punch", "sway", "clap"]))
    z_rest = plan.z_rest
    end_heading = yaw_keys[-1][1]

    def fn(tt):
        env = _window(tt, t0, t_end, Tb)
        ph = 2 * np.pi * (tt - t0) / Tb
        P = _neutral(plan, len(tt))
        if pattern == "pump":
            P.arm("left", elbow=env * (1.5 - st["elbow"]), fwd=env * (0.3 + 0.4 * np.sin(ph)))
            P.arm("right", elbow=env * (1.5 - st["elbow"]), fwd=env * (0.3 - 0.4 * np.sin(ph)))
        elif pattern == "updown":
            for sd in SIDES:
                P.arm(sd, down=env * (-0.6 - st["arm_down"]) * (0.5 + 0.5 * np.cos(ph / 2)),
                      elbow=env * 0.4)
        elif pattern == "punch":
            P.arm("left", fwd=env * 1.4 * (0.5 + 0.5 * np.sin(ph / 2)),
                  elbow=env * 1.6 * (0.5 - 0.5 * np.sin(ph / 2)))
            P.arm("right", fwd=env * 1.4 * (0.5 - 0.5 * np.sin(ph / 2)),
                  elbow=env * 1.6 * (0.5 + 0.5 * np.sin(ph / 2)))
        elif pattern == "sway":
            for sd in SIDES:
                P.arm(sd, down=env * (0.7 - st["arm_down"]), elbow=env * 0.3)
            P.spine(lat=env * 0.15 * np.sin(ph / 2))
        else:
            osc = 0.5 - 0.5 * np.cos(ph)
            for sd in SIDES:
                P.arm(sd, fwd=env * (1.2 + 0.25 * osc), elbow=env * (0.4 + 0.4 * osc), twist=env * 0.8)
        z = z_rest - env * (0.01 * s + bounce * (0.5 + 0.5 * np.cos(ph)))
        return dict(z=z, yaw=_keys(tt, yaw_keys), roll=env * 0.04 * np.sin(ph / 2), upper=P.array())

    plan.add_segment("dance", t0, t_end, fn, beat=Tb, pattern=pattern)
    plan.heading = end_heading


# -- the extended generator's everyday motions (issue 15 item 1) ---------------------------

def _heel_rise(plan: Plan, phi: float) -> float:
    """How far the ankles rise when both heels lift by ``phi`` about the balls of the feet."""
    ch = plan.ch
    G = np.zeros(3)
    return float(ch.stance_pose(0, G, np.array(phi))[1][2] - ch.stance_pose(0, G, np.array(0.0))[1][2])


def _rep_knots(t_start, reps, T_down, T_hold, T_up, gaps):
    """Profile knots 0 -> 1 (hold) -> 0 for each repetition; returns (knots, end time)."""
    knots = [(t_start - 1.0, 0.0), (t_start, 0.0)]
    a = t_start
    for r in range(reps):
        knots += [(a + T_down, 1.0), (a + T_down + T_hold, 1.0), (a + T_down + T_hold + T_up, 0.0)]
        a += T_down + T_hold + T_up + gaps[r]
    return knots, a


def _set_stance(plan: Plan, mid, heading, width, stagger, t, foot_first):
    """Step both feet (one after the other) to a stance of ``width`` about ``mid``, the first
    foot ``stagger`` ahead; returns the time after the second step."""
    for f, fwd in ((foot_first, stagger), (1 - foot_first, 0.0)):
        _step_to(plan, f, _place(mid, heading, _sgn(f), width, plan.style["toe_out"], forward=fwd), t,
                 dur=0.4, clear=0.04)
        t += 0.6
    return t


def seg_bend(plan: Plan):
    """Bending down to the floor and back up: picking something up or putting it down, by a
    stoop (knees nearly straight, trunk and hips flexed) or a squat-lift (knees deep, back
    bent), one or both hands reaching to just above the floor in front of the feet, 1-2 times;
    the feet first move to a wider or staggered stance half of the time."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    mid = plan.mid()
    t = t0 + float(rng.uniform(0.2, 0.5))
    moved = rng.uniform() < 0.5
    first = int(rng.integers(2))
    if moved:
        t = _set_stance(plan, mid, heading, float(rng.uniform(0.2, 0.36)) * s,
                        float(rng.uniform(-0.05, 0.25)) * s, t, first)
    stoop = rng.uniform() < 0.5
    if stoop:
        pitch_max = float(rng.uniform(0.75, 1.25))
        flex_max = float(rng.uniform(0.45, 1.0))
        depth = float(rng.uniform(0.02, 0.1)) * s
    else:
        pitch_max = float(rng.uniform(0.4, 0.8))
        flex_max = float(rng.uniform(0.3, 0.7))
        depth = float(rng.uniform(0.22, 0.38)) * s
    reps = int(rng.integers(1, 3))
    T_down, T_up = float(rng.uniform(0.7, 1.4)), float(rng.uniform(0.7, 1.5))
    T_hold = float(rng.uniform(0.2, 1.0))
    knots, t_after = _rep_knots(t + 0.1, reps, T_down, T_hold, T_up, rng.uniform(0.3, 0.9, reps))
    hands = str(rng.choice(["both", "left", "right"]))
    reach = float(rng.uniform(0.0, 0.35))
    t = t_after
    if moved:
        t = _set_stance(plan, mid, heading, st["width"], 0.0, t + 0.1, first)
    t_end = t + float(rng.uniform(0.2, 0.5))
    plan.lam_pins.append((t_end, 0.5))
    z_rest = plan.z_rest

    def fn(tt):
        prof = np.clip(_keys(tt, knots), 0, 1)
        P = _neutral(plan, len(tt))
        # an arm hanging straight down from a trunk pitched by (pitch + flex) swings forward by
        # that angle relative to the trunk; ``reach`` takes the hand further ahead of the feet
        down_fwd = pitch_max + flex_max + reach
        for sd in SIDES:
            if hands == "both" or hands == sd:
                P.arm(sd, fwd=prof * (down_fwd - st["arm_fwd"]), elbow=prof * (0.1 - st["elbow"]),
                      down=prof * (1.45 - st["arm_down"]))
            else:
                P.arm(sd, fwd=prof * 0.5 * pitch_max, elbow=prof * 0.6)
        P.spine(flex=prof * flex_max)
        P.neck(flex=-prof * 0.5 * (pitch_max + flex_max) * 0.4)
        return dict(z=z_rest - depth * prof, yaw=np.full(len(tt), heading), pitch=prof * pitch_max,
                    upper=P.array())

    plan.add_segment("bend", t0, t_end, fn, stoop=bool(stoop), reps=reps)


def seg_crouch(plan: Plan):
    """Crouching low and holding it: a deep crouch on the balls of the feet (heels up) or a
    flat-footed one, arms on the knees, forward to the floor or free, looking around, then
    standing up; the feet usually widen first."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    mid = plan.mid()
    first = int(rng.integers(2))
    t = t0 + float(rng.uniform(0.2, 0.5))
    widen = rng.uniform() < 0.75
    if widen:
        t = _set_stance(plan, mid, heading, float(rng.uniform(0.22, 0.4)) * s,
                        float(rng.uniform(-0.1, 0.15)) * s, t, first)
    toes = rng.uniform() < 0.6
    if toes:
        depth = float(rng.uniform(0.32, 0.44)) * s
        heel = float(rng.uniform(0.5, 0.9))
    else:
        depth = float(rng.uniform(0.24, 0.33)) * s
        heel = 0.0
    T_down, T_hold, T_up = float(rng.uniform(0.8, 1.5)), float(rng.uniform(0.8, 2.5)), float(rng.uniform(0.8, 1.5))
    a = t + 0.1
    b, c_ = a + T_down, a + T_down + T_hold
    d = c_ + T_up
    knots = [(a - 1.0, 0.0), (a, 0.0), (b, 1.0), (c_, 1.0), (d, 0.0)]
    if toes:
        for f in (0, 1):
            plan.stance(f).phi += [(a + 0.2 * T_down, 0.0), (b, heel), (c_, heel), (d - 0.2 * T_up, 0.0)]
    t = d + 0.1
    if widen:
        t = _set_stance(plan, mid, heading, st["width"], 0.0, t, first)
    t_end = t + float(rng.uniform(0.2, 0.5))
    share = float(rng.uniform(0.4, 0.6))
    plan.lam_pins += [(b, share), (c_, share), (t_end, 0.5)]
    arms = str(rng.choice(["knees", "floor", "free", "hug"]))
    look = float(rng.uniform(-0.8, 0.8))
    lean = float(rng.uniform(0.35, 0.7))
    z_rest = plan.z_rest

    def fn(tt):
        prof = np.clip(_keys(tt, knots), 0, 1)
        hold = _window(tt, b, c_, 0.3)
        P = _neutral(plan, len(tt))
        for sd in SIDES:
            if arms == "knees":
                P.arm(sd, fwd=prof * (1.0 - st["arm_fwd"]), elbow=prof * (0.9 - st["elbow"]))
            elif arms == "floor":
                P.arm(sd, fwd=prof * (0.7 + lean - st["arm_fwd"]), elbow=prof * (0.3 - st["elbow"]))
            elif arms == "hug":
                P.arm(sd, fwd=prof * (1.3 - st["arm_fwd"]), elbow=prof * (1.9 - st["elbow"]), twist=0.4 * prof)
            else:
                P.arm(sd, fwd=prof * 0.6, elbow=prof * 0.5)
        P.spine(flex=prof * 0.5 * lean)
        P.neck(flex=-prof * 0.35, turn=hold * look * np.sin(np.pi * np.clip((tt - b) / max(c_ - b, 1e-3), 0, 1)))
        return dict(z=z_rest - depth * prof, yaw=np.full(len(tt), heading), pitch=prof * lean,
                    upper=P.array())

    plan.add_segment("crouch", t0, t_end, fn, on_toes=bool(toes), depth=depth)


def seg_reach(plan: Plan):
    """Reaching: up high on the toes (one or both arms overhead), out to the side over a wide
    step with the weight shifted onto that foot and the trunk bent sideways, or forward and
    down over a forward step; held, then back to standing."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    kind = str(rng.choice(["high", "side", "forward"], p=[0.4, 0.3, 0.3]))
    A = int(rng.integers(2))  # the reaching side (and, for side/forward, the stepping foot)
    side = SIDES[A]
    T_in, T_hold, T_out = float(rng.uniform(0.6, 1.1)), float(rng.uniform(0.3, 1.5)), float(rng.uniform(0.6, 1.1))
    t = t0 + float(rng.uniform(0.2, 0.5))
    both = rng.uniform() < 0.4
    rise = z_lat = 0.0
    pitch_max = roll_max = flex = lat = 0.0
    G_home = feet[A].copy()
    if kind == "high":
        phi = float(rng.uniform(0.25, 0.6))
        rise = 0.85 * _heel_rise(plan, phi)
        a = t
        b, c_ = a + T_in, a + T_in + T_hold
        d = c_ + T_out
        for f in (0, 1):
            plan.stance(f).phi += [(a, 0.0), (b, phi), (c_, phi), (d, 0.0)]
        lat = -_sgn(A) * float(rng.uniform(0.0, 0.15))
        t_back = d
    else:
        c, sn = math.cos(heading), math.sin(heading)
        if kind == "side":
            dist = float(rng.uniform(0.25, 0.45)) * s
            G_new = G_home + np.array([-sn * _sgn(A) * dist, c * _sgn(A) * dist, 0.0])
            lat = -_sgn(A) * float(rng.uniform(0.15, 0.35))  # bend towards the reaching side
            roll_max = -_sgn(A) * float(rng.uniform(0.05, 0.12))
            z_lat = float(rng.uniform(0.03, 0.1)) * s
        else:
            dist = float(rng.uniform(0.3, 0.55)) * s
            G_new = G_home + np.array([c * dist, sn * dist, 0.0])
            pitch_max = float(rng.uniform(0.3, 0.7))
            flex = float(rng.uniform(0.2, 0.5))
            z_lat = float(rng.uniform(0.06, 0.16)) * s
        _step_to(plan, A, G_new, t, dur=0.45, clear=0.05)
        a = t + 0.5
        b, c_ = a + T_in, a + T_in + T_hold
        d = c_ + T_out
        share = float(rng.uniform(0.65, 0.8))
        lamL = share if A == 0 else 1 - share
        plan.lam_pins += [(b, lamL), (c_, lamL)]
        t_back = d + 0.05
        _step_to(plan, A, G_home, t_back, dur=0.45, clear=0.05)
        t_back += 0.5
    t_end = t_back + float(rng.uniform(0.25, 0.5))
    plan.lam_pins.append((t_end, 0.5))
    knots = [(a - 1.0, 0.0), (a, 0.0), (b, 1.0), (c_, 1.0), (d, 0.0)]
    wiggle = float(rng.uniform(0.0, 0.25))
    z_rest = plan.z_rest

    def fn(tt):
        prof = np.clip(_keys(tt, knots), 0, 1)
        hold = _window(tt, b, c_, 0.25)
        osc = wiggle * hold * np.sin(2 * np.pi * 1.2 * (tt - b))
        P = _neutral(plan, len(tt))
        for sd in SIDES:
            reaching = sd == side or both
            if kind == "high" and reaching:
                P.arm(sd, down=prof * (-1.3 - st["arm_down"]) + osc * 0.3, fwd=prof * 0.2,
                      elbow=prof * (0.05 - st["elbow"]))
            elif kind == "side" and reaching:
                P.arm(sd, down=prof * (-0.1 - st["arm_down"]) + osc * 0.3, fwd=prof * 0.3,
                      elbow=prof * (0.05 - st["elbow"]))
            elif kind == "forward" and reaching:
                P.arm(sd, fwd=prof * (1.0 + pitch_max + flex - st["arm_fwd"]) + osc * 0.3,
                      elbow=prof * (0.05 - st["elbow"]))
            elif kind == "side":
                P.arm(sd, down=prof * (0.8 - st["arm_down"]))
        P.spine(flex=prof * flex, lat=prof * lat)
        P.neck(flex=prof * (-0.45 if kind == "high" else 0.1))
        return dict(z=z_rest + prof * rise - prof * z_lat, yaw=np.full(len(tt), heading),
                    pitch=prof * pitch_max, roll=prof * roll_max, upper=P.array())

    plan.add_segment("reach", t0, t_end, fn, reach=kind)


SEGMENTS: dict[str, Callable[[Plan], None]] = {
    "stand": lambda plan: seg_stand(plan),
    "walk": lambda plan: seg_locomotion(plan, backward=plan.rng.uniform() < 0.25),
    "run": lambda plan: seg_locomotion(plan, run=True),
    "jump": seg_jump,
    "squat": seg_squat,
    "lunge": seg_lunge,
    "kick": seg_kick,
    "dance": seg_dance,
    "bend": seg_bend,
    "crouch": seg_crouch,
    "reach": seg_reach,
}
CLASSIC_KINDS = ("stand", "walk", "run", "jump", "squat", "lunge", "kick", "dance")
"""The kinds the classic generator draws from, in its draw order (the default of
``generate_motion``; the archives documented before the extended generator are made of these)."""
EXTENDED_KINDS = tuple(SEGMENTS)
"""The extended generator's kinds: the classic ones and the everyday bend, crouch and reach."""


def generate_motion(
    height_m: float, rng: np.random.Generator, duration: float, fps: float = 30.0,
    kinds: Sequence[str] | None = None, extended: bool = False, terrain: str | None = None,
) -> Motion:
    """Plan and solve one kinematic motion of at least ``duration`` seconds (uncropped).
    ``extended``: the extended generator's variation inside the segments (gestures and speed
    changes while walking; the default kinds then are :data:`EXTENDED_KINDS`). ``terrain``: a
    kind of :data:`~.terrain.TERRAIN_KINDS` placed under the plan's footsteps
    (:func:`~.terrain.place_terrain`; the motion carries the scene)."""
    ch = character(height_m)
    style = _style(rng, ch)
    plan = Plan(ch, rng, style, extended=extended)
    plan.upper_names = _upper_names(ch)
    heading = float(rng.uniform(-np.pi, np.pi))
    x0, y0 = rng.uniform(-1.0, 1.0, 2)
    feet = [_place((x0, y0), heading, _sgn(f), style["width"], style["toe_out"]) for f in (0, 1)]
    plan.start(feet, heading, style["alpha"])
    seg_stand(plan, float(rng.uniform(0.4, 0.9)), gestures=False)
    kinds = list(kinds or (EXTENDED_KINDS if extended else CLASSIC_KINDS))
    while plan.t < duration:
        kind = kinds[int(rng.integers(len(kinds)))]
        SEGMENTS[kind](plan)
        seg_stand(plan, float(rng.uniform(0.3, 0.8)), gestures=False)
    if terrain is not None:
        place_terrain(plan, rng, terrain)
    return _realize(plan, fps)
