"""Plot a training run's curves from its ``log.jsonl`` (jmocap.train) to a PNG.

    .venv/bin/python experiments/plot_training.py runs/extended --out docs/figures/training_extended.png

Left: each stage's training loss (the logged batch losses, and their running mean over 10 log
lines), stages one after the other on a shared step axis; right: the validation MPJPE
(``val_mpjpe_mm``, TPNet's root-relative joint error on the config's ``val_data`` windows)
with the best check marked. Needs the ``viz`` extra (matplotlib).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def read_log(run: Path):
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    train = [r for r in rows if "loss" in r]
    val = [r for r in rows if "val_mpjpe_mm" in r]
    return train, val


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a training run's folder (with log.jsonl)")
    ap.add_argument("--out", required=True, help="PNG to write")
    args = ap.parse_args(argv)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    train, val = read_log(Path(args.run))
    if not train:
        raise SystemExit(f"{args.run}/log.jsonl has no training lines")
    stages = []  # (name, offset) in order of appearance
    offset, prev, last_step = 0, None, 0
    xs, ys, names = [], [], []
    for r in train:
        if r["stage"] != prev or r["step"] < last_step:
            if prev is not None:
                offset += last_step
            stages.append((r["stage"], offset))
            prev = r["stage"]
        last_step = r["step"]
        xs.append(offset + r["step"])
        ys.append(r["loss"])
        names.append(r["stage"])
    fig = Figure(figsize=(11, 4))
    FigureCanvasAgg(fig)
    a, b = fig.subplots(1, 2)
    xs, ys, names = np.array(xs), np.array(ys), np.array(names)
    for name, off in stages:
        m = (names == name) & (xs > off)
        if not m.any():
            continue
        x, y = xs[m], ys[m]
        k = min(10, len(y))
        run_mean = np.convolve(y, np.ones(k) / k, mode="valid")
        a.plot(x, y, lw=0.5, alpha=0.35)
        a.plot(x[k - 1:], run_mean, lw=1.5, label=f"{name} (mean of {k})")
    a.set_yscale("log")
    a.set_xlabel("step (stages in sequence)")
    a.set_ylabel("training loss")
    a.legend(fontsize=8)
    a.grid(alpha=0.3)
    if val:
        offs = dict(stages)
        vx = np.array([offs.get(r["stage"], 0) + r["step"] for r in val])
        vy = np.array([r["val_mpjpe_mm"] for r in val])
        b.plot(vx, vy, "o-", ms=3)
        i = int(np.argmin(vy))
        b.plot(vx[i], vy[i], "r*", ms=12, label=f"best {vy[i]:.1f} mm at step {vx[i]}")
        b.legend(fontsize=8)
    b.set_xlabel("step")
    b.set_ylabel("validation MPJPE (mm, TPNet, root-relative)")
    b.grid(alpha=0.3)
    fig.suptitle(f"{args.run}: training curves", fontsize=10)
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
