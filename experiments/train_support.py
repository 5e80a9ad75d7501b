"""Train the learned support prior (:mod:`jmocap.methods.support`): the net vertical ground
reaction force per frame, in body weights, from the 2D keypoints.

    .venv/bin/python experiments/train_support.py [--ship] [--eval data/val data/val_flight]

1. Uses (and generates if missing, resumable) the contact refiner's training archives
   (``experiments/train_contact_refiner.py``: ``data/refine_cls``, 240 clips of seed 17, and
   ``data/refine_ext``, 240 extended clips of seed 18, 90-180 frames, physics): clips the
   contact MLP never saw, whose forces are the simulator's.
2. Splits each archive by clip into training and validation (``--val-fraction``); per clip (and
   its horizontal mirror image, the same force) the network's input sequence
   (:func:`jmocap.methods.support.support_inputs` over the shipped contact MLP) and the target,
   the ground truth's net vertical force over the body weight. Frames whose ground-truth root the
   generator's rescue pushed (residual > :data:`jmocap.metrics.GT_MAX_RESIDUAL_PCT_BW`) carry no
   loss: their forces do not explain their motion.
3. Trains with the mean absolute error over the scored frames (the net GRF error is a mean
   absolute error), AdamW with cosine decay, dropout 0.1, early stopping on the validation loss
   (``--patience``), the best epoch kept. Resumable (``RUN/checkpoint.msgpack``,
   ``RUN/log.jsonl``).
4. Reports on its validation clips and every ``--eval`` archive the mean absolute error of the
   vertical force (% body weight) against one body weight in every frame (the prior before it),
   and their correlation with the truth; ``RUN/summary.json``. ``--ship`` writes
   ``src/jmocap/assets/support_tcn.msgpack`` (float16) and ``support_tcn.json``.

Never on the held-out archives (refused).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import train_contact_refiner as TR  # noqa: E402  (ARCHIVES, FRAMES)
import train_contacts as TC  # noqa: E402  (load_clips, split, refuse_heldout, ensure_archive, early_stop)

ROOT = TC.ROOT
log = TC.log


def scored(c) -> np.ndarray:
    """Frames (T,) whose ground-truth forces explain the motion."""
    from jmocap.metrics import GT_MAX_RESIDUAL_PCT_BW

    r = c.residual_percent_bw
    return np.ones(c.num_frames, bool) if r is None else r <= GT_MAX_RESIDUAL_PCT_BW


def sequences(clips, flip: bool):
    """Inputs (N, L, C), targets (N, L) (net vertical force minus one body weight), loss masks
    (N, L) and real frames (N, L), padded to one length ``L`` (a multiple of 64)."""
    import jax

    from jmocap.methods import contact_estimation as ce
    from jmocap.methods import support as S

    mlp = ce.default_contact_params()
    L = max(TC._bucket(c.num_frames) for c in clips)

    @jax.jit
    def one(kp, size, mask):
        f = ce.contact_features(kp, size, mask)
        return S.support_inputs(mlp, f, mask), S.support_inputs(mlp, ce.flip_features(f), mask)

    X, Y, M, F = [], [], [], []
    for c in clips:
        T = c.num_frames
        kp = np.zeros((L, *c.keypoints.shape[1:]), np.float32)
        kp[:T] = c.to_layout("body25").keypoints if c.layout != "body25" else c.keypoints
        mask = np.arange(L) < T
        y = np.zeros(L, np.float32)
        y[:T] = S.target(c.gt_grf, c.mass_kg) - 1.0
        m = np.zeros(L, np.float32)
        m[:T] = scored(c)
        a, b = one(kp, np.asarray(c.image_size, np.float32), mask)
        for x in ((a, b) if flip else (a,)):
            X.append(np.asarray(x))
            Y.append(y)
            M.append(m)
            F.append(mask)
    return np.stack(X), np.stack(Y), np.stack(M), np.stack(F)


def train(args, Xtr, Ytr, Mtr, Ftr, Xva, Yva, Mva, Fva, run: Path):
    import jax
    import jax.numpy as jnp
    import optax

    from jmocap.methods import support as S

    steps_per_epoch = max(1, len(Xtr) // args.batch)
    schedule = optax.cosine_decay_schedule(args.lr, steps_per_epoch * args.max_epochs, alpha=0.05)
    tx = optax.adamw(schedule, weight_decay=args.weight_decay)

    @jax.jit
    def train_step(p, opt, x, y, m, frames, key):
        def lf(p):
            keys = jax.random.split(key, x.shape[0])
            z = jax.vmap(lambda xi, fi, ki: S.support_raw(p, xi, fi, train=True, rngs={"dropout": ki}))(x, frames, keys)
            return jnp.sum(jnp.abs(z - y) * m) / jnp.maximum(jnp.sum(m), 1.0)

        loss, g = jax.value_and_grad(lf)(p)
        upd, opt = tx.update(g, opt, p)
        return optax.apply_updates(p, upd), opt, loss

    @jax.jit
    def eval_batch(p, x, y, m, frames):
        z = jax.vmap(lambda xi, fi: S.support_raw(p, xi, fi))(x, frames)
        return jnp.sum(jnp.abs(z - y) * m), jnp.sum(m)

    def evaluate(p, X, Y, M, F):
        tot, n = 0.0, 0.0
        for i in range(0, len(X), 64):
            a, b = eval_batch(p, X[i:i + 64], Y[i:i + 64], M[i:i + 64], F[i:i + 64])
            tot, n = tot + float(a), n + float(b)
        return tot / max(n, 1.0)

    p = S.init_support_params(jax.random.PRNGKey(args.seed), Xtr.shape[-1], args.width, args.blocks)
    state = {"params": p, "opt": tx.init(p), "epoch": 0, "best_val": float("inf"), "best_epoch": -1,
             "bad_epochs": 0, "best": p, "done": False}

    def step(p, opt, idx, key):
        return train_step(p, opt, Xtr[idx], Ytr[idx], Mtr[idx], Ftr[idx], key)

    def record(train_loss, val_loss, _):
        return ({"train_mae_bw": train_loss, "val_mae_bw": val_loss},
                f"train {100 * train_loss:.2f} val {100 * val_loss:.2f} % BW")

    return TC.resumable_epochs(run, state, seed=args.seed, max_epochs=args.max_epochs, patience=args.patience,
                               n_train=len(Xtr), batch=args.batch, step=step,
                               validate=lambda p: (evaluate(p, Xva, Yva, Mva, Fva), None), record=record)


def compare(variables, clips) -> dict:
    """Mean absolute error (% BW) of the vertical net force over the scored frames: the network
    (mirror-averaged, as used) against one body weight; and the correlation of each with the
    truth's deviation from one body weight (pooled)."""
    import jax

    from jmocap.inputs import ClipInputs
    from jmocap.methods import contact_estimation as ce
    from jmocap.methods import support as S

    mlp = ce.default_contact_params()
    run = jax.jit(lambda inp: S.support_force(mlp, variables, inp))
    est, gt = [], []
    for c in clips:
        inp = ClipInputs.from_clip(c, TC._bucket(c.num_frames))
        ok = scored(c)
        est.append(np.asarray(run(inp))[: c.num_frames][ok])
        gt.append(S.target(c.gt_grf, c.mass_kg)[ok])
    est, gt = np.concatenate(est), np.concatenate(gt)
    return {"clips": len(clips), "frames": int(len(gt)),
            "mae_pct_bw": round(100 * float(np.mean(np.abs(est - gt))), 2),
            "mae_one_bw_pct_bw": round(100 * float(np.mean(np.abs(1.0 - gt))), 2),
            "corr": round(float(np.corrcoef(est, gt)[0, 1]), 3),
            "std_est_gt": [round(float(np.std(est)), 3), round(float(np.std(gt)), 3)]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    TC.temporal_arguments(ap, "runs/support", "data/val data/val_flight")
    args = ap.parse_args(argv)
    run = ROOT / args.run
    run.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    tr, va, used = TC.split_archives(TR.ARCHIVES, TR.FRAMES, args.workers, args.val_fraction)
    t0 = time.time()
    Xtr, Ytr, Mtr, Ftr = sequences(tr, flip=True)
    Xva, Yva, Mva, Fva = sequences(va, flip=False)
    feat_s = time.time() - t0
    log(f"{len(tr)} training clips (x2 mirrored), {len(va)} validation; inputs {Xtr.shape} ({feat_s:.0f} s); "
        f"scored frames {100 * Mtr.sum() / max(Ftr.sum(), 1):.1f} %")
    t0 = time.time()
    best, best_epoch, epochs = train(args, Xtr, Ytr, Mtr, Ftr, Xva, Yva, Mva, Fva, run)
    train_s = time.time() - t0

    from jmocap.weights import save_params

    save_params(run / "support_tcn.msgpack", best)
    report = TC.report_archives(compare, best, va, args.eval)
    for k, v in report.items():
        log(f"{k}: {v}")
    seconds = {"inputs": round(feat_s, 1), "train": round(train_s, 1), "total_this_call": round(time.time() - t_start, 1)}
    summary = TC.temporal_summary("train_support.py", argv, args, used,
                                 ("lr", "weight_decay", "batch", "max_epochs", "patience", "val_fraction"),
                                 best_epoch, epochs, report, seconds)
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if args.ship:
        TC.ship_half(best, "support_tcn", summary)
    log(f"done in {time.time() - t_start:.0f} s this call")
    return 0


if __name__ == "__main__":
    sys.exit(main())
