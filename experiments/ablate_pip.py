"""Ablations of ``pip`` on held-out clips: its reference pose, contact source and gains.

    jmocap data synth --out data/val --clips 16 --seed 77 --physics     # the validation archive
    .venv/bin/python experiments/ablate_pip.py --archive data/val --max-clips 16
    .venv/bin/python experiments/ablate_pip.py --archive data/val --set reference_source=tpnet kp_anchor=100

Tune on the validation archive (seed 77), never on the held-out one (seed 123) that
docs/evaluation.md reports.

Runs ``jmocap.evaluate`` (the same metrics as ``jmocap eval``) with the ``kinematic`` method
and ``pip`` under the config changes given by ``--set`` (traced fields do not recompile, static
ones do), on a seeded subset of the held-out archive, and prints the metrics the
physical-dynamics issue targets, plus the per-foot vertical GRF correlation over the walking
clips alone. The XLA compilation cache is ~/.cache/jmocap/xla-dev.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import jax
import numpy as np

from jmocap import evaluate as E
from jmocap import methods as methods_
from jmocap.weights import default_config_fields, default_params

KEYS = ("reproj_input_px", "mpjpe_mm", "pa_mpjpe_mm", "root_err_mm", "root_residual_pct_bw", "grf_err_pct_bw",
        "grf_ballistic_pct_bw", "foot_grf_corr", "pnp_pct", "penetrate_pct", "skate_pct", "cone_violation_pct",
        "jitter_km_s3", "contact_f1_pct")
SHORT = ("reproj", "mpjpe", "pa", "root", "resid", "grf_err", "ballist", "corr", "pnp", "pen3", "skate", "cone",
         "jitter", "f1")


def parse_set(items, config) -> dict:
    out = {}
    fields = {f.name: f for f in dataclasses.fields(config)}
    for s in items:
        k, v = s.split("=", 1)
        if k not in fields:
            raise SystemExit(f"unknown field {k!r}")
        cur = getattr(config, k)
        if isinstance(cur, tuple):
            out[k] = tuple(json.loads(v))  # a JSON list, e.g. sigma_scales=[0.25,0.5,1.0]
        elif isinstance(cur, str):
            out[k] = v
        elif isinstance(cur, bool):
            out[k] = v.lower() in ("1", "true", "yes")
        else:
            out[k] = int(v) if isinstance(cur, int) else float(v)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/val")
    ap.add_argument("--max-clips", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", nargs="*", default=[], help="pip config fields, name=value")
    ap.add_argument("--methods", nargs="*", default=["kinematic", "pip"])
    ap.add_argument("--batch-size", type=int, default=4)
    args = ap.parse_args()
    jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/jmocap/xla-dev"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)

    params, base_cfg = default_params("pip")
    changes = parse_set(args.set, base_cfg)
    # pip (and its variants) get the shipped pip config with the changes as their own config;
    # other methods the weights' config
    own = dataclasses.replace(base_cfg, **changes)
    mine = {m: (params, own) for m in args.methods if methods_.resolve(m)[0].name == "pip"}
    clips = E.select_clips(args.archive, args.max_clips, args.seed)
    t0 = time.perf_counter()
    res = E.evaluate(args.archive, params, default_config_fields(),
                     E.EvalConfig(methods=tuple(args.methods), batch_size=args.batch_size, progress=False),
                     clips=clips, method_params=mine)
    dt = time.perf_counter() - t0
    for f in res.failures:
        print("FAILED", f)
    walk = [c.name for c in clips if c.meta.get("kind") == "walk"]
    print(f"{len(clips)} clips ({len(walk)} walking), {dt:.0f} s; set: {changes}")
    print("method      " + " ".join(f"{s:>8}" for s in SHORT) + "  walk_corr")
    for m in args.methods:
        row = [res.summary[m].get(k, float("nan")) for k in KEYS]
        wc = [res.per_clip[m][n].get("foot_grf_corr", np.nan) for n in walk if n in res.per_clip[m]]
        print(f"{m:<11} " + " ".join(f"{v:8.2f}" for v in row) + f"  {np.nanmean(wc) if wc else np.nan:8.2f}")


if __name__ == "__main__":
    main()
