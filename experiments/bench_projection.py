"""Throughput and accuracy of the contact-projection QP (paper eq. 15), side by side, in one run.

Every solver gets the SAME problems, built from the default humanoid with MuJoCo C in float64:
random configurations shifted so that the lowest contact point is between 3 cm below and 2 cm
above the floor, random velocities, the mass-matrix metric ``W = M(q)`` (``W^-1`` computed once
in float64), ``G`` the contact-normal rows of the point Jacobians (every point constrained),
``v = qd`` and ``lower = beta max(0, -z) / dt`` (beta = 0.2, dt = 1/180 s as in the dynamic cycle):

    x* = argmin 1/2 (x - v)^T W (x - v)   s.t.   G x >= lower

Point sets: the four foot sites (m = 4), PIP's foot corners (``physics.foot_corner_points``, two
feet, m = 8) and four corner squares (ankles and toes, m = 16).

Competitors (batch 256 by default, CPU):
  (a) jmocap: ``physics.qp.solve_projection(Winv, G, v, lower)``, jit of vmap;
  (b) qpax: ``qpax.solve_qp_primal(W, -W v, A=(0,n), b=(0,), -G, -lower)`` (generic
      differentiable primal-dual interior point), jit of vmap, its default tolerance 1e-5 and
      30 iterations, and (float64) tightened to 1e-9 / 50 iterations;
  (c) Clarabel (interior point, float64) in a Python loop, through tests/qp_reference.py, at
      tolerance 1e-8 and at 1e-14.

Accuracy: max |x - x_ref| over the batch, in float64 and float32 (inputs rounded to float32
once, identically for every float32 solver).  The reference x_ref is Clarabel at 1e-14 polished
on its own active set in float64 (``qp_reference.polished_projection``): Clarabel alone stops
1e-5..2e-4 from the optimum on these degenerate (dependent corner rows), ill-conditioned QPs.

Then end-to-end ``physics.project_velocity(model, q, qd, active)`` throughput (kinematics, the
contact rows, M, its Cholesky factor and inverse, and the QP), against the same pipeline with qpax
as the QP solver, and against MuJoCo C (mj_kinematics, mj_comPos, mj_crb, mj_fullM, jacobians) +
Clarabel in a Python loop.

Timing: the competitors are run in interleaved rounds (a, b, c, a, b, c, ...) and the median
per competitor is reported, so that a load change on the machine hits all of them alike.

Usage:  python experiments/bench_projection.py [--quick] [--batch 256] [--points 4 8 16]
"""

from __future__ import annotations

import os

# jaxlib's CPU Cholesky / triangular solves call scipy's OpenBLAS, whose worker threads fight
# XLA's own thread pool (and any other process) for the cores: with the default thread count a
# batched M^-1 ran up to ~1000x slower on the 2-core benchmark machine (docs/performance.md).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)  # float64 available; float32 runs cast explicitly

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from bench_physics import machine  # noqa: E402
from qp_reference import clarabel_projection, polished_projection  # noqa: E402

REF_RESOLUTION = 1e-8  # errors below this are at the accuracy of the (polished) reference itself
DT = 1.0 / 180.0  # 30 fps, k = 6 cycle iterations per frame
BETA = 0.2


# ------------------------------------------------------------------------------- problems


def point_sets(model):
    from jmocap.physics.contact import default_contact_points, foot_corner_points

    return {
        4: ("4 foot sites", default_contact_points(model)),
        8: ("8 foot corners (PIP)", foot_corner_points(model)),
        16: (
            "16 corners (ankles + toes)",
            foot_corner_points(model, ("left_ankle", "left_foot", "right_ankle", "right_foot")),
        ),
    }


def random_configurations(model, n, seed):
    mj = model.mj
    rng = np.random.default_rng(seed)
    q = np.tile(mj.qpos0, (n, 1))
    quat = rng.normal(size=(n, 4))
    q[:, 3:7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    lo, hi = np.asarray(model.q_lower), np.asarray(model.q_upper)
    hq = model.topo.hinge_qadr
    q[:, hq] = rng.uniform(lo[hq], hi[hq], (n, hq.size))
    q[:, :2] = rng.uniform(-2, 2, (n, 2))
    qd = rng.normal(scale=2.0, size=(n, mj.nv))
    return q, qd, rng


def _point_world(model, d, points, i):
    b = points.bodies[i]
    off = model.mj.site_pos[points.site_ids[i]] if points.site_ids else np.asarray(points.offsets[i])
    return d.xpos[b] + d.xmat[b].reshape(3, 3) @ off


def mujoco_problem(model, d, points, q, qd):
    """(W, G, lower) at (q, qd) from MuJoCo C, float64; every point constrained."""
    mj = model.mj
    d.qpos[:] = q
    d.qvel[:] = qd
    mujoco.mj_kinematics(mj, d)
    mujoco.mj_comPos(mj, d)
    mujoco.mj_crb(mj, d)
    W = np.zeros((mj.nv, mj.nv))
    mujoco.mj_fullM(mj, d, W)
    jp = np.zeros((3, mj.nv))
    G = np.zeros((len(points), mj.nv))
    z = np.zeros(len(points))
    for i in range(len(points)):
        p = _point_world(model, d, points, i)
        mujoco.mj_jac(mj, d, jp, None, p, points.bodies[i])
        G[i] = jp[2]
        z[i] = p[2]
    lower = BETA * np.maximum(0.0, -z) / DT
    return W, G, lower


def near_floor(model, points, n, seed):
    """Configurations whose lowest point of ``points`` is 3 cm deep to 2 cm high, and the QPs."""
    mj = model.mj
    q, qd, rng = random_configurations(model, n, seed)
    d = mujoco.MjData(mj)
    for k in range(n):
        d.qpos[:] = q[k]
        mujoco.mj_kinematics(mj, d)
        zmin = min(_point_world(model, d, points, i)[2] for i in range(len(points)))
        q[k, 2] += -zmin + rng.uniform(-0.03, 0.02)
    Ws, Gs, lows = zip(*(mujoco_problem(model, d, points, q[k], qd[k]) for k in range(n)), strict=True)
    W = np.stack(Ws)
    Winv = np.linalg.inv(W)
    Winv = 0.5 * (Winv + np.swapaxes(Winv, 1, 2))
    return dict(q=q, qd=qd, W=W, Winv=Winv, G=np.stack(Gs), v=qd.copy(), lower=np.stack(lows))


# ------------------------------------------------------------------------------- solvers


def jmocap_solver():
    from jmocap.physics.qp import solve_projection

    return jax.jit(jax.vmap(lambda W, Winv, G, v, lo: solve_projection(Winv, G, v, lo)))


def qpax_solver(tol=1e-5, max_iter=30):
    import qpax

    def one(W, Winv, G, v, lo):
        n = W.shape[0]
        A = jnp.zeros((0, n), W.dtype)
        b = jnp.zeros((0,), W.dtype)
        return qpax.solve_qp_primal(W, -W @ v, A, b, -G, -lo, solver_tol=tol, max_iter=max_iter)

    return jax.jit(jax.vmap(one))


def qpax_info(tol=1e-5, max_iter=30):
    """Converged flags and iteration counts of qpax (reported, not timed)."""
    import qpax

    def one(W, G, v, lo):
        n = W.shape[0]
        out = qpax.solve_qp(W, -W @ v, jnp.zeros((0, n), W.dtype), jnp.zeros((0,), W.dtype), -G, -lo,
                            solver_tol=tol, max_iter=max_iter)
        return out[4], out[5]

    return jax.jit(jax.vmap(one))


def clarabel_loop(tol):
    def run(W, Winv, G, v, lo):
        return np.stack([clarabel_projection(W[i], G[i], v[i], lo[i], tol=tol)[0] for i in range(len(v))])

    return run


# ------------------------------------------------------------------------------- timing


def reference(prob):
    """Polished Clarabel solutions of a batch of problems (float64)."""
    return np.stack([polished_projection(prob["W"][i], prob["G"][i], prob["v"][i], prob["lower"][i])[0]
                     for i in range(len(prob["v"]))])


def block(x):
    return jax.block_until_ready(x)


def interleaved(fns: dict, args: dict, rounds: int, min_time: float) -> dict:
    """Median seconds per call of each competitor, over interleaved rounds (after a warm-up)."""
    for k, f in fns.items():
        block(f(*args[k]))
    samples = {k: [] for k in fns}
    for _ in range(rounds):
        for k, f in fns.items():
            n, t0 = 0, time.perf_counter()
            while True:
                block(f(*args[k]))
                n += 1
                dt = time.perf_counter() - t0
                if dt >= min_time or n >= 200:
                    break
            samples[k].append(dt / n)
    return {k: statistics.median(v) for k, v in samples.items()}


def compile_seconds(fn, *args):
    t0 = time.perf_counter()
    exe = fn.lower(*args).compile()
    return exe, time.perf_counter() - t0


def cast(prob, dtype):
    return tuple(jnp.asarray(prob[k], dtype) for k in ("W", "Winv", "G", "v", "lower"))


def max_err(x, ref):
    x = np.asarray(x, np.float64)
    return float(np.max(np.abs(x - ref))) if np.all(np.isfinite(x)) else float("inf")


# ------------------------------------------------------------------------------- main


def bench_qp(model, m, label, points, B, rounds, min_time, lines, summary):
    prob = near_floor(model, points, B, seed=100 + m)
    ref = reference(prob)
    np_args = tuple(prob[k] for k in ("W", "Winv", "G", "v", "lower"))
    a64, a32 = cast(prob, jnp.float64), cast(prob, jnp.float32)
    jm, qp_def, qp_tight = jmocap_solver(), qpax_solver(), qpax_solver(1e-9, 50)
    fns, args, comp = {}, {}, {}
    for name, f, a in (
        ("jmocap f32", jm, a32), ("qpax f32", qp_def, a32),
        ("jmocap f64", jm, a64), ("qpax f64", qp_def, a64), ("qpax f64 tight", qp_tight, a64),
    ):
        fns[name], comp[name] = compile_seconds(f, *a)
        args[name] = a
    fns["Clarabel loop"], args["Clarabel loop"] = clarabel_loop(1e-8), np_args
    fns["Clarabel ref"], args["Clarabel ref"] = clarabel_loop(1e-14), np_args
    t = interleaved(fns, args, rounds, min_time)
    err = {k: max_err(fns[k](*args[k]), ref) for k in fns}
    conv = {}
    for name, a, tol, it in (("qpax f32", a32, 1e-5, 30), ("qpax f64", a64, 1e-5, 30), ("qpax f64 tight", a64, 1e-9, 50)):
        c, n_it = qpax_info(tol, it)(a[0], a[2], a[3], a[4])
        conv[name] = f"{np.mean(np.asarray(c) == 1):.0%} conv., {float(np.mean(np.asarray(n_it))):.0f} it."
    lines.append(f"\n### m = {m}: {label}, batch {B}\n")
    lines.append("| solver | dtype | QPs/s | jmocap (same dtype) / this | max abs error of x vs reference | compile (s) | notes |")
    lines.append("|---|---|---:|---:|---:|---:|---|")
    for name in fns:
        dtype = "f64" if ("f64" in name or "Clarabel" in name) else "f32"
        base = t["jmocap f32"] if dtype == "f32" else t["jmocap f64"]
        solver = name.replace(" f32", "").replace(" f64", "")
        note = conv.get(name, "")
        if "tight" in name:
            solver = "qpax (tol 1e-9, 50 it.)"
        elif solver == "qpax":
            solver = "qpax (default tol 1e-5, 30 it.)"
        elif solver == "Clarabel loop":
            solver = "Clarabel, Python loop (tol 1e-8)"
        elif solver == "Clarabel ref":
            solver, note = "Clarabel, Python loop (tol 1e-14)", "unpolished"
        lines.append(
            f"| {solver} | {dtype} | {B / t[name]:,.0f} | {t[name] / base:,.1f}x | {err[name]:.1e} | "
            f"{comp.get(name, float('nan')):.1f} | {note} |"
        )
    summary.append((m, t, err))
    print(f"  measured QPs, m = {m}", flush=True)


def bench_end_to_end(model, m, label, points, B, rounds, min_time, lines):
    import qpax

    from jmocap.physics.contact import contact_constraints, project_velocity
    from jmocap.physics.dynamics import mass_matrix
    from jmocap.physics.kinematics import forward_kinematics

    prob = near_floor(model, points, B, seed=200 + m)
    active = np.ones((B, len(points)), bool)

    def jm_one(q, qd, a):
        return project_velocity(model, q, qd, a, dt=DT, beta=BETA, points=points)

    def qpax_one(q, qd, a):
        kin = forward_kinematics(model, q)
        G, lo = contact_constraints(model, q, a, dt=DT, beta=BETA, points=points, kin=kin)
        W = mass_matrix(model, q, kin=kin)
        n = W.shape[0]
        return qpax.solve_qp_primal(W, -W @ qd, jnp.zeros((0, n), W.dtype), jnp.zeros((0,), W.dtype), -G, -lo)

    d = mujoco.MjData(model.mj)

    def c_loop(q, qd, a):
        out = []
        for i in range(len(q)):
            W, G, lo = mujoco_problem(model, d, points, q[i], qd[i])
            out.append(clarabel_projection(W, G, qd[i], lo, tol=1e-8)[0])
        return np.stack(out)

    ref = reference(prob)
    fns, args, comp = {}, {}, {}
    for dt_name, dtype in (("f32", jnp.float32), ("f64", jnp.float64)):
        a = (jnp.asarray(prob["q"], dtype), jnp.asarray(prob["qd"], dtype), jnp.asarray(active))
        for name, one in (("jmocap project_velocity", jm_one), ("jmocap M, G, lower + qpax", qpax_one)):
            key = f"{name} {dt_name}"
            fns[key], comp[key] = compile_seconds(jax.jit(jax.vmap(one)), *a)
            args[key] = a
    fns["MuJoCo C + Clarabel loop"] = c_loop
    args["MuJoCo C + Clarabel loop"] = (prob["q"], prob["qd"], active)
    t = interleaved(fns, args, rounds, min_time)
    err = {k: max_err(fns[k](*args[k]), ref) for k in fns}
    lines.append(f"\n### end to end, m = {m}: {label}, batch {B} (q, qd -> qd*, mass matrix included)\n")
    lines.append("| pipeline | dtype | projections/s | jmocap (same dtype) / this | max abs error vs reference (MuJoCo C + polished Clarabel) | compile (s) |")
    lines.append("|---|---|---:|---:|---:|---:|")
    for key in fns:
        dtype = "f32" if key.endswith("f32") else "f64"
        base = t[f"jmocap project_velocity {dtype}"]
        name = key.rsplit(" ", 1)[0] if key.endswith(("f32", "f64")) else key
        lines.append(f"| {name} | {dtype} | {B / t[key]:,.0f} | {t[key] / base:,.1f}x | {err[key]:.1e} | "
                     f"{comp.get(key, float('nan')):.1f} |")
    print(f"  measured end to end, m = {m}", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="batch 32, m = 4 and 8, few rounds (smoke run)")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--points", type=int, nargs="+", default=[4, 8, 16], choices=[4, 8, 16])
    ap.add_argument("--end-to-end-points", type=int, nargs="*", default=[4, 8], choices=[4, 8, 16],
                    help="point sets of the end-to-end project_velocity table (none: skip it)")
    args = ap.parse_args(argv)
    from jmocap.model import load_model

    model = load_model(with_mjx=False)
    B = 32 if args.quick else args.batch
    ms = [4, 8] if args.quick else args.points
    rounds, min_time = (2, 0.05) if args.quick else (5, 0.2)
    sets = point_sets(model)
    print(f"machine: {machine()}")
    print(f"model: default humanoid, nv={model.nv}; W = M(q); beta = {BETA}, dt = 1/180 s\n", flush=True)
    lines, summary = [], []
    for m in ms:
        bench_qp(model, m, *sets[m], B, rounds, min_time, lines, summary)
    for m in [m for m in args.end_to_end_points if m in ms]:
        bench_end_to_end(model, m, *sets[m], B, rounds, min_time, lines)
    print(f"\n{time.strftime('%Y-%m-%d %H:%M')}; the solver that the ratio column divides by is jmocap in the same dtype "
          "(a ratio of 120x means jmocap solves 120 times as many QPs per second)")
    print("\n".join(lines))
    print("\n### targets: solve_projection >= 100x qpax's throughput at better accuracy\n")
    print("| m | vs qpax f32 (default tol) | vs qpax f64 (default tol) | vs qpax f64 (tol 1e-9) | vs Clarabel loop (tol 1e-8) |")
    print("|---:|---|---|---|---|")
    pairs = (("jmocap f32", "qpax f32"), ("jmocap f64", "qpax f64"), ("jmocap f64", "qpax f64 tight"),
             ("jmocap f64", "Clarabel loop"))
    for m, t, err in summary:
        cells = []
        for a, b in pairs:
            r = t[b] / t[a]
            # errors below REF_RESOLUTION are the reference's own
            acc = err[a] <= max(err[b], REF_RESOLUTION)
            verdict = "met" if r >= 100 and acc else "NOT met (" + ", ".join(
                w for w, bad in (("speed", r < 100), ("accuracy", not acc)) if bad) + ")"
            cells.append(f"{r:,.0f}x, error {err[a]:.0e} vs {err[b]:.0e}: {verdict}")
        print(f"| {m} | " + " | ".join(cells) + " |")

if __name__ == "__main__":
    main()
