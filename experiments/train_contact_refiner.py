"""Train the temporal contact refiner (:class:`jmocap.nets.ContactTCN`) over the shipped contact MLP.

    .venv/bin/python experiments/train_contact_refiner.py [--ship]

The contact MLP (Rempe et al. 2020, Sec. 3.2; ``experiments/train_contacts.py``) reads 9 frames
and votes over 5; the refiner reads the MLP's outputs over about a second on each side (a gait
cycle) and classifies every frame again (docs/method.md, "The temporal refiner").

1. Generates its training archives if they are missing or short (resumable, deterministic):
   ``jmocap data synth --out data/refine_cls --clips 240 --seed 17 --physics --frames-per-clip
   90:180`` and the same with ``--extended --seed 18`` in ``data/refine_ext``. *Fresh* seeds:
   the MLP was trained on seeds 7 and 8, and its outputs on its own training clips are better
   than on clips it never saw, so a refiner trained on them would learn to trust it too much.
   Longer clips than the MLP's (60-150 frames) because the refiner reads more context.
2. Splits every archive by clip into training and validation (``--val-fraction``); per clip
   (and its horizontal mirror image, left/right labels swapped) the refiner's input sequence
   (:func:`jmocap.methods.contact_estimation.refiner_inputs` of the shipped MLP) and the
   force-and-floor labels.
3. Trains with binary cross-entropy over the real frames, AdamW (``--lr``, cosine decay over
   ``--max-epochs``), batch ``--batch`` clips, dropout 0.1; early stopping on the validation
   loss (``--patience``), the best epoch kept. Resumable (``RUN/checkpoint.msgpack`` after
   every epoch, ``RUN/log.jsonl``).
4. Reports, on its validation clips and on every ``--eval`` archive, the shipped voted MLP
   against the refined estimate (both with the mirror image, ``> 0.5`` = contact): F1,
   balanced accuracy, accuracy, precision, recall; ``RUN/summary.json``. ``--ship`` writes
   ``src/jmocap/assets/contact_refiner.msgpack`` (float16) and ``contact_refiner.json``.

Never on the held-out archives (``data/heldout``, ``data/heldout_ext``, seeds 123 and 2026):
refused as training data; report them with ``experiments/eval_contacts.py``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import train_contacts as TC  # noqa: E402  (load_clips, split, refuse_heldout, ensure_archive, evaluate_arrays)

ROOT = TC.ROOT
log = TC.log
#: the training archives: (folder, clips, seed, extended)
ARCHIVES = (("data/refine_cls", 240, 17, False), ("data/refine_ext", 240, 18, True))
FRAMES = "90:180"


def sequences(clips, flip: bool):
    """Refiner inputs (N, L, C), labels (N, L, 4) and masks (N, L) of the clips (and their mirror
    images), all padded to one length ``L`` (a multiple of 64)."""
    import jax

    from jmocap.methods import contact_estimation as ce

    mlp = ce.default_contact_params()
    L = max(TC._bucket(c.num_frames) for c in clips)

    @jax.jit
    def one(kp, size, mask):
        f = ce.contact_features(kp, size, mask)
        return ce.refiner_inputs(mlp, f, mask), ce.refiner_inputs(mlp, ce.flip_features(f), mask)

    X, Y, M = [], [], []
    for c in clips:
        T = c.num_frames
        kp = np.zeros((L, *c.keypoints.shape[1:]), np.float32)
        kp[:T] = c.to_layout("body25").keypoints if c.layout != "body25" else c.keypoints
        mask = np.arange(L) < T
        y = np.zeros((L, 4), np.float32)
        y[:T] = np.asarray(c.gt_contacts) > 0.5
        a, b = one(kp, np.asarray(c.image_size, np.float32), mask)
        X.append(np.asarray(a))
        Y.append(y)
        M.append(mask)
        if flip:
            X.append(np.asarray(b))
            Y.append(y[:, list(ce.CONTACT_FLIP)])
            M.append(mask)
    return np.stack(X), np.stack(Y), np.stack(M).astype(np.float32)


def make_steps(lr_schedule, weight_decay: float, flight_weight: float = 1.0):
    import jax
    import jax.numpy as jnp
    import optax

    from jmocap.methods import contact_estimation as ce

    tx = optax.adamw(lr_schedule, weight_decay=weight_decay)

    def loss_fn(p, x, y, m, key):
        keys = jax.random.split(key, x.shape[0])
        logits = jax.vmap(lambda xi, mi, ki: ce.refiner_logits(p, xi, mi, train=True, rngs={"dropout": ki}))(x, m, keys)
        # flight frames (no point in contact: a run's or jump's airborne instants) weigh
        # flight_weight: rare, and every force on them is wrong
        w = m * jnp.where(jnp.any(y > 0.5, -1), 1.0, flight_weight)
        per = optax.sigmoid_binary_cross_entropy(logits, y) * w[..., None]
        return jnp.sum(per) / jnp.maximum(4.0 * jnp.sum(w), 1.0)

    @jax.jit
    def train_step(p, opt, x, y, m, key):
        loss, g = jax.value_and_grad(loss_fn)(p, x, y, m, key)
        upd, opt = tx.update(g, opt, p)
        return optax.apply_updates(p, upd), opt, loss

    @jax.jit
    def eval_batch(p, x, y, m):
        logits = jax.vmap(lambda xi, mi: ce.refiner_logits(p, xi, mi))(x, m)
        per = optax.sigmoid_binary_cross_entropy(logits, y) * m[..., None]
        pr, g, ok = logits > 0, y > 0.5, m[..., None] > 0
        tp, fp, fn = jnp.sum(pr & g & ok), jnp.sum(pr & ~g & ok), jnp.sum(~pr & g & ok)
        return jnp.sum(per), 4.0 * jnp.sum(m), jnp.array([tp, fp, fn])

    return tx, train_step, eval_batch


def train(args, Xtr, Ytr, Mtr, Xva, Yva, Mva, run: Path):
    import jax
    import optax

    from jmocap.methods import contact_estimation as ce

    steps_per_epoch = max(1, len(Xtr) // args.batch)
    schedule = optax.cosine_decay_schedule(args.lr, steps_per_epoch * args.max_epochs, alpha=0.05)
    tx, train_step, eval_batch = make_steps(schedule, args.weight_decay, args.flight_weight)
    p = ce.init_refiner_params(jax.random.PRNGKey(args.seed), Xtr.shape[-1], args.width, args.blocks)
    state = {"params": p, "opt": tx.init(p), "epoch": 0, "best_val": float("inf"), "best_epoch": -1,
             "bad_epochs": 0, "best": p, "done": False}

    def step(p, opt, idx, key):
        return train_step(p, opt, Xtr[idx], Ytr[idx], Mtr[idx], key)

    def record(train_loss, val_loss, val_f1):
        return ({"train_loss": train_loss, "val_loss": val_loss, "val_f1": val_f1},
                f"train {train_loss:.4f} val {val_loss:.4f} val F1 {val_f1:.2f}")

    return TC.resumable_epochs(run, state, seed=args.seed, max_epochs=args.max_epochs, patience=args.patience,
                               n_train=len(Xtr), batch=args.batch, step=step,
                               validate=lambda p: TC.evaluate_arrays(eval_batch, p, Xva, Yva, Mva, chunk=64),
                               record=record)


def scores(pred: np.ndarray, gt: np.ndarray) -> dict:
    """Pooled F1, balanced accuracy, accuracy, precision, recall (%) of boolean (N, 4) arrays
    (:func:`jmocap.metrics.contact_classification`), rounded to 0.01."""
    from jmocap import metrics as M

    got = M.contact_classification(pred.astype(np.float32), gt.astype(np.float32))
    return {k: round(float(got[k]), 2) for k in ("f1", "balanced_accuracy", "accuracy", "precision", "recall")}


def compare(refiner, clips) -> dict:
    """The shipped voted MLP against the refined estimate on the clips (mirror image on, ``> 0.5``)."""
    import jax

    from jmocap.inputs import ClipInputs
    from jmocap.methods import contact_estimation as ce

    mlp = ce.default_contact_params()
    voted = jax.jit(lambda inp: ce.estimate_contacts(mlp, inp))
    refined = jax.jit(lambda inp: ce.estimate_contacts(mlp, inp, refiner=refiner))
    a, b, g = [], [], []
    for c in clips:
        inp = ClipInputs.from_clip(c, TC._bucket(c.num_frames))
        a.append(np.asarray(voted(inp))[: c.num_frames] > 0.5)
        b.append(np.asarray(refined(inp))[: c.num_frames] > 0.5)
        g.append(np.asarray(c.gt_contacts) > 0.5)
    a, b, g = np.concatenate(a), np.concatenate(b), np.concatenate(g)
    return {"clips": len(clips), "frames": int(len(g)), "voted_mlp": scores(a, g), "refined": scores(b, g)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    TC.temporal_arguments(ap, "runs/contact_refiner", "data/val data/val_walk data/val_flight")
    ap.add_argument("--flight-weight", type=float, default=1.0,
                    help="loss weight of flight frames (no point in contact) against 1 for the others")
    args = ap.parse_args(argv)
    run = ROOT / args.run
    run.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    tr, va, used = TC.split_archives(ARCHIVES, FRAMES, args.workers, args.val_fraction)
    t0 = time.time()
    Xtr, Ytr, Mtr = sequences(tr, flip=True)
    Xva, Yva, Mva = sequences(va, flip=False)
    feat_s = time.time() - t0
    log(f"{len(tr)} training clips (x2 mirrored), {len(va)} validation; inputs {Xtr.shape} ({feat_s:.0f} s)")
    t0 = time.time()
    best, best_epoch, epochs = train(args, Xtr, Ytr, Mtr, Xva, Yva, Mva, run)
    train_s = time.time() - t0

    from jmocap.weights import save_params

    save_params(run / "contact_refiner.msgpack", best)
    report = TC.report_archives(compare, best, va, args.eval)
    for k, v in report.items():
        log(f"{k}: voted MLP {v['voted_mlp']}  refined {v['refined']}")
    seconds = {"inputs": round(feat_s, 1), "train": round(train_s, 1), "total_this_call": round(time.time() - t_start, 1)}
    summary = TC.temporal_summary("train_contact_refiner.py", argv, args, used,
                                 ("lr", "weight_decay", "batch", "flight_weight", "max_epochs", "patience", "val_fraction"),
                                 best_epoch, epochs, report, seconds)
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if args.ship:
        TC.ship_half(best, "contact_refiner", summary)
    log(f"done in {time.time() - t_start:.0f} s this call")
    return 0


if __name__ == "__main__":
    sys.exit(main())
