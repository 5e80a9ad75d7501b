"""Terrain for synthetic clips (issue 21, item 1): boxes placed under a plan's footsteps.

:func:`place_terrain` takes a finished :class:`~.plan.Plan` (its footsteps in time order, both
feet) and a terrain kind, gives every footstep a *level*, and builds the boxes that put each
footstep on the surface of its level:

* ``step_up`` / ``step_down``: a platform the walk steps onto (or starts on and steps off);
* ``stairs_up`` / ``stairs_down``: a flight of 2-4 steps, one footstep per tread, then the
  landing (one box per step, each reaching to the end of the flight: a union of nested boxes);
* ``block``: a low box the walk steps onto and off again (one to three footsteps on it);
* ``ramp_up`` / ``ramp_down``: a box pitched by 5-12 degrees whose top rises from the floor,
  walked up (or down to the floor).

Box ``j`` covers exactly the footsteps of level ``>= j`` and has its top at ``j`` rises; it is
turned to the feet's heading at its edge and fitted around those footprints (its edges a few
centimetres from the footprints next to a lower footstep, farther elsewhere). A plan whose
footsteps cannot be separated that way (a turn that brings a later footstep back beside the
edge) raises :class:`~.errors.GenerationError` and the clip is drawn again. Every footstep then
stands on exactly one surface, at the height its :class:`~.plan.Stance` carries (``h``): the
realisation (:mod:`~.motion`) raises feet, pelvis and swings by it, and measures every
clearance against :func:`jmocap.scene.surface_height`. Boxes reach 5 cm below the floor so that
the scene's signed distance is exact inside them (:mod:`jmocap.scene`). A footstep on a ramp
also carries the slope's rotation (``Stance.tilt``): its level foot pose, rocking included, is
turned onto the slope about its ground frame's origin (:func:`~.motion.on_surface`).
"""

from __future__ import annotations

import math

import numpy as np

from jmocap.data.synthetic.errors import GenerationError
from jmocap.data.synthetic.motion import on_surface
from jmocap.data.synthetic.plan import Plan, Stance
from jmocap.scene import Scene, surface_height

TERRAIN_KINDS = ("step_up", "step_down", "stairs_up", "stairs_down", "block", "ramp_up", "ramp_down")
"""The terrain kinds :func:`place_terrain` builds (``jmocap data synth --terrain``)."""
TERRAIN_WALK_KINDS = ("walk",)
"""The motion kinds of a terrain clip unless its configuration names others: walking, between
standing (stepping, squatting or jumping onto a box is possible but not drawn by default)."""

#: platform and block heights, stair rises and step counts (m, for a subject of the model's
#: nominal height; scaled by the subject's ``scale``)
PLATFORM_M = (0.08, 0.25)
BLOCK_M = (0.08, 0.20)
#: ramp slopes (degrees) and the thickness of a ramp's box (m)
RAMP_DEG = (5.0, 12.0)
RAMP_THICKNESS_M = 0.3
RISE_M = (0.10, 0.18)
STAIR_STEPS = (2, 4)
#: a footprint stays this far inside its box's edges, and a footstep of a lower level this far
#: outside a box (m)
INNER_MARGIN_M = 0.05
OUTER_MARGIN_M = 0.10
#: how far below the floor every box reaches (m)
BELOW_FLOOR_M = 0.05
#: a swinging foot passes every box by this much: above its top within this distance of its
#: edges (the realisation lifts swings over :func:`swing_clearance_scene`), so that the simulated
#: foot, a few centimetres off the plan, does not catch an edge
SWING_CLEARANCE_M = 0.05


def _footprint(plan: Plan, s: Stance) -> np.ndarray:
    """The sole points (n, 2) of a flat foot on the stance's ground frame."""
    ch = plan.ch
    R, p, toe = ch.stance_pose(s.foot, s.G, np.array(0.0))
    return ch.foot_points(s.foot, R, p, toe)[..., :2]


def _levels(kind: str, n: int, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Each footstep's level (n,) and the height of one level (m, before scaling)."""
    i = np.arange(n)
    if kind in ("step_up", "step_down"):
        k = int(rng.integers(2, max(3, n - 1)))
        lev = (i >= k).astype(int)
        rise = float(rng.uniform(*PLATFORM_M))
    elif kind in ("stairs_up", "stairs_down"):
        steps = int(rng.integers(STAIR_STEPS[0], STAIR_STEPS[1] + 1))
        k = int(rng.integers(2, max(3, n - steps)))
        lev = np.clip(i - k + 1, 0, steps)
        rise = float(rng.uniform(*RISE_M))
    elif kind in ("ramp_up", "ramp_down"):
        k = int(rng.integers(2, max(3, n - 2)))
        lev = (i >= k).astype(int)
        rise = 0.0  # the slope is drawn by _ramp
    elif kind == "block":
        m = int(rng.integers(1, 4))
        k = int(rng.integers(2, max(3, n - m)))
        lev = ((i >= k) & (i < k + m)).astype(int)
        rise = float(rng.uniform(*BLOCK_M))
    else:
        raise ValueError(f"unknown terrain kind {kind!r}; one of {', '.join(TERRAIN_KINDS)}")
    if kind.endswith("_down"):
        lev = lev[::-1].copy()
    return lev, rise


def _box_frame(stances: list[Stance], lev: np.ndarray, j: int, prints: list[np.ndarray]):
    """The frame of the box that carries the footsteps of level ``>= j``: its heading (the feet's
    mean facing at its edge(s), the footsteps next to a lower one) as a 2D rotation ``R2``, the
    footprints inside and outside it in that frame (``uv = xy @ R2``) and the inside ones'
    bounds ``lo``, ``hi``."""
    n = len(stances)
    inside, outside = np.nonzero(lev >= j)[0], np.nonzero(lev < j)[0]
    edge = [i for i in inside if (i > 0 and lev[i - 1] < j) or (i + 1 < n and lev[i + 1] < j)]
    yaw = math.atan2(sum(math.sin(stances[i].G[2]) for i in edge), sum(math.cos(stances[i].G[2]) for i in edge))
    R2 = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    uv_in = np.concatenate([prints[i] for i in inside]) @ R2
    uv_out = np.concatenate([prints[i] for i in outside]) @ R2
    return R2, uv_in, uv_out, uv_in.min(0), uv_in.max(0)


def place_terrain(plan: Plan, rng: np.random.Generator, kind: str) -> Scene:
    """Boxes under the plan's footsteps for a terrain ``kind`` (:data:`TERRAIN_KINDS`); sets each
    stance's ``h`` and returns the scene. Raises :class:`GenerationError` when the footsteps
    cannot carry the terrain (too few of them, or a box that would also cover a lower one)."""
    stances = sorted((s for f in (0, 1) for s in plan.stances[f]), key=lambda s: (s.t_on, s.foot))
    n = len(stances)
    if n < 5:
        raise GenerationError(f"terrain {kind!r} needs at least 5 footsteps, the plan has {n}")
    lev, rise = _levels(kind, n, rng)
    if lev.max() == 0 or lev.min() == lev.max():
        raise GenerationError(f"terrain {kind!r}: every footstep on one level")
    prints = [_footprint(plan, s) for s in stances]
    if kind.startswith("ramp"):
        return _ramp(plan, rng, kind, stances, lev, prints)
    rise *= plan.ch.scale
    centers, halves, rots = [], [], []
    for j in range(1, int(lev.max()) + 1):
        R2, uv_in, uv_out, lo, hi = _box_frame(stances, lev, j, prints)
        lo_m, hi_m = lo.copy(), hi.copy()
        # along the heading: tight where a lower footstep lies beyond the edge, long elsewhere
        far = rng.uniform(0.3, 1.0, 2) * plan.ch.scale
        tight = rng.uniform(INNER_MARGIN_M, 0.10, 2)
        lo_m[0] -= tight[0] if np.any(uv_out[:, 0] < lo[0]) else far[0]
        hi_m[0] += tight[1] if np.any(uv_out[:, 0] > hi[0]) else far[1]
        # across: 0.15-0.6 m beyond the footprints, less where a lower footstep lies beside them
        side = rng.uniform(0.15, 0.6, 2) * plan.ch.scale
        beside = uv_out[(uv_out[:, 0] > lo_m[0] - OUTER_MARGIN_M) & (uv_out[:, 0] < hi_m[0] + OUTER_MARGIN_M), 1]
        room_lo = lo[1] - beside[beside < lo[1]].max(initial=-np.inf) - 2 * OUTER_MARGIN_M
        room_hi = beside[beside > hi[1]].min(initial=np.inf) - hi[1] - 2 * OUTER_MARGIN_M
        lo_m[1] -= max(min(side[0], room_lo), INNER_MARGIN_M)
        hi_m[1] += max(min(side[1], room_hi), INNER_MARGIN_M)
        grown_lo, grown_hi = lo_m - OUTER_MARGIN_M, hi_m + OUTER_MARGIN_M
        hit = np.all((uv_out > grown_lo) & (uv_out < grown_hi), axis=1)
        if hit.any():
            raise GenerationError(f"terrain {kind!r}: box {j} would cover a footstep of a lower level")
        c2 = R2 @ ((lo_m + hi_m) / 2)
        top = j * rise
        centers.append([c2[0], c2[1], (top - BELOW_FLOOR_M) / 2])
        halves.append([(hi_m[0] - lo_m[0]) / 2, (hi_m[1] - lo_m[1]) / 2, (top + BELOW_FLOOR_M) / 2])
        rots.append([[R2[0, 0], R2[0, 1], 0.0], [R2[1, 0], R2[1, 1], 0.0], [0.0, 0.0, 1.0]])
    scene = Scene(np.array(centers), np.array(halves), np.array(rots))
    for s, lv in zip(stances, lev, strict=True):
        s.h = float(lv * rise)
    return _attach(plan, scene, stances, kind)


def _attach(plan: Plan, scene: Scene, stances: list[Stance], kind: str) -> Scene:
    """Check that every footstep's sole lies on its surface (the plane through its ground frame's
    origin at height ``h``, tilted by ``tilt`` on a ramp) as the scene has it there, and give the
    plan the scene and its swing-clearance scene. A footprint across an edge raises (it cannot
    happen by construction)."""
    ch = plan.ch
    for s in stances:
        Rf, pf, toe = ch.stance_pose(s.foot, s.G, np.array(0.0))
        Rf, pf = on_surface(s, Rf, pf.copy())
        sole = ch.foot_points(s.foot, Rf, pf, toe)
        n_up = (s.tilt if s.tilt is not None else np.eye(3))[:, 2]
        plane = s.h - (n_up[0] * (sole[:, 0] - s.G[0]) + n_up[1] * (sole[:, 1] - s.G[1])) / n_up[2]
        if np.max(np.abs(surface_height(scene, sole[:, :2]) - plane)) > 1e-9:
            raise GenerationError(f"terrain {kind!r}: a footprint is not on one surface")
    plan.scene = scene
    plan.swing_scene = swing_clearance_scene(scene)
    return scene


def _ramp(plan: Plan, rng: np.random.Generator, kind: str, stances: list[Stance], lev: np.ndarray,
          prints: list[np.ndarray]) -> Scene:
    """A ramp under the footsteps of level 1: a box pitched by 5-12 degrees whose top rises away
    from the level-0 footsteps, from the floor at its low edge (a few centimetres before the
    first footstep on it) to beyond the last. Each footstep on it stands at the slope's height
    under its ground frame's origin, tilted with it (``Stance.tilt``)."""
    R2, uv_in, uv_out, lo, hi = _box_frame(stances, lev, 1, prints)
    d = 1.0 if np.any(uv_out[:, 0] < lo[0]) else -1.0  # the slope rises away from the level footsteps
    if np.any(uv_out[:, 0] < lo[0]) and np.any(uv_out[:, 0] > hi[0]):
        raise GenerationError(f"terrain {kind!r}: level footsteps on both sides of the ramp")
    alpha = math.radians(float(rng.uniform(*RAMP_DEG)))
    tight = float(rng.uniform(INNER_MARGIN_M, 0.10))
    far = float(rng.uniform(0.3, 1.0)) * plan.ch.scale
    u0 = lo[0] - tight if d > 0 else hi[0] + tight  # the low edge, on the floor
    u1 = hi[0] + far if d > 0 else lo[0] - far
    side = rng.uniform(0.15, 0.6, 2) * plan.ch.scale
    v_lo, v_hi = lo[1] - side[0], hi[1] + side[1]
    a, b = min(u0, u1), max(u0, u1)
    hit = np.all((uv_out > [a - OUTER_MARGIN_M, v_lo - OUTER_MARGIN_M]) & (uv_out < [b + OUTER_MARGIN_M, v_hi + OUTER_MARGIN_M]), 1)
    if hit.any():
        raise GenerationError(f"terrain {kind!r}: the ramp would cover a level footstep")
    # the box: its top face the plane z = d (u - u0) tan(alpha) over [a, b] x [v_lo, v_hi]
    c, s_, t = R2[0, 0], R2[1, 0], -d * alpha
    Rz = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[math.cos(t), 0.0, math.sin(t)], [0.0, 1.0, 0.0], [-math.sin(t), 0.0, math.cos(t)]])
    R = Rz @ Ry
    u_mid, v_mid = (a + b) / 2, (v_lo + v_hi) / 2
    top_mid = np.array([*(R2 @ [u_mid, v_mid]), d * (u_mid - u0) * math.tan(alpha)])
    half = np.array([(b - a) / 2 / math.cos(alpha), (v_hi - v_lo) / 2, RAMP_THICKNESS_M / 2])
    scene = Scene(np.array([top_mid - R[:, 2] * half[2]]), np.array([half]), np.array([R]))
    tilt = Rz @ Ry @ Rz.T  # about the horizontal axis across the heading
    for i, s in enumerate(stances):
        if lev[i] >= 1:
            u = float(np.asarray(s.G[:2]) @ R2[:, 0])
            s.h, s.tilt = d * (u - u0) * math.tan(alpha), tilt
    return _attach(plan, scene, stances, kind)


def swing_clearance_scene(scene: Scene, margin: float = SWING_CLEARANCE_M) -> Scene:
    """The scene's boxes grown by ``margin`` sideways and upwards: what a swinging foot must
    stay above (its stances stand on the real scene)."""
    grow = np.array([margin, margin, margin / 2])
    centers = np.asarray(scene.centers) + np.array([0.0, 0.0, margin / 2])
    return Scene(centers, np.asarray(scene.half_sizes) + grow, np.asarray(scene.rotations))
