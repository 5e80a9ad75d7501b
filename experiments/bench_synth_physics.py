"""Speed of the synthetic generator's physics controllers, side by side on the same motions.

For each motion kind and seed, one planned motion (``generate_motion``, with the settled start's
lead-in) is simulated by

  (a) the QP tracker (``simulate_tracking``: a bounded least squares per 2 ms substep, a root
      residual where the plan is infeasible),
  (b) the sampling controller with its QP actuation (``simulate_sampling``, the default: 16
      samples x 15 frames per 3-frame window, each sample's QP solved every 6 substeps between
      ``mujoco.rollout`` chunks, no root force), and
  (c) the sampling controller with servo actuation (``SamplingConfig(actuation="servo")``: 64
      samples x 15 frames per window, one ``mujoco.rollout`` each),

and the wall time per simulated frame is printed, with (b) / (a) and (c) / (a) per motion and
overall, plus the rollout throughput of (b) and (c) (substeps simulated per second, the samples
included) and their backtracks. A motion that one controller cannot simulate (it falls / runs out
of backtracks) is reported and left out of the ratios.

Usage:  python experiments/bench_synth_physics.py [--kinds walk,run] [--seeds 0,1,2] [--frames 90]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv=None) -> int:
    from jmocap.data.synthetic.errors import GenerationError
    from jmocap.data.synthetic.physics import PhysicsConfig, SamplingConfig, simulate_tracking
    from jmocap.data.synthetic.repertoire import generate_motion
    from jmocap.data.synthetic.sampling import simulate_sampling

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kinds", default="walk,run")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--frames", type=int, default=90, help="frames after the lead-in")
    args = ap.parse_args(argv)
    fps = 30.0
    qp_cfg = PhysicsConfig()
    controllers = [("qp", simulate_tracking, qp_cfg),
                   ("sampling_qp", simulate_sampling, PhysicsConfig(controller="sampling")),
                   ("sampling_servo", simulate_sampling,
                    PhysicsConfig(controller="sampling", sampling=SamplingConfig(actuation="servo")))]
    lead = qp_cfg.settle_frames(fps)
    rows = []
    print(f"{'kind':6} {'seed':>4} {'frames':>6} " + " ".join(f"{n + ' s/frame':>22}" for n, _, _ in controllers)
          + f" {'ratios to qp':>14} {'substeps/s':>17} {'backtracks':>10}")
    for kind in args.kinds.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            m = generate_motion(1.75, np.random.default_rng(seed), args.frames / fps + 0.5, fps, (kind,))
            q = np.concatenate([np.repeat(m.q[:1], lead, axis=0), m.q[: args.frames]])
            T = len(q)
            times, stats = [], []
            for name, fn, cfg in controllers:
                extra = () if fn is simulate_tracking else (np.random.default_rng(seed),)
                t0 = time.perf_counter()
                try:
                    out = fn(m.character, q, fps, cfg, lead, *extra)
                except GenerationError as e:
                    times.append(None)
                    print(f"{kind:6} {seed:>4} {name}: {e}")
                    continue
                times.append((time.perf_counter() - t0) / T)
                stats.append(out["stats"])
            if None in times:
                continue
            sub_s = [st["samples_simulated"] / (t * T) for st, t in zip(stats[1:], times[1:], strict=True)]
            rows.append(times)
            print(f"{kind:6} {seed:>4} {T:>6} " + " ".join(f"{t:>22.4f}" for t in times)
                  + f" {times[1] / times[0]:>6.1f} {times[2] / times[0]:>6.1f}"
                  + f" {sub_s[0]:>8.0f} {sub_s[1]:>8.0f} {stats[1]['backtracks']:>4} {stats[2]['backtracks']:>4}")
    if rows:
        a = np.array(rows)
        print("overall s/frame: " + ", ".join(f"{n} {a[:, i].mean():.4f}" for i, (n, _, _) in enumerate(controllers))
              + f"; sampling_qp / qp {a[:, 1].sum() / a[:, 0].sum():.1f}x, sampling_servo / qp "
              f"{a[:, 2].sum() / a[:, 0].sum():.1f}x, sampling_qp / sampling_servo {a[:, 1].sum() / a[:, 2].sum():.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
