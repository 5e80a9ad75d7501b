"""Frames per second of the whole pipeline, the ``physcap`` method's ``reconstruct``, side by side,
in one run.

``jax.jit(jax.vmap(reconstruct))`` (``jmocap.methods.get_method("physcap").reconstruct``) over a
batch of clips (TPNet, then k = 6 dynamic-cycle iterations per frame: DyNet, PD, GRFNet, friction
pyramid, forward dynamics, contact projection, integration), with the physics terms M, h, J_c from

  (a) jmocap (``PhysCapConfig(physics_backend="jmocap")``, the default), at 1, 64 and 512 clips;
  (b) MJX's own functions (``physics_backend="mjx"``): the same pipeline, only M, h and J_c
      differ. It is slow on CPU, so it is measured on 1 clip of a few frames.

Inputs: synthetic clips (``jmocap.data.synthetic``, 300 frames, 30 fps, BODY_25), tiled to the
batch; parameters: the shipped weights (``jmocap.weights.default_params``) when they exist, else
the method's ``init_params`` (the speed does not depend on the weights' values).

Every configuration runs in its own subprocess (so its peak memory, ``ru_maxrss``, is its own):
compile (trace + lower + XLA compile) is timed separately, then the compiled executable is called
until ``--min-time`` seconds have passed (at least once, at most 5 times); the median call gives
frames/s = clips x frames / seconds. Per-frame cost does not depend on the clip length (a
``lax.scan`` over frames), so configurations too slow for ~5 minutes are run on fewer frames and
the table says so (frames/s is then a per-frame extrapolation to 300-frame clips).

``--profile`` also times the pieces of one cycle iteration separately at the largest batch
(smooth dynamics, DyNet, GRFNet + friction pyramid, Cholesky + forward dynamics, projection,
integration)
and prints XLA's cost analysis of one iteration.

Every jmocap configuration at batch 64 and 512 is also run with the batch sharded over one host
CPU device per core (``--xla_force_host_platform_device_count``, a ``NamedSharding`` over the
clip axis, as ``jmocap.batch`` does): XLA's CPU backend runs one device's program on one thread.

Usage:  python experiments/bench_reconstruct.py [--quick [--mjx]] [--pip] [--profile] [--large-frames N]
        python experiments/bench_reconstruct.py --one BATCH FRAMES BACKEND   (one configuration)
"""

from __future__ import annotations

import os

# jaxlib's CPU Cholesky / triangular solves (used by every cycle iteration) call scipy's OpenBLAS,
# whose threads fight XLA's thread pool for the 2 cores: see docs/performance.md
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

HERE = Path(__file__).resolve().parent
CLIP_FRAMES = 300
N_DISTINCT = 4  # distinct synthetic clips, tiled to the batch


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def load_params(model, cfg):
    import jax

    from jmocap.methods import get_method

    try:
        from jmocap.weights import default_params

        params, shipped_cfg = default_params("physcap")
        return params, shipped_cfg, "shipped weights"
    except (FileNotFoundError, ImportError):
        return get_method("physcap").init_params(jax.random.PRNGKey(0), model, cfg), cfg, "init_params (random)"


def make_inputs(batch: int, frames: int):
    import jax
    import numpy as np

    from jmocap.data.synthetic import SynthConfig, generate_clip
    from jmocap.inputs import ClipInputs

    clips = [generate_clip(0, i, SynthConfig(frames=CLIP_FRAMES)) for i in range(min(N_DISTINCT, batch))]
    one = [ClipInputs.from_clip(c) for c in clips]
    one = [jax.tree.map(lambda x: np.asarray(x)[:frames] if np.ndim(x) and len(x) == CLIP_FRAMES else x, c)
           for c in one]
    idx = [i % len(one) for i in range(batch)]
    return jax.tree.map(lambda *xs: np.stack(xs), *[one[i] for i in idx])


def make_imu_inputs(batch: int, frames: int):
    """IMU inputs of ``pip_imu`` (``jmocap.methods.pip_imu.IMUInputs``) from simulated synthetic
    IMU clips (300 frames, 30 fps) on the nominal character, tiled to the batch."""
    import jax
    import numpy as np

    from jmocap.data.synthetic import SynthConfig
    from jmocap.data.synthetic.imu import IMUSynthConfig, generate_imu_clip
    from jmocap.methods import pip_imu as PI
    from jmocap.model import character

    model = character()
    one = []
    for i in range(min(N_DISTINCT, batch)):
        c = generate_imu_clip(0, i, IMUSynthConfig(synth=SynthConfig(frames=CLIP_FRAMES)))
        inp = PI.IMUInputs.from_clip(c, model)  # the clip's own first pose, on the nominal character
        one.append(jax.tree.map(lambda x: np.asarray(x)[:frames] if np.ndim(x) and len(x) == CLIP_FRAMES else x, inp))
    idx = [i % len(one) for i in range(batch)]
    return jax.tree.map(lambda *xs: np.stack(xs), *[one[i] for i in idx])


def run_one(batch: int, frames: int, backend: str, min_time: float, devices: int = 1, changes=(),
            tile: int = 0) -> dict:
    """Measure one configuration in this process; returns a JSON-able dict.

    ``devices`` > 1 shards the batch of clips over that many host CPU devices (the process must
    have been started with ``--xla_force_host_platform_device_count``; :func:`in_subprocess`
    does this), exactly as ``jmocap.batch`` shards its groups of clips.
    """
    import jax
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    from jmocap.methods import PhysCapConfig, get_method
    from jmocap.model import load_model
    from jmocap.pipeline import tiled_vmap

    model = load_model(with_mjx=backend == "mjx")
    inputs = None
    if backend == "pip_imu":  # PIP on six IMUs (jmocap.methods.pip_imu), the shipped weights
        from jmocap.methods import pip_imu as PI

        reconstruct = PI.reconstruct
        params, net = PI.load_params()
        cfg = PI.PIPIMUConfig(net=net)
        source = "shipped weights"
        inputs = make_imu_inputs(batch, frames)
        changes = ()  # (its config nests the physics: no --set)
    elif backend in ("pip", "pip_tpnet"):  # the pip method (dual PD + tracking QP) or its variant
        from jmocap.weights import load_run_params

        reconstruct = get_method("pip").reconstruct
        params, cfg = load_run_params(None, method=backend)
        source = "shipped weights"
    else:
        reconstruct = get_method("physcap").reconstruct
        params, cfg, source = load_params(model, PhysCapConfig())
        cfg = cfg.replace(physics_backend=backend)
    # the experiments' one "name=value" parser (this folder is on sys.path)
    from ablate_pip import parse_set

    cfg = cfg.replace(**parse_set(changes or (), cfg))
    if inputs is None:
        inputs = make_inputs(batch, frames)
    if devices > 1:
        if len(jax.devices()) < devices or batch % devices:
            raise SystemExit(f"need {devices} devices (have {len(jax.devices())}) and a batch divisible by them")
        mesh = Mesh(jax.devices()[:devices], ("clips",))
        inputs = jax.device_put(inputs, NamedSharding(mesh, PartitionSpec("clips")))
        params = jax.device_put(params, NamedSharding(mesh, PartitionSpec()))
    rss_setup = rss_mb()
    # the config is an ordinary argument (its static fields are part of the compiled program,
    # its physical parameters are traced), passed to the executable like the others
    # with ``tile``: each device's clips in tiles of ``tile`` (jmocap.pipeline.tiled_vmap, as
    # jmocap reconstruct runs its batches)
    fn = jax.jit(lambda p, m, i, c: tiled_vmap(lambda x: reconstruct(p, m, x, c), (i,), tile, devices))
    t0 = time.perf_counter()
    exe = fn.lower(params, model, inputs, cfg).compile()
    compile_s = time.perf_counter() - t0
    times = []
    t_start, c_start = time.perf_counter(), cpu_s()
    while True:
        t0 = time.perf_counter()
        out = jax.block_until_ready(exe(params, model, inputs, cfg))
        times.append(time.perf_counter() - t0)
        if time.perf_counter() - t_start >= min_time or len(times) >= 5:
            break
    # CPU cores this process obtained during the timed calls (2 on an idle machine at best)
    cores = (cpu_s() - c_start) / (time.perf_counter() - t_start)
    finite = bool(jax.numpy.all(jax.numpy.isfinite(out.q)))
    # the first call of a fresh executable pays one-off allocation; drop it when there are others
    t = statistics.median(times[1:] if len(times) > 2 else times)
    return dict(batch=batch, frames=frames, backend=backend, params=source, compile_s=compile_s,
                call_s=t, calls=len(times), fps=batch * frames / t, cores=cores,
                fps_per_core=batch * frames / t / max(cores, 1e-9), rss_setup_mb=rss_setup,
                rss_peak_mb=rss_mb(), finite=finite, devices=devices, changes=list(changes), tile=tile)


def in_subprocess(batch, frames, backend, min_time, timeout, devices: int = 1, tile: int = 0, changes=()) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--one", str(batch), str(frames), backend,
           "--min-time", str(min_time), "--devices", str(devices), "--tile", str(tile)]
    if changes:
        cmd += ["--set", *changes]
    env = dict(os.environ)
    if devices > 1:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}").strip()
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return dict(batch=batch, frames=frames, backend=backend, devices=devices,
                    error=f"timed out after {timeout} s")
    for line in reversed(p.stdout.splitlines()):
        if line.startswith("{"):
            r = json.loads(line)
            r["wall_s"] = time.perf_counter() - t0
            return r
    return dict(batch=batch, frames=frames, backend=backend, devices=devices, error=(p.stderr or p.stdout)[-400:])


def profile(batch: int, min_time: float = 1.0):
    """Time the pieces of one cycle iteration at ``batch``, and XLA's cost analysis of it."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jmocap import physics as P
    from jmocap.constants import FLOOR_NORMAL
    from jmocap.methods import PhysCapConfig
    from jmocap.methods.physcap import CycleState, cycle_step
    from jmocap.methods.stages import dynet_features, grfnet_features, pd_error, target_pose
    from jmocap.model import load_model
    from jmocap.nets import DyNet, GRFNet

    model = load_model(with_mjx=False)
    params, cfg, _ = load_params(model, PhysCapConfig())
    inputs = make_inputs(batch, 30)
    tp = jax.jit(jax.vmap(lambda i: target_pose(params, model, i, cfg)))(inputs)
    q = tp.q_hat[:, 5]
    rng = np.random.default_rng(0)
    qd = jnp.asarray(rng.normal(scale=0.5, size=(batch, model.nv)), q.dtype)
    q_hat = tp.q_hat[:, 6]
    prob = jax.nn.sigmoid(tp.contact_logits[:, 6])
    grf = jnp.zeros((batch, 4, 3), q.dtype)
    dt = jnp.asarray(1 / 180, q.dtype)
    dyn = jax.vmap(lambda q, qd: P.smooth_dynamics(model, q, qd))(q, qd)
    M, h, Jc = dyn.M, dyn.h, dyn.Jc
    e = jax.vmap(lambda a, b: pd_error(model, a, b))(q_hat, q)
    L = jax.vmap(P.cholesky)(M)
    contact = prob > cfg.contact_threshold

    def dynet(q_hat, q, qd, M, e):
        return DyNet(nv=model.nv, width=cfg.nets.dyn_width).apply(
            {"params": params["dynet"]}, dynet_features(model, q_hat, q, qd, M, e))

    def grfnet(tau_root, Jc, prob, grf):
        raw = GRFNet(n_points=4, width=cfg.nets.grf_width).apply(
            {"params": params["grfnet"]}, grfnet_features(model, tau_root, Jc, prob, grf))
        return P.project_friction_pyramid(raw, jnp.asarray(FLOOR_NORMAL, raw.dtype), cfg.mu)

    pieces = {
        "smooth_dynamics (M, h, J_c)": (lambda q, qd: P.smooth_dynamics(model, q, qd), (q, qd)),
        "DyNet (features + MLP)": (dynet, (q_hat, q, qd, M, e)),
        "GRFNet + friction pyramid": (grfnet, (h[:, :6], Jc, prob, grf)),
        "Cholesky + cho_solve (forward dynamics)": (lambda M, b: P.cho_solve(P.cholesky(M), b), (M, h)),
        "project_velocity (given L, kin)": (
            lambda q, qd, a, L, kin: P.project_velocity(model, q, qd, a, dt=1 / 180, beta=cfg.beta,
                                                        chol=L, kin=kin),
            (q, qd, contact, L, dyn.kin)),
        "integrate_positions": (lambda q, qd: P.integrate_positions(model, q, qd, 1 / 180), (q, qd)),
        "whole cycle_step": (
            lambda q, qd, g, qh, p: cycle_step(params, model, CycleState(q, qd, g), qh, p, dt, cfg),
            (q, qd, grf, q_hat, prob)),
    }
    print(f"\n{time.strftime('%Y-%m-%d %H:%M')}; profile: one dynamic-cycle iteration, batch {batch} "
          "(each piece jit of vmap on its own; x6 per frame)\n", flush=True)
    print("| piece | ms per call | us per clip-iteration | share of cycle_step |")
    print("|---|---:|---:|---:|")
    res, ca = {}, None
    for name, (f, args) in pieces.items():
        exe = jax.jit(jax.vmap(f)).lower(*args).compile()
        jax.block_until_ready(exe(*args))
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < min_time:
            jax.block_until_ready(exe(*args))
            n += 1
        res[name] = (time.perf_counter() - t0) / n
        if name == "whole cycle_step":
            ca = exe.cost_analysis()
            ca = ca[0] if isinstance(ca, (list, tuple)) else ca
    whole = res["whole cycle_step"]
    for name, s in res.items():
        print(f"| {name} | {1e3 * s:.2f} | {1e6 * s / batch:.1f} | {s / whole:.0%} |", flush=True)
    tpn = jax.jit(jax.vmap(lambda i: target_pose(params, model, i, cfg).q_hat)).lower(inputs).compile()
    jax.block_until_ready(tpn(inputs))
    t0 = time.perf_counter()
    jax.block_until_ready(tpn(inputs))
    t_tp = (time.perf_counter() - t0) / 30
    print(f"| TPNet (target pose), per frame | {1e3 * t_tp:.2f} | {1e6 * t_tp / batch:.1f} | "
          f"{t_tp / (6 * whole):.0%} of a frame's 6 iterations |")
    ca_tp = tpn.cost_analysis()
    ca_tp = ca_tp[0] if isinstance(ca_tp, (list, tuple)) else ca_tp
    if ca_tp:
        print(f"\nXLA cost analysis of TPNet: {ca_tp.get('flops', float('nan')) / (30 * batch) / 1e6:.1f} MFLOP "
              "per clip-frame")
    if ca:
        fl = ca.get("flops", float("nan"))
        by = ca.get("bytes accessed", float("nan"))
        print(f"\nXLA cost analysis of one cycle_step at batch {batch}: {fl / 1e9:.2f} GFLOP "
              f"({fl / batch / 1e6:.2f} MFLOP per clip-iteration), {by / 1e6:.0f} MB accessed; "
              f"achieved {fl / whole / 1e9:.1f} GFLOP/s")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small batches and clips (smoke run)")
    ap.add_argument("--profile", action="store_true", help="also time the pieces of one cycle iteration")
    ap.add_argument("--profile-only", action="store_true", help="only the profile (no frames/s table)")
    ap.add_argument("--profile-batch", type=int, nargs="+", default=None,
                    help="batches of the profile (default 512; 8 with --quick)")
    ap.add_argument("--one", nargs=3, metavar=("BATCH", "FRAMES", "BACKEND"), help=argparse.SUPPRESS)
    ap.add_argument("--min-time", type=float, default=3.0, help="seconds of timed calls per configuration")
    ap.add_argument("--mjx-frames", type=int, default=5, help="frames of the MJX-backend clip")
    ap.add_argument("--mjx", action="store_true", help="with --quick: also run the MJX backend")
    ap.add_argument("--large-frames", type=int, default=30,
                    help="frames per clip at batch 512 (extrapolated per frame; 300 takes too long)")
    ap.add_argument("--devices", type=int, default=1, help=argparse.SUPPRESS)  # with --one
    ap.add_argument("--tile", type=int, default=None,
                    help="clips per tile of each device's batch (jmocap.pipeline.tiled_vmap; 0: one vmap); "
                    "default jmocap.pipeline.TILE, as jmocap reconstruct runs")
    ap.add_argument("--tiles", action="store_true",
                    help="only physcap and pip at batch 512 on every core, each with and without tiles")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="with --one: config changes of the method (e.g. fit_iterations=5)")
    ap.add_argument("--imu", action="store_true",
                    help="also PIP on six IMUs (backend column 'pip_imu') at batch 1 (latency) and 512")
    ap.add_argument("--pip", action="store_true",
                    help="also the pip method and its variant pip_tpnet (backend columns 'pip', 'pip_tpnet')")
    args = ap.parse_args(argv)
    from jmocap.pipeline import TILE

    tile = TILE if args.tile is None else args.tile
    if args.one:
        b, f, backend = args.one
        print(json.dumps(run_one(int(b), int(f), backend, args.min_time, args.devices, args.set, tile)), flush=True)
        return

    sys.path.insert(0, str(HERE))
    from bench_physics import machine

    if args.profile_only:
        print(f"machine: {machine()}  (OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']})", flush=True)
        for b in args.profile_batch or [8 if args.quick else 512]:
            profile(b)
        return

    cores = os.cpu_count() or 1
    if args.quick:  # smoke run; MJX's cycle alone compiles for about 2 minutes on 2 cores
        configs = [(1, 30, "jmocap", 1), (8, 30, "jmocap", 1), (8, 30, "jmocap", 2)] + (
            [(1, 2, "mjx", 1)] if args.mjx else [])
    else:
        configs = [(1, CLIP_FRAMES, "jmocap", 1), (64, CLIP_FRAMES, "jmocap", 1),
                   (512, args.large_frames, "jmocap", 1)]
        if cores > 1:  # the batch sharded over one host device per core (as jmocap.batch does)
            configs += [(64, CLIP_FRAMES, "jmocap", cores), (512, args.large_frames, "jmocap", cores)]
        configs += [(1, args.mjx_frames, "mjx", 1)]
    if args.pip:  # the pip method beside physcap at the same batches
        configs += [(64, CLIP_FRAMES if not args.quick else 30, "pip", 1),
                    (512 if not args.quick else 8, args.large_frames, "pip", 1)]
        if cores > 1:
            configs += [(512 if not args.quick else 8, args.large_frames, "pip", cores)]
        configs += [(512 if not args.quick else 8, args.large_frames, "pip_tpnet", cores)]
    if args.imu:  # PIP on IMUs: batch 1 (an online stream) and 512 (throughput)
        configs += [(1, CLIP_FRAMES if not args.quick else 30, "pip_imu", 1),
                    (512 if not args.quick else 8, args.large_frames, "pip_imu", cores)]
    configs = [(*c, tile, ()) for c in configs]
    if args.tiles:  # one vmap over each device's clips against tiles of TILE, side by side; pip
        # also with its per-frame fit as one vmap over the frames (fit_tile=0)
        configs = [(512, args.large_frames, "jmocap", cores, t, ()) for t in (0, tile)] + [
            (512, args.large_frames, "pip", cores, t, ch) for t, ch in ((0, ("fit_tile=0",)), (0, ()), (tile, ()))]
    print(f"machine: {machine()}  (OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']})", flush=True)
    rows = []
    for b, f, backend, ndev, t, ch in configs:
        r = in_subprocess(b, f, backend, 0.5 if args.quick else args.min_time, timeout=900, devices=ndev, tile=t,
                          changes=ch)
        r.setdefault("tile", t)
        if ch:
            r["backend"] = f"{backend} ({', '.join(ch)})"
        rows.append(r)
        msg = r.get("error") or f"{r['fps']:,.1f} frames/s, compile {r['compile_s']:.0f} s, wall {r['wall_s']:.0f} s"
        print(f"  batch {b} x {f} frames, {backend}, {ndev} device(s), tile {t}: {msg}", flush=True)
    ok = [r for r in rows if "error" not in r]
    print(f"\n{time.strftime('%Y-%m-%d %H:%M')}; reconstruct = TPNet + 6 cycle iterations per frame; "
          f"params: {ok[0]['params'] if ok else '?'}\n")
    mjx = [r for r in ok if r["backend"] == "mjx"]
    mjx_fps = max((r["fps"] for r in mjx), default=float("nan"))
    mjx_fpc = max((r["fps_per_core"] for r in mjx), default=float("nan"))
    print("| backend | host devices | clips | tile | frames per clip (measured) | frames/s | vs MJX backend (best) | "
          "CPU cores obtained | frames per CPU-second | vs MJX per CPU-second | call (s) | compile (s) | peak RSS (MB) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        if "error" in r:
            print(f"| {r['backend']} | {r['devices']} | {r['batch']} | {r['tile']} | {r['frames']} | "
                  f"failed: {r['error'][:80]} | | | | | | | |")
            continue
        ext = "" if r["frames"] == CLIP_FRAMES else " (extrapolated per frame)"
        vs = f"{r['fps'] / mjx_fps:,.0f}x" if mjx else "-"
        vs_c = f"{r['fps_per_core'] / mjx_fpc:,.0f}x" if mjx else "-"
        print(f"| {r['backend']} | {r['devices']} | {r['batch']} | {r['tile']} | {r['frames']}{ext} | {r['fps']:,.1f} | {vs} | "
              f"{r['cores']:.2f} | {r['fps_per_core']:,.1f} | {vs_c} | "
              f"{r['call_s']:.2f} | {r['compile_s']:.1f} | {r['rss_peak_mb']:,.0f} |")
    jm = [r for r in ok if r["backend"] == "jmocap"]
    if jm:
        top = max(r["batch"] for r in jm)
        big = max((r for r in jm if r["batch"] == top), key=lambda r: r["fps"])
        same = [r for r in jm if r["batch"] == 1]
        print(f"\ntargets (batch {big['batch']}, {big['devices']} host device(s)):")
        print(f"  >= 1,000 frames/s: {big['fps']:,.0f}  {'met' if big['fps'] >= 1000 else 'NOT met'}"
              f" ({big['cores']:.2f} of 2 cores obtained; {big['fps_per_core']:,.0f} frames per CPU-second)")
        if mjx:
            r = big["fps"] / mjx_fps
            print(f"  >= 100x the MJX backend: {r:,.0f}x  {'met' if r >= 100 else 'NOT met'}"
                  + (f" (same batch 1: {same[0]['fps'] / mjx_fps:,.0f}x)" if same else ""))
    if args.tiles:
        for m in ("jmocap", "pip"):
            by = {r["tile"]: r for r in ok if r["backend"] == m}
            if 0 in by and tile in by:
                print(f"  {m}: tiles of {tile} / one vmap = {by[tile]['fps'] / by[0]['fps']:.2f}x")
        old = [r for r in ok if r["backend"].startswith("pip (")]
        new = [r for r in ok if r["backend"] == "pip" and r["tile"] == tile]
        if old and new:
            print(f"  pip, tiles of {tile} and fit tiles / one vmap everywhere = {new[0]['fps'] / old[0]['fps']:.2f}x")
    pp = [r for r in ok if r["backend"] in ("pip", "pip_tpnet")]
    for r in pp:
        ref = [j for j in jm if j["batch"] == r["batch"] and j["devices"] == r["devices"]
               and j["tile"] == r["tile"]]
        ratio = f"{r['fps'] / ref[0]['fps']:.2f}x physcap's" if ref else "no physcap row at this batch"
        print(f"  {r['backend']}, batch {r['batch']}, {r['devices']} host device(s): {r['fps']:,.0f} frames/s "
              f"({'met' if r['fps'] >= 500 else 'NOT met'}: >= 500), {ratio}")
    if args.profile:
        for b in args.profile_batch or [8 if args.quick else 512]:
            profile(b)


if __name__ == "__main__":
    main()
