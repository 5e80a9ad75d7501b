"""Throughput of the dynamic cycle's physics terms (M, h, J_c) side by side, in one run.

Competitors, on identical random configurations of the default humanoid:
  (a) jmocap: `physics.smooth_dynamics`, jitted and vmapped;
  (b) MJX: kinematics, com_pos, crb, full_m, com_vel, rne and the four contact-site
      Jacobians (mjx.jac), jitted and vmapped;
  (c) MuJoCo C in a Python loop: mj_kinematics, mj_comPos, mj_crb, mj_fullM, mj_comVel,
      mj_rne and four mj_jacSite calls per evaluation.

Prints one markdown table: evaluations per second at batch 1, 64 and 1024, ratios, and
compile times. Usage:  python experiments/bench_physics.py [--quick] [--float64] [--no-mjx] [--mjx-max-batch N]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np


def machine() -> str:
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, jax {jax.__version__} ({jax.default_backend()}), mujoco {mujoco.__version__}"


def configs(model, n, seed=0):
    from jmocap.model import DEFAULT_MODEL_PATH  # noqa: F401  (model is the default humanoid)

    mj = model.mj
    rng = np.random.default_rng(seed)
    q = np.tile(mj.qpos0, (n, 1))
    q[:, :3] = rng.uniform([-2, -2, 0.8], [2, 2, 1.2], (n, 3))
    quat = rng.normal(size=(n, 4))
    q[:, 3:7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    lo, hi = np.asarray(model.q_lower), np.asarray(model.q_upper)
    hq = model.topo.hinge_qadr
    q[:, hq] = rng.uniform(lo[hq], hi[hq], (n, hq.size))
    qd = rng.normal(scale=2.0, size=(n, mj.nv))
    return q, qd


def time_fn(fn, *args, repeats: int, min_time: float = 0.2, warmup: bool = True) -> float:
    """Median seconds per call (after one warm-up call unless ``warmup=False``)."""
    if warmup:
        jax.block_until_ready(fn(*args))
    samples = []
    for _ in range(repeats):
        n, t0 = 0, time.perf_counter()
        while True:
            jax.block_until_ready(fn(*args))
            n += 1
            dt = time.perf_counter() - t0
            if dt >= min_time or n >= 50:
                break
        samples.append(dt / n)
    return statistics.median(samples)


def compiled(fn, *args):
    """(compiled executable, seconds to trace + lower + compile it)."""
    t0 = time.perf_counter()
    exe = fn.lower(*args).compile()
    return exe, time.perf_counter() - t0


def make_jmocap(model):
    from jmocap.physics import smooth_dynamics

    def f(q, qd):
        d = smooth_dynamics(model, q, qd)
        return d.M, d.h, d.Jc

    return jax.jit(jax.vmap(f))


def make_mjx(model):
    from jmocap.model import _import_mjx

    mjx = _import_mjx()
    mx = model.mjx
    sites = np.asarray(model.topo.contact_sites)
    site_body = np.asarray(model.mj.site_bodyid)[sites]

    def f(q, qd):
        d = mjx.make_data(mx).replace(qpos=q, qvel=qd)
        d = mjx.kinematics(mx, d)
        d = mjx.com_pos(mx, d)
        d = mjx.crb(mx, d)
        d = mjx.com_vel(mx, d)
        d = mjx.rne(mx, d)
        M = mjx.full_m(mx, d)
        jacs = [mjx.jac(mx, d, d.site_xpos[s], int(b))[0].T for s, b in zip(sites, site_body, strict=True)]
        return M, d.qfrc_bias, jnp.concatenate(jacs, 0)

    return jax.jit(jax.vmap(f))


def mujoco_c_loop(model, d, qs, qds):
    """One evaluation per row; ``d`` (MjData) is allocated once, outside the timed loop."""
    mj = model.mj
    M = np.zeros((mj.nv, mj.nv))
    jac = np.zeros((3, mj.nv))
    h = np.zeros(mj.nv)
    sites = model.topo.contact_sites
    for q, qd in zip(qs, qds, strict=True):
        d.qpos[:] = q
        d.qvel[:] = qd
        mujoco.mj_kinematics(mj, d)
        mujoco.mj_comPos(mj, d)
        mujoco.mj_crb(mj, d)
        mujoco.mj_fullM(mj, d, M)
        mujoco.mj_comVel(mj, d)
        mujoco.mj_rne(mj, d, 0, h)
        for s in sites:
            mujoco.mj_jacSite(mj, d, jac, None, s)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small batches, few repeats (smoke run)")
    ap.add_argument("--float64", action="store_true", help="run jmocap and MJX in float64")
    ap.add_argument("--no-mjx", action="store_true", help="skip MJX (slow to compile and run on CPU)")
    ap.add_argument("--mjx-max-batch", type=int, default=1024,
                    help="skip MJX above this batch (batch 1024 takes ~2-3 minutes on a 2-core CPU)")
    args = ap.parse_args(argv)
    if args.float64:
        jax.config.update("jax_enable_x64", True)
    from jmocap.model import load_model

    model = load_model(with_mjx=not args.no_mjx)
    batches = [1, 64] if args.quick else [1, 64, 1024]
    repeats = 2 if args.quick else 5
    dtype = np.float64 if args.float64 else np.float32
    jm = make_jmocap(model)
    mx = None if args.no_mjx else make_mjx(model)

    print(f"machine: {machine()}")
    print(f"model: default humanoid, nq={model.nq}, nv={model.nv}, nbody={model.topo.nbody}; dtype {np.dtype(dtype).name}\n")
    rows = []
    d_c = mujoco.MjData(model.mj)
    for B in batches:
        q, qd = configs(model, B, seed=B)
        qj, qdj = jnp.asarray(q, dtype), jnp.asarray(qd, dtype)
        exe, c_jm = compiled(jm, qj, qdj)
        t_jm = time_fn(exe, qj, qdj, repeats=repeats)
        if mx is not None and B <= args.mjx_max_batch:
            exe, c_mx = compiled(mx, qj, qdj)
            # MJX is slow on CPU (a batch of 1024 takes minutes): already compiled, so no
            # warm-up call; one timed call per repeat, a single one for large batches
            t_mx = time_fn(exe, qj, qdj, repeats=1 if B >= 256 else repeats, min_time=0.0,
                           warmup=B < 256)
        else:
            c_mx = t_mx = float("nan")
        t_c = time_fn(lambda a, b: mujoco_c_loop(model, d_c, a, b), q, qd, repeats=repeats)
        rows.append((B, B / t_jm, B / t_mx, B / t_c, c_jm, c_mx))
        print(f"  measured batch {B}", flush=True)

    print(f"\n{time.strftime('%Y-%m-%d %H:%M')}; evaluations/s of (M, h, J_c); compile = trace + lower + compile\n")
    print("| batch | jmocap evals/s | MJX evals/s | MuJoCo C loop evals/s | jmocap / MJX | jmocap / C | compile jmocap (s) | compile MJX (s) |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for B, jm_r, mx_r, c_r, cj, cm in rows:
        print(
            f"| {B} | {jm_r:,.0f} | {mx_r:,.1f} | {c_r:,.0f} | {jm_r / mx_r:,.1f}x | "
            f"{jm_r / c_r:.2f}x | {cj:.1f} | {cm:.1f} |"
        )
    B, jm_r, mx_r, c_r, cj, cm = rows[-1]
    c_best = max(r[3] for r in rows)  # MuJoCo C's per-evaluation cost does not depend on B
    print(f"\ntargets (batch {B}):")
    print(f"  jmocap / MJX >= 100x: {jm_r / mx_r:,.1f}x  {_verdict(jm_r / mx_r >= 100)}")
    print(f"  jmocap / MuJoCo C >= 0.5x (goal > 1x): {jm_r / c_best:.2f}x  {_verdict(jm_r / c_best >= 0.5)}")
    worst = max(r[4] for r in rows)
    print(f"  jmocap compile < 30 s: worst {worst:.1f} s  {_verdict(worst < 30)}")


def _verdict(ok) -> str:
    return "met" if ok else "NOT met"


if __name__ == "__main__":
    main()
