"""End-to-end archive throughput of ``jmocap reconstruct`` (clips/s, frames/s), I/O included.

One synthetic clip archive (jmocap.data.synthetic, written once), reconstructed side by side by:

  (a) jmocap.batch.reconstruct_archive - chunked, vmapped over ``--batch`` clips per device,
      sharded over the local devices - at each batch size of ``--batches``;
  (b) the same with the ``kinematic`` method (TPNet only) at the largest batch size;
  (c) a per-clip loop: read the clip, ``jax.jit`` of the ``physcap`` method's ``reconstruct`` on
      it alone (padded to a multiple of ``--bucket`` frames, so lengths share compilations, as
      the engine's buckets do), world keypoints, write the same result file. What a script
      without the batch engine would do.

Each is run twice into fresh output folders: "cold" includes compilation, "warm" reuses the
compiled code (the persistent compilation cache is off). Throughput is from the warm run;
ratios are against (c). Every run reads the archive, checks every output for NaN, and writes
compressed .npz results and a manifest, so the numbers are what a user gets.

Usage:  python experiments/bench_batch.py [--quick] [--clips N] [--frames MIN:MAX]
            [--batches 1,8] [--chunk 256] [--bucket 64] [--params PATH | --random-init]
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import jax
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
    devs = jax.devices()
    return f"{cpu}, {os.cpu_count()} cores, jax {jax.__version__} ({devs[0].platform} x {len(devs)})"


def make_archive(root: Path, clips: int, frames: tuple[int, int], seed: int = 0) -> int:
    from jmocap.data.archive import ArchiveWriter
    from jmocap.data.synthetic import SynthConfig, generate_clip

    total = 0
    with ArchiveWriter(root) as w:
        for i in range(clips):
            c = generate_clip(seed, i, SynthConfig(frames=frames))
            w.add(c)
            total += c.num_frames
    return total


def run_engine(archive, out, params, config, options, method="physcap"):
    from jmocap.batch import reconstruct_archive

    t = time.perf_counter()
    s = reconstruct_archive(archive, out, params, config, options, method=method)
    el = time.perf_counter() - t
    if s["failed"]:
        raise RuntimeError(f"{s['failed']} clips failed: {s['failures'][:3]}")
    return el, s["frames"]


@jax.jit
def _one_clip(params, model, inputs, config):
    # the config is an ordinary argument: its static fields (layout, iterations, ...) are part
    # of the jit cache key, its physical parameters are traced
    from jmocap import physics as P
    from jmocap.methods import get_method

    r = get_method("physcap").reconstruct(params, model, inputs, config)
    return r, jax.vmap(lambda q: P.keypoints(model, q, config.layout))(r.q)


def run_loop(archive, out, params, config, bucket):
    """(c): one clip at a time through jit(reconstruct), same inputs and result files."""
    from jmocap.batch import run_identity
    from jmocap.data.archive import Archive
    from jmocap.inputs import ClipInputs
    from jmocap.methods import get_method
    from jmocap.pipeline import subject_height, subject_model
    from jmocap.results import ResultWriter, assumed_fields, check_finite, result_arrays

    method = get_method("physcap")
    identity = run_identity(params, config, method.name)
    t, frames = time.perf_counter(), 0
    with Archive(archive) as a, ResultWriter(out) as w:
        for name in a.names():
            clip = a.load(name)
            T = clip.num_frames
            h, model = subject_height(clip), subject_model(clip)
            x = ClipInputs.from_clip(clip, length=-(-T // bucket) * bucket)
            r, kp = jax.device_get(_one_clip(params, model, x, config))
            res = dict(q=r.q, qd=r.qd, tau=r.tau, grf=r.grf, contact_prob=r.contact_prob,
                       target_q=r.target_q, keypoints3d=kp)
            res = {k: np.asarray(v)[:T] for k, v in res.items()}
            check_finite(res, name)
            w.add_result(name, result_arrays(clip, res, method=method.name, height_m=h,
                                             mass_kg=model.total_mass,
                                             forces_estimated=method.estimates_forces,
                                             identity=identity, source=name,
                                             assumed=assumed_fields(clip)), frames=T)
            frames += T
    return time.perf_counter() - t, frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="8 short clips, small networks, batch 1 and 4")
    ap.add_argument("--clips", type=int, default=64)
    ap.add_argument("--frames", default="150:300", help="MIN:MAX frames per clip (default 150:300)")
    ap.add_argument("--batches", default="1,8", help="clips per device, comma separated (default 1,8)")
    ap.add_argument("--chunk", type=int, default=256)
    ap.add_argument("--bucket", type=int, default=64)
    ap.add_argument("--params", help="parameters (.msgpack); default: the shipped weights")
    ap.add_argument("--random-init", action="store_true", help="freshly initialised parameters")
    ap.add_argument("--no-loop", action="store_true", help="skip the per-clip loop (c)")
    ap.add_argument("--keep", help="keep the archive and outputs in this folder")
    args = ap.parse_args()

    from jmocap import methods
    from jmocap.batch import BatchOptions
    from jmocap.methods import PhysCapConfig
    from jmocap.model import character
    from jmocap.nets import NetConfig
    from jmocap.weights import load_run_params

    physcap = methods.get_method("physcap")
    if args.quick:
        args.clips, args.frames, args.batches, args.chunk, args.bucket = 8, "20:40", "1,4", 32, 32
        config = PhysCapConfig(iterations=2, nets=NetConfig(tp_width=32, dyn_width=64, grf_width=64, tp_blocks=2))
        params, source = physcap.init_params(jax.random.PRNGKey(0), character(), config), "random init, small nets"
    elif args.random_init:
        config = PhysCapConfig()
        params, source = physcap.init_params(jax.random.PRNGKey(0), character(), config), "random init"
    else:
        params, config = load_run_params(args.params, method="physcap")
        source = args.params or "shipped weights"
    lo, hi = (int(v) for v in args.frames.split(":"))
    batches = [int(b) for b in args.batches.split(",")]

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="jmocap-bench-batch-"))
    work.mkdir(parents=True, exist_ok=True)
    archive = work / "archive"
    t = time.perf_counter()
    if not (archive / "manifest.jsonl").exists():
        make_archive(archive, args.clips, (lo, hi))
    print(f"machine: {machine()}")
    print(f"archive: {args.clips} clips of {lo}-{hi} frames ({time.perf_counter() - t:.1f} s to make); "
          f"params: {source}; k = {config.iterations}, TPNet width {config.nets.tp_width}; "
          f"chunk {args.chunk}, bucket {args.bucket}")

    rows = []

    def bench(label, batch, fn):
        outs = [work / f"out_{label}_{batch}_{i}" for i in range(2)]
        for o in outs:
            shutil.rmtree(o, ignore_errors=True)
        cold, _ = fn(outs[0])
        warm, frames = fn(outs[1])
        rows.append((label, batch, frames, cold, warm))
        print(f"  {label} batch {batch}: cold {cold:.1f} s, warm {warm:.1f} s", flush=True)

    for b in batches:
        opts = BatchOptions(chunk=args.chunk, bucket=args.bucket, batch=b)
        bench("engine", b, lambda o, opts=opts: run_engine(archive, o, params, config, opts))
    kin = methods.get_method("kinematic").make_config(methods.config_dict(config))
    opts = BatchOptions(chunk=args.chunk, bucket=args.bucket, batch=max(batches))
    bench("engine kinematic", max(batches), lambda o: run_engine(archive, o, params, kin, opts, "kinematic"))
    if not args.no_loop:
        bench("per-clip loop", 1, lambda o: run_loop(archive, o, params, config, args.bucket))

    loop = next((r for r in rows if r[0] == "per-clip loop"), None)
    n_dev = len(jax.devices())
    print()
    print("| method | clips/device/call | clips | frames | cold s | warm s | clips/s | frames/s | vs loop |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, b, frames, cold, warm in rows:
        ratio = f"{loop[4] / warm:.1f}x" if loop and label != "per-clip loop" else "1.0x" if loop else "-"
        print(f"| {label} | {b if label != 'per-clip loop' else '1 (no vmap)'} | {args.clips} | {frames} | "
              f"{cold:.1f} | {warm:.1f} | {args.clips / warm:.2f} | {frames / warm:.0f} | {ratio} |")
    print(f"\n{n_dev} device(s); cold - warm is about the compilation time. Work folder: {work}")
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
