"""Dump, per clip, what a contact classifier could read after each stage of ``trajopt``: the
contact estimator's probabilities, TPNet's contact head, and the four contact sites' sole heights
and speeds on the per-frame fit (with and without the labels' pull to the floor), the kinematic
fit and the physics fit; with the ground-truth labels.

    .venv/bin/python experiments/contact_features.py --archive data/val --clips 0..15 --out out/cfeat_val
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jmocap import physics as P
from jmocap.data.clip import load_clip
from jmocap.inputs import ClipInputs
from jmocap.methods import stages as S
from jmocap.methods import trajopt as TO
from jmocap.pipeline import subject_model
from jmocap.weights import default_params


def site_features(model, q):
    """(T, 4) lowest sole-point height of each site and (T, 4) the site's sole speed (m/frame,
    backward difference; the first frame repeats the second)."""
    pts = jax.vmap(lambda x: S.sole_points(model, P.forward_kinematics(model, x))[0])(q)  # (T, 8, 3)
    h = jnp.min(pts[..., 2].reshape(-1, 4, 2), -1)
    d = jnp.linalg.norm(pts[1:] - pts[:-1], axis=-1).reshape(-1, 4, 2).mean(-1)
    return h, jnp.concatenate([d[:1], d], 0)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/val")
    ap.add_argument("--clips", default="0..15")
    ap.add_argument("--length", type=int, default=304)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/jmocap/xla-dev"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    a, b = (int(v) for v in args.clips.split(".."))
    params, config = default_params("trajopt")

    @jax.jit
    def run(params, model, inputs, config):
        tp = S.target_pose(params, model, inputs, config)
        mask = jnp.asarray(inputs.mask)
        p_head = S.contact_probability(tp.contact_logits)
        p_mlp = TO.contact_labels(params, inputs, p_head, config)
        q0 = TO.initial_trajectory(model, tp.q_hat, mask)
        prob = TO.problem(model, inputs, tp.q_hat, p_mlp, config)
        x0, base = TO.from_q(model, q0)
        prob1 = prob.replace(base_quat=base)
        pf = config.replace(w_accel=0.0, w_contact_vel=0.0)
        track = TO.depth_track(q0, prob1, config)
        q1 = TO.per_frame_fit(model, q0, prob1, pf, config.frame_iterations, config.gm_scale_initial,
                              config.gm_scale, track, prob1.contacts, tile=config.frame_tile)
        q1n = TO.per_frame_fit(model, q0, prob1, pf, config.frame_iterations, config.gm_scale_initial,
                               config.gm_scale, track, None, tile=config.frame_tile)
        out = TO.fit(model, prob, q0, config)
        feats = {}
        for name, q in (("pf", q1), ("pfn", q1n), ("kin", out.q_kinematic), ("phys", out.q)):
            h, v = site_features(model, q)
            feats[f"h_{name}"], feats[f"v_{name}"] = h, v
        return dict(p_mlp=p_mlp, p_head=p_head, used=out.contacts, **feats)

    Path(args.out).mkdir(parents=True, exist_ok=True)
    for i in range(a, b + 1):
        clip = load_clip(Path(args.archive) / f"synth_{i:06d}.npz")
        T = clip.num_frames
        model = subject_model(clip)
        inputs = ClipInputs.from_clip(clip, args.length)
        t0 = time.perf_counter()
        r = jax.block_until_ready(run(params, model, inputs, config))
        r = {k: np.asarray(v[:T]) for k, v in r.items()}
        np.savez(Path(args.out) / f"clip{i}.npz", gt=clip.gt_contacts, fps=clip.fps,
                 kind=clip.meta.get("kind", "?"), **r)
        print(i, clip.meta.get("kind", "?"), f"{time.perf_counter() - t0:.1f}s", flush=True)


if __name__ == "__main__":
    main()
