"""System identification through the functional API: recover perturbed PD gains by gradient
descent through ``reconstruct``.

The shipped ``physcap`` method reconstructs the first frames of the demo walk with its shipped
config (the "true" gains k_p = 1600 s^-2 and damping ratio 1.0); we then start from wrong gains
and fit them, by Adam on the log-gains, to make ``reconstruct``'s motion match the observed one.
Nothing recompiles between steps: the gains are traced leaves of the config pytree
(docs/architecture.md, "Static structure and traced parameters").

    python experiments/system_identification.py [--frames 30] [--steps 150]

Prints the gains per step and the final relative errors (docs/architecture.md records a run).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jmocap.data.formats import read_clip
from jmocap.demo import demo_assets
from jmocap.inputs import ClipInputs
from jmocap.methods import get_method
from jmocap.model import character
from jmocap.weights import default_params


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=30, help="frames of the demo walk used (default 30)")
    ap.add_argument("--steps", type=int, default=150, help="Adam steps (default 150)")
    ap.add_argument("--lr", type=float, default=0.05,
                    help="initial Adam learning rate on the log-gains (decays 50x over the steps)")
    args = ap.parse_args()

    method = get_method("physcap")
    params, config = default_params("physcap")
    clip = read_clip(demo_assets() / "input" / "demo_walk").slice(0, args.frames)
    inputs = ClipInputs.from_clip(clip)
    model = character()
    reconstruct = jax.jit(method.reconstruct)

    truth = {"kp_joint": config.kp_joint, "damping_ratio": config.damping_ratio}
    observed = reconstruct(params, model, inputs, config).q

    def loss(log_gains):
        cfg = config.replace(kp_joint=jnp.exp(log_gains[0]), damping_ratio=jnp.exp(log_gains[1]))
        q = method.reconstruct(params, model, inputs, cfg).q
        return jnp.mean((q - observed) ** 2) * 1e6  # mm^2-ish scale

    opt = optax.adam(optax.exponential_decay(args.lr, args.steps, 0.02))
    x = jnp.log(jnp.array([900.0, 0.6]))  # wrong by -44 % and -40 %
    state = opt.init(x)

    @jax.jit
    def step(x, state):
        value, g = jax.value_and_grad(loss)(x)
        updates, state = opt.update(g, state, x)
        return optax.apply_updates(x, updates), state, value

    t0 = time.perf_counter()
    for i in range(args.steps):
        x, state, value = step(x, state)
        if i % 25 == 0 or i == args.steps - 1:
            kp, zeta = np.exp(np.asarray(x))
            print(f"step {i:3d}  loss {float(value):10.4f}  k_p {kp:8.1f}  damping {zeta:6.3f}")
    kp, zeta = np.exp(np.asarray(x))
    print(f"recovered k_p = {kp:.1f} (true {truth['kp_joint']:.0f}, error {abs(kp / truth['kp_joint'] - 1):.2%}), "
          f"damping = {zeta:.4f} (true {truth['damping_ratio']:.1f}, error {abs(zeta / truth['damping_ratio'] - 1):.2%}); "
          f"{args.steps} steps in {time.perf_counter() - t0:.0f} s (first includes compilation)")


if __name__ == "__main__":
    main()
