"""Train ``mocon``'s learned distribution prior (Neural MoCon, Sec. 3.3; jmocap.methods.mocon_prior).

    .venv/bin/python experiments/train_mocon_prior.py --run runs/mocon_prior \\
        --archives data/train_terrain data/val [--max-clips N] [--deadline-min M] [--ship]

Three stages, each resumable (``RUN/``: ``windows/`` one file per clip, ``pretrain.msgpack``,
``checkpoint.msgpack`` after every round, ``log.jsonl``):

1. **collect**: every training clip is fitted by ``trajopt`` (the reference ``mocon`` tracks) and
   tracked by ``mocon`` with its cross-entropy sampler (the default config, ``sampling="gaussian"``);
   every window's start state, features and the distribution of its last round's elites are
   written to ``RUN/windows/<archive>__<clip>.npz``. ``--deadline-min`` stops starting new clips
   after that many minutes (the rest of the recipe runs on what was collected).
2. **pretrain**: the encoder on the recorded distributions, Eq. 5 (KL), Adam; a tenth of the
   windows held back, the epoch with the lowest KL on them kept.
3. **two-branch**: ``--rounds`` rounds (the first ``--warmup-rounds`` train the decoder alone); in each, every recorded window (those with a full
   lookahead) gets ``--draws`` corrections drawn from the current encoder, simulated from the
   window's recorded state by MuJoCo C (``mujoco.rollout``, the physical branch); the pose decoder
   learns the simulated deviations (Eq. 6) and the encoder learns through it (Eq. 7), with the KL
   term at ``--kl-weight`` (Eq. 9) and the L2 regulariser (Eq. 8). The decoder's error on the
   round's fresh simulations (before it trains on them) is logged as ``sim_heldout``, their mean
   squared scaled deviation from the reference as ``simulated_deviation``: the encoder whose
   draws simulated closest to the reference (after the warm-up) is the one kept
   (``RUN/best.msgpack``).

``--ship`` writes ``src/jmocap/assets/mocon_prior.msgpack`` (float16) and ``mocon_prior.json``.
Never on the held-out archives (``data/heldout*``): refused.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import optax
from flax import serialization
from mujoco import rollout

from jmocap import weights
from jmocap.evaluate import select_clips
from jmocap.inputs import ClipInputs
from jmocap.inputs import stack as stack_inputs
from jmocap.io import atomic_write
from jmocap.methods import mocon as MC
from jmocap.methods import mocon_prior as MP
from jmocap.pipeline import padded_length, subject_model
from jmocap.scene import boxes

_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CONTROL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_QFRC_APPLIED


def log(run: Path, **entry) -> None:
    entry["time"] = time.strftime("%Y-%m-%d %H:%M:%S")
    with open(run / "log.jsonl", "a") as f:
        f.write(json.dumps(entry) + "\n")
    print(json.dumps(entry), flush=True)


def clip_key(archive: str, name: str) -> str:
    return f"{Path(archive).name}__{name}"


def clip_parts(clip):
    """The clip's estimate model and its inputs (one clip, padded; the scene among them)."""
    model = subject_model(clip)
    inputs = ClipInputs.from_clip(clip, padded_length(clip.num_frames))
    return model, inputs


def collect(run: Path, archives: list[str], max_clips: int | None, deadline: float, config) -> None:
    out = run / "windows"
    out.mkdir(parents=True, exist_ok=True)
    params, _ = weights.load_run_params(None, method="trajopt")
    clips = []
    for a in archives:
        clips += [(a, c) for c in select_clips(a, max_clips)]
    # interleave the archives (terrain and flat) so a deadline leaves a mix
    order = sorted(range(len(clips)), key=lambda i: (sum(1 for j in range(i) if clips[j][0] == clips[i][0]), i))
    for i in order:
        a, clip = clips[i]
        path = out / f"{clip_key(a, clip.name)}.npz"
        if path.exists():
            continue
        if time.time() > deadline:
            log(run, stage="collect", stopped="deadline", done=len(list(out.glob('*.npz'))))
            return
        t = time.time()
        model, inputs = clip_parts(clip)
        stacked = jax.tree.map(lambda x: np.asarray(x)[None], model)
        ref = jax.device_get(MC._batched_reference()(params, stacked, stack_inputs([inputs]), config))
        one_ref = jax.tree.map(lambda x: np.asarray(x)[0], ref)
        one_in = jax.tree.map(np.asarray, inputs)
        rec: dict = {}
        motion = MC.track(model, one_in, one_ref, config, record=rec)
        w = rec["windows"]
        arrays = {k: np.stack([x[k] for x in w]) for k in ("k0", "k1", "k2", "retry", "state", "features", "prev",
                                                           "mu", "sigma", "best", "loss")}
        arrays.update({f"clip_{k}": np.asarray(v) for k, v in rec["clip"].items()})
        arrays["archive"] = np.asarray(a)
        arrays["name"] = np.asarray(clip.name)
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, **arrays)
        tmp.rename(path)
        log(run, stage="collect", clip=path.stem, windows=len(w), resets=float(motion.diagnostics["mocon_resets"]),
            seconds=round(time.time() - t, 1))


def load_windows(run: Path) -> list[dict]:
    return [dict(np.load(p, allow_pickle=False)) for p in sorted((run / "windows").glob("*.npz"))]


def stack_pretrain(data: list[dict]):
    f = np.concatenate([d["features"] for d in data])
    mu = np.concatenate([d["mu"] for d in data]).astype(np.float32)
    sigma = np.concatenate([d["sigma"] for d in data]).astype(np.float32)
    # backtracking windows draw with backtrack_sigma x the spread: in base units their sigma is
    # larger; they are the states where the controller failed, kept at full weight
    return f, mu, sigma


def adam_steps(params, opt, state, grad, batches):
    """Adam steps over ``batches`` with ``grad`` (a jitted value-and-grad with aux)."""
    loss = jnp.nan
    for b in batches:
        (loss, _), g = grad(params, *b)
        upd, state = opt.update(g, state, params)
        params = optax.apply_updates(params, upd)
    return params, state, float(loss)


def minibatches(rng, n, size, arrays):
    idx = rng.permutation(n)
    size = min(size, n)
    for s in range(0, n - size + 1, size):
        j = idx[s:s + size]
        yield tuple(jnp.asarray(a[j]) for a in arrays)


def pretrain(run: Path, data: list[dict], nu: int, epochs: int, lr: float, seed: int) -> dict:
    path = run / "pretrain.msgpack"
    params = MP.init_prior_params(jax.random.PRNGKey(seed), nu)
    if path.exists():
        return serialization.from_bytes(params, path.read_bytes())
    f, mu, sigma = stack_pretrain(data)
    rng = np.random.default_rng(seed)
    val = rng.random(len(f)) < 0.1
    opt = optax.adam(lr)
    state = opt.init(params)

    def loss_fn(p, ff, m, s):
        loss = MP.pretrain_loss(p, ff, m, s, jnp.ones(ff.shape[0]))
        return loss, {}

    grad = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))
    ones = jnp.ones(int(val.sum()))
    best, best_kl = params, np.inf
    for e in range(epochs):
        params, state, loss = adam_steps(params, opt, state, grad,
                                         minibatches(rng, int((~val).sum()), 256, (f[~val], mu[~val], sigma[~val])))
        v = float(MP.pretrain_loss(params, jnp.asarray(f[val]), jnp.asarray(mu[val]), jnp.asarray(sigma[val]), ones))
        if v < best_kl:  # early stopping on the held-back windows
            best, best_kl = params, v
        if e % 10 == 0 or e == epochs - 1:
            log(run, stage="pretrain", epoch=e, train_kl=round(loss, 3), val_kl=round(v, 3), best_val_kl=round(best_kl, 3))
    atomic_write(path, serialization.to_bytes(best))
    return best


@functools.cache
def archive_clips(archive: str) -> dict:
    return {c.name: c for c in select_clips(archive)}


class Branch:
    """A clip's physical branch: its simulated character and recorded windows."""

    def __init__(self, d: dict, config):
        archive, name = str(d["archive"]), str(d["name"])
        clip = archive_clips(archive)[name]
        model, inputs = clip_parts(clip)
        scene = inputs.scene if inputs.scene is not None and boxes(inputs.scene) else None
        self.sim = MC.Simulation(model, scene, float(inputs.fps), config)
        self.datas = [mujoco.MjData(self.sim.mj) for _ in range(2)]
        K = config.window_frames + config.lookahead_frames
        full = (d["k2"] - d["k0"]) == K
        self.sel = np.flatnonzero(full)
        self.d = d
        self.config = config

    def simulate(self, corr: np.ndarray) -> np.ndarray:
        """Deviations (len(sel), num_decoded) of the windows simulated with corrections ``corr``
        (len(sel), nu) in base-spread units."""
        d, c, n = self.d, self.config, int(self.d["clip_n"])
        q_ref, ff, hq = d["clip_q_ref"], d["clip_ff"], d["clip_hinge_q"]
        spread = d["clip_spread"]
        ctrls = []
        for j, i in enumerate(self.sel):
            k0, k1, k2 = int(d["k0"][i]), int(d["k1"][i]), int(d["k2"][i])
            prev = d["prev"][i] * spread
            ctrls.append(MC.window_controls(q_ref, ff, hq, n, prev, (corr[j] * spread)[None], k0, k1, k2,
                                            c.lookahead_gain)[0])
        ctrls = np.stack(ctrls)
        states, _ = rollout.rollout(self.sim.mj, self.datas, d["state"][self.sel], ctrls, control_spec=_CONTROL)
        mj = self.sim.mj
        k0, k1, k2 = d["k0"][self.sel], d["k1"][self.sel], d["k2"][self.sel]
        e1 = (k1 - k0) * n - 1
        e2 = (k2 - k0) * n - 1
        rows = np.arange(len(self.sel))
        q1 = states[rows, e1, 1:1 + mj.nq]
        q2 = states[rows, e2, 1:1 + mj.nq]
        out = np.concatenate([MP.deviation(q1, q_ref[k1], q_ref[k0]), MP.deviation(q2, q_ref[k2], q_ref[k0])], -1)
        return np.where(np.isfinite(out), out, 0.0).clip(-50, 50)


def two_branch(run: Path, data: list[dict], params: dict, rounds: int, warmup: int, draws: int, steps: int,
               lr: float, kl_weight: float, seed: int, config) -> dict:
    ck = run / "checkpoint.msgpack"
    opt = optax.adam(lr)
    state = opt.init(params)
    start = 0
    if ck.exists():
        saved = serialization.msgpack_restore(ck.read_bytes())
        params = serialization.from_state_dict(params, saved["params"])
        state = serialization.from_state_dict(state, saved["opt"])
        start = int(saved["round"])
    branches = [Branch(d, config) for d in data]
    feats = [b.d["features"][b.sel] for b in branches]
    mu_ce = [b.d["mu"][b.sel].astype(np.float32) for b in branches]
    sig_ce = [b.d["sigma"][b.sel].astype(np.float32) for b in branches]

    def loss_fn(p, f, eps, sim, m, s):
        return MP.two_branch_loss(p, f, eps, sim, m, s, jnp.ones(f.shape[0]), kl_weight=kl_weight)

    def decoder_loss(p, f, eps, sim, m, s):  # the warm-up: L_sim alone, the encoder held
        p = {"encoder": jax.lax.stop_gradient(p["encoder"]), "decoder": p["decoder"]}
        return MP.two_branch_loss(p, f, eps, sim, m, s, jnp.ones(f.shape[0]), kl_weight=0.0, reg_weight=0.0)

    grad = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))
    warm_grad = jax.jit(jax.value_and_grad(decoder_loss, has_aux=True))
    best_path = run / "best.msgpack"
    best_dev = float(json.loads((run / "best.json").read_text())["simulated_deviation"]) \
        if (run / "best.json").exists() else np.inf
    decode = jax.jit(MP.decode)
    for r in range(start, rounds):
        rng = np.random.default_rng(seed * 1000 + r)
        t = time.time()
        F, E, C, S, M, G = [], [], [], [], [], []
        for b, f, m, s in zip(branches, feats, mu_ce, sig_ce, strict=True):
            mu, sig = jax.device_get(MP.encode_jit(params, jnp.asarray(f)))
            for _ in range(draws):
                eps = rng.normal(size=mu.shape).astype(np.float32)
                C.append(mu + sig * eps)
                S.append(b.simulate(C[-1]))
                F.append(f), E.append(eps), M.append(m), G.append(s)
        F, E, C, S, M, G = (np.concatenate(x) for x in (F, E, C, S, M, G))
        pred = np.asarray(decode(params, jnp.asarray(F), jnp.asarray(C)))
        sim_heldout = float(np.mean((pred - S) ** 2))
        sim_dev = float(np.mean(S**2))
        # the encoder that drew this round's corrections, judged by the simulator: kept if its
        # draws came closest to the reference so far (after the decoder's warm-up rounds)
        if r >= warmup and sim_dev < best_dev:
            best_dev = sim_dev
            atomic_write(best_path, serialization.to_bytes(params))
            (run / "best.json").write_text(json.dumps({"round": r, "simulated_deviation": sim_dev}))
        aux = {}
        g_fn = warm_grad if r < warmup else grad
        for _ in range(steps):
            for batch in minibatches(rng, len(F), 256, (F, E, S, M, G)):
                (loss, aux), g = g_fn(params, *batch)
                upd, state = opt.update(g, state, params)
                params = optax.apply_updates(params, upd)
        atomic_write(ck, serialization.msgpack_serialize({
            "params": serialization.to_state_dict(params), "opt": serialization.to_state_dict(state), "round": r + 1}))
        log(run, stage="two_branch", round=r, warmup=r < warmup, windows=len(F), simulated_deviation=round(sim_dev, 3),
            sim_heldout=round(sim_heldout, 3), **{k: round(float(v), 3) for k, v in aux.items()},
            seconds=round(time.time() - t, 1))
    if best_path.exists():
        return serialization.from_bytes(params, best_path.read_bytes())
    return params


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default="runs/mocon_prior")
    ap.add_argument("--archives", nargs="+", default=["data/train_terrain", "data/val"])
    ap.add_argument("--max-clips", type=int, default=None)
    ap.add_argument("--deadline-min", type=float, default=float("inf"))
    ap.add_argument("--pretrain-epochs", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--warmup-rounds", type=int, default=2, help="rounds that train the decoder alone")
    ap.add_argument("--draws", type=int, default=4)
    ap.add_argument("--steps", type=int, default=5, help="passes over a round's simulations")
    ap.add_argument("--pretrain-lr", type=float, default=1e-3)
    ap.add_argument("--lr", type=float, default=3e-4, help="the two-branch stage's")
    ap.add_argument("--kl-weight", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ship", action="store_true")
    args = ap.parse_args()
    for a in args.archives:
        if Path(a).name.startswith("heldout"):
            raise SystemExit(f"{a}: a held-out archive is never training data")
    run = Path(args.run)
    run.mkdir(parents=True, exist_ok=True)
    config = MC.MoconConfig()
    t0 = time.time()
    collect(run, args.archives, args.max_clips, t0 + args.deadline_min * 60, config)
    data = load_windows(run)
    if not data:
        raise SystemExit("no windows collected")
    nu = int(data[0]["mu"].shape[1])
    params = pretrain(run, data, nu, args.pretrain_epochs, args.pretrain_lr, args.seed)
    params = two_branch(run, data, params, args.rounds, args.warmup_rounds, args.draws, args.steps, args.lr,
                        args.kl_weight, args.seed, config)
    summary = {"clips": len(data), "windows": int(sum(len(d["mu"]) for d in data)),
               "collected": [f"{d['archive']}/{d['name']}" for d in data],
               "kept_round": json.loads((run / "best.json").read_text()) if (run / "best.json").exists() else None,
               "archives": args.archives, "rounds": args.rounds, "draws": args.draws, "kl_weight": args.kl_weight,
               "command": "python experiments/train_mocon_prior.py " + " ".join(
                   f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}"
                   for k, v in vars(args).items() if k not in ("ship",) and v not in (None, float("inf")))}
    (run / "summary.json").write_text(json.dumps(summary, indent=2))
    if args.ship:
        half = jax.tree.map(lambda x: np.asarray(x, np.float16), params)
        atomic_write(MP.ASSET, serialization.msgpack_serialize(half))
        atomic_write(MP.ASSET.with_suffix(".json"), json.dumps(
            {"paper": "Neural MoCon (Huang et al. 2022), Sec. 3.3", **summary, "hidden": list(MP.HIDDEN)},
            indent=2).encode())
        print(f"shipped {MP.ASSET}")


if __name__ == "__main__":
    main()
