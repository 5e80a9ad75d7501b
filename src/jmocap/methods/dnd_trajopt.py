"""``dnd_trajopt``: offline reconstruction from a moving camera whose track is unknown.

D&D (:mod:`jmocap.methods.dnd`, Li et al. 2022) estimates the camera's motion from the person's
dynamics, but its own forces are not fitted to its motion (the residual root force is of the
order of a body weight) and it cannot tell that a camera is still (its world root then drifts
with its contacts). Whole-clip trajectory optimisation (:mod:`jmocap.methods.trajopt`, Rempe et
al. 2020) fits the clip to its 2D evidence and to the equations of motion, but needs the camera
of every frame. This method composes the two, in one pure function of the clip:

1. **Camera track.** D&D runs on the clip (reading its first frame's camera only) and returns
   the camera track its world motion implies (:func:`jmocap.methods.dnd.estimated_track`).
2. **Fit, under two hypotheses** (jmocap's): ``trajopt`` runs with that track as if it were
   known, and again with the first frame's camera held still for every frame. D&D has no notion
   of a still camera (its estimate of one drifts with its contacts, 0.2-0.4 m/s), and a moving
   camera taken as still makes the world swing with it. Each fit is trajopt's three stages: the
   per-frame and whole-clip kinematic fits through every frame's camera, then the physics
   stage, whose contact forces (friction pyramids, variable projection) explain the world motion
   up to a penalised residual.
3. **Choice.** The still camera if its fit reprojects closer to the 2D keypoints (trajopt's
   final robust reprojection energy, ``term_reproj``) *and* needs at most ``still_max_residual``
   (5 % of body weight) of residual root force on average; else D&D's track. Both fits obey the
   same contacts and equations of motion; under a wrong camera the motion that obeys them cannot
   also follow the image, and a panned subject taken as filmed by a still camera swings in a way
   only a residual force explains. Measured on validation archives (60 clips, docs/method.md,
   "Offline D&D"): the reprojection energy told still from moving cameras better than the total
   energy or any other term (the total lets the priors' share decide, and picked a still camera
   on most dollies and orbits); the residual check then rejects the still camera where its fit
   needs more force than a physical motion may (the still clips' fits need 0.8-3.3 % BW).
   ``camera_choice="estimated"`` skips the still hypothesis (one fit: the variant
   ``dnd_trajopt_estimated``); the still hypothesis alone is ``trajopt`` ignoring the camera's
   motion.

The result's ``camera_track`` is the track the fit used (``camera_track_estimated`` in a result
file); its diagnostics add ``camera_still`` (1: the still camera was chosen), both hypotheses'
reprojection energies, the still fit's residual (``residual_still_bw``), the estimated track's
``camera_speed_m_s`` and ``camera_turn_deg_s``, and trajopt's convergence report of the chosen
fit.
docs/method.md ("Offline D&D") and docs/evaluation.md give the measurements behind the choice.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from jmocap.inputs import ClipInputs
from jmocap.methods import dnd as D
from jmocap.methods import trajopt as TO
from jmocap.methods.base import Method, Variant, register, register_variant, static, whole_clip
from jmocap.methods.kinematic import LEARNED_STAGE_FIELDS
from jmocap.model import Model
from jmocap.motion import Motion

Array = jnp.ndarray


CAMERA_CHOICES = ("reprojection", "estimated")


@struct.dataclass
class DnDTrajOptConfig(TO.TrajOptConfig, D.DnDConfig):
    """D&D's fields (its networks and dynamics) and trajopt's (the fit), plus how the camera is
    chosen. ``contact_threshold`` is shared: D&D's contact probability and trajopt's labels."""

    # "reprojection": D&D's track or a still camera, whichever fit reprojects better; "estimated"
    camera_choice: str = static("reprojection")
    # a still camera whose fit needs more residual root force than this (body weights, mean over
    # frames) is rejected whatever its reprojection: a physical motion needs none
    still_max_residual: float = 0.05


def track_motion_stats(track: Array, mask: Array, fps) -> tuple[Array, Array]:
    """``(speed, turn)``: a camera track's (T, 4, 4) mean centre speed (m/s) and mean turning
    rate (deg/s) over the clip's real frames (``mask``, the real frames first)."""
    R, t = track[:, :3, :3], track[:, :3, 3]
    centre = -jnp.einsum("tji,tj->ti", R, t)
    step = mask[1:] & mask[:-1]
    n = jnp.maximum(jnp.sum(step), 1)
    speed = jnp.linalg.norm(centre[1:] - centre[:-1], axis=-1)
    rel = jnp.einsum("tij,tkj->tik", R[1:], R[:-1])  # R_{t+1} R_t^T
    cos = jnp.clip((jnp.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    turn = jnp.degrees(jnp.arccos(cos))
    fps = jnp.asarray(fps, track.dtype)
    return jnp.sum(jnp.where(step, speed, 0.0)) / n * fps, jnp.sum(jnp.where(step, turn, 0.0)) / n * fps


def reconstruct(params: dict, model: Model, inputs: ClipInputs,
                config: DnDTrajOptConfig = DnDTrajOptConfig()) -> Motion:  # noqa: B008
    """2D keypoints of one clip (and its first frame's camera) -> a world :class:`Motion` fitted
    to them and to the equations of motion, under D&D's estimate of the camera track or, where
    its fit reprojects better and needs at most ``still_max_residual`` of residual root force, a
    still camera."""
    if config.camera_choice not in CAMERA_CHOICES:
        raise ValueError(f"camera_choice must be one of {CAMERA_CHOICES}, got {config.camera_choice!r}")
    est = D.estimate_track(params, model, inputs, config)
    mask = jnp.asarray(inputs.mask)
    speed, turn = track_motion_stats(est, mask, inputs.fps)

    def fit(track):
        return TO.reconstruct(params, model, inputs.replace(camera_track=track), config).replace(camera_track=track)

    if config.camera_choice == "estimated":
        out, still = fit(est), jnp.zeros((), est.dtype)
    else:
        first = jnp.broadcast_to(jnp.asarray(inputs.world_to_camera(), est.dtype)[0], est.shape)
        # one after the other in one program (as trajopt runs a batch's clips: its optimiser
        # must not be vmapped, see :func:`jmocap.methods.trajopt.fit_clip`)
        both = jax.lax.map(fit, jnp.stack([est, first]))
        reproj = both.diagnostics["term_reproj"]
        residual = both.diagnostics["residual_mean_bw"]
        take = ((reproj[1] < reproj[0]) & (residual[1] <= config.still_max_residual)).astype(jnp.int32)
        out = jax.tree.map(lambda a: a[take], both)
        still = take.astype(est.dtype)
        extra = dict(reproj_estimated=reproj[0], reproj_still=reproj[1], residual_still_bw=residual[1])
        out = out.replace(diagnostics={**out.diagnostics, **extra})
    report = dict(camera_still=still, camera_speed_m_s=speed, camera_turn_deg_s=turn)
    return out.replace(diagnostics={**out.diagnostics, **report})


METHOD = register(
    Method(
        name="dnd_trajopt",
        summary="offline, unknown moving camera: trajopt under D&D's estimate of the camera track, "
        "or under a still camera where that fit reprojects better and needs at most 5 % BW of residual",
        paper="003 (D&D, Li et al. 2022) for the camera, 001 (Rempe et al. 2020) for the fit",
        config_type=DnDTrajOptConfig,
        reconstruct=reconstruct,
        init_params=D.init_params,
        **whole_clip(reconstruct),
        from_weights=LEARNED_STAGE_FIELDS,
        shipped_networks=("dnd",),
    )
)

register_variant(Variant("dnd_trajopt_estimated", "dnd_trajopt", {"camera_choice": "estimated"},
                         "dnd_trajopt always under D&D's camera track (no still-camera hypothesis)"))

__all__ = ["CAMERA_CHOICES", "METHOD", "DnDTrajOptConfig", "reconstruct", "track_motion_stats"]
