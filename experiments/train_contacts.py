"""Train Rempe et al.'s foot-contact MLP (2020, Sec. 3.2 and Appendix A.2) on synthetic clips.

    .venv/bin/python experiments/train_contacts.py [--ship]

1. Generates the training archive if it is missing or short (resumable, deterministic):
   ``jmocap data synth --out data/contacts_train --clips 1000 --seed 7 --physics
   --frames-per-clip 60:150`` -- clips tracked in MuJoCo simulation, whose ``gt_contacts`` are
   labelled by *force and floor* (docs/data.md), like the held-out archive
   ``data/heldout`` (seed 123, which this script refuses: never train or tune on it). Kinematic
   clips (no ``--physics``) label contacts by Rempe's geometric rule instead, which disagrees
   with the physics labels on a large share of the contact-point frames.
   Short clips: one subject and one camera per clip, so more of both per generated frame; 100
   clips of 150-300 frames (the same number of frames) gave a worse model on validation
   (docs/method.md, "Contact estimation"). An archive made with other settings is refused.
2. Splits the clips (by clip) into training and validation (``--val-fraction``) and computes the
   features of every real target frame (:func:`jmocap.methods.contact_estimation
   .contact_features`) of each clip and of its horizontal mirror image (x mirrored, left/right
   joints and left/right contact labels swapped), with the labels of frames ``t-2 .. t+2``
   (targets near a clip's ends do not train the frames outside it).
3. Trains :class:`jmocap.nets.ContactMLP` with binary cross-entropy, Adam (``--lr`` 3e-4; the
   paper's 1e-4 and 1e-3 gave the same validation F1 within 0.5 points) with L2 weight decay
   1e-4 added to the gradient (PyTorch's ``Adam(weight_decay=...)``, as in the paper), batch
   256; augmentation per sample: Gaussian noise sigma 0.005 on the normalised positions (A.2),
   random keypoint dropout (each joint-frame of the window dropped with a probability drawn
   uniformly in [0, 0.1]), a random global scale in [0.9, 1.1] and, for a share of the windows
   (``--layout-drop``, 0.25), all six foot joints removed, as in a COCO-17 or Human3.6M-17 clip
   converted to BODY_25 (those reconstruct with the same weights). Early
   stopping on the validation loss (patience ``--patience`` epochs); the best epoch's weights
   are kept. BatchNorm: batch statistics in training, the running averages (momentum 0.9) for
   validation and inference.
4. Resumable: ``RUN/checkpoint.msgpack`` after every epoch (weights, running statistics,
   optimiser state, the best weights so far, epoch, early-stopping state); ``RUN/log.jsonl``
   one line per epoch. Re-running continues; a finished run only re-writes its outputs.
5. Writes ``RUN/contact_mlp.msgpack`` (best weights, float32) and ``RUN/summary.json`` (the
   training split's per-contact label rates and majority labels, the 2D-velocity baseline's
   threshold fitted on the training split, validation metrics, timings); ``--ship`` copies the
   weights as float16 to ``src/jmocap/assets/contact_mlp.msgpack`` and the summary to
   ``src/jmocap/assets/contact_mlp.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: the held-out evaluation archives (docs/evaluation.md): never trained or tuned on
HELDOUT = ("data/heldout", "data/heldout_ext")
HELDOUT_SEEDS = (123, 2026)
#: the BODY_25 joints that COCO-17 and Human3.6M-17 do not have (dropped together by --layout-drop)
FEET = ("LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel")
BATCH = 256


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def ensure_archive(path: Path, clips: int, seed: int, frames: str, workers: int = 1, extended: bool = False) -> float:
    """Generate (or resume) the training archive; returns the seconds spent."""
    from jmocap.cli import main as jmocap

    manifest = path / "manifest.jsonl"
    meta = path / "archive.json"
    if meta.exists():  # an archive made with other settings is not resumed (nor silently used)
        got = json.loads(meta.read_text())
        cfg = got.get("config", {})
        lo, hi = (int(x) for x in frames.split(":")) if ":" in frames else (int(frames),) * 2
        want_frames = [lo, hi] if ":" in frames else lo
        if (got.get("seed") != seed or not cfg.get("physics") or cfg.get("frames") != want_frames
                or bool(cfg.get("extended")) != extended):
            sys.exit(f"{path} was made with seed {got.get('seed')}, frames {cfg.get('frames')}, physics "
                     f"{cfg.get('physics')}, extended {bool(cfg.get('extended'))}; this run asks for seed "
                     f"{seed}, frames {frames}, physics, extended {extended}: use another --data folder")
    have = sum(1 for line in manifest.read_text().splitlines() if line.strip()) if manifest.exists() else 0
    if have >= clips:
        return 0.0
    cmd = ["data", "synth", "--out", str(path), "--clips", str(clips), "--seed", str(seed), "--physics",
           "--frames-per-clip", frames, "--workers", str(workers), "--quiet"] + (["--extended"] if extended else [])
    log("+ jmocap " + " ".join(cmd))
    t0 = time.time()
    if jmocap(cmd) != 0:
        sys.exit(f"could not generate the training archive {path}")
    return time.time() - t0


def refuse_heldout(path: Path, seed) -> None:
    """Exit when ``path`` is a held-out archive's folder or ``seed`` a held-out archive's seed."""
    if any(path.resolve() == (ROOT / h).resolve() for h in HELDOUT) or seed in HELDOUT_SEEDS:
        sys.exit(f"{path} (seed {seed}) is a held-out evaluation archive: never train on it")


def check_extra(path: Path) -> dict:
    """An additional training archive (``--extra-data``): it must exist, come from the physics
    generator (force-and-floor contact labels) and not be a held-out archive; returns its
    ``archive.json``."""
    meta = path / "archive.json"
    if not meta.exists():
        sys.exit(f"--extra-data {path}: no archive.json (make it with jmocap data synth --physics first)")
    got = json.loads(meta.read_text())
    refuse_heldout(path, got.get("seed"))
    if not got.get("config", {}).get("physics"):
        sys.exit(f"--extra-data {path}: not a physics archive (its contact labels follow the geometric rule)")
    return got


def load_clips(path: Path, clips: int | None = None):
    from jmocap.data.archive import Archive

    with Archive(path) as a:
        names = a.names()
        out = [a.load(n) for n in (names if clips is None else names[:clips])]
    bad = [c.name for c in out if c.gt_contacts is None or c.meta.get("contact_rule", {}).get("rule") != "force_floor"]
    if bad:
        sys.exit(f"{path}: clips without force-and-floor contact labels: {bad[:5]}")
    return out


def split(clips, val_fraction: float, seed: int):
    rng = np.random.default_rng([seed, 1])
    order = rng.permutation(len(clips))
    n_val = max(1, int(round(val_fraction * len(clips))))
    val = sorted(order[:n_val].tolist())
    train = sorted(order[n_val:].tolist())
    return [clips[i] for i in train], [clips[i] for i in val]


def _bucket(T: int) -> int:
    return int(-(-T // 64) * 64)


def window_labels(labels: np.ndarray, T: int):
    """Labels (T, 5, 4) of frames t-2 .. t+2 per target t, and their mask (T, 5)."""
    from jmocap.methods.contact_estimation import HALF_OUT, OUT_FRAMES

    idx = np.arange(T)[:, None] + np.arange(OUT_FRAMES)[None, :] - HALF_OUT
    ok = (idx >= 0) & (idx < T)
    return labels[np.clip(idx, 0, T - 1)].astype(np.float32), ok.astype(np.float32)


def clip_arrays(clips, flip: bool = True, window: int = 9):
    """Features (N, window x 39), window labels (N, 5, 4) and label masks (N, 5) of every real
    target frame of the clips (and of their mirror images)."""
    import jax

    from jmocap.methods import contact_estimation as ce

    feats = jax.jit(ce.contact_features, static_argnums=(3, 4))
    flipk = jax.jit(ce.flip_keypoints, static_argnums=2)
    X, Y, M = [], [], []
    for c in clips:
        T = c.num_frames
        L = _bucket(T)
        kp = np.zeros((L, *c.keypoints.shape[1:]), np.float32)
        kp[:T] = c.keypoints
        mask = np.arange(L) < T
        size = np.asarray(c.image_size, np.float32)
        y, m = window_labels(np.asarray(c.gt_contacts), T)
        X.append(np.asarray(feats(kp, size, mask, c.layout, window))[:T])
        Y.append(y)
        M.append(m)
        if flip:
            X.append(np.asarray(feats(flipk(kp, size, c.layout), size, mask, c.layout, window))[:T])
            Y.append(np.asarray(ce.flip_contacts(y)))
            M.append(m)
    return np.concatenate(X), np.concatenate(Y), np.concatenate(M)


# ---------------------------------------------------------------------------------------
# training
# ---------------------------------------------------------------------------------------


def make_steps(lr: float, weight_decay: float, noise: float, drop_max: float, scale_jitter: float,
               layout_drop: float = 0.0):
    import jax
    import jax.numpy as jnp
    import optax

    from jmocap.methods import contact_estimation as ce

    tx = optax.chain(optax.add_decayed_weights(weight_decay), optax.adam(lr))
    FOOT_MASK = jnp.array([j in FEET for j in ce.LOWER_BODY])

    def augment(x, key):
        k1, k2, k3, k4 = jax.random.split(key, 4)
        B = x.shape[0]
        f = x.reshape(B, -1, ce.NUM_JOINTS, 3)
        vis = f[..., 2] > 0
        scale = jax.random.uniform(k4, (B, 1, 1, 1), minval=1 - scale_jitter, maxval=1 + scale_jitter)
        xy = f[..., :2] * scale + noise * jax.random.normal(k1, (*f.shape[:-1], 2))
        p = jax.random.uniform(k2, (B, 1, 1)) * drop_max
        keep = vis & (jax.random.uniform(k3, vis.shape) >= p)
        # layouts without feet (COCO-17, Human3.6M-17 converted to BODY_25): no foot joint at all
        no_feet = jax.random.uniform(jax.random.fold_in(k2, 1), (B, 1, 1)) < layout_drop
        keep = keep & ~(no_feet & FOOT_MASK)
        out = jnp.concatenate([xy, f[..., 2:]], -1) * keep[..., None]
        return out.reshape(x.shape)

    def bce(logits, y, m):
        per = optax.sigmoid_binary_cross_entropy(logits, y) * m[..., None]
        return jnp.sum(per) / jnp.maximum(4.0 * jnp.sum(m), 1.0)

    def loss_fn(p, bs, x, y, m, key):
        ka, kd = jax.random.split(key)
        logits, upd = ce.window_logits({"params": p, "batch_stats": bs}, augment(x, ka), train=True,
                                       rngs={"dropout": kd})
        return bce(logits, y, m), upd["batch_stats"]

    @jax.jit
    def train_step(p, bs, opt, x, y, m, key):
        (loss, bs), g = jax.value_and_grad(loss_fn, has_aux=True)(p, bs, x, y, m, key)
        upd, opt = tx.update(g, opt, p)
        return optax.apply_updates(p, upd), bs, opt, loss

    @jax.jit
    def eval_batch(variables, x, y, m):
        logits = ce.window_logits(variables, x)
        prob = jax.nn.sigmoid(logits)
        per = optax.sigmoid_binary_cross_entropy(logits, y) * m[..., None]
        pr, g = prob[:, ce.HALF_OUT] > 0.5, y[:, ce.HALF_OUT] > 0.5  # centre frame
        tp = jnp.sum(pr & g)
        fp = jnp.sum(pr & ~g)
        fn = jnp.sum(~pr & g)
        return jnp.sum(per), 4.0 * jnp.sum(m), jnp.array([tp, fp, fn])

    return tx, train_step, eval_batch


def evaluate_arrays(eval_batch, variables, X, Y, M, chunk: int = 2048):
    """Mean loss and F1 (%) of ``eval_batch`` (returning the summed loss, its count and the
    true-positive, false-positive and false-negative counts) over the arrays, in chunks."""
    loss, n, counts = 0.0, 0.0, np.zeros(3)
    for i in range(0, len(X), chunk):
        a, b, c = eval_batch(variables, X[i:i + chunk], Y[i:i + chunk], M[i:i + chunk])
        loss, n, counts = loss + float(a), n + float(b), counts + np.asarray(c, float)
    tp, fp, fn = counts
    return loss / max(n, 1.0), 100.0 * 2 * tp / max(2 * tp + fp + fn, 1.0)


def early_stop(state: dict, val_loss: float, epoch: int, patience: int, weights) -> bool:
    """Early stopping on the validation loss: keep ``weights`` as the best when ``val_loss``
    improves on the state's best by more than 1e-5 (then True), else count a bad epoch; the
    state is done after ``patience`` bad epochs in a row."""
    improved = val_loss < float(state["best_val"]) - 1e-5
    if improved:
        state.update(best_val=val_loss, best_epoch=epoch, bad_epochs=0, best=weights)
    else:
        state["bad_epochs"] = int(state["bad_epochs"]) + 1
    state["done"] = int(state["bad_epochs"]) >= patience
    return improved


def resumable_epochs(run: Path, state: dict, *, seed: int, max_epochs: int, patience: int, n_train: int,
                     batch: int, step, validate, record):
    """The epoch loop of the temporal networks' recipes (``train_contact_refiner.py``,
    ``train_support.py``): resumable from ``run/checkpoint.msgpack`` (written atomically after
    every epoch; ``state`` is the fresh state's template: params, opt, epoch, best_val,
    best_epoch, bad_epochs, best, done), one permutation of the ``n_train`` sequences per epoch
    (seeded by ``(seed, epoch)``) cut into sorted batches of ``batch``, early stopping on the
    validation loss (:func:`early_stop`), one record per epoch in ``run/log.jsonl``.

    ``step(params, opt, idx, key) -> (params, opt, loss)``; ``validate(params) -> (val_loss,
    extra)``; ``record(train_loss, val_loss, extra) -> (fields, text)``: the epoch's log record
    fields and its printed line. Returns the best weights, their epoch and the epochs run."""
    import jax
    from flax import serialization

    from jmocap.io import atomic_write

    ckpt = run / "checkpoint.msgpack"
    if ckpt.exists():
        state = serialization.from_bytes(state, ckpt.read_bytes())
        state["done"] = bool(state["done"])
        log(f"resumed {ckpt} at epoch {int(state['epoch'])} (best val {float(state['best_val']):.4f})")
    key = jax.random.PRNGKey(seed + 1)
    steps_per_epoch = max(1, n_train // batch)
    with open(run / "log.jsonl", "a") as logf:
        while not state["done"] and int(state["epoch"]) < max_epochs:
            ep = int(state["epoch"])
            t0 = time.time()
            order = np.random.default_rng([seed, ep]).permutation(n_train)
            p, opt, losses = state["params"], state["opt"], []
            for s in range(steps_per_epoch):
                idx = np.sort(order[s * batch:(s + 1) * batch])
                p, opt, loss = step(p, opt, idx, jax.random.fold_in(key, ep * 100003 + s))
                losses.append(loss)
            train_loss = float(np.mean(jax.device_get(losses)))
            val_loss, extra = validate(p)
            state.update(params=p, opt=opt, epoch=ep + 1)
            improved = early_stop(state, val_loss, ep, patience, p)
            fields, text = record(train_loss, val_loss, extra)
            rec = {"epoch": ep, **fields, "best_epoch": int(state["best_epoch"]), "seconds": round(time.time() - t0, 2)}
            logf.write(json.dumps(rec) + "\n")
            logf.flush()
            log(f"epoch {ep}: {text} ({rec['seconds']} s){' *' if improved else ''}")
            atomic_write(ckpt, serialization.to_bytes(state))
    return jax.device_get(state["best"]), int(state["best_epoch"]), int(state["epoch"])


def temporal_arguments(ap, run: str, eval_example: str):
    """The options the temporal networks' recipes share (``train_contact_refiner.py``,
    ``train_support.py``): run folder, generation workers, split, network size, optimiser,
    early stopping, seed, validation archives and shipping."""
    ap.add_argument("--run", default=run)
    ap.add_argument("--workers", type=int, default=2, help="generation processes")
    ap.add_argument("--val-fraction", type=float, default=0.15)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--blocks", type=int, default=5, help="dilated convolutions (dilations 1, 2, 4, ...)")
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--weight-decay", type=float, default=1e-4)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--max-epochs", type=int, default=60)
    ap.add_argument("--patience", type=int, default=8)
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--eval", nargs="*", default=[], metavar="ARCHIVE",
                    help=f"validation archives to report at the end (e.g. {eval_example})")
    ap.add_argument("--ship", action="store_true", help="copy the weights into the package (float16)")


def temporal_summary(script: str, argv, args, used, hyper: tuple[str, ...], best_epoch: int, epochs: int,
                     report: dict, seconds: dict) -> dict:
    """The run's ``summary.json`` of a temporal network's recipe (the shipped asset's ``.json``)."""
    return {
        "command": f"python experiments/{script} " + " ".join(argv if argv is not None else sys.argv[1:]),
        "archives": used, "contact_mlp": "src/jmocap/assets/contact_mlp.msgpack (shipped)",
        "width": args.width, "blocks": args.blocks,
        "hyper": {k: getattr(args, k) for k in hyper},
        "best_epoch": best_epoch, "epochs_run": epochs, "report": report, "seconds": seconds,
    }


def split_archives(archives, frames: str, workers: int, val_fraction: float):
    """The temporal networks' training archives (``(folder, clips, seed, extended)`` each, made
    when missing, never a held-out one), each split into training and validation clips:
    ``(train, val, used)`` with ``used`` the archives' record for the run's summary."""
    tr, va, used = [], [], []
    for folder, n, seed, extended in archives:
        refuse_heldout(ROOT / folder, seed)
        ensure_archive(ROOT / folder, n, seed, frames, workers, extended)
        clips = load_clips(ROOT / folder, n)
        a, b = split(clips, val_fraction, seed)
        tr, va = tr + a, va + b
        used.append({"path": folder, "clips": n, "seed": seed, "extended": extended, "frames_per_clip": frames,
                     "frames": int(sum(c.num_frames for c in clips))})
    return tr, va, used


def report_archives(compare, weights, val_clips, archives) -> dict:
    """``compare(weights, clips)`` on the validation split and on every archive of ``archives``
    (validation archives; a held-out one is refused)."""
    from jmocap.data.archive import Archive

    report = {"validation_split": compare(weights, val_clips)}
    for e in archives:
        refuse_heldout(ROOT / e, json.loads((ROOT / e / "archive.json").read_text()).get("seed"))
        with Archive(ROOT / e) as arch:
            report[e] = compare(weights, [arch.load(n) for n in arch.names()])
    return report


def ship_half(weights, name: str, summary: dict) -> None:
    """Copy ``weights`` into the package as ``src/jmocap/assets/NAME.msgpack`` in float16, with
    the run's summary beside it (``NAME.json``)."""
    from jmocap.weights import save_params

    asset = ROOT / "src/jmocap/assets" / f"{name}.msgpack"
    save_params(asset, _half_raw(weights))
    asset.with_suffix(".json").write_text(json.dumps(summary, indent=2) + "\n")
    log(f"shipped {asset} ({asset.stat().st_size / 1e6:.2f} MB)")


def train(args, Xtr, Ytr, Mtr, Xva, Yva, Mva, run: Path):
    import jax
    from flax import serialization

    from jmocap.io import atomic_write
    from jmocap.methods import contact_estimation as ce

    tx, train_step, eval_batch = make_steps(args.lr, args.weight_decay, args.noise, args.drop_max,
                                            args.scale_jitter, args.layout_drop)
    variables = ce.init_contact_params(jax.random.PRNGKey(args.seed), tuple(args.widths), args.window)
    state = {
        "params": variables["params"], "batch_stats": variables["batch_stats"],
        "opt": tx.init(variables["params"]), "epoch": 0, "best_val": float("inf"), "best_epoch": -1,
        "bad_epochs": 0, "best": variables, "done": False,
    }
    ckpt = run / "checkpoint.msgpack"
    if ckpt.exists():
        state = serialization.from_bytes(state, ckpt.read_bytes())
        state["done"] = bool(state["done"])
        log(f"resumed {ckpt} at epoch {int(state['epoch'])} (best val {float(state['best_val']):.4f})")
    key = jax.random.PRNGKey(args.seed + 1)
    n = len(Xtr)
    logf = open(run / "log.jsonl", "a")
    while not state["done"] and int(state["epoch"]) < args.max_epochs:
        ep = int(state["epoch"])
        t0 = time.time()
        order = np.random.default_rng([args.seed, ep]).permutation(n)
        ek = jax.random.fold_in(key, ep)
        p, bs, opt = state["params"], state["batch_stats"], state["opt"]
        losses = []
        for s, i in enumerate(range(0, n - BATCH + 1, BATCH)):
            idx = order[i:i + BATCH]
            p, bs, opt, loss = train_step(p, bs, opt, Xtr[idx], Ytr[idx], Mtr[idx], jax.random.fold_in(ek, s))
            losses.append(loss)
        train_loss = float(np.mean(jax.device_get(losses)))
        cur = {"params": p, "batch_stats": bs}
        val_loss, val_f1 = evaluate_arrays(eval_batch, cur, Xva, Yva, Mva)
        state.update(params=p, batch_stats=bs, opt=opt, epoch=ep + 1)
        improved = early_stop(state, val_loss, ep, args.patience, cur)
        rec = {"epoch": ep, "train_loss": train_loss, "val_loss": val_loss, "val_f1_centre": val_f1,
               "best_epoch": int(state["best_epoch"]), "seconds": round(time.time() - t0, 2)}
        logf.write(json.dumps(rec) + "\n")
        logf.flush()
        log(f"epoch {ep}: train {train_loss:.4f} val {val_loss:.4f} val F1 {val_f1:.1f} "
            f"({rec['seconds']} s){' *' if improved else ''}")
        atomic_write(ckpt, serialization.to_bytes(state))
    logf.close()
    return jax.device_get(state["best"]), int(state["best_epoch"]), int(state["epoch"])


# ---------------------------------------------------------------------------------------
# summary: baselines' training-set quantities, validation metrics
# ---------------------------------------------------------------------------------------


def _f1(pred: np.ndarray, gt: np.ndarray) -> float:
    tp = np.sum(pred & gt)
    return 100.0 * 2 * tp / max(2 * tp + np.sum(pred & ~gt) + np.sum(~pred & gt), 1)


def fit_velocity_threshold(clips) -> float:
    """The 2D-velocity baseline's threshold (body sizes per frame) with the best pooled F1 on
    the training clips."""
    import jax

    from jmocap.methods import contact_estimation as ce

    speed_fn = jax.jit(ce.foot_speed, static_argnums=3)
    speeds, gts = [], []
    for c in clips:
        T = c.num_frames
        L = _bucket(T)
        kp = np.zeros((L, *c.keypoints.shape[1:]), np.float32)
        kp[:T] = c.keypoints
        speeds.append(np.asarray(speed_fn(kp, np.asarray(c.image_size, np.float32), np.arange(L) < T,
                                          c.layout))[:T])
        gts.append(np.asarray(c.gt_contacts) > 0.5)
    sp, gt = np.concatenate(speeds), np.concatenate(gts)
    grid = np.geomspace(1e-3, 0.3, 120)
    f1 = [_f1(sp < th, gt) for th in grid]
    return float(grid[int(np.argmax(f1))])


def voted_f1(variables, clips, mirror: bool = True) -> dict:
    """Validation scores of the voted estimate (``estimate_contacts``, with or without the
    mirror image), ``> 0.5`` = in contact."""
    import jax

    from jmocap.inputs import ClipInputs
    from jmocap.methods import contact_estimation as ce

    fn = jax.jit(ce.estimate_contacts, static_argnums=(2, 3))
    preds, gts = [], []
    for c in clips:
        inp = ClipInputs.from_clip(c, _bucket(c.num_frames))
        preds.append(np.asarray(fn(variables, inp, c.layout, mirror))[: c.num_frames] > 0.5)
        gts.append(np.asarray(c.gt_contacts) > 0.5)
    from jmocap import metrics as M

    pr, gt = np.concatenate(preds), np.concatenate(gts)
    scores = M.contact_classification(pr.astype(np.float32), gt.astype(np.float32))
    return {"f1": round(_f1(pr, gt), 2), "accuracy": round(100.0 * float(np.mean(pr == gt)), 2),
            "balanced_accuracy": round(float(scores["balanced_accuracy"]), 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="data/contacts_train", help="training archive folder")
    ap.add_argument("--clips", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=7, help="archive and training seed (never 123)")
    ap.add_argument("--frames-per-clip", default="60:150",
                    help="clip lengths (short clips: more subjects and cameras per generated frame)")
    ap.add_argument("--extended", action="store_true",
                    help="the archive is the extended generator's (jmocap data synth --extended)")
    ap.add_argument("--extra-data", nargs="*", default=[], metavar="ARCHIVE",
                    help="further physics archives trained on with --data (all their clips, each split "
                         "into training and validation the same way), e.g. data/train_ext")
    ap.add_argument("--run", default="runs/contacts", help="checkpoint, log and outputs")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="generation processes")
    ap.add_argument("--val-fraction", type=float, default=0.15)
    ap.add_argument("--widths", type=int, nargs="+", default=[512, 256, 128, 32])
    ap.add_argument("--window", type=int, default=9, help="input window (odd number of frames)")
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--weight-decay", type=float, default=1e-4)
    ap.add_argument("--noise", type=float, default=0.005)
    ap.add_argument("--drop-max", type=float, default=0.1)
    ap.add_argument("--scale-jitter", type=float, default=0.1)
    ap.add_argument("--layout-drop", type=float, default=0.25,
                    help="share of training windows whose six foot joints are all removed (clips in "
                         "layouts without feet, e.g. COCO-17, reconstruct with these weights)")
    ap.add_argument("--max-epochs", type=int, default=60)
    ap.add_argument("--patience", type=int, default=6)
    ap.add_argument("--ship", action="store_true", help="copy the weights into the package (float16)")
    args = ap.parse_args(argv)
    if args.ship:
        from jmocap.methods.contact_estimation import WINDOW
        if args.window != WINDOW:
            sys.exit(f"--ship needs --window {WINDOW} (jmocap.methods.contact_estimation.WINDOW, which "
                     f"sizes the methods' history and lookahead); change that constant first")
    data, run = ROOT / args.data, ROOT / args.run
    refuse_heldout(data, args.seed)
    run.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    gen_s = ensure_archive(data, args.clips, args.seed, args.frames_per_clip, args.workers, args.extended)
    clips = load_clips(data, args.clips)
    tr, va = split(clips, args.val_fraction, args.seed)
    main_frames = int(sum(c.num_frames for c in clips))
    split_names = {"train_clips": [c.name for c in tr], "val_clips": [c.name for c in va]}
    extra = []
    for e in args.extra_data:
        meta = check_extra(ROOT / e)
        more = load_clips(ROOT / e)
        etr, eva = split(more, args.val_fraction, args.seed)
        tr, va, clips = tr + etr, va + eva, clips + more
        split_names["train_clips"] += [f"{e}/{c.name}" for c in etr]
        split_names["val_clips"] += [f"{e}/{c.name}" for c in eva]
        extra.append({"path": e, "clips": len(more), "seed": meta.get("seed"),
                      "extended": bool(meta.get("config", {}).get("extended")),
                      "frames": int(sum(c.num_frames for c in more))})
        log(f"+ {e}: {len(more)} clips ({extra[-1]['frames']} frames)")
    log(f"{len(clips)} clips ({sum(c.num_frames for c in clips)} frames): {len(tr)} train, {len(va)} validation")
    t0 = time.time()
    Xtr, Ytr, Mtr = clip_arrays(tr, flip=True, window=args.window)
    Xva, Yva, Mva = clip_arrays(va, flip=False, window=args.window)
    feat_s = time.time() - t0
    log(f"features: {len(Xtr)} training windows (with mirrored), {len(Xva)} validation ({feat_s:.0f} s)")
    t0 = time.time()
    best, best_epoch, epochs = train(args, Xtr, Ytr, Mtr, Xva, Yva, Mva, run)
    train_s = time.time() - t0

    from jmocap.methods import contact_estimation as ce
    from jmocap.weights import load_params, save_params

    save_params(run / "contact_mlp.msgpack", best)
    gt_tr = np.concatenate([np.asarray(c.gt_contacts) for c in tr]) > 0.5
    rate = gt_tr.mean(0)
    half = _half(best)
    summary = {
        "paper": "Rempe et al. 2020, Sec. 3.2 / Appendix A.2",
        "command": "python experiments/train_contacts.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "archive": {"path": args.data, "clips": args.clips, "seed": args.seed, "physics": True, "extended": args.extended,
                    "frames_per_clip": args.frames_per_clip, "frames": main_frames,
                    "contact_rule": "force_floor"},
        "extra_archives": extra,
        "split": split_names,
        "widths": list(ce.mlp_widths(best)),
        "window": ce.window_of(best),
        "hyper": {k: getattr(args, k) for k in ("lr", "weight_decay", "noise", "drop_max", "scale_jitter", "layout_drop",
                                                "patience", "max_epochs", "val_fraction")},
        "best_epoch": best_epoch, "epochs_run": epochs,
        "train_contact_rate": [round(float(r), 4) for r in rate],
        "train_majority": [int(r > 0.5) for r in rate],
        "velocity_threshold": fit_velocity_threshold(tr),
        "val_voted": voted_f1(best, va),
        "val_voted_no_mirror": voted_f1(best, va, mirror=False),
        "val_voted_float16": voted_f1(half, va),
        # the validation clips as a COCO-17 detector would give them (no feet), converted back
        "val_voted_coco17": voted_f1(best, [c.to_layout("coco17").to_layout("body25") for c in va]),
        "seconds": {"generate": round(gen_s, 1), "features": round(feat_s, 1), "train": round(train_s, 1),
                    "total_this_call": round(time.time() - t_start, 1)},
    }
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    log(f"validation (voted): {summary['val_voted']}  float16: {summary['val_voted_float16']}")
    if args.ship:
        asset = ROOT / "src/jmocap/assets/contact_mlp.msgpack"
        save_params(asset, _half_raw(best))
        (ROOT / "src/jmocap/assets/contact_mlp.json").write_text(json.dumps(
            {k: v for k, v in summary.items() if k != "split"}, indent=2) + "\n")
        back = load_params(asset)
        assert all(np.asarray(x).dtype == np.float32 for x in __import__("jax").tree.leaves(back))
        log(f"shipped {asset} ({asset.stat().st_size / 1e6:.2f} MB)")
    log(f"done in {time.time() - t_start:.0f} s this call")
    return 0


def _half_raw(tree):
    import jax

    return jax.tree.map(lambda x: np.asarray(x, np.float16), tree)


def _half(tree):
    """The float16 round trip the shipped weights go through, back in float32."""
    import jax

    return jax.tree.map(lambda x: np.asarray(np.asarray(x, np.float16), np.float32), tree)


if __name__ == "__main__":
    sys.exit(main())
