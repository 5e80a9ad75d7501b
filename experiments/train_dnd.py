"""Train D&D's networks (DyNet and the attentive PD controller; jmocap.train_dnd) on a
moving-camera archive, resumably, within a 2-core CPU session.

    .venv/bin/python experiments/train_dnd.py [--variant dnd] [--steps 1200] [--ship]

1. Generates the training archive if it is missing (deterministic, resumable):
   ``jmocap data synth --out data/train_moving --clips 600 --seed 48 --frames-per-clip 90:180
   --moving-camera handheld,pan,dolly,orbit,static`` (a fifth of the clips from a static camera,
   so that the networks also learn a camera at rest). Seed 123 (the held-out archives') is refused.
2. Trains with ``jmocap.train_dnd.train`` into ``RUN`` (default ``runs/<variant>``):
   ``checkpoint.msgpack``, ``log.jsonl``, ``dnd_params.msgpack``. Re-running continues.
3. ``--ship`` (``--variant dnd`` only) writes the networks as float16 to
   ``src/jmocap/assets/dnd_nets.msgpack`` and the training config beside them (``dnd_nets.json``).

The ablations (paper Tab. 3) train with ``--variant dnd_residual_force``,
``dnd_discrete_contacts`` or ``dnd_meta_pd``; evaluate them with
``jmocap eval ARCHIVE --methods VARIANT --params RUN/params.msgpack`` (the run's folder holds the
TPNet weights it was trained with next to D&D's networks: ``params.msgpack``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="data/train_moving")
    ap.add_argument("--clips", type=int, default=600)
    ap.add_argument("--seed", type=int, default=48, help="archive seed (never 123)")
    ap.add_argument("--variant", default="dnd")
    ap.add_argument("--run", default=None, help="checkpoint, log and outputs (default runs/<variant>)")
    ap.add_argument("--steps", type=int, default=1200)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--context", type=int, default=96, help="frames per training window (the networks read all)")
    ap.add_argument("--warmup", type=int, default=16, help="the dynamics start at this frame of a window")
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--max-clips", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--ship", action="store_true")
    args = ap.parse_args()
    if args.seed == 123:
        sys.exit("seed 123 makes the held-out archives: never train on it")
    if args.ship and args.variant != "dnd":
        sys.exit("--ship ships the full method's networks: --variant dnd")
    data = Path(args.data)
    if len(list(data.glob("*.npz"))) < args.clips:
        subprocess.run([sys.executable, "-m", "jmocap", "data", "synth", "--out", str(data), "--clips", str(args.clips),
                        "--seed", str(args.seed), "--frames-per-clip", "90:180", "--moving-camera",
                        "handheld,pan,dolly,orbit,static", "--workers", str(args.workers), "--quiet"], check=True)

    from flax import serialization

    from jmocap.io import atomic_write
    from jmocap.methods import config_dict
    from jmocap.methods import dnd as D
    from jmocap.train_dnd import DnDTrainConfig, train
    from jmocap.weights import load_run_params, save_params

    params, kin = load_run_params(None, method="kinematic")
    base = D.DnDConfig(layout=kin.layout, canonicalise=kin.canonicalise, nets=kin.nets)
    run = Path(args.run or f"runs/{args.variant}")
    cfg = DnDTrainConfig(data=str(data), out=str(run), variant=args.variant, steps=args.steps, batch=args.batch,
                         context=args.context, warmup=args.warmup,
                         lr=args.lr, max_clips=args.max_clips)
    net = train(cfg, params, base)
    tp = {k: v for k, v in params.items() if k == "tpnet"}
    save_params(run / "params.msgpack", {**tp, "dnd": net})
    if args.ship:
        half = jax.tree.map(lambda x: np.asarray(x, np.float16), net)
        atomic_write(D.ASSET, serialization.msgpack_serialize(half))
        meta = {"cycle": config_dict(base), "trained_by": "experiments/train_dnd.py " + " ".join(sys.argv[1:]),
                "log_tail": (run / "log.jsonl").read_text().splitlines()[-1]}
        atomic_write(D.ASSET.with_suffix(".json"), json.dumps(meta, indent=2).encode())
        print(f"shipped {D.ASSET} ({D.ASSET.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
