"""The whole-clip kinematic stage of ``trajopt`` by its two optimisers, side by side: L-BFGS (the
default, ``kinematic_solver="lbfgs"``) and Levenberg-Marquardt on the block-banded normal
equations (``"gauss_newton"``), on one held-out clip after the per-frame stage, exactly as
:func:`jmocap.methods.trajopt.fit` starts stage 1. Prints, per optimiser and iteration count,
the objective reached and the milliseconds the stage takes (the best of 3 runs after the
compiling one), and the cost of one normal-equations assembly and of one banded solve.

    .venv/bin/python experiments/bench_kinematic_stage.py --clip 0 --frames 300
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from jmocap.data.archive import Archive
from jmocap.inputs import ClipInputs
from jmocap.methods import get_method
from jmocap.methods import stages as S
from jmocap.methods import trajopt as TO
from jmocap.physics.linalg import banded_solve
from jmocap.pipeline import subject_model
from jmocap.weights import default_config_fields, default_params


def _best(fn, *args, repeats: int = 3):
    out = jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return out, min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/heldout")
    ap.add_argument("--clip", type=int, default=0)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--lbfgs", type=int, nargs="*", default=[60])
    ap.add_argument("--gauss-newton", type=int, nargs="*", default=[5, 10, 20])
    args = ap.parse_args()

    arch = Archive(args.archive)
    clip = arch.load(arch.names()[args.clip])
    clip = clip.slice(0, min(args.frames, clip.num_frames))
    inputs, model = ClipInputs.from_clip(clip, length=args.frames), subject_model(clip)
    params, _ = default_params()
    method = get_method("trajopt")
    cfg = method.make_config(method.weights_config(default_config_fields()))

    @jax.jit
    def stage1_start(params, model, inputs):  # fit()'s stage 0 and label pruning
        tp = S.target_pose(params, model, inputs, cfg)
        labels = TO.contact_labels(params, inputs, S.contact_probability(tp.contact_logits), cfg, tp.trans_cam[:, 2])
        prob = TO.problem(model, inputs, tp.q_hat, labels, cfg)
        q0 = TO.initial_trajectory(model, tp.q_hat, prob.mask, prob.scene)
        prob = prob.replace(base_quat=TO.from_q(model, q0)[1])
        per_frame = cfg.replace(w_accel=0.0, w_contact_vel=0.0)
        q1 = TO.per_frame_fit(model, q0, prob, per_frame, cfg.frame_iterations, cfg.gm_scale_initial, cfg.gm_scale,
                              TO.depth_track(q0, prob, cfg), prob.contacts, tile=cfg.frame_tile)
        sole_h = TO._sole_heights(model, q1, prob.scene)
        low = jnp.min(jnp.where(prob.mask[:, None], sole_h, jnp.inf))
        low = jnp.where(jnp.isfinite(low), low, 0.0)
        site_h = jnp.min(sole_h.reshape(-1, 4, 2), -1) - low
        return q1.at[:, 2].add(-low), prob.replace(contacts=prob.contacts * (site_h < cfg.outlier_height_m))

    q1, prob = stage1_start(params, model, inputs)
    x1, base = TO.from_q(model, q1)
    pr = prob.replace(base_quat=base)
    print(f"{arch.names()[args.clip]}: {int(prob.length)} frames in a {args.frames}-frame bucket, "
          f"{jax.devices()[0].device_kind}")
    print("| optimiser | iterations | objective | ms | x L-BFGS 60 time |")
    print("|---|---:|---:|---:|---:|")
    ref = None
    for k in args.lbfgs:
        run = jax.jit(lambda x, k=k: TO.lbfgs(lambda y: TO.objective(model, y, pr, cfg, physics=False), x, k,
                                              cfg.memory, TO.diagonal_scale(model, x, pr, cfg), cfg.linesearch))
        (_, rep), t = _best(run, x1)
        ref = ref or t
        print(f"| L-BFGS | {k} | {float(rep.final):.1f} | {1e3 * t:.0f} | {t / ref:.2f} |", flush=True)
    for k in args.gauss_newton:
        run = jax.jit(lambda q, k=k: TO.gauss_newton(model, q, prob, cfg, k))
        (_, rep), t = _best(run, q1)
        print(f"| Gauss-Newton | {k} | {float(rep.final):.1f} | {1e3 * t:.0f} | {t / (ref or t):.2f} |", flush=True)
    ne, t_ne = _best(jax.jit(lambda q: TO.kinematic_normal_equations(model, q, prob, cfg)), q1)
    _, t_solve = _best(jax.jit(banded_solve), ne.blocks.at[0].add(jax.vmap(jnp.diag)(
        1e-3 * jnp.diagonal(ne.blocks[0], axis1=-2, axis2=-1) + 1e-6)), ne.grad)
    print(f"one normal-equations assembly {1e3 * t_ne:.1f} ms, one banded solve {1e3 * t_solve:.1f} ms")


if __name__ == "__main__":
    main()
