"""Speed of ``mocon``'s simulation backends side by side: MuJoCo C rollouts (``mujoco.rollout``,
1 thread and one per core) and MJX, on the same clip, window and samples.

    .venv/bin/python experiments/bench_mocon.py [--frames 60] [--samples 32] [--mjx]

Two measurements per backend:

* **rollouts**: one control window's samples (``--samples`` x (window + lookahead) frames of
  substeps) simulated from the same state, repeated; simulated steps per second (a "step" is one
  sample advanced by one simulation substep) and the ratio to MuJoCo C on one thread;
* **clip**: :func:`jmocap.methods.mocon.track` of a synthetic walk of ``--frames`` frames
  (its ground truth as the reference, so no ``trajopt`` compile is timed): seconds per clip and
  frames per second, MuJoCo C (MJX on a CPU runs one sample at a time, minutes per window
  of the defaults: it is for an accelerator).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import mujoco
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))

from jmocap.data import synthetic as S  # noqa: E402
from jmocap.inputs import ClipInputs  # noqa: E402
from jmocap.methods import mocon as MC  # noqa: E402
from jmocap.pipeline import subject_model  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--mjx", action="store_true", help="also time MJX (compiles for a minute or more on a CPU)")
    ap.add_argument("--only-mjx", action="store_true", help="MJX alone (its own process: no MuJoCo C thread pool)")
    args = ap.parse_args()
    from test_mocon import _reference

    clip = S.generate_clip(1, 0, S.SynthConfig(frames=args.frames, kinds=("walk",), physics=True))
    model = subject_model(clip)
    ref = _reference(clip)
    config = MC.MoconConfig(samples=args.samples)
    sim = MC.Simulation(model, None, clip.fps, config)
    d = mujoco.MjData(sim.mj)
    d.qpos[:], d.qvel[:] = ref.q[10], ref.qd[10]
    mujoco.mj_forward(sim.mj, d)
    K = config.window_frames + config.lookahead_frames
    steps = K * sim.n
    rng = np.random.default_rng(0)
    ctrl = np.asarray(ref.q[10], np.float64)[sim.hinge_q][None, None] + 0.1 * rng.normal(size=(args.samples, 1, sim.mj.nu))
    controls = np.concatenate([np.broadcast_to(ctrl, (args.samples, steps, sim.mj.nu)),
                               np.zeros((args.samples, steps, sim.mj.nv))], -1)
    ends = np.arange(1, K + 1) * sim.n - 1
    cores = os.cpu_count() or 1
    backends = [] if args.only_mjx else [("mujoco C, 1 thread", MC.MujocoRollouts(sim.mj, 1)),
                                         (f"mujoco C, {cores} threads", MC.MujocoRollouts(sim.mj, cores))]
    if args.mjx or args.only_mjx:
        backends.append(("MJX (jax " + __import__("jax").default_backend() + ")", MC.MjxRollouts(sim.mj)))
    print(f"one window: {args.samples} samples x {K} frames x {sim.n} substeps = {args.samples * steps} steps")
    base = None
    for name, run in backends:
        t = time.perf_counter()
        run(d, controls, ends)  # warm-up (MJX compiles)
        print(f"  {name:28s} first call {time.perf_counter() - t:.1f} s", flush=True)
        t = time.perf_counter()
        for _ in range(args.repeat):
            run(d, controls, ends)
        dt = (time.perf_counter() - t) / args.repeat
        rate = args.samples * steps / dt
        base = base or rate
        print(f"  {name:28s} {dt * 1000:8.1f} ms/window  {rate:10.0f} steps/s  x{rate / base:.2f}", flush=True)
    # a whole clip with MuJoCo C only: MJX on a CPU simulates one sample at a time (tens of
    # minutes a clip); on an accelerator, time it with config.replace(backend="mjx")
    for backend in () if args.only_mjx else ("mujoco",):
        cfg = config.replace(backend=backend)
        t = time.perf_counter()
        m = MC.track(model, ClipInputs.from_clip(clip), ref, cfg)
        dt = time.perf_counter() - t
        print(f"clip ({backend}): {clip.num_frames} frames in {dt:.1f} s = {clip.num_frames / dt:.1f} frames/s, "
              f"{m.diagnostics['mocon_samples_simulated'] / dt:.0f} steps/s, resets {int(m.diagnostics['mocon_resets'])}")


if __name__ == "__main__":
    main()
