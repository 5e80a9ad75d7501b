"""Evaluate ``mocon`` with config changes beside other methods on a subset of an archive.

    .venv/bin/python experiments/eval_mocon.py data/heldout_terrain --max-clips 6 \\
        --methods trajopt mocon mocon_uniform --set samples=64 window_frames=3 --out out/eval_mocon

``--set`` changes the config of every ``mocon`` method or variant (fields of
:class:`jmocap.methods.mocon.MoconConfig`); the other methods run their defaults. ``--prior``:
the learned prior's variables (a msgpack of ``experiments/train_mocon_prior.py``'s run, e.g.
``RUN/pretrain.msgpack``) instead of the shipped ones, for ``mocon_prior``. Writes the
evaluation's tables (``jmocap eval``'s outputs) to ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from jmocap import evaluate as E
from jmocap import methods, weights


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("archive")
    ap.add_argument("--methods", nargs="+", default=["trajopt", "mocon"])
    ap.add_argument("--max-clips", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--prior", default=None, help="a mocon prior msgpack instead of the shipped one")
    ap.add_argument("--out", default="out/eval_mocon")
    args = ap.parse_args()
    params, base = weights.load_run_params(None, method="trajopt")
    fields = {f.name: f for f in dataclasses.fields(methods.get_method("mocon").config_type)}
    changes = {}
    for item in args.set:
        k, v = item.split("=", 1)
        if k not in fields:
            raise SystemExit(f"--set: mocon has no field {k!r}")
        kind = type(getattr(methods.get_method("mocon").config_type(), k))
        changes[k] = v == "True" if kind is bool else kind(v)
    own = {}
    for m in args.methods:
        method, variant = methods.resolve(m) if m != "ground_truth" else (None, {})
        if method is not None and method.name == "mocon":
            p, cfg = weights.load_run_params(None, method=m)
            if args.prior is not None:
                p = {**p, "mocon_prior": weights.load_params(args.prior)}
            own[m] = (p, methods.config_dict(cfg.replace(**changes)))
    t = time.time()
    res = E.evaluate(args.archive, params, methods.config_dict(base),
                     E.EvalConfig(methods=tuple(args.methods), max_clips=args.max_clips, seed=args.seed),
                     method_params=own)
    E.write_outputs(res, args.out, title=f"mocon {' '.join(args.set)}")
    print(E.markdown_table(res))
    print(f"{time.time() - t:.0f} s; failures: {res.failures}")


if __name__ == "__main__":
    main()
