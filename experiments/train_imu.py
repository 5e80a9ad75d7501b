"""Train PIP's kinematics module (jmocap.nets_imu) on synthetic IMU clips, and evaluate it.

    PYTHONPATH=src python experiments/train_imu.py --data data/imu_train --out runs/imu_kin \
        --steps 2500 --eval data/imu_test
    PYTHONPATH=src python experiments/train_imu.py ... --no-learned-init --out runs/imu_kin_zero

1. Data: an archive of IMU clips (``jmocap data synth --imu``; e.g. 300 clips of seed 1), split
   by clip into training and validation (``--val-fraction``, the last clips of the manifest).
   Per clip: the network input (:func:`jmocap.nets_imu.imu_features` of
   ``IMUClip.calibrated()``) and the targets (:func:`jmocap.nets_imu.targets` on the subject's
   own character, ``jmocap.model.character(height, mass)``).
2. Training: random windows of ``--frames`` frames (batch ``--batch``), each started from its
   first frame's ground truth by the learned initial-state networks (PIP: "for each mini-batch,
   the ground-truth pose at the beginning is fed into the FCN"), or from zero
   (``--no-learned-init``, the paper's ablation); all five networks trained together on the
   weighted sum of their losses (``nets_imu.LOSS_WEIGHTS``); Adam with global-norm clipping 1.0,
   the rate warmed up linearly over 5 % of the steps and decayed to 2 % by a half cosine; input
   dropout ``--dropout``.
3. Resumable: ``OUT/checkpoint.msgpack`` every ``--checkpoint-every`` steps and at the end
   (parameters, optimiser state, step, the window sampler's state, the best validation loss and
   its parameters); ``OUT/log.jsonl`` one JSON line per logged step (training loss parts, rate,
   and every ``--val-every`` steps the validation loss over the validation clips' first
   ``--val-frames`` frames). Re-running continues; a finished run only re-evaluates.
4. Outputs: ``OUT/params.msgpack`` (the best validation parameters, float32), ``OUT/config.json``
   (the network config and this run's arguments) and, with ``--eval ARCHIVE`` (a held-out
   archive of another seed), ``OUT/eval.json``: SIP error (deg), joint position error with root
   position and orientation aligned (mm), jitter (km/s^3), contact F1, with the learned initial
   state (first frame's ground-truth pose and velocity; and with zero velocity) and with the zero
   state.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization

from jmocap import metrics as M
from jmocap import nets_imu as N
from jmocap import physics as P
from jmocap.data.archive import Archive
from jmocap.io import atomic_write
from jmocap.model import character
from jmocap.weights import load_params, save_params

PAD = 320  # clips are padded to a multiple of this (one compile per padded length)


def _padded_len(T: int) -> int:
    return int(np.ceil(T / PAD) * PAD)


_targets_jit = jax.jit(N.targets)
_features_jit = jax.jit(N.imu_features)


def sticking_labels(model, gt_q: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """``labels`` (T, 4) kept only where the contact point is also still and low by Rempe et al.'s
    geometric rule (``jmocap.metrics.contact_labels``: moved < 2 cm since the last frame, < 5 cm
    above the floor): a loaded point that rolls or pivots is not a sticking contact."""
    T = len(gt_q)
    q = np.concatenate([gt_q, np.repeat(gt_q[-1:], _padded_len(T) - T, 0)])  # one compile per padded length
    feet = np.asarray(_feet_jit(model, jnp.asarray(q, jnp.float32)))[:T]
    return (np.asarray(labels) > 0.5) & np.asarray(M.contact_labels(feet))


@jax.jit
def _feet_jit(model, q):
    return jax.vmap(lambda x: P.site_positions(model, x, model.topo.contact_sites))(q)


def load_clips(path: str, labels: str = "archive") -> list[dict]:
    """Every IMU clip of an archive as numpy arrays: input ``x`` (T, 72), targets, fps, model.
    ``labels``: the archive's contact labels, or ``sticking`` (:func:`sticking_labels`)."""
    out = []
    with Archive(path) as a:
        for clip in a:
            ori, acc = clip.calibrated()
            model = character(clip.height_m, clip.mass_kg)
            T = clip.num_frames
            n = _padded_len(T)
            q = np.concatenate([clip.gt_q, np.repeat(clip.gt_q[-1:], n - T, 0)])
            gc = sticking_labels(model, clip.gt_q, clip.gt_contacts) if labels == "sticking" else clip.gt_contacts
            c = np.concatenate([gc, np.repeat(gc[-1:], n - T, 0)]).astype(np.float32)
            tgt = _targets_jit(model, jnp.asarray(q, jnp.float32), jnp.float32(clip.fps), jnp.asarray(c))
            tgt = {k: np.asarray(v[:T]) for k, v in tgt.items()}
            pad = np.zeros(n - T, int) + T - 1  # edge padding: one compile per padded length
            idx = np.concatenate([np.arange(T), pad])
            x = np.asarray(_features_jit(jnp.asarray(ori[idx]), jnp.asarray(acc[idx])))[:T]
            out.append({"name": clip.name, "x": x, "tgt": tgt, "fps": float(clip.fps), "model": model,
                        "gt_q": clip.gt_q, "ori": ori})
    return out


def sample_windows(rng: np.random.Generator, clips: list[dict], batch: int, L: int):
    lens = np.array([len(c["x"]) for c in clips])
    ok = np.nonzero(lens >= L)[0]
    w = (lens[ok] - L + 1).astype(float)
    idx = rng.choice(ok, size=batch, p=w / w.sum())
    xs, tg = [], []
    for i in idx:
        s = int(rng.integers(0, lens[i] - L + 1))
        xs.append(clips[i]["x"][s:s + L])
        tg.append({k: v[s:s + L] for k, v in clips[i]["tgt"].items() if k in ("leaf", "joints", "hinges", "vel",
                                                                            "contacts", "R_root")})
    return np.stack(xs), {k: np.stack([t[k] for t in tg]) for k in tg[0]}


def make_schedule(lr: float, steps: int):
    warm = max(1, steps // 20)
    return optax.warmup_cosine_decay_schedule(0.0, lr, warm, steps, end_value=0.02 * lr)


# --- evaluation -------------------------------------------------------------------------------


def clip_outputs(params, model, cfg, x, tgt, init: str):
    """Outputs over a whole clip (padded inside to a multiple of PAD; causal, so the padding does
    not change the real frames). ``init``: ``learned`` (first frame's ground truth pose and
    velocity), ``learned_v0`` (its pose, zero velocity) or ``zero``."""
    T = len(x)
    n = _padded_len(T)
    xp = jnp.asarray(np.concatenate([x, np.repeat(x[-1:], n - T, 0)]))
    return _run_jit(params, model, cfg, xp, jnp.asarray(tgt["leaf"][0]), jnp.asarray(tgt["vel"][0]), init)


def _run_impl(params, model, cfg, x, leaf0, vel0, init):
    if init == "zero":
        carry = N.zero_state(cfg, (), x.dtype)
    else:
        carry = N.initial_state(params, model, cfg, leaf0, vel0 if init == "learned" else jnp.zeros_like(vel0))
    return N.run(params, model, cfg, carry, x)[1]


_run_jit = jax.jit(_run_impl, static_argnums=(2, 6))


@jax.jit
def _clip_metrics(model, out, tgt, fps, start):
    """The kinematics module's scores on one clip (``jmocap.metrics``): the pose ``q`` it gives
    (hinges from ``R_A``, root orientation from the pelvis sensor, root position integrated from
    ``V_A``) against the truth, on the character's body origins."""
    R = tgt["R_root"]  # the pelvis body's true orientation
    ori_pelvis = tgt["ori_pelvis"]  # what the pelvis sensor says (the estimate's root orientation)
    root = N.integrate_root(out, ori_pelvis, fps, start)
    q = N.pose(model, out, ori_pelvis, root)
    kin = jax.vmap(lambda qq: P.forward_kinematics(model, qq))(q)
    sip = jnp.asarray([model.body_id(n) for n in M.SIP_BODIES])
    b = N.body_indices(model)["bodies"]  # the root (pelvis) first
    return {"sip_deg": M.sip_error(kin.xmat[:, sip], tgt["xmat"][:, sip]),
            "mpjpe_mm": M.mpjpe_root_frame(kin.xpos[:, b], tgt["xpos"][:, b], ori_pelvis, R, root=(0,)),
            "net_joints_mm": 1000 * jnp.linalg.norm(out.joints - tgt["joints"], axis=-1).mean(),
            "jitter_km_s3": M.jitter(kin.xpos[:, b], fps),
            "gt_jitter_km_s3": M.jitter(tgt["xpos"][:, b], fps),
            "root_vel_err_m_s": jnp.linalg.norm(out.vel[:, 0] - tgt["vel"][:, 0], axis=-1).mean()}


def evaluate(params, cfg: N.IMUNetConfig, clips: list[dict], init: str) -> dict:
    per, probs, labels = [], [], []
    for c in clips:
        T = len(c["x"])
        out = clip_outputs(params, c["model"], cfg, c["x"], c["tgt"], init)
        out = jax.tree.map(lambda a, T=T: a[:T], out)
        tgt = {k: jnp.asarray(v) for k, v in c["tgt"].items()}
        tgt["ori_pelvis"] = jnp.asarray(c["ori"][:, 5])
        m = _clip_metrics(c["model"], out, tgt, jnp.float32(c["fps"]), tgt["xpos"][0, c["model"].body_id(N.ROOT_BODY)])
        per.append({k: float(v) for k, v in m.items()})
        probs.append(np.asarray(N.contact_probability(out)))
        labels.append(np.asarray(c["tgt"]["contacts"]))
    res = {k: float(np.mean([p[k] for p in per])) for k in per[0]}
    # pooled over every clip's frames and the four points, in %
    res["contact_f1"] = float(M.contact_classification(np.concatenate(probs), np.concatenate(labels))["f1"])
    res["clips"] = len(clips)
    return res


# --- training ---------------------------------------------------------------------------------


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="data/imu_train")
    ap.add_argument("--out", default="runs/imu_kin")
    ap.add_argument("--eval", help="held-out IMU archive to evaluate the final parameters on")
    ap.add_argument("--val-fraction", type=float, default=0.1)
    ap.add_argument("--val-frames", type=int, default=150)
    ap.add_argument("--steps", type=int, default=2500)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--contact-width", type=int, default=32)
    ap.add_argument("--layers", type=int, default=2)
    ap.add_argument("--dropout", type=float, default=0.1)
    ap.add_argument("--contact-labels", choices=("archive", "sticking"), default="archive",
                    help="the archive's contact labels, or only those also still and low (sticking contacts)")
    ap.add_argument("--contact-pos-weight", type=float, default=1.0,
                    help="weight of the in-contact class in the contacts' BCE (> 1: towards recall)")
    ap.add_argument("--no-learned-init", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--log-every", type=int, default=50)
    ap.add_argument("--val-every", type=int, default=250)
    ap.add_argument("--checkpoint-every", type=int, default=250)
    ap.add_argument("--eval-only", action="store_true",
                    help="write the checkpoint's best parameters and evaluate them (no training)")
    ap.add_argument("--time-limit-min", type=float, default=None, help="stop (with a checkpoint) after this long")
    ap.add_argument("--ship", action="store_true",
                    help="copy the best parameters into the package (float16, src/jmocap/assets/imu_kinematics.msgpack "
                         "and its .json: the network config and this command), the weights of jmocap.methods.pip_imu")
    a = ap.parse_args(argv)

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = N.IMUNetConfig(width=a.width, contact_width=a.contact_width, layers=a.layers, dropout=a.dropout,
                         learned_init=not a.no_learned_init, contact_pos_weight=a.contact_pos_weight)
    atomic_write(out / "config.json", json.dumps({"net": cfg.to_json(), "args": vars(a)}, indent=2).encode())

    t0 = time.time()
    clips = load_clips(a.data, a.contact_labels)
    n_val = max(1, int(round(a.val_fraction * len(clips))))
    train, val = clips[:-n_val], clips[-n_val:]
    print(f"loaded {len(clips)} clips ({len(train)} train, {len(val)} val) in {time.time() - t0:.1f} s", flush=True)
    model0 = train[0]["model"]  # topology only (every clip's character shares it)
    fps = train[0]["fps"]

    params = N.init_params(jax.random.PRNGKey(a.seed), model0, cfg)
    sched = make_schedule(a.lr, a.steps)
    opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(sched))
    opt_state = opt.init(params)
    step0, best, best_params = 0, float("inf"), params
    sampler = np.random.default_rng(a.seed)
    key = jax.random.PRNGKey(a.seed + 1)
    ck = out / "checkpoint.msgpack"
    if ck.exists():
        state = serialization.msgpack_restore(ck.read_bytes())
        params = serialization.from_state_dict(params, state["params"])
        best_params = serialization.from_state_dict(params, state["best_params"])
        opt_state = serialization.from_state_dict(opt_state, state["opt_state"])
        step0, best = int(state["step"]), float(state["best"])
        sampler.bit_generator.state = json.loads(str(state["sampler"]))
        key = jnp.asarray(state["key"])
        print(f"resumed at step {step0}", flush=True)

    def batch_loss(p, xb, tb, k):
        ks = jax.random.split(k, xb.shape[0])
        tot, parts = jax.vmap(lambda x, t, kk: N.clip_loss(p, model0, cfg, x, t, fps, train=True, rng=kk))(xb, tb, ks)
        return tot.mean(), jax.tree.map(jnp.mean, parts)

    @jax.jit
    def train_step(p, s, xb, tb, k):
        (loss, parts), g = jax.value_and_grad(batch_loss, has_aux=True)(p, xb, tb, k)
        upd, s = opt.update(g, s, p)
        return optax.apply_updates(p, upd), s, loss, parts, optax.global_norm(g)

    Lv = min(a.val_frames, min(len(c["x"]) for c in val))
    xv = jnp.asarray(np.stack([c["x"][:Lv] for c in val]))
    tv = {k: jnp.asarray(np.stack([c["tgt"][k][:Lv] for c in val]))
          for k in ("leaf", "joints", "hinges", "vel", "contacts", "R_root")}

    @jax.jit
    def val_loss(p):
        tot, parts = jax.vmap(lambda x, t: N.clip_loss(p, model0, cfg, x, t, fps))(xv, tv)
        return tot.mean(), jax.tree.map(jnp.mean, parts)

    def checkpoint(step):
        state = {"params": serialization.to_state_dict(params), "best_params": serialization.to_state_dict(best_params),
                 "opt_state": serialization.to_state_dict(opt_state), "step": step, "best": best,
                 "sampler": json.dumps(sampler.bit_generator.state), "key": np.asarray(key)}
        atomic_write(ck, serialization.msgpack_serialize(state))

    if a.eval_only:
        a.steps = step0
    log = open(out / "log.jsonl", "a")
    t_start = time.time()
    step = step0
    for step in range(step0, a.steps):
        xb, tb = sample_windows(sampler, train, a.batch, a.frames)
        key, k = jax.random.split(key)
        params, opt_state, loss, parts, gnorm = train_step(params, opt_state, xb, tb, k)
        done = step + 1
        rec = None
        if done % a.log_every == 0 or done == a.steps:
            rec = {"step": done, "loss": float(loss), **{k: float(v) for k, v in parts.items()},
                   "grad_norm": float(gnorm), "lr": float(sched(step)), "time_s": round(time.time() - t_start, 1)}
        if done % a.val_every == 0 or done == a.steps:
            vl, vparts = val_loss(params)
            rec = rec or {"step": done}
            rec.update(val_loss=float(vl), **{f"val_{k}": float(v) for k, v in vparts.items()})
            if float(vl) < best:
                best, best_params = float(vl), params
        if rec is not None:
            log.write(json.dumps(rec) + "\n")
            log.flush()
            print(json.dumps(rec), flush=True)
        if done % a.checkpoint_every == 0 or done == a.steps:
            checkpoint(done)
        if a.time_limit_min is not None and time.time() - t_start > 60 * a.time_limit_min:
            checkpoint(done)
            print(f"time limit: stopped at step {done}", flush=True)
            return 0
    train_s = time.time() - t_start
    if step0 == a.steps and not a.eval_only:
        print("the run is finished: only re-evaluating", flush=True)
    save_params(out / "params.msgpack", best_params)
    size = (out / "params.msgpack").stat().st_size
    print(f"trained to step {step0 if a.eval_only else a.steps} ({train_s:.0f} s this run); best val loss {best:.4f}; "
          f"params.msgpack {size / 1e6:.2f} MB, {sum(x.size for x in jax.tree.leaves(best_params))} parameters",
          flush=True)

    if a.ship:
        ship(best_params, cfg, a)
    if a.eval:
        params = load_params(out / "params.msgpack")
        test = load_clips(a.eval)
        res = {"archive": a.eval}
        inits = ("zero",) if not cfg.learned_init else ("learned", "learned_v0", "zero")
        for init in inits:
            t1 = time.time()
            res[init] = evaluate(params, cfg, test, init)
            print(init, json.dumps(res[init]), f"({time.time() - t1:.0f} s)", flush=True)
        res["val"] = {"loss": best}
        atomic_write(out / "eval.json", json.dumps(res, indent=2).encode())
    return 0


def ship(params, cfg: N.IMUNetConfig, a) -> None:
    """Write the weights (float16) and their network config where ``jmocap.methods.pip_imu`` loads them."""
    from jmocap.methods import pip_imu as PI

    half = jax.tree.map(lambda x: np.asarray(x, np.float16), params)
    atomic_write(PI.ASSET, serialization.msgpack_serialize(half))
    meta = {"net": cfg.to_json(), "made_by": "python experiments/train_imu.py " + " ".join(
        f"--{k.replace('_', '-')} {v}" for k, v in vars(a).items()
        if k in ("data", "out", "steps", "batch", "frames", "lr", "width", "contact_width", "layers", "dropout",
                  "contact_pos_weight", "seed"))}
    atomic_write(PI.ASSET_CONFIG, json.dumps(meta, indent=2).encode())
    print(f"shipped {PI.ASSET} ({PI.ASSET.stat().st_size / 1e6:.2f} MB)", flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
