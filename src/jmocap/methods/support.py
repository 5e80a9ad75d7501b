"""A learned estimate of the net vertical ground reaction force from the 2D keypoints.

The net external force on a person is ``m (c'' + g)``: the centre of mass's acceleration. A
fit to 2D keypoints at 30 fps fixes the centre of mass's path only to centimetres, and its
second differences are noise of metres per second squared, so :mod:`jmocap.methods.trajopt`'s
physics stage holds the net force near a prior (``w_com_accel``). Until stop 59 that prior was
one body weight straight up in every frame: a person standing still. A walk's vertical force is
not that: it peaks at 1.1-1.3 body weights after each heel strike and dips to 0.7-0.8 in single
support; a run's swings between about 2.5 body weights and zero. That shape follows the gait's
phase, which the 2D evidence shows well (the contact estimator's F1 is 90 %) where the
acceleration itself is lost in the noise.

This module regresses the net vertical force (body weights) per frame from what the contact
estimator already reads: the same ±1 s temporal network as the contact refiner
(:class:`jmocap.nets.ContactTCN`, one output), whose input per frame is the refiner's (the
contact MLP's window probabilities, vote and last hidden layer,
:func:`~jmocap.methods.contact_estimation.refiner_inputs`) and the MLP's own normalised
9-frame window of the lower body (:func:`~jmocap.methods.contact_estimation.contact_features`:
the root's motion over the window relative to the person's size). The estimate is the mean over
the keypoints and their mirror image (the vertical force of a person and of their mirror image
are the same). Trained on simulated clips whose forces are the simulator's
(``experiments/train_support.py``; frames the generator's rescue pushed are left out of the
loss). jmocap's addition, not a paper's method: Rempe et al. (2020) hold the forces only by
their physics; docs/method.md, "The learned support prior".
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jmocap.inputs import ClipInputs
from jmocap.methods import contact_estimation as ce
from jmocap.methods.base import load_float32_params
from jmocap.nets import ContactTCN

Array = jax.Array

ASSET = Path(__file__).resolve().parent.parent / "assets" / "support_tcn.msgpack"


def support_inputs(contact_params, features: Array, mask: Array) -> Array:
    """The network's per-frame input (T, 24 + H + w x 39): the contact refiner's
    (:func:`~jmocap.methods.contact_estimation.refiner_inputs`) and the MLP's window features;
    padded frames zeros."""
    seq = ce.refiner_inputs(contact_params, features, mask)
    return jnp.concatenate([seq, features * jnp.asarray(mask, features.dtype)[:, None]], -1)


def init_support_params(key, channels: int, width: int = 64, blocks: int = 5, kernel: int = 3) -> dict:
    """Fresh variables ``{"params"}`` of the one-output :class:`~jmocap.nets.ContactTCN` for
    ``channels`` input features per frame."""
    net = ContactTCN(width=width, dilations=tuple(2 ** i for i in range(blocks)), kernel=kernel, out=1)
    return net.init(key, jnp.zeros((8, channels)), jnp.ones(8, bool))


def support_raw(variables, seq: Array, mask: Array, train: bool = False, rngs=None) -> Array:
    """The network's output (T,) for one clip's input ``seq`` (T, C): net vertical force minus
    one body weight (body weights)."""
    cfg = ce.tcn_config(variables)
    return ContactTCN(**cfg, out=1).apply(variables, seq, mask, train=train, rngs=rngs)[..., 0]


def support_force(contact_params, variables, inputs: ClipInputs, layout: str = "body25", mirror: bool = True,
                  depth: Array | None = None) -> Array:
    """Net vertical ground reaction force (T,) of one clip, body weights; padded frames 1.
    ``mirror`` (static): the mean with the horizontally mirrored keypoints' estimate. ``depth``
    (T,), the person's depth in every frame's camera: each window is first seen from its target
    frame's camera, as the contact estimator's (a moving camera's motion is not the body's
    acceleration). ``jax.jit`` / ``jax.vmap`` over clips apply (``layout`` and ``mirror``
    static)."""
    f = ce.window_features(contact_params, inputs, layout, depth)
    z = support_raw(variables, support_inputs(contact_params, f, inputs.mask), inputs.mask)
    if mirror:
        ff = ce.flip_features(f)
        z = 0.5 * (z + support_raw(variables, support_inputs(contact_params, ff, inputs.mask), inputs.mask))
    return jnp.where(jnp.asarray(inputs.mask, bool), 1.0 + z, 1.0)


def support_params(params) -> dict:
    """The support network's variables a method uses: ``params["support"]`` where a run's
    parameters carry their own, else the shipped ones (:func:`default_support_params`)."""
    if isinstance(params, dict) and "support" in params:
        return params["support"]
    return default_support_params()


@functools.cache
def default_support_params() -> dict:
    """The shipped variables (``jmocap/assets/support_tcn.msgpack``, float16 on disk, float32
    here), made by ``experiments/train_support.py --ship``."""
    if not ASSET.exists():
        raise FileNotFoundError(f"no shipped support network at {ASSET}; train it with "
                                f"experiments/train_support.py --ship")
    return load_float32_params(ASSET)


def target(grf: np.ndarray, mass_kg: float) -> np.ndarray:
    """Training target (T,): the net vertical ground-truth force in body weights."""
    from jmocap.constants import GRAVITY

    return np.asarray(grf, np.float64)[:, :, 2].sum(-1) / (float(mass_kg) * GRAVITY)
