"""Synthetic clips: the configuration and the generator of whole :class:`~jmocap.data.clip.Clip` s.

:func:`generate_clip` draws a subject height, plans and solves a motion (retrying with fresh
draws when an attempt fails), crops a window, optionally tracks it in simulation, adds the
ground truth, samples a camera and projects and corrupts the 2D keypoints; everything is
deterministic in ``(seed, index, config)``. :func:`synthesize` iterates over a seed's clips.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from jmocap.data.clip import Clip
from jmocap.data.synthetic.cameras import (
    MOVING_KINDS,
    CameraConfig,
    project_points,
    sample_camera,
    sample_moving_camera,
)
from jmocap.data.synthetic.character import site_trajectories
from jmocap.data.synthetic.curves import _runs
from jmocap.data.synthetic.errors import GenerationError
from jmocap.data.synthetic.ground_truth import (
    CONTACT_MAX_HEIGHT_M,
    CONTACT_MAX_STEP_M,
    _ground_truth,
    velocities,
)
from jmocap.data.synthetic.keypoints import Corruption, corrupt_keypoints
from jmocap.data.synthetic.motion import check_motion
from jmocap.data.synthetic.physics import PhysicsConfig, simulate_tracking
from jmocap.data.synthetic.plan import MOTION_KINDS
from jmocap.data.synthetic.repertoire import (
    CLASSIC_KINDS,
    EXTENDED_KINDS,
    SEGMENTS,
    generate_motion,
)
from jmocap.data.synthetic.sampling import simulate_sampling
from jmocap.data.synthetic.terrain import TERRAIN_KINDS, TERRAIN_WALK_KINDS
from jmocap.layouts import CONTACT_SITES, get_layout
from jmocap.scene import height_above

GENERATOR = "jmocap.data.synthetic/1"


@dataclass(frozen=True)
class SynthConfig:
    """What :func:`generate_clip` makes. ``frames`` is a clip length or a (min, max) range.

    ``extended`` turns on the extended generator's variation inside the motion segments and,
    when ``kinds`` is None, draws from all of :data:`~.repertoire.EXTENDED_KINDS`;
    :meth:`extended_generator` is the whole extended distribution (docs/data.md)."""

    frames: int | tuple[int, int] = (150, 300)
    fps: float = 30.0
    layout: str = "body25"
    physics: bool = False
    kinds: tuple[str, ...] | None = None  # motion kinds to draw from (default: all)
    height_m: tuple[float, float] = (1.5, 1.95)
    camera: CameraConfig = field(default_factory=CameraConfig)
    corruption: Corruption = field(default_factory=Corruption)
    physics_cfg: PhysicsConfig = field(default_factory=PhysicsConfig)
    max_attempts: int = 12
    extended: bool = False
    # cameras to draw from for each clip: "static" and MOVING_KINDS (handheld, pan, dolly,
    # orbit); () is a static camera (sample_camera) without the extra draw
    moving_camera: tuple[str, ...] = ()
    # terrain kinds to draw from for each clip (terrain.TERRAIN_KINDS, and "flat" for the floor
    # alone); () is the flat floor without the extra draw. Terrain clips walk (``kinds``
    # defaults to walking) and carry their scene (Clip.scene)
    terrain: tuple[str, ...] = ()

    def __post_init__(self):
        bad = [k for k in self.moving_camera if k not in MOVING_KINDS + ("static",)]
        if bad:
            raise ValueError(f"unknown camera kind(s) {bad}: one of {', '.join(MOVING_KINDS + ('static',))}")
        bad = [k for k in self.terrain if k not in TERRAIN_KINDS + ("flat",)]
        if bad:
            raise ValueError(f"unknown terrain kind(s) {bad}: one of {', '.join(TERRAIN_KINDS + ('flat',))}")
        if self.terrain and self.physics and self.physics_cfg.controller != "qp":
            raise ValueError("terrain clips are simulated with the QP tracker only (physics_cfg.controller='qp')")

    @classmethod
    def extended_generator(cls, **changes) -> SynthConfig:
        """The extended generator (issue 15 item 1): everyday motions (bend, crouch, reach)
        beside the classic ones, gestures and speed changes while walking, subjects 1.45-2.0 m,
        :meth:`CameraConfig.extended` cameras and :meth:`Corruption.extended` occlusions."""
        base = cls(extended=True, height_m=(1.45, 2.0), camera=CameraConfig.extended(),
                   corruption=Corruption.extended())
        return dataclasses.replace(base, **changes)

    def to_json(self) -> dict:
        return _jsonable(dataclasses.asdict(self))


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


def _stance_runs(planted: np.ndarray) -> dict:
    return {name: [[int(a), int(b)] for a, b in _runs(planted[:, i])]
            for i, name in enumerate(CONTACT_SITES)}


def simulate(ch, q_ref: np.ndarray, fps: float, cfg: PhysicsConfig = PhysicsConfig(),  # noqa: B008
             lead: int = 0, rng: np.random.Generator | None = None, scene=None) -> dict:
    """The physics variant's simulation with ``cfg.controller``:
    :func:`~jmocap.data.synthetic.physics.simulate_tracking` ("qp", the QP tracker with its rescue
    residual; on the terrain ``scene`` when given) or
    :func:`~jmocap.data.synthetic.sampling.simulate_sampling` ("sampling", a root force only in its rescues, drawing
    from ``rng``; flat floor only)."""
    if cfg.controller == "qp":
        return simulate_tracking(ch, q_ref, fps, cfg, lead, scene=scene)
    if scene is not None:
        raise ValueError("the sampling controller simulates the flat floor only")
    if cfg.controller == "sampling":
        return simulate_sampling(ch, q_ref, fps, cfg, lead, rng)
    raise ValueError(f"unknown physics controller {cfg.controller!r} (qp, sampling)")


def _lead_in(q: np.ndarray, start: int, frames: int) -> np.ndarray:
    """The ``frames`` reference frames before ``q[start]`` that the physics variant simulates and
    drops (the settled start): the motion's own frames where it has them, before them its first
    frame held (every motion begins with a standing segment, ``generate_motion``)."""
    own = q[max(0, start - frames):start]
    return np.concatenate([np.repeat(q[:1], frames - len(own), axis=0), own])


def clip_name(index: int) -> str:
    return f"synth_{index:06d}"


def generate_clip(seed: int, index: int = 0, config: SynthConfig = SynthConfig(),
                  name: str | None = None) -> Clip:
    """One synthetic clip, deterministic in ``(seed, index, config)``.

    Draws a subject height, plans and solves a motion (retrying with fresh draws when a
    motion fails its kinematic checks, or falls in the physics variant), crops a window of the
    requested length, optionally tracks it in simulation, samples a camera and projects and
    corrupts the 2D keypoints.
    """
    return generate_clip_and_character(seed, index, config, name)[0]


def generate_clip_and_character(seed: int, index: int = 0, config: SynthConfig = SynthConfig(),
                                name: str | None = None):
    """:func:`generate_clip` and the :class:`~jmocap.data.synthetic.character.Character` whose
    model its ground truth ``gt_q`` is a motion of (the synthetic IMUs are computed on it)."""
    layout = get_layout(config.layout)
    layout.require_sites("synthesising a clip")  # every 2D keypoint is a projected site
    kinds = tuple(config.kinds) if config.kinds else (
        TERRAIN_WALK_KINDS if config.terrain else EXTENDED_KINDS if config.extended else CLASSIC_KINDS)
    for k in kinds:
        if k not in SEGMENTS:
            raise ValueError(f"unknown motion kind {k!r}; known: {sorted(SEGMENTS)}")
    fr = config.frames
    errors = []
    for attempt in range(config.max_attempts):
        rng = np.random.default_rng([int(seed), int(index), attempt])
        T = int(fr) if np.isscalar(fr) else int(rng.integers(int(fr[0]), int(fr[1]) + 1))
        if T < 2:
            raise ValueError(f"frames per clip must be >= 2, got {T}")
        height = round(float(rng.uniform(*config.height_m)), 2)
        terrain = config.terrain[int(rng.integers(len(config.terrain)))] if config.terrain else "flat"
        try:
            motion = generate_motion(height, rng, T / config.fps + 0.5, config.fps, kinds,
                                     extended=config.extended, terrain=None if terrain == "flat" else terrain)
            check_motion(motion)
            if motion.num_frames < T:
                raise GenerationError("motion shorter than the clip")
            start = int(rng.integers(0, motion.num_frames - T + 1))
            planned = motion.q
            motion = motion.slice(start, start + T)
            ch = motion.character
            meta: dict[str, Any] = {}
            q = motion.q
            sim = {}
            if config.physics:
                q_lead = _lead_in(planned, start, config.physics_cfg.settle_frames(config.fps))
                sim = simulate(ch, np.concatenate([q_lead, q]), config.fps, config.physics_cfg,
                               lead=len(q_lead), rng=np.random.default_rng([int(seed), int(index), attempt, 1]),
                               scene=motion.scene)
                q, qd = sim["q"], sim["qd"]
                meta["physics"] = sim["stats"]
            else:
                qd = velocities(ch.mj, q, config.fps)
            kp3d, contacts = _ground_truth(ch, q, layout, config.fps, motion.scene)
            if config.physics:
                contacts = sim["contacts"]  # force and floor (docs/data.md)
                heights = height_above(motion.scene, site_trajectories(ch, q, ch.check_sites))
                meta["physics"]["min_site_height"] = float(heights.min())
            cam_kind = (config.moving_camera[int(rng.integers(len(config.moving_camera)))]
                        if config.moving_camera else "static")
            track = None
            if cam_kind == "static":
                K, size, E, cam_info = sample_camera(rng, kp3d, config.camera)
            else:
                K, size, track, cam_info = sample_moving_camera(rng, kp3d, config.fps, cam_kind, config.camera)
                E = track[0]
            uv, _ = project_points(K, E if track is None else track, kp3d)
            kp2d, corr = corrupt_keypoints(rng, uv, layout, size, config.corruption)
        except GenerationError as e:
            errors.append(f"attempt {attempt}: {e}")
            continue
        counts = np.bincount(motion.kind, minlength=len(MOTION_KINDS))
        present = [MOTION_KINDS[i] for i in np.nonzero(counts)[0]]
        main = [MOTION_KINDS[i] for i in np.argsort(-counts) if counts[i] > 0 and MOTION_KINDS[i] != "stand"]
        kind = main[0] if main else "stand"
        meta.update(
            generator=GENERATOR,
            seed=int(seed),
            index=int(index),
            attempt=attempt,
            kind=kind,
            kinds=present,
            kind_per_frame=[[MOTION_KINDS[int(motion.kind[a])], int(a), int(b)]
                            for a, b in _kind_runs(motion.kind)],
            physics_variant=bool(config.physics),
            terrain=terrain,
            planned_contacts=_stance_runs(motion.planted),
            flight_frames=int(motion.flight.sum()),
            camera=_jsonable(cam_info),
            corruption=_jsonable(dataclasses.asdict(config.corruption)),
            corruption_stats=corr,
            contact_rule=_contact_rule(config),
            clean_keypoints2d="project gt_keypoints3d with intrinsics/extrinsics "
                              "(jmocap.data.synthetic.clean_keypoints2d)",
            kinematic=_jsonable({k: v for k, v in motion.info.items() if k in ("passes", "ik_err")}),
        )
        return Clip(
            name=name or clip_name(index),
            layout=layout.name,
            fps=config.fps,
            keypoints=kp2d,
            intrinsics=K,
            image_size=size,
            extrinsics=E,
            camera_track=track,
            gt_q=q,
            gt_qd=qd,
            gt_keypoints3d=kp3d,
            gt_contacts=contacts,
            gt_tau=sim.get("tau"),
            gt_grf=sim.get("grf"),
            gt_residual=sim.get("residual"),
            gt_foot_force=sim.get("foot_force"),
            gt_cop=sim.get("cop"),
            gt_free_moment=sim.get("free_moment"),
            height_m=round(ch.height, 6),
            mass_kg=round(ch.mass, 6),
            scene=motion.scene,
            meta=meta,
        ), ch
    raise GenerationError(f"clip {index} (seed {seed}): no valid motion in {config.max_attempts} "
                          f"attempts: " + "; ".join(errors[-3:]))


def _contact_rule(config: SynthConfig) -> dict:
    """How ``gt_contacts`` was labelled: force and floor for simulated clips, Rempe et al.'s
    geometric rule otherwise (docs/data.md)."""
    if config.physics:
        return dict(rule="force_floor", min_vertical_force_bw=config.physics_cfg.contact_force_threshold,
                    site_floor_m=config.physics_cfg.site_floor_m)
    return dict(rule="geometric", max_step_m=CONTACT_MAX_STEP_M, max_height_m=CONTACT_MAX_HEIGHT_M,
                frame0="displacement to frame 1")


def _kind_runs(kind):
    out = []
    a = 0
    for i in range(1, len(kind) + 1):
        if i == len(kind) or kind[i] != kind[a]:
            out.append((a, i))
            a = i
    return out


def synthesize(n: int, seed: int, config: SynthConfig = SynthConfig(), start: int = 0) -> Iterator[Clip]:
    """Clips ``start .. start + n - 1`` of the stream for ``seed``."""
    for i in range(start, start + n):
        yield generate_clip(seed, i, config)
