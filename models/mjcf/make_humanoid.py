#!/usr/bin/env python
"""Generate ``src/jmocap/assets/mjcf/humanoid.xml``, jmocap's character.

Run from anywhere (pure Python + numpy, no jmocap import)::

    python models/mjcf/make_humanoid.py            # writes src/jmocap/assets/mjcf/humanoid.xml
    python models/mjcf/make_humanoid.py --check    # exit 1 if that file is out of date

The XML ships inside the package (``jmocap/assets/mjcf/``, where :func:`jmocap.load_model`
finds it in an installed wheel); this generator stays in the source tree.

The XML is the source of truth that users read; this script is how it is made, so that
the numbers in it (landmarks, de Leva 1996 parameters, joint limits) are derived in one
place and every derived number is reproducible.  ``docs/model.md`` describes the result.

Geometry
--------
Rest pose = SMPL's rest pose: standing upright, facing +x, left = +y, z up, arms in a
T-pose along +-y with the palms down.  All body frames are aligned with the world at rest
(no body quaternions) and every joint is anchored at its body origin, so a hinge's axis
reads as a world axis at rest.  Everything below is written as *world* coordinates of
the rest pose; the script turns them into parent-relative body positions.

The vertical chain is 0.07 (sole to ankle centre) + 0.43 (shank) + 0.42 (thigh) + 0.59
(hip centres to C7, de Leva's trunk) + 0.24 (C7 to vertex, de Leva's head) = 1.75 m.

Mass properties
---------------
de Leva (1996), "Adjustments to Zatsiorsky-Seluyanov's segment inertia parameters",
J. Biomech. 29(9):1223-1230, Table 4 (male): mass fraction, COM position and the three
principal radii of gyration (sagittal = about the antero-posterior axis, transverse =
about the medio-lateral axis, longitudinal), as fractions of the segment length.  The
segment lengths are ours (for a 1.75 m adult), the fractions are de Leva's.

Where one de Leva segment is carried by several bodies, the split reproduces the
segment's mass, COM and central inertia *exactly* (to rounding) in the rest pose: the
small parts (neck, collars, toes, fingers) get a solid-shape inertia of their own, and the
main part gets the segment's inertia minus the small parts' inertia and the
parallel-axis terms of all parts.  All split displacements lie along a principal axis,
so every body's inertia stays diagonal in world axes (no inertial quaternions).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

TOTAL_MASS = 73.0  # kg
HEIGHT = 1.75  # m, floor to vertex in the standing rest pose
ARMATURE = 0.01  # kg m^2 on every hinge (rotor-like inertia; keeps MuJoCo C stable at dt = 0.01)
DAMPING = 0.0  # passive joint damping: none (the controller supplies all joint torques)

# ----------------------------------------------------------------------------------------
# de Leva (1996) Table 4, male.  length_mm is de Leva's mean segment length (for his
# 1.741 m sample), listed for reference only; com_pct is measured from `origin`.
# radii (% of length): sagittal (about the AP axis), transverse (about the ML axis),
# longitudinal (about the segment's long axis).
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DeLeva:
    origin: str
    end: str
    length_mm: float
    mass_pct: float
    com_pct: float
    r_sag: float
    r_trans: float
    r_long: float


DE_LEVA = {
    "head": DeLeva("VERT", "CERV", 242.9, 6.94, 50.02, 30.3, 31.5, 26.1),  # head + neck
    "upper_trunk": DeLeva("SUPR", "XYPH", 170.7, 15.96, 29.99, 71.6, 45.4, 65.9),
    "middle_trunk": DeLeva("XYPH", "OMPH", 215.5, 16.33, 45.02, 48.2, 38.3, 46.8),
    "lower_trunk": DeLeva("OMPH", "MIDH", 145.7, 11.17, 61.15, 61.5, 55.1, 58.7),
    "upper_arm": DeLeva("SJC", "EJC", 281.7, 2.71, 57.72, 28.5, 26.9, 15.8),
    "forearm": DeLeva("EJC", "WJC", 268.9, 1.62, 45.74, 27.6, 26.5, 12.1),
    "hand": DeLeva("WJC", "DAC3", 187.9, 0.61, 36.24, 28.8, 23.5, 18.4),
    "thigh": DeLeva("HJC", "KJC", 422.2, 14.16, 40.95, 32.9, 32.9, 14.9),
    "shank": DeLeva("KJC", "LMAL", 434.0, 4.33, 44.59, 25.5, 24.9, 10.3),
    "foot": DeLeva("HEEL", "TTIP", 258.1, 1.37, 44.15, 25.7, 24.5, 12.4),
}
assert abs(sum(
    s.mass_pct * (2 if k in ("upper_arm", "forearm", "hand", "thigh", "shank", "foot") else 1)
    for k, s in DE_LEVA.items()) - 100.0) < 1e-9

# Which world axis (x, y, z) carries the (sagittal, transverse, longitudinal) radius in the
# rest pose.  Trunk, head, legs: x = AP, y = ML, z = long.  Upper arm (abducted 90 deg about
# x): AP stays x, long -> y, ML -> z.  Forearm and hand (T-pose palms down = pronated): the
# palm normal (AP in the anatomical position) -> z, ML -> x, long -> y.  Foot: long = x
# (heel to toe), ML = y, the remaining "sagittal" axis is vertical (z).
AXES = {
    "default": ("x", "y", "z"),
    "upper_arm": ("x", "z", "y"),
    "forearm": ("z", "x", "y"),
    "hand": ("z", "x", "y"),
    "foot": ("z", "y", "x"),
}

# ----------------------------------------------------------------------------------------
# Landmarks (world, rest pose, metres).  Left side; the right side is the mirror (y -> -y).
# ----------------------------------------------------------------------------------------
ANKLE_H = 0.07  # ankle joint centre (lateral malleolus) above the sole
SHANK = 0.43  # KJC - LMAL   (de Leva 434.0 mm)
THIGH = 0.42  # HJC - KJC    (de Leva 422.2 mm)
HIP_Y = 0.085  # half the distance between the hip joint centres
Z_HIP = ANKLE_H + SHANK + THIGH  # 0.92, MIDH
# de Leva's trunk CERV-MIDH (603.3 mm) scaled to 0.59 m; landmarks rounded to 1 mm:
Z_OMPH = 1.062  # omphalion (navel):     lower trunk 0.142 m (de Leva 145.7 mm)
Z_XYPH = 1.273  # xiphion:               middle trunk 0.211 m (de Leva 215.5 mm)
Z_SUPR = 1.440  # suprasternale:         upper trunk 0.167 m (de Leva 170.7 mm)
Z_CERV = 1.510  # C7 spinous process:    trunk CERV-MIDH 0.590 m (de Leva 603.3 mm)
Z_VERT = HEIGHT  # vertex:               head+neck VERT-CERV 0.240 m (de Leva 242.9 mm)
Z_PELVIS = 1.00  # pelvis (root) origin, 0.08 m above the hip centres as in SMPL
Z_SPINE2 = 1.17  # spine2 origin: splits the middle trunk in two
Z_HEAD = 1.60  # head origin: atlanto-occipital joint
Z_SHOULDER = 1.42  # height of the sternoclavicular and glenohumeral centres (arms level)
COLLAR_Y = 0.03  # sternoclavicular joint
SHOULDER_Y = 0.18  # glenohumeral joint centre
UPPER_ARM = 0.283  # SJC - EJC   (de Leva 281.7 mm x 1.75/1.741)
FOREARM = 0.270  # EJC - WJC     (de Leva 268.9 mm x 1.75/1.741)
PALM = 0.087  # WJC - MET3 (SMPL hand joint at the third knuckle; de Leva 86.2 mm)
HAND = 0.189  # WJC - DAC3 (fingertip; de Leva 187.9 mm x 1.75/1.741)
Y_ELBOW = SHOULDER_Y + UPPER_ARM  # 0.463
Y_WRIST = Y_ELBOW + FOREARM  # 0.733
Y_HAND = Y_WRIST + PALM  # 0.820
FOOT_Z = 0.025  # height of the foot's long axis (HEEL - TTIP line) and of the MTP joint
X_HEEL = -0.05  # back of the heel
X_MTP = 0.14  # ball of the foot (MTP joint): origin of the toes body (SMPL "foot")
X_TTIP = 0.21  # tip of the longest toe: foot length 0.26 m (de Leva 258.1 mm)
FOOT_HALF_WIDTH = 0.045

# Fractions of a de Leva segment given to its small part (modelling assumptions).
NECK_FRACTION = 0.15  # of head+neck: the head proper of an adult male is ~4.3 kg of ~5.1 kg
COLLAR_FRACTION = 0.10  # of the upper trunk, each side: clavicle, scapula and their muscles
TOES_FRACTION = 0.15  # of the foot: volume distal to the MTP joints
FINGERS_FRACTION = 0.25  # of the hand: the fingers distal to the knuckles

MIRROR = np.array([1.0, -1.0, 1.0])


def v(*xs: float) -> np.ndarray:
    return np.array(xs, dtype=float)


# ----------------------------------------------------------------------------------------
# Data model
# ----------------------------------------------------------------------------------------


@dataclass
class Joint:
    axis: str  # "x" | "y" | "z"
    neg_deg: float  # range = [-neg_deg, +pos_deg] (left side)
    pos_deg: float
    neg_means: str  # anatomical meaning of negative angles (left side)
    pos_means: str  # ... of positive angles (left side)
    source: str


@dataclass
class Geom:
    kind: str  # "capsule" (fromto, world) | "box" (centre, world; half sizes)
    a: np.ndarray
    b: np.ndarray  # capsule: other end; box: half sizes
    size: float = 0.0  # capsule radius


@dataclass
class Body:
    name: str
    parent: str | None
    pos: np.ndarray  # origin, world, rest pose
    joints: list[Joint] = field(default_factory=list)
    order_note: str = ""
    limits_note: str = ""
    geom: Geom | None = None
    sites: list[tuple[str, np.ndarray, str]] = field(default_factory=list)  # name, world, class
    mass: float = 0.0
    com: np.ndarray | None = None  # world
    inertia: np.ndarray | None = None  # diagonal, world axes, about the COM
    mass_note: str = ""


# ----------------------------------------------------------------------------------------
# Mass properties
# ----------------------------------------------------------------------------------------


def segment(key: str, origin: np.ndarray, end: np.ndarray):
    """de Leva segment `key` from landmark `origin` to `end` (world): mass, COM, inertia."""
    s = DE_LEVA[key]
    length = float(np.linalg.norm(end - origin))
    mass = round(TOTAL_MASS * s.mass_pct / 100.0, 4)  # exact: pct has 2 decimals, 73 kg
    com = origin + s.com_pct / 100.0 * (end - origin)
    radii = dict(zip(AXES.get(key, AXES["default"]), (s.r_sag, s.r_trans, s.r_long), strict=True))
    inertia = np.array([mass * (radii[a] / 100.0 * length) ** 2 for a in "xyz"])
    return mass, com, inertia, length


def box_inertia(m: float, sx: float, sy: float, sz: float) -> np.ndarray:
    """Solid box with full side lengths sx, sy, sz."""
    return m / 12.0 * np.array([sy**2 + sz**2, sx**2 + sz**2, sx**2 + sy**2])


def cylinder_inertia(m: float, r: float, length: float, axis: str) -> np.ndarray:
    """Solid cylinder of radius r and length `length` along world `axis`."""
    perp = m * (3 * r**2 + length**2) / 12.0
    out = np.full(3, perp)
    out["xyz".index(axis)] = m * r**2 / 2.0
    return out


def split(key, seg_mass, seg_com, seg_inertia, parts):
    """Split a de Leva segment over bodies, reproducing its mass, COM and central inertia.

    parts: list of (body, mass, com, own_inertia).  Exactly one part has mass=None and
    com=None (the main part): it gets the remaining mass and the COM that restores the
    segment COM.  Parts with own_inertia=None share the remaining inertia in proportion
    to their mass.
    """
    given = [p for p in parts if p[1] is not None]
    (main,) = [p for p in parts if p[1] is None]
    masses = {p[0].name: round(p[1], 4) for p in given}
    m_main = round(seg_mass - sum(masses.values()), 4)
    masses[main[0].name] = m_main
    moment = seg_mass * seg_com - sum(masses[p[0].name] * p[2] for p in given)
    coms = {p[0].name: p[2] for p in given}
    coms[main[0].name] = moment / m_main
    assert abs(sum(masses.values()) - seg_mass) < 1e-12
    residual = np.diag(seg_inertia).astype(float)
    for body, *_ in parts:
        d = coms[body.name] - seg_com
        residual -= masses[body.name] * (d @ d * np.eye(3) - np.outer(d, d))
    own = {p[0].name: p[3] for p in parts if p[3] is not None}
    for inertia in own.values():
        residual -= np.diag(inertia)
    assert np.allclose(residual, np.diag(np.diag(residual)), atol=1e-12), (key, residual)
    sharing = [p[0].name for p in parts if p[3] is None]
    m_share = sum(masses[n] for n in sharing)
    for body, *_ in parts:
        n = body.name
        inertia = own[n] if n in own else np.diag(residual) * masses[n] / m_share
        body.mass, body.com, body.inertia = masses[n], coms[n], inertia


def linear_density_part(c: float, a: float, b: float):
    """Mass fraction and COM (fraction of length) of [a, b] of a unit segment whose linear
    density is linear, rho(u) = 1 + k (u - 1/2), with its COM at fraction c."""
    k = 12.0 * (c - 0.5)
    assert abs(k) < 2.0  # density stays positive
    mass = (b - a) + k * ((b - 0.5) ** 2 - (a - 0.5) ** 2) / 2.0
    moment = (b**2 - a**2) / 2.0 + k * ((b**3 - a**3) / 3.0 - (b**2 - a**2) / 4.0)
    return mass, moment / mass


# ----------------------------------------------------------------------------------------
# Joint limits.  Degrees; AAOS = American Academy of Orthopaedic Surgeons (1965), "Joint
# Motion: Method of Measuring and Recording" (normal values as tabulated in Norkin & White,
# "Measurement of Joint Motion", appendix).  Angle signs: a positive hinge angle is a
# right-handed rotation about the +world axis (at rest).  The neg/pos texts are for the
# left side (and the midline); the right side mirrors: x and z ranges are negated.
# ----------------------------------------------------------------------------------------
AAOS = "AAOS 1965"
AAOS_TL = "AAOS 1965 thoracolumbar, split"
AAOS_C = "AAOS 1965 cervical"
NEUMANN = "Neumann 2010, sternoclavicular joint"
TL_NOTE = ("limits: AAOS 1965 thoracolumbar flexion 80, extension 25, lateral bending 35, rotation "
           "45 deg, split lumbar (spine1) 50/15/20/15 + thoracic (spine3) 30/10/15/30 (assumption: "
           "the lumbar spine flexes most, the thoracic spine rotates most)")


def J(axis, neg, pos, neg_means, pos_means, source=AAOS) -> Joint:
    return Joint(axis, neg, pos, neg_means, pos_means, source)


SPINE_ORDER = "y, x, z: flexion/extension, then lateral bending, then axial rotation (ISB trunk order)"


def build() -> list[Body]:
    B: dict[str, Body] = {}

    def add(b: Body) -> Body:
        B[b.name] = b
        return b

    # ---- trunk ----------------------------------------------------------------------
    pelvis = add(Body("pelvis", None, v(0, 0, Z_PELVIS)))
    pelvis.geom = Geom("capsule", v(0, -0.07, 0.97), v(0, 0.07, 0.97), 0.09)
    pelvis.sites = [("kp_mid_hip", v(0, 0, Z_HIP), "kp")]

    spine1 = add(Body("spine1", "pelvis", v(0, 0, Z_OMPH), order_note=SPINE_ORDER))
    spine1.limits_note = TL_NOTE
    spine1.joints = [
        J("y", 15, 50, "extension", "flexion (trunk bends forward)", AAOS_TL),
        J("x", 20, 20, "left lateral bending", "right lateral bending", AAOS_TL),
        J("z", 15, 15, "axial rotation to the right", "axial rotation to the left", AAOS_TL),
    ]
    spine1.geom = Geom("capsule", v(0, -0.065, 1.115), v(0, 0.065, 1.115), 0.08)
    spine1.sites = [("kp_spine", v(0, 0, 1.15), "kp")]

    spine2 = add(Body("spine2", "spine1", v(0, 0, Z_SPINE2)))
    spine2.geom = Geom("capsule", v(0, -0.07, 1.22), v(0, 0.07, 1.22), 0.085)

    spine3 = add(Body("spine3", "spine2", v(0, 0, Z_XYPH), order_note=SPINE_ORDER))
    spine3.limits_note = TL_NOTE
    spine3.joints = [
        J("y", 10, 30, "extension", "flexion", AAOS_TL),
        J("x", 15, 15, "left lateral bending", "right lateral bending", AAOS_TL),
        J("z", 30, 30, "axial rotation to the right", "axial rotation to the left", AAOS_TL),
    ]
    spine3.geom = Geom("capsule", v(0, -0.075, 1.36), v(0, 0.075, 1.36), 0.1)
    spine3.sites = [
        ("kp_thorax", v(0, 0, 1.40), "kp"),
        ("kp_neck", v(0, 0, Z_SHOULDER), "kp"),  # OpenPose neck: between the shoulders
    ]

    neck = add(Body("neck", "spine3", v(0, 0, Z_CERV), order_note=SPINE_ORDER))
    neck.joints = [
        J("y", 45, 45, "extension", "flexion (chin to chest)", AAOS_C),
        J("x", 45, 45, "left lateral flexion", "right lateral flexion", AAOS_C),
        J("z", 60, 60, "rotation to the right", "rotation to the left", AAOS_C),
    ]
    neck.geom = Geom("capsule", v(0, 0, 1.52), v(0, 0, 1.59), 0.05)

    head = add(Body("head", "neck", v(0, 0, Z_HEAD)))
    head.geom = Geom("capsule", v(0.02, 0, 1.63), v(0.02, 0, 1.67), 0.08)  # top at 1.75
    head.sites = [
        ("kp_head_top", v(0, 0, Z_VERT), "kp"),
        ("kp_nose", v(0.11, 0, 1.60), "kp"),
        ("kp_left_eye", v(0.085, 0.032, 1.64), "kp"),
        ("kp_left_ear", v(0.0, 0.075, 1.62), "kp"),
    ]

    # ---- left leg --------------------------------------------------------------------
    hip = add(Body("left_hip", "pelvis", v(0, HIP_Y, Z_HIP),
                   order_note="y, x, z: flexion/extension, ab/adduction, axial rotation (ISB hip)"))
    hip.joints = [
        J("y", 120, 30, "flexion (thigh forward)", "extension (thigh backward)"),
        J("x", 30, 45, "adduction", "abduction"),
        J("z", 45, 45, "internal rotation", "external rotation"),
    ]
    hip.geom = Geom("capsule", v(0, HIP_Y, Z_HIP - 0.05), v(0, HIP_Y, 0.55), 0.07)
    hip.sites = [("kp_left_hip", v(0, HIP_Y, Z_HIP), "kp")]

    knee = add(Body("left_knee", "left_hip", v(0, HIP_Y, ANKLE_H + SHANK)))
    knee.joints = [J("y", 0, 135, "no hyperextension",
                     "flexion (shank moves backward, -x)")]
    knee.geom = Geom("capsule", v(0, HIP_Y, 0.45), v(0, HIP_Y, ANKLE_H + 0.05), 0.05)
    knee.sites = [("kp_left_knee", v(0, HIP_Y, ANKLE_H + SHANK), "kp")]

    ankle = add(Body("left_ankle", "left_knee", v(0, HIP_Y, ANKLE_H),
                     order_note="y, z, x: plantar/dorsiflexion, ab/adduction, inversion/eversion (ISB ankle)"))
    ankle.joints = [
        J("y", 20, 50, "dorsiflexion (toes up)", "plantarflexion (toes down)"),
        J("z", 30, 30, "adduction (toes inward)", "abduction (toes outward)",
          "assumption (not in AAOS; also stands in for tibial rotation, as the knee has 1 DoF)"),
        J("x", 35, 15, "inversion (sole turns inward)", "eversion (sole turns outward)"),
    ]
    x0 = X_HEEL
    ankle.geom = Geom("box", v((x0 + X_MTP) / 2, HIP_Y, 0.03),
                      v((X_MTP - x0) / 2, FOOT_HALF_WIDTH, 0.03))
    ankle.sites = [
        ("kp_left_ankle", v(0, HIP_Y, ANKLE_H), "kp"),
        ("kp_left_heel", v(X_HEEL, HIP_Y, FOOT_Z), "kp"),
        ("contact_left_heel", v(-0.03, HIP_Y, 0.0), "contact"),
    ]

    toes = add(Body("left_foot", "left_ankle", v(X_MTP, HIP_Y, FOOT_Z)))
    toes.joints = [J("y", 70, 45, "extension (toes up)", "flexion (toes curl down)",
                     "AAOS 1965 first MTP")]
    toes.geom = Geom("box", v((X_MTP + X_TTIP) / 2, HIP_Y, FOOT_Z / 2),
                     v((X_TTIP - X_MTP) / 2, FOOT_HALF_WIDTH, FOOT_Z / 2))
    toes.sites = [
        ("kp_left_big_toe", v(X_TTIP, HIP_Y - 0.025, 0.02), "kp"),
        ("kp_left_small_toe", v(0.17, HIP_Y + 0.035, 0.02), "kp"),
        ("contact_left_toe", v(0.16, HIP_Y, 0.0), "contact"),
    ]

    # ---- left arm --------------------------------------------------------------------
    collar = add(Body("left_collar", "spine3", v(0, COLLAR_Y, Z_SHOULDER),
                      order_note="z, x: protraction/retraction, then elevation/depression (ISB clavicle)"))
    collar.joints = [
        J("z", 20, 20, "protraction (shoulder forward)", "retraction (shoulder backward)",
          NEUMANN),
        J("x", 10, 45, "depression", "elevation (shrug)",
          NEUMANN),
    ]
    collar.geom = Geom("capsule", v(0, COLLAR_Y + 0.02, Z_SHOULDER),
                       v(0, SHOULDER_Y - 0.05, Z_SHOULDER), 0.035)

    shoulder = add(Body(
        "left_shoulder", "left_collar", v(0, SHOULDER_Y, Z_SHOULDER),
        order_note=("x, z, y: elevation in the frontal plane, horizontal flexion/extension, axial "
                    "rotation; singular only with the arm pointing straight forward/backward "
                    "(z = -+90 deg), not with the arms down at the sides")))
    shoulder.joints = [
        J("x", 105, 90, "adduction (90 = arm down at the side, then 15 across the body)",
          "abduction beyond the T-pose (90 = arm overhead)",
          "AAOS 1965 abduction 0-180 from the arm at the side; T-pose = 90"),
        J("z", 135, 45, "horizontal flexion (arm forward, across the chest)",
          "horizontal extension (arm backward)", "AAOS 1965 horizontal flexion/extension"),
        J("y", 90, 70, "external rotation", "internal rotation",
          "AAOS 1965, measured in 90 deg abduction"),
    ]
    shoulder.geom = Geom("capsule", v(0, SHOULDER_Y + 0.03, Z_SHOULDER),
                         v(0, Y_ELBOW - 0.03, Z_SHOULDER), 0.045)
    shoulder.sites = [("kp_left_shoulder", v(0, SHOULDER_Y, Z_SHOULDER), "kp")]

    elbow = add(Body("left_elbow", "left_shoulder", v(0, Y_ELBOW, Z_SHOULDER)))
    elbow.joints = [J("z", 150, 0, "flexion (forearm moves forward, +x)",
                      "no hyperextension")]
    elbow.geom = Geom("capsule", v(0, Y_ELBOW + 0.03, Z_SHOULDER),
                      v(0, Y_WRIST - 0.03, Z_SHOULDER), 0.035)
    elbow.sites = [("kp_left_elbow", v(0, Y_ELBOW, Z_SHOULDER), "kp")]

    wrist = add(Body("left_wrist", "left_elbow", v(0, Y_WRIST, Z_SHOULDER),
                     order_note="x, z: flexion/extension, then radial/ulnar deviation (ISB wrist)"))
    wrist.joints = [
        J("x", 80, 70, "flexion (fingers down, to the palm side)", "extension (fingers up)"),
        J("z", 20, 30, "radial deviation (fingers forward, thumb side)",
          "ulnar deviation (fingers backward, little-finger side)"),
    ]
    wrist.geom = Geom("capsule", v(0, Y_WRIST + 0.02, Z_SHOULDER),
                      v(0, Y_HAND - 0.01, Z_SHOULDER), 0.03)
    wrist.sites = [("kp_left_wrist", v(0, Y_WRIST, Z_SHOULDER), "kp")]

    hand = add(Body("left_hand", "left_wrist", v(0, Y_HAND, Z_SHOULDER)))
    hand.geom = Geom("capsule", v(0, Y_HAND + 0.015, Z_SHOULDER),
                     v(0, Y_WRIST + HAND - 0.015, Z_SHOULDER), 0.015)

    # ---- mass properties (left side and trunk) ---------------------------------------
    m, c, inertia, _ = segment("lower_trunk", v(0, 0, Z_OMPH), v(0, 0, Z_HIP))
    pelvis.mass, pelvis.com, pelvis.inertia = m, c, inertia
    pelvis.mass_note = "lower trunk (OMPH-MIDH), all of it"

    # middle trunk: linear mass density along the segment, matching de Leva's COM
    top, bottom = v(0, 0, Z_XYPH), v(0, 0, Z_OMPH)
    m, c, inertia, length = segment("middle_trunk", top, bottom)
    u = (Z_XYPH - Z_SPINE2) / length
    f1, c1 = linear_density_part(DE_LEVA["middle_trunk"].com_pct / 100, u, 1.0)
    split("middle_trunk", m, c, inertia, [
        (spine1, m * f1, top + c1 * (bottom - top), None),
        (spine2, None, None, None),
    ])
    spine1.mass_note = (f"middle trunk (XYPH-OMPH) below z = {Z_SPINE2}: {100 * f1:.1f}% of it "
                        "(linear density matching its COM); inertia shared by mass")
    spine2.mass_note = f"middle trunk above z = {Z_SPINE2}: the rest of it"

    m, c, inertia, _ = segment("upper_trunk", v(0, 0, Z_SUPR), v(0, 0, Z_XYPH))
    m_collar = round(m * COLLAR_FRACTION, 4)
    collar_len = SHOULDER_Y - COLLAR_Y
    collar_com = v(0, (COLLAR_Y + SHOULDER_Y) / 2, Z_SHOULDER)
    collar_I = cylinder_inertia(m_collar, 0.04, collar_len, "y")
    # the right collar is made later by mirroring; this stand-in only carries its share here
    right_collar_dummy = Body("right_collar", None, v(0, 0, 0))
    split("upper_trunk", m, c, inertia, [
        (spine3, None, None, None),
        (collar, m_collar, collar_com, collar_I),
        (right_collar_dummy, m_collar, collar_com * MIRROR, collar_I),
    ])
    spine3.mass_note = (f"upper trunk (SUPR-XYPH) less the two collars ({100 - 200 * COLLAR_FRACTION:.0f}%)")
    collar.mass_note = (f"{100 * COLLAR_FRACTION:.0f}% of the upper trunk (shoulder girdle; "
                        f"assumption), COM mid-clavicle, solid cylinder r 0.04 m")

    m, c, inertia, _ = segment("head", v(0, 0, Z_VERT), v(0, 0, Z_CERV))
    neck_len = Z_HEAD - Z_CERV
    m_neck = m * NECK_FRACTION
    split("head", m, c, inertia, [
        (head, None, None, None),
        (neck, m_neck, v(0, 0, (Z_CERV + Z_HEAD) / 2), cylinder_inertia(round(m_neck, 4), 0.055, neck_len, "z")),
    ])
    neck.mass_note = (f"{100 * NECK_FRACTION:.0f}% of de Leva's head+neck (assumption: the head proper "
                      "of an adult male is ~4.3 kg), COM mid-neck, solid cylinder r 0.055 m")
    head.mass_note = f"de Leva's head+neck (VERT-CERV) less the neck ({100 - 100 * NECK_FRACTION:.0f}%)"

    m, c, inertia, _ = segment("thigh", v(0, HIP_Y, Z_HIP), v(0, HIP_Y, ANKLE_H + SHANK))
    hip.mass, hip.com, hip.inertia = m, c, inertia
    hip.mass_note = "thigh (HJC-KJC)"
    m, c, inertia, _ = segment("shank", v(0, HIP_Y, ANKLE_H + SHANK), v(0, HIP_Y, ANKLE_H))
    knee.mass, knee.com, knee.inertia = m, c, inertia
    knee.mass_note = "shank (KJC-LMAL)"

    m, c, inertia, _ = segment("foot", v(X_HEEL, HIP_Y, FOOT_Z), v(X_TTIP, HIP_Y, FOOT_Z))
    m_toes = round(m * TOES_FRACTION, 4)
    split("foot", m, c, inertia, [
        (ankle, None, None, None),
        (toes, m_toes, v((X_MTP + X_TTIP) / 2, HIP_Y, FOOT_Z),
         box_inertia(m_toes, X_TTIP - X_MTP, 2 * FOOT_HALF_WIDTH, FOOT_Z)),
    ])
    ankle.mass_note = f"foot (HEEL-TTIP) less the toes ({100 - 100 * TOES_FRACTION:.0f}%)"
    toes.mass_note = (f"{100 * TOES_FRACTION:.0f}% of the foot (toes distal to the MTP joint; "
                      "assumption), solid box of the toe geom")

    m, c, inertia, _ = segment("upper_arm", v(0, SHOULDER_Y, Z_SHOULDER), v(0, Y_ELBOW, Z_SHOULDER))
    shoulder.mass, shoulder.com, shoulder.inertia = m, c, inertia
    shoulder.mass_note = "upper arm (SJC-EJC)"
    m, c, inertia, _ = segment("forearm", v(0, Y_ELBOW, Z_SHOULDER), v(0, Y_WRIST, Z_SHOULDER))
    elbow.mass, elbow.com, elbow.inertia = m, c, inertia
    elbow.mass_note = "forearm (EJC-WJC)"

    m, c, inertia, _ = segment("hand", v(0, Y_WRIST, Z_SHOULDER), v(0, Y_WRIST + HAND, Z_SHOULDER))
    m_fingers = round(m * FINGERS_FRACTION, 4)
    split("hand", m, c, inertia, [
        (wrist, None, None, None),
        (hand, m_fingers, v(0, (Y_HAND + Y_WRIST + HAND) / 2, Z_SHOULDER),
         box_inertia(m_fingers, 0.08, Y_WRIST + HAND - Y_HAND, 0.02)),
    ])
    wrist.mass_note = f"hand (WJC-DAC3) less the fingers ({100 - 100 * FINGERS_FRACTION:.0f}%)"
    hand.mass_note = (f"{100 * FINGERS_FRACTION:.0f}% of the hand (fingers distal to the knuckles; "
                      "assumption), solid box 0.08 x 0.102 x 0.02 m")

    # ---- mirror the left side --------------------------------------------------------
    order = ["pelvis",
             "left_hip", "left_knee", "left_ankle", "left_foot",
             "right_hip", "right_knee", "right_ankle", "right_foot",
             "spine1", "spine2", "spine3", "neck", "head",
             "left_collar", "left_shoulder", "left_elbow", "left_wrist", "left_hand",
             "right_collar", "right_shoulder", "right_elbow", "right_wrist", "right_hand"]
    for name in list(B):
        if name.startswith("left_"):
            add(mirror(B[name]))
    for b in (head, spine3):  # midline bodies carrying left-side sites
        b.sites += [(n.replace("left_", "right_"), p * MIRROR, k)
                    for n, p, k in b.sites if "left_" in n]
    return [B[n] for n in order]


def mirror(b: Body) -> Body:
    r = lambda s: s.replace("left_", "right_") if s else s  # noqa: E731
    joints = []
    for j in b.joints:
        if j.axis == "y":  # rotations about y are unchanged by the y-mirror
            joints.append(j)
        else:  # about x or z: the mirror image of angle a is -a
            joints.append(Joint(j.axis, j.pos_deg, j.neg_deg, j.pos_means, j.neg_means, j.source))
    g = b.geom
    geom = None if g is None else Geom(
        g.kind, g.a * MIRROR, g.b * MIRROR if g.kind == "capsule" else g.b, g.size)
    return Body(r(b.name), r(b.parent), b.pos * MIRROR, joints, order_note=b.order_note,
                limits_note=b.limits_note, geom=geom,
                sites=[(r(n), p * MIRROR, k) for n, p, k in b.sites],
                mass=b.mass, com=b.com * MIRROR, inertia=b.inertia.copy(), mass_note=b.mass_note)


# ----------------------------------------------------------------------------------------
# XML writing
# ----------------------------------------------------------------------------------------


def fmt(x: float, digits: int = 6) -> str:
    s = f"{x:.{digits}f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def vec(a, digits: int = 6) -> str:
    return " ".join(fmt(float(x), digits) for x in a)


def gfmt(x: float) -> str:
    return f"{x:.6g}"


def signed(sign: str, deg: float, text: str) -> str:
    return f"{sign}{deg:g} {text}" if deg else f"{sign}0 ({text})"


def check_inertia(b: Body) -> None:
    i = b.inertia
    assert b.mass > 0 and np.all(i > 0), b.name
    for k in range(3):
        assert i[k] <= i[(k + 1) % 3] + i[(k + 2) % 3], (b.name, i)


def body_xml(b: Body, by_parent: dict[str, list[Body]], depth: int) -> list[str]:
    ind = "  " * depth
    out: list[str] = []
    parent_pos = BODIES[b.parent].pos if b.parent else np.zeros(3)
    rel = b.pos - parent_pos
    out.append(f'{ind}<body name="{b.name}" pos="{vec(rel, 4)}">')
    i2 = ind + "  "
    if b.parent is None:
        out.append(f'{i2}<freejoint name="root"/>')
    if b.joints:
        if len(b.joints) > 1:
            out.append(f"{i2}<!-- Euler order {b.order_note} -->")
        if b.limits_note:
            out.append(f"{i2}<!-- {b.limits_note} -->")
        for j in b.joints:
            lo, hi = -math.radians(j.neg_deg), math.radians(j.pos_deg)
            axis = {"x": "1 0 0", "y": "0 1 0", "z": "0 0 1"}[j.axis]
            note = (f"deg: {signed('+', j.pos_deg, j.pos_means)} / "
                    f"{signed('-', j.neg_deg, j.neg_means)}; {j.source}")
            out.append(f'{i2}<joint name="{b.name}_{j.axis}" axis="{axis}" '
                       f'range="{fmt(lo, 4)} {fmt(hi, 4)}"/>  <!-- {note} -->')
    check_inertia(b)
    out.append(f"{i2}<!-- {b.mass_note} -->")
    out.append(f'{i2}<inertial pos="{vec(b.com - b.pos)}" mass="{fmt(b.mass, 4)}" '
               f'diaginertia="{" ".join(gfmt(x) for x in b.inertia)}"/>')
    g = b.geom
    if g is not None:
        if g.kind == "capsule":
            out.append(f'{i2}<geom name="{b.name}_col" type="capsule" '
                       f'fromto="{vec(g.a - b.pos, 4)}  {vec(g.b - b.pos, 4)}" size="{fmt(g.size, 4)}"/>')
        else:
            out.append(f'{i2}<geom name="{b.name}_col" type="box" class="foot" '
                       f'pos="{vec(g.a - b.pos, 4)}" size="{vec(g.b, 4)}"/>')
    for name, p, kind in b.sites:
        cls = ' class="contact"' if kind == "contact" else ""
        out.append(f'{i2}<site name="{name}"{cls} pos="{vec(p - b.pos, 4)}"/>')
    for child in by_parent.get(b.name, []):
        out.extend(body_xml(child, by_parent, depth + 1))
    out.append(f"{ind}</body>")
    return out


BODIES: dict[str, Body] = {}


def deleva_table() -> list[str]:
    lines = ["  de Leva (1996) Table 4, male; lengths in mm (de Leva's mean / this model's);",
             "  COM % from the first landmark; radii of gyration % of length (sag / trans / long):"]
    ours = {"head": Z_VERT - Z_CERV, "upper_trunk": Z_SUPR - Z_XYPH,
            "middle_trunk": Z_XYPH - Z_OMPH, "lower_trunk": Z_OMPH - Z_HIP,
            "upper_arm": UPPER_ARM, "forearm": FOREARM, "hand": HAND, "thigh": THIGH,
            "shank": SHANK, "foot": X_TTIP - X_HEEL}
    for k, s in DE_LEVA.items():
        lines.append(
            f"    {k:<13} {s.origin:>4}-{s.end:<4} {s.length_mm:6.1f} / {1000 * ours[k]:5.1f}"
            f"  mass {s.mass_pct:5.2f}% = {TOTAL_MASS * s.mass_pct / 100:7.4f} kg"
            f"  COM {s.com_pct:5.2f}%  r {s.r_sag:4.1f} / {s.r_trans:4.1f} / {s.r_long:4.1f}")
    return lines


HEADER = """\
<!--
  jmocap_humanoid: the character of jmocap.  GENERATED by models/mjcf/make_humanoid.py:
  edit that script and re-run it, do not edit this file by hand.  See docs/model.md.

  World: z up, floor z = 0, gravity -9.81 z.  Rest pose (all hinge angles 0) = SMPL's rest
  pose: standing upright, facing +x, left = +y, arms in a T-pose along +-y, palms down.
  24 bodies named and parented as SMPL's joints (left_hip = thigh, left_knee = shank,
  left_ankle = hindfoot, left_foot = toes, left_wrist = palm, left_hand = fingers, ...).
  Every body frame is aligned with the world at rest (no body quats) and every joint is
  anchored at its body origin, so hinge axes read as world axes at rest.  A positive
  hinge angle is a right-handed rotation about +axis; the comment on each joint says
  what that means anatomically.  Left/right mirror: a left pose (x, y, z angles) mirrors
  to the right pose (-x, y, -z), hence the right side's x and z ranges are negated.

  Segment lengths (m): sole-ankle {ankle} | shank {shank} | thigh {thigh} | hip centres
  {hipw} apart | MIDH-C7 {trunk} | C7-vertex {headlen} | clavicle (SC-GH) {clav} |
  upper arm {ua} | forearm {fa} | wrist-knuckle {palm} | hand (wrist-fingertip) {hand} |
  foot (heel-toe tip) {foot}, ball of foot {mtp} ahead of the ankle.  Height {height} m,
  mass {mass} kg.

  qpos (nq = {nq}) = root position (3, world), root quaternion (4, w x y z), then hinges:
{qpos}
  Sites (group 3 = keypoints kp_*, group 4 = contacts contact_*; hidden by default).
  Contacts on the soles (z = 0 standing): heel on left_/right_ankle, toe on left_/right_foot.

  Mass properties: de Leva (1996), "Adjustments to Zatsiorsky-Seluyanov's segment inertia
  parameters", J. Biomech. 29(9):1223-1230, male, for {mass} kg, {height} m.  Each <inertial>
  is explicit (no inertia from geoms); where a de Leva segment spans several bodies, the
  bodies together reproduce its mass, COM and central inertia exactly in the rest pose.
  Sagittal radius = about the antero-posterior axis, transverse = about the medio-lateral
  axis.  World axes of (sag, trans, long) at rest: trunk, head, legs (x, y, z); upper arm
  (x, z, y); forearm, hand (palms down) (z, x, y); foot (z, y, x).
{deleva}

  Joint limits (range, radians; comments in degrees): AAOS (1965) "Joint Motion: Method of
  Measuring and Recording" normal values (as tabulated by Norkin & White, "Measurement of
  Joint Motion"), which agree to within a few degrees with the adult male reference values
  of Soucie et al. (2011), "Range of motion measurements: reference values and a database
  for comparison studies", Haemophilia 17:500-507.  Collars (sternoclavicular joint):
  Neumann (2010), "Kinesiology of the Musculoskeletal System", 2nd ed., ch. 5 (approximate
  values).  0 (the T-pose) lies in every range.
-->
"""


def qpos_listing(bodies: list[Body]) -> tuple[str, int]:
    names = [f"{b.name}_{j.axis}" for b in bodies for j in b.joints]
    lines, line = [], "   "
    for i, n in enumerate(names):
        item = f" {7 + i}:{n}"
        if len(line) + len(item) > 92:
            lines.append(line)
            line = "   "
        line += item
    lines.append(line)
    return "\n".join(lines), 7 + len(names)


def generate() -> str:
    bodies = build()
    BODIES.clear()
    BODIES.update({b.name: b for b in bodies})
    total = sum(b.mass for b in bodies)
    assert abs(total - TOTAL_MASS) < 1e-9, total
    by_parent: dict[str, list[Body]] = {}
    for b in bodies:
        if b.parent:
            by_parent.setdefault(b.parent, []).append(b)
    qpos, nq = qpos_listing(bodies)
    n_hinge = nq - 7
    header = HEADER.format(
        ankle=ANKLE_H, shank=SHANK, thigh=THIGH, hipw=fmt(2 * HIP_Y), trunk=fmt(Z_CERV - Z_HIP),
        headlen=fmt(Z_VERT - Z_CERV), clav=fmt(SHOULDER_Y - COLLAR_Y), ua=UPPER_ARM, fa=FOREARM,
        palm=PALM, hand=HAND, foot=fmt(X_TTIP - X_HEEL), mtp=X_MTP, height=HEIGHT,
        mass=TOTAL_MASS, nq=nq, qpos=qpos, deleva="\n".join(deleva_table()))
    xml = [header.rstrip("\n"), '<mujoco model="jmocap_humanoid">',
           '  <compiler angle="radian" autolimits="true" inertiafromgeom="false"/>',
           '  <option timestep="0.01" gravity="0 0 -9.81" cone="pyramidal"/>',
           '  <statistic center="0 0 0.9" extent="2"/>',
           "",
           "  <default>",
           f"    <!-- Hinges: armature {ARMATURE} kg m^2 (reflected rotor-like inertia added to the",
           "         diagonal of M; keeps explicit MuJoCo C simulations stable at dt = 0.01) and",
           f"         damping {fmt(DAMPING)} (no passive damping: the controller supplies every joint",
           "         torque).  The root freejoint ignores defaults: no armature on the root. -->",
           f'    <joint type="hinge" armature="{ARMATURE}" damping="{fmt(DAMPING)}"/>',
           "    <!-- Collision: body geoms (contype 1, conaffinity 0) collide with the floor",
           "         (contype 0, conaffinity 1) only, never with each other. -->",
           '    <geom contype="1" conaffinity="0" condim="3" friction="0.8 0.005 0.0001" rgba="0.8 0.62 0.48 1"/>',
           '    <site size="0.012" group="3" rgba="0.1 0.4 0.9 1"/>',
           '    <default class="foot"><geom rgba="0.25 0.25 0.3 1"/></default>',
           '    <default class="contact"><site size="0.015" group="4" rgba="0.9 0.1 0.1 1"/></default>',
           "  </default>",
           "",
           "  <asset>",
           '    <texture name="grid" type="2d" builtin="checker" width="512" height="512"',
           '             rgb1="0.25 0.3 0.35" rgb2="0.18 0.22 0.26" mark="edge" markrgb="0.4 0.45 0.5"/>',
           '    <material name="grid" texture="grid" texrepeat="1 1" texuniform="true" reflectance="0.1"/>',
           "  </asset>",
           "",
           "  <worldbody>",
           '    <light name="sun" pos="0 0 4" dir="0 0 -1" directional="true"/>',
           '    <geom name="floor" type="plane" size="0 0 0.05" material="grid" contype="0" conaffinity="1"/>',
           '    <camera name="front" mode="trackcom" pos="3.5 0 1.0" xyaxes="0 1 0 -0.05 0 1"/>',
           '    <camera name="side" mode="trackcom" pos="0 3.5 1.0" xyaxes="-1 0 0 0 -0.05 1"/>',
           f"    <!-- {len(bodies)} bodies, {n_hinge} hinges (+ free root): nq = {nq}, nv = {nq - 1} -->"]
    xml += body_xml(bodies[0], by_parent, 2)
    xml += ["  </worldbody>", "", "  <keyframe>",
            "    <!-- standing rest pose: soles at z = 0, identity root orientation, all hinges 0 -->",
            f'    <key name="stand" qpos="0 0 {fmt(Z_PELVIS)} 1 0 0 0{" 0" * n_hinge}"/>',
            "  </keyframe>", "</mujoco>", ""]
    return "\n".join(xml)


DEFAULT_OUT = Path(__file__).resolve().parents[2] / "src" / "jmocap" / "assets" / "mjcf" / "humanoid.xml"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--check", action="store_true", help="exit 1 if --out is out of date")
    args = ap.parse_args(argv)
    xml = generate()
    if args.check:
        ok = args.out.exists() and args.out.read_text() == xml
        print(f"{args.out}: {'up to date' if ok else 'OUT OF DATE'}")
        return 0 if ok else 1
    tmp = args.out.with_suffix(".xml.tmp")
    tmp.write_text(xml)
    tmp.replace(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
