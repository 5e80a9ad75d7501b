"""A motion plan: stances (footsteps) of both feet, time segments, upper-body poses.

A :class:`Plan` is what the motion segments (:mod:`jmocap.data.synthetic.repertoire`) write:
:class:`Stance` s (a foot on a ground frame ``(x, y, yaw)``, rocked about heel or ball, and how
it swings to its next stance), :class:`Segment` s (pelvis height / yaw / pitch / roll and
upper-body joint tracks as functions of time) and weight-share pins. :class:`Pose` builds
upper-body joint tracks with mirrored left/right helpers.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from jmocap.data.synthetic.character import SIDES, Character
from jmocap.data.synthetic.curves import _Track
from jmocap.data.synthetic.errors import GenerationError

MOTION_KINDS = ("walk", "run", "jump", "squat", "lunge", "kick", "stand", "dance", "bend", "crouch", "reach")
"""Every segment kind; a frame's ``Motion.kind`` indexes this tuple (append only: the archives'
``kind`` indices stay valid). The first eight are the classic generator's, the last three
the extended generator's everyday motions (:mod:`~.repertoire`)."""


@dataclass
class Stance:
    """One contact of one foot with the floor, on ground frame ``G = (x, y, yaw)`` at height ``h``
    (0: the floor; the top of a box of the plan's terrain otherwise), tilted by ``tilt`` on a ramp.

    ``phi`` knots (t, angle) rock the foot during the stance (< 0 about the heel contact
    point, > 0 about the ball of the foot); ``alpha`` knots (t, a) place the foot's share of the
    zero-moment point between heel (0) and toe (1). ``swing`` says how the foot moves after
    ``t_off`` until its next stance: ``{"mode": "world", "clear": m}`` (a swing between the
    two footsteps, lifted by ``clear``) or ``{"mode": "rel", "keys": [...], "tuck": m}``
    (relative to the pelvis heading frame: flights and kicks).
    """

    foot: int
    G: np.ndarray
    t_on: float
    t_off: float = math.inf
    phi: list = field(default_factory=list)
    alpha: list = field(default_factory=list)
    load: bool = True
    swing: dict | None = None
    h: float = 0.0  # height of the surface the footstep stands on (terrain, :mod:`~.terrain`)
    # (3, 3) the surface's rotation from level about the ground frame's origin at height h (a
    # ramp), or None (level)
    tilt: np.ndarray | None = None

    def phi_at(self, t):
        return _Track(self.phi)(t) if self.phi else np.zeros(np.shape(t))

    def alpha_at(self, t):
        return _Track(self.alpha)(t) if self.alpha else np.full(np.shape(t), 0.3)


@dataclass
class Segment:
    kind: str
    t0: float
    t1: float
    fn: Callable[[np.ndarray], dict]  # times -> {"z", "yaw", "pitch", "roll", "upper", ...}
    info: dict = field(default_factory=dict)


class Plan:
    """A motion under construction: stances of both feet, segments, weight pins."""

    def __init__(self, ch: Character, rng: np.random.Generator, style: dict, extended: bool = False):
        self.ch = ch
        self.extended = extended  # the extended generator: segments add their extra variation
        self.rng = rng
        self.style = style
        self.t = 0.0
        self.stances: tuple[list[Stance], list[Stance]] = ([], [])
        self.segments: list[Segment] = []
        self.lam_pins: list[tuple[float, float]] = []  # (t, share of the left foot)
        self.heading = 0.0
        self.z_rest = ch.z_stand - style["z_rest_drop"]
        self.scene = None  # the terrain under the footsteps (:func:`~.terrain.place_terrain`), or None
        self.swing_scene = None  # what swinging feet stay above (the terrain grown by a margin)

    # -- state -----------------------------------------------------------------------------
    def stance(self, foot: int) -> Stance:
        return self.stances[foot][-1]

    def feet(self):
        return [self.stance(0).G.copy(), self.stance(1).G.copy()]

    def mid(self):
        a, b = self.feet()
        return (a[:2] + b[:2]) / 2

    # -- footsteps -----------------------------------------------------------------------
    def start(self, feet, heading, alpha):
        for f in (0, 1):
            self.stances[f].append(Stance(f, np.asarray(feet[f], float), -math.inf,
                                          phi=[], alpha=[(0.0, alpha)]))
        self.heading = heading

    def lift(self, foot, t, phi_off=0.0, r_off=0.0, alpha_off=None, swing=None, alpha_flat=None):
        s = self.stance(foot)
        if t <= s.t_on:
            raise GenerationError("lift before landing")
        s.t_off = t
        if phi_off != 0.0 and r_off > 0:
            s.phi += [(t - r_off, 0.0), (t, phi_off)]
        elif phi_off != 0.0:
            raise GenerationError("a rocker needs a duration")
        if alpha_off is None:
            alpha_off = 1.0 if phi_off > 0 else (0.0 if phi_off < 0 else None)
        if alpha_flat is not None and r_off > 0:
            s.alpha.append((t - r_off, alpha_flat))
        if alpha_off is not None:
            s.alpha.append((t, alpha_off))
        s.swing = swing or {"mode": "world", "clear": 0.05 * self.ch.scale}

    def land(self, foot, G, t, phi_on=0.0, r_on=0.0, alpha_on=None, alpha_flat=None, load=True):
        prev = self.stance(foot)
        if t <= prev.t_off:
            raise GenerationError("landing before lift-off")
        s = Stance(foot, np.asarray(G, float), t, load=load)
        if phi_on != 0.0:
            if r_on <= 0:
                raise GenerationError("a rocker needs a duration")
            s.phi = [(t, phi_on), (t + r_on, 0.0)]
        if alpha_on is None:
            alpha_on = 1.0 if phi_on > 0 else (0.0 if phi_on < 0 else self.style["alpha"])
        s.alpha = [(t, alpha_on)]
        if alpha_flat is not None and r_on > 0:
            s.alpha.append((t + r_on, alpha_flat))
        self.stances[foot].append(s)
        return s

    def step(self, foot, G, t_lift, t_land, phi_off=0.0, r_off=0.0, phi_on=0.0, r_on=0.0,
             clear=None, swing=None, alpha_flat_off=None, alpha_flat_on=None, load=True):
        if swing is None:
            swing = {"mode": "world", "clear": (0.05 * self.ch.scale) if clear is None else clear}
        self.lift(foot, t_lift, phi_off, r_off, swing=swing, alpha_flat=alpha_flat_off)
        return self.land(foot, G, t_land, phi_on, r_on, alpha_flat=alpha_flat_on, load=load)

    def add_segment(self, kind, t0, t1, fn, **info):
        if t1 <= t0:
            raise GenerationError("empty segment")
        self.segments.append(Segment(kind, t0, t1, fn, info))
        self.t = t1


_MIRROR_SIGN = {"x": -1.0, "y": 1.0, "z": -1.0}


def _upper_names(ch: Character) -> list[str]:
    legs = set()
    for L in ch.legs:
        legs.update(int(a) for a in L.ik_qadr)
        legs.add(L.toe_qadr)
    return [n for n, a in sorted(ch.qadr.items(), key=lambda kv: kv[1]) if a not in legs]


class Pose:
    """Upper-body hinge angles (radians) as a dict of (T,) arrays, with mirrored helpers.

    Arm angles are given for the *left* side's sign convention and mirrored for the right
    (x and z negated, y kept), as ``docs/model.md`` describes.
    """

    def __init__(self, names, T, base=None):
        self.names = names
        self.v = {n: np.zeros(T) for n in names}
        if base:
            for k, val in base.items():
                self.v[k] = self.v[k] + val

    def add(self, name, val):
        if name in self.v:
            self.v[name] = self.v[name] + val

    def add_sym(self, side, joint, axis, val):
        s = 1.0 if side == "left" else _MIRROR_SIGN[axis]
        self.add(f"{side}_{joint}_{axis}", s * np.asarray(val))

    def arm(self, side, down=0.0, fwd=0.0, twist=0.0, elbow=0.0, wrist=0.0, shrug=0.0, protract=0.0):
        """Arm relative to the T-pose: ``down`` lowers it (rad, pi/2 = at the side, < 0 raises it
        above the shoulder), ``fwd`` swings it forward, ``twist`` internal rotation, ``elbow``
        flexion, ``wrist`` flexion; collar ``shrug`` / ``protract``."""
        self.add_sym(side, "shoulder", "x", -np.asarray(down))
        self.add_sym(side, "shoulder", "z", -np.asarray(fwd))
        self.add_sym(side, "shoulder", "y", np.asarray(twist))
        self.add_sym(side, "elbow", "z", -np.asarray(elbow))
        self.add_sym(side, "wrist", "x", -np.asarray(wrist))
        self.add_sym(side, "collar", "x", np.asarray(shrug))
        self.add_sym(side, "collar", "z", -np.asarray(protract))

    def spine(self, flex=0.0, lat=0.0, twist=0.0):
        """Trunk flexion (forward), lateral bend (to the right), twist (to the left), split
        between the lumbar (spine1) and thoracic (spine3) joints."""
        self.add("spine1_y", 0.6 * np.asarray(flex))
        self.add("spine3_y", 0.4 * np.asarray(flex))
        self.add("spine1_x", 0.55 * np.asarray(lat))
        self.add("spine3_x", 0.45 * np.asarray(lat))
        self.add("spine1_z", 0.35 * np.asarray(twist))
        self.add("spine3_z", 0.65 * np.asarray(twist))

    def neck(self, flex=0.0, lat=0.0, turn=0.0):
        self.add("neck_y", np.asarray(flex))
        self.add("neck_x", np.asarray(lat))
        self.add("neck_z", np.asarray(turn))

    def array(self):
        return np.stack([self.v[n] for n in self.names], axis=1)


def _neutral(plan: Plan, T) -> Pose:
    st = plan.style
    P = Pose(plan.upper_names, T)
    for side in SIDES:
        P.arm(side, down=st["arm_down"], fwd=st["arm_fwd"], twist=st["arm_twist"], elbow=st["elbow"])
    P.spine(flex=st["spine_flex"])
    P.neck(flex=st["neck_flex"])
    return P
