"""Is ``trajopt``'s kinematic fit an optimisation failure or a modelling one? For each clip, the
kinematic stage's objective (its terms, weighted) at the fit and at the ground-truth motion,
with the labels the fit used.

    .venv/bin/python experiments/objective_at_truth.py --archive data/val --clips 0..15 [--clean-2d]

If the truth scores lower than the fit, the optimiser stopped in a worse basin; if higher, the
energies prefer something other than the truth (priors, weights, noise model).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jmocap.data.clip import load_clip
from jmocap.inputs import ClipInputs
from jmocap.methods import stages as S
from jmocap.methods import trajopt as TO
from jmocap.pipeline import subject_model
from jmocap.weights import default_params


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/val")
    ap.add_argument("--clips", default="0..15")
    ap.add_argument("--length", type=int, default=304)
    ap.add_argument("--clean-2d", action="store_true")
    ap.add_argument("--set", nargs="*", default=[])
    args = ap.parse_args()
    jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/jmocap/xla-dev"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    from ablate_pip import parse_set
    from ablate_trajopt import clean_2d

    params, config = default_params("trajopt")
    config = config.replace(**parse_set(args.set, config))
    a, b = (int(v) for v in args.clips.split(".."))

    @jax.jit
    def run(params, model, inputs, q_gt, config):
        tp = S.target_pose(params, model, inputs, config)
        mask = jnp.asarray(inputs.mask)
        p = TO.contact_labels(params, inputs, S.contact_probability(tp.contact_logits), config)
        q0 = TO.initial_trajectory(model, tp.q_hat, mask)
        prob = TO.problem(model, inputs, tp.q_hat, p, config)
        out = TO.fit(model, prob, q0, config)
        prob = prob.replace(contacts=out.contacts)

        def terms(q):
            x, base = TO.from_q(model, q)
            t = TO.objective_terms(model, x, prob.replace(base_quat=base), config, physics=False)
            return {k: TO._weight(config, k) * v for k, v in t.items()}

        return terms(out.q_kinematic), terms(q_gt), terms(q0)

    tot = {"fit": [], "gt": [], "init": []}
    for i in range(a, b + 1):
        clip = load_clip(Path(args.archive) / f"synth_{i:06d}.npz")
        if args.clean_2d:
            clip = clean_2d(clip)
        T = clip.num_frames
        model = subject_model(clip)
        inputs = ClipInputs.from_clip(clip, args.length)
        q_gt = np.concatenate([clip.gt_q, np.repeat(clip.gt_q[-1:], args.length - T, 0)]).astype(np.float32)
        f, g, z = jax.device_get(run(params, model, inputs, q_gt, config))
        for name, t in (("fit", f), ("gt", g), ("init", z)):
            tot[name].append(sum(t.values()))
        print(i, clip.meta.get("kind"), "fit", f"{sum(f.values()):.2f}", "gt", f"{sum(g.values()):.2f}", "|",
              " ".join(f"{k}={f[k]:.2f}/{g[k]:.2f}" for k in f), flush=True)
    print("mean fit", np.mean(tot["fit"]), "gt", np.mean(tot["gt"]), "init", np.mean(tot["init"]))


if __name__ == "__main__":
    main()
