"""``kinematic``: TPNet's target pose alone (Neural PhysCap's kinematic stage, Sec. 3.2-3.3).

Keypoint normalisation, then TPNet's causal windows give the root orientation, hinge angles,
root translation and contact probabilities per frame; velocities are backward differences.
It estimates no forces: the Motion's ``tau`` and ``grf`` are zero.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from jmocap.constants import NUM_CONTACTS
from jmocap.inputs import ClipInputs
from jmocap.methods.base import Method, register, static
from jmocap.methods.stages import contact_probability, init_tpnet, target_pose
from jmocap.model import Model
from jmocap.motion import Motion
from jmocap.nets import NetConfig
from jmocap.physics import finite_difference_velocity


@struct.dataclass
class KinematicConfig:
    """The learned stage's structure (all static): keypoint layout, C_T's input, network sizes."""

    layout: str = static("body25")
    canonicalise: bool = static(True)  # False: C_T sees K_rr instead of K_c (and no closed form)
    nets: NetConfig = static(NetConfig())


#: the learned stage's fields: what a method on TPNet takes from its weights' training config
#: (``Method.from_weights``)
LEARNED_STAGE_FIELDS = ("layout", "canonicalise", "nets")


def init_params(key, model: Model, config: KinematicConfig = KinematicConfig()) -> dict:
    return {"tpnet": init_tpnet(key, model, config.layout, config.nets)}


def history(config) -> int:
    """TPNet's receptive field ``2 (W - 1)`` plus one frame for the backward difference: C_T
    reads a window of per-frame features that include C_P's pose, whose own window reaches
    ``W - 1`` frames further back."""
    return 2 * config.nets.window - 1


def _motion(model: Model, q_hat, logits, fps, mask, drop: int = 0) -> Motion:
    prob = contact_probability(logits)[drop:]
    qd = finite_difference_velocity(model, q_hat, fps)[drop:]
    q_hat = q_hat[drop:]
    z = jnp.zeros_like(qd)
    return Motion(q_hat, qd, z, jnp.zeros((*prob.shape[:-1], NUM_CONTACTS, 3), z.dtype), prob, q_hat, mask)


def reconstruct(params: dict, model: Model, inputs: ClipInputs, config: KinematicConfig = KinematicConfig()) -> Motion:
    """TPNet's pose of every frame of one clip."""
    tp = target_pose(params, model, inputs, config)
    return _motion(model, tp.q_hat, tp.contact_logits, inputs.fps, jnp.asarray(inputs.mask))


def init_carry(model: Model, config=None, dtype=jnp.float32):
    """The kinematic method carries no state between chunks (its history frames suffice)."""
    return jnp.zeros((), dtype)


def reconstruct_chunk(params, model: Model, inputs: ClipInputs, carry, first, config, history: int):
    """One chunk: ``inputs`` holds ``history`` frames before the chunk's frames; their outputs
    are dropped."""
    tp = target_pose(params, model, inputs, config)
    mask = jnp.asarray(inputs.mask)[history:]
    return carry, _motion(model, tp.q_hat, tp.contact_logits, inputs.fps, mask, drop=history)


METHOD = register(
    Method(
        name="kinematic",
        summary="TPNet's target pose alone: the kinematic baseline (no forces)",
        paper="000 (Neural PhysCap), Sec. 3.2-3.3",
        config_type=KinematicConfig,
        reconstruct=reconstruct,
        reconstruct_chunk=reconstruct_chunk,
        init_carry=init_carry,
        history=history,
        init_params=init_params,
        estimates_forces=False,
    )
)

__all__ = ["METHOD", "KinematicConfig", "history", "init_params", "reconstruct", "reconstruct_chunk"]
