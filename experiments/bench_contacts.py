"""Speed of contact estimation: Rempe's voted MLP against jmocap's temporal refiner over it, and
the learned support (the net vertical force, :mod:`jmocap.methods.support`, the same network over
the same inputs).

    .venv/bin/python experiments/bench_contacts.py [--archive data/heldout] [--frames 300] [--batches 1 64]

Both competitors run in one process on the same clips (the archive's first clips, each cut or
padded to ``--frames``), ``jax.jit(jax.vmap(...))`` over a batch, compile timed apart; prints
milliseconds per clip and each cost as a ratio of the voted MLP's (docs/performance.md,
"Contact estimation").
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/heldout")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)

    from jmocap.data.archive import Archive
    from jmocap.inputs import ClipInputs
    from jmocap.methods import contact_estimation as ce
    from jmocap.methods import support as sp

    mlp, refiner, support = ce.default_contact_params(), ce.default_refiner_params(), sp.default_support_params()
    with Archive(args.archive) as a:
        names = a.names()
        clips = [a.load(n) for n in names[: max(args.batches)]]
    clips = (clips * (max(args.batches) // len(clips) + 1))[: max(args.batches)]
    inputs = [ClipInputs.from_clip(c.slice(0, args.frames), args.frames) for c in clips]
    competitors = {
        "voted MLP (Rempe)": jax.jit(jax.vmap(lambda inp: ce.estimate_contacts(mlp, inp))),
        "refined (MLP + ContactTCN)": jax.jit(jax.vmap(lambda inp: ce.estimate_contacts(mlp, inp, refiner=refiner))),
        "support (MLP + one-output ContactTCN)": jax.jit(jax.vmap(lambda inp: sp.support_force(mlp, support, inp))),
    }
    print(f"{args.frames}-frame clips of {args.archive}; ms per clip (best of {args.repeats}), compile s")
    print("| batch | competitor | compile s | ms / clip | x voted |")
    print("|---:|---|---:|---:|---:|")
    for B in args.batches:
        batch = jax.tree.map(lambda *x: np.stack(x), *inputs[:B])
        base = None
        for name, fn in competitors.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(batch))
            compile_s = time.perf_counter() - t0
            best = float("inf")
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(batch))
                best = min(best, time.perf_counter() - t0)
            ms = 1e3 * best / B
            base = ms if base is None else base
            print(f"| {B} | {name} | {compile_s:.1f} | {ms:.2f} | {ms / base:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
