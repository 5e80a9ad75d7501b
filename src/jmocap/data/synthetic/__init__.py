"""Synthetic motion clips with exact ground truth: a procedural motion generator on MuJoCo.

See ``docs/data.md`` for the full description. In short:

* :func:`generate_motion` plans a motion (walking, running, jumps, squats, lunges, kicks,
  standing with arm motion, dance-like stepping, and transitions between them; the
  extended generator adds bending to the floor, crouching and reaching, arm tasks and speed
  changes while walking: ``SynthConfig.extended_generator``) for a character of random height, as footsteps + a centre-of-mass (COM) trajectory + upper-body
  joint tracks, and turns it into MuJoCo joint angles:

  - every foot contact is a *stance* on a planned footstep: the foot is flat, or rocks about
    the heel contact point (heel strike) or about the ball of the foot (heel off / toe off);
    the rocking pivot stays exactly where it is (no sliding);
  - the horizontal COM trajectory is solved from the support phases (a least-squares
    "dynamics filter" on the linear inverted pendulum: the zero-moment point stays on the
    loaded feet; ballistic, ``x'' = 0``, while no foot touches the floor);
  - the root (pelvis) height follows a ``g = 9.81`` parabola whenever both feet are off the
    floor (running, jumps);
  - the legs are solved by Gauss-Newton inverse kinematics on MuJoCo C Jacobians
    (``mj_jacBody``) so that the feet are exactly where planned; every joint is clipped to
    its range.

* :func:`generate_clip` adds ground truth (``gt_q``, ``gt_qd`` by ``mj_differentiatePos``,
  3D keypoints, Rempe et al.'s geometric contact labels), optionally tracks the motion in a
  MuJoCo simulation (``physics=True``: a whole-body tracking controller whose root is moved by
  gravity and MuJoCo's contact forces only, with jmocap's one friction model, plus a recorded
  rescue residual where the root strays too far; giving ``gt_tau``, ``gt_grf``,
  ``gt_residual``, per-foot force, centre of pressure and free moment, and force contact
  labels), samples a static camera and projects noisy 2D keypoints (:class:`Corruption`).

Everything is deterministic for a seed: a clip's random stream is
``numpy.random.default_rng([seed, index])``.

The package, one concern per module (each imports only the ones above it):

* :mod:`~jmocap.data.synthetic.errors` -- :class:`GenerationError`;
* :mod:`~jmocap.data.synthetic.bridge` -- calling the package's JAX code (the look-at camera)
  on numpy arrays in float64;
* :mod:`~jmocap.data.synthetic.rotations`, :mod:`~jmocap.data.synthetic.curves` -- numpy
  rotation helpers (why they stay numpy: see there) and scalar functions of time;
* :mod:`~jmocap.data.synthetic.character` -- :class:`Character` (the scaled humanoid, foot
  geometry, leg IK), :func:`character`;
* :mod:`~jmocap.data.synthetic.plan` -- :class:`Plan`, :class:`Stance`, :class:`Segment`,
  :class:`Pose`;
* :mod:`~jmocap.data.synthetic.motion` -- :class:`Motion`, the realisation of a plan (pelvis
  height, COM filter, foot targets, leg solve), :func:`check_motion`;
* :mod:`~jmocap.data.synthetic.repertoire` -- the motion segments, :func:`generate_motion`;
* :mod:`~jmocap.data.synthetic.ground_truth` -- :func:`velocities`, :func:`contact_labels`;
* :mod:`~jmocap.data.synthetic.physics` -- :class:`PhysicsConfig`, :class:`SamplingConfig`,
  :func:`simulate_tracking` (the QP tracker);
* :mod:`~jmocap.data.synthetic.sampling` -- :func:`simulate_sampling` (sampling-based control
  with ``mujoco.rollout``: a root force only in its rare rescues);
* :mod:`~jmocap.data.synthetic.cameras`, :mod:`~jmocap.data.synthetic.keypoints` --
  :class:`CameraConfig`, :func:`sample_camera`; :class:`Corruption`,
  :func:`corrupt_keypoints`, :func:`clean_keypoints2d`;
* :mod:`~jmocap.data.synthetic.clips` -- :class:`SynthConfig`, :func:`generate_clip`, :func:`simulate`,
  :func:`synthesize`;
* :mod:`~jmocap.data.synthetic.imu` -- six virtual IMUs on the same motion
  (:func:`~jmocap.data.synthetic.imu.generate_imu_clip`, ``IMUSynthConfig``, ``IMUCorruption``;
  imported from there, not re-exported here).
"""

from __future__ import annotations

from jmocap.data.synthetic.cameras import (
    MOVING_KINDS,
    CameraConfig,
    look_at_extrinsics,
    project_points,
    sample_camera,
    sample_moving_camera,
)
from jmocap.data.synthetic.character import SIDES, Character, character, site_trajectories
from jmocap.data.synthetic.clips import (
    GENERATOR,
    SynthConfig,
    clip_name,
    generate_clip,
    simulate,
    synthesize,
)
from jmocap.data.synthetic.errors import GenerationError
from jmocap.data.synthetic.ground_truth import (
    CONTACT_MAX_HEIGHT_M,
    CONTACT_MAX_STEP_M,
    contact_labels,
    velocities,
)
from jmocap.data.synthetic.keypoints import Corruption, clean_keypoints2d, corrupt_keypoints
from jmocap.data.synthetic.motion import Motion, check_motion, motion_report
from jmocap.data.synthetic.physics import PhysicsConfig, SamplingConfig, simulate_tracking
from jmocap.data.synthetic.plan import MOTION_KINDS, Plan, Pose, Segment, Stance
from jmocap.data.synthetic.repertoire import (
    CLASSIC_KINDS,
    EXTENDED_KINDS,
    GESTURES,
    SEGMENTS,
    generate_motion,
    seg_bend,
    seg_crouch,
    seg_dance,
    seg_jump,
    seg_kick,
    seg_locomotion,
    seg_lunge,
    seg_reach,
    seg_squat,
    seg_stand,
)
from jmocap.data.synthetic.sampling import simulate_sampling

__all__ = [
    "CLASSIC_KINDS",
    "CONTACT_MAX_HEIGHT_M",
    "CONTACT_MAX_STEP_M",
    "EXTENDED_KINDS",
    "GENERATOR",
    "GESTURES",
    "MOTION_KINDS",
    "MOVING_KINDS",
    "SEGMENTS",
    "SIDES",
    "CameraConfig",
    "Character",
    "Corruption",
    "GenerationError",
    "Motion",
    "PhysicsConfig",
    "Plan",
    "Pose",
    "Segment",
    "Stance",
    "SynthConfig",
    "character",
    "check_motion",
    "clean_keypoints2d",
    "clip_name",
    "contact_labels",
    "corrupt_keypoints",
    "generate_clip",
    "generate_motion",
    "look_at_extrinsics",
    "motion_report",
    "project_points",
    "sample_camera",
    "sample_moving_camera",
    "seg_bend",
    "seg_crouch",
    "seg_dance",
    "seg_jump",
    "seg_kick",
    "seg_locomotion",
    "seg_lunge",
    "seg_reach",
    "seg_squat",
    "seg_stand",
    "SamplingConfig",
    "simulate",
    "simulate_sampling",
    "simulate_tracking",
    "site_trajectories",
    "synthesize",
    "velocities",
]
