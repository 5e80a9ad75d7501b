"""Speed of the synthetic generator's two physics controllers, side by side on the same motions.

For each motion kind and seed, one planned motion (``generate_motion``, with the settled start's
lead-in) is simulated by

  (a) the QP tracker (``simulate_tracking``: a bounded least squares per 2 ms substep, a root
      residual where the plan is infeasible), and
  (b) the sampling controller (``simulate_sampling``: ``mujoco.rollout`` of 64 samples x 15
      frames per 3-frame window, no root force),

and the wall time per simulated frame is printed, with (b) / (a) per motion and overall, plus
(b)'s rollout throughput (substeps simulated per second, the samples included) and its
backtracks. A motion that one controller cannot simulate (it falls / runs out of backtracks) is
reported and left out of the ratios.

Usage:  python experiments/bench_synth_physics.py [--kinds walk,run] [--seeds 0,1,2] [--frames 90]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv=None) -> int:
    from jmocap.data.synthetic.errors import GenerationError
    from jmocap.data.synthetic.physics import PhysicsConfig, simulate_tracking
    from jmocap.data.synthetic.repertoire import generate_motion
    from jmocap.data.synthetic.sampling import simulate_sampling

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kinds", default="walk,run")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--frames", type=int, default=90, help="frames after the lead-in")
    args = ap.parse_args(argv)
    fps = 30.0
    qp_cfg = PhysicsConfig()
    sa_cfg = PhysicsConfig(controller="sampling")
    lead = qp_cfg.settle_frames(fps)
    rows = []
    print(f"{'kind':6} {'seed':>4} {'frames':>6} {'qp s/frame':>11} {'sampling s/frame':>17} {'ratio':>6} "
          f"{'substeps/s':>11} {'backtracks':>10}")
    for kind in args.kinds.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            m = generate_motion(1.75, np.random.default_rng(seed), args.frames / fps + 0.5, fps, (kind,))
            q = np.concatenate([np.repeat(m.q[:1], lead, axis=0), m.q[: args.frames]])
            T = len(q)
            times, stats = [], None
            for fn, extra in ((simulate_tracking, ()), (simulate_sampling, (np.random.default_rng(seed),))):
                cfg = qp_cfg if fn is simulate_tracking else sa_cfg
                t0 = time.perf_counter()
                try:
                    out = fn(m.character, q, fps, cfg, lead, *extra)
                except GenerationError as e:
                    times.append(None)
                    print(f"{kind:6} {seed:>4}: {e}")
                    continue
                times.append((time.perf_counter() - t0) / T)
                stats = out["stats"]
            if None in times:
                continue
            sub_s = stats["samples_simulated"] / (times[1] * T)
            rows.append((times[0], times[1]))
            print(f"{kind:6} {seed:>4} {T:>6} {times[0]:>11.4f} {times[1]:>17.4f} {times[1] / times[0]:>6.1f} "
                  f"{sub_s:>11.0f} {stats['backtracks']:>10}")
    if rows:
        a = np.array(rows)
        print(f"overall: qp {a[:, 0].mean():.4f} s/frame, sampling {a[:, 1].mean():.4f} s/frame, "
              f"sampling / qp {a[:, 1].sum() / a[:, 0].sum():.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
