"""Seconds per clip of ``trajopt`` at batch 1 and batch B, with the share of each stage.

    .venv/bin/python experiments/bench_trajopt.py                     # 300-frame clips, batch 1 and 64
    .venv/bin/python experiments/bench_trajopt.py --frames 120 --batches 1 8   # a quick run
    .venv/bin/python experiments/bench_trajopt.py --pipeline --batches 1 64    # as jmocap reconstruct runs it
    .venv/bin/python experiments/bench_trajopt.py --no-stages --batches 1 --against linesearch=backtracking

``--pipeline`` times the batch engine of ``jmocap reconstruct`` instead (:class:`jmocap.pipeline.Reconstructor`:
the batch sharded over one host CPU device per core, ``--host-devices``), side by side with one
device, and prints the ratio; every batch is filled up to a multiple of the device count.

Clips are the held-out archive's (``data/heldout``; made by ``experiments/evaluate_default.py``
if missing), cropped or edge-padded to ``--frames``. For each batch size: the compile time
(first call, reported separately), then the steady time of ``jit(vmap(reconstruct))`` per clip,
and the same with each later stage's iterations set to zero, so that the stages' shares follow
by difference (stages 0 + 1: the per-frame and whole-clip kinematic fits; stage 2: physics; the
rest: TPNet, contacts, outputs). Times are wall-clock on this machine (see docs/performance.md for the record).
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from jmocap.data.archive import Archive
from jmocap.inputs import ClipInputs
from jmocap.methods import get_method
from jmocap.pipeline import subject_model
from jmocap.weights import default_config_fields, default_params


def _stack(trees):
    return jax.tree.map(lambda *xs: np.stack(xs), *trees)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/heldout")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--no-stages", action="store_true", help="time the full method only (one compile per batch)")
    ap.add_argument("--pipeline", action="store_true",
                    help="time jmocap reconstruct's batch engine with 1 and --host-devices devices")
    ap.add_argument("--host-devices", type=int, default=0, help="with --pipeline (0: one per CPU core)")
    ap.add_argument("--tile", type=int, default=None, help="with --pipeline: clips per tile (default: the engine's)")
    ap.add_argument("--against", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="also time the default config with these changes, side by side (with --no-stages), "
                         "and print its time as a ratio of the default's")
    args = ap.parse_args()
    if args.pipeline:
        return bench_pipeline(args)

    arch = Archive(args.archive)
    names = arch.names()
    params, _ = default_params()
    trajopt = get_method("trajopt")
    base = trajopt.make_config(trajopt.weights_config(default_config_fields()))
    variants = {"full": base}
    if args.against:
        if not args.no_stages:
            raise SystemExit("--against needs --no-stages")
        import json

        def value(v):  # a JSON value (numbers, true/false, lists) or else the string itself
            try:
                return json.loads(v)
            except json.JSONDecodeError:
                return v

        changes = {k: value(v) for k, v in (a.split("=", 1) for a in args.against)}
        variants["against"] = base.replace(**changes)
    if not args.no_stages:
        variants.update({"no physics": base.replace(physics_iterations=0),
                         "no fit": base.replace(physics_iterations=0, kinematic_iterations=0,
                                               frame_iterations=0)})
    fn = jax.jit(jax.vmap(get_method("trajopt").reconstruct, in_axes=(None, 0, 0, None)))
    print(f"trajopt, {args.frames}-frame clips, {jax.device_count()} device(s): {jax.devices()[0].device_kind}")
    print("| batch | compile s | s / clip | kinematic fit | physics | rest |")
    print("|---|---|---|---|---|---|")
    for B in args.batches:
        clips = [arch.load(names[i % len(names)]) for i in range(B)]
        clips = [c.slice(0, min(args.frames, c.num_frames)) for c in clips]
        inputs = _stack([ClipInputs.from_clip(c, length=args.frames) for c in clips])
        models = _stack([subject_model(c) for c in clips])
        per = {}
        compile_s = None
        for name, cfg in variants.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(params, models, inputs, cfg).q)
            first = time.perf_counter() - t
            if compile_s is None:
                compile_s = first
            runs = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                jax.block_until_ready(fn(params, models, inputs, cfg).q)
                runs.append(time.perf_counter() - t)
            per[name] = min(runs) / B
        full = per["full"]
        if args.no_stages:
            print(f"| {B} | {compile_s - full * B:.0f} | {full:.2f} | | | |")
            if "against" in per:
                print(f"| {B} | with {' '.join(args.against)} | {per['against']:.2f} "
                      f"| x{per['against'] / full:.2f} of the default | | |", flush=True)
            continue
        nophys, nofit = per["no physics"], per["no fit"]
        share = lambda x, full=full: f"{100 * x / full:.0f} %"  # noqa: E731
        print(f"| {B} | {compile_s - full * B:.0f} | {full:.2f} | {share(nophys - nofit)} | {share(full - nophys)} "
              f"| {share(nofit)} |")


def bench_pipeline(args) -> None:
    """Seconds per clip of the batch engine (:class:`jmocap.pipeline.Reconstructor`) on one device
    and on ``--host-devices`` devices, side by side."""
    import os

    from jmocap.cli import set_host_devices

    set_host_devices(args.host_devices)
    from jmocap.pipeline import Reconstructor

    devices = jax.devices()
    arch = Archive(args.archive)
    names = arch.names()
    params, _ = default_params()
    trajopt = get_method("trajopt")
    cfg = trajopt.make_config(trajopt.weights_config(default_config_fields()))
    print(f"trajopt through jmocap.pipeline.Reconstructor, {args.frames}-frame clips, "
          f"{os.cpu_count()} cores, {len(devices)} host device(s), tile {args.tile or 'default'}")
    print("| batch | devices | compile s | s / clip | vs 1 device |")
    print("|---|---|---|---|---|")
    for B in args.batches:
        clips = [arch.load(names[i % len(names)]) for i in range(B)]
        clips = [c.slice(0, min(args.frames, c.num_frames)) for c in clips]
        base = None
        for n in sorted({1, len(devices)}):
            per_device = -(-B // n)
            eng = Reconstructor(params, cfg, method="trajopt", bucket=args.frames, batch=per_device,
                                devices=devices[:n], **({} if args.tile is None else {"tile": args.tile}))
            t = time.perf_counter()
            eng.run(clips)
            first = time.perf_counter() - t
            runs = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                eng.run(clips)
                runs.append(time.perf_counter() - t)
            s = min(runs) / B
            base = base or s
            print(f"| {B} | {n} | {first - s * B:.0f} | {s:.2f} | {base / s:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
