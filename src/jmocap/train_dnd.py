"""Training of D&D's two networks (DyNet and the attentive PD controller, paper Sec. 3.6) with
optax, on an archive of moving-camera clips (``jmocap data synth --moving-camera``).

The kinematics backbone (TPNet, the shipped weights) is frozen, as the paper's HybrIK is during
D&D's training, so its output is computed once per clip. A sample is a window of ``context``
frames: the networks read all of it; the dynamics start from the ground truth at frame
``warmup`` (its pose and velocity relative to the true camera, the true camera orientation, the
root's world position and velocity) and run to the window's end. Losses (eq. 16-21, plus two of
jmocap's, marked):

* ``3d``: camera-frame joints, L1 (m) (eq. 17, joints);
* ``2d``: their projection against the clean 2D projection, per image size (eq. 18);
* ``trans``: the root's world position, L1 (m) (eq. 19);
* ``con``: contact probabilities against the labels, binary cross-entropy (eq. 20);
* ``reg``: the root actuation ``|eta|^2`` per body weight and the contact entropy (eq. 21);
* ``cam`` (jmocap): DyNet's camera angular velocity (rad/s) and acceleration (per 10 m/s^2)
  against the true track's, L1: synthetic archives know the track, and the paper's weak signal
  (``trans``) alone leaves the camera's yaw nearly free on short windows;
* ``impulse`` (jmocap): the world velocity change the constrained update made (m/s, squared):
  forces that explain the trajectory need no projection.

Resumable: ``out/checkpoint.msgpack`` (parameters, optimiser state, step, key, sampler state)
every ``checkpoint_every`` steps, a JSON line per logged step in ``out/log.jsonl``;
``out/dnd_params.msgpack`` holds D&D's networks at the end.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization

from jmocap import physics as P
from jmocap.camera import Camera, project
from jmocap.inputs import ClipInputs
from jmocap.io import atomic_write
from jmocap.layouts import get_layout
from jmocap.methods import dnd as D
from jmocap.methods import stages as S
from jmocap.model import Model, character
from jmocap.physics.rotations import mat_to_quat, quat_to_mat
from jmocap.train import load_training_clip

LOSS_WEIGHTS = {"3d": 5.0, "2d": 1.0, "trans": 1.0, "con": 0.5, "reg": 0.1, "cam": 0.5, "impulse": 1.0}


@dataclass(frozen=True)
class DnDTrainConfig:
    data: str = "data/train_moving"
    out: str = "runs/dnd"
    variant: str = "dnd"  # dnd or one of its ablations (dnd_meta_pd, dnd_discrete_contacts, ...)
    steps: int = 1200
    batch: int = 8
    context: int = 96  # frames the networks read per sample
    warmup: int = 16  # the dynamics start at this frame of the window
    lr: float = 5e-4
    clip_grad_norm: float = 1.0
    seed: int = 0
    max_clips: int = 0
    log_every: int = 10
    checkpoint_every: int = 50
    weights: dict = field(default_factory=lambda: dict(LOSS_WEIGHTS))


def _camera_frame(E: jnp.ndarray, q: jnp.ndarray) -> jnp.ndarray:
    """World poses (T, nq) seen from cameras (T, 4, 4): root position and orientation in each."""
    R, t = E[:, :3, :3], E[:, :3, 3]
    pos = jnp.einsum("tij,tj->ti", R, q[:, 0:3]) + t
    return q.at[:, 0:3].set(pos).at[:, 3:7].set(mat_to_quat(R @ quat_to_mat(q[:, 3:7])))


def _prepare(params, model: Model, inputs: ClipInputs, gt_q, kp_w, cfg: D.DnDConfig) -> dict:
    """One clip's (padded) arrays: the frozen backbone's output and the camera-frame truth."""
    init = D.initial_motion(params, model, D.seen_inputs(inputs, cfg), cfg)
    E = inputs.world_to_camera()
    kp_c = jnp.einsum("tij,tkj->tki", E[:, :3, :3], kp_w) + E[:, None, :3, 3]
    omega, _, accel = D.track_motion(E, inputs.fps)
    cam = Camera(inputs.intrinsics, inputs.image_size, jnp.eye(4, dtype=kp_w.dtype))
    return dict(q_cam=init.q_cam, p_rr=init.p_rr, logits=init.contact_logits, q_world=init.q_world,
                contacts=init.contacts, track=E,
                gt_q_cam=_camera_frame(E, gt_q), gt_kp_cam=kp_c, gt_2d=project(cam, kp_c),
                gt_omega=omega, gt_accel=accel)


class DnDData:
    """Clips held as numpy arrays with the frozen backbone's output and the camera-frame ground
    truth, and one character per subject."""

    def __init__(self, path, config: DnDTrainConfig, params: dict, cfg: D.DnDConfig, progress: bool = False):

        files = sorted(Path(path).glob("*.npz"))
        if config.max_clips:
            files = files[: config.max_clips]
        if not files:
            raise FileNotFoundError(f"no clip .npz files in {path}")
        self.models: list[Model] = []
        buckets: dict = {}
        self.clips = []
        layout = get_layout(cfg.layout)
        prepare = jax.jit(lambda p, m, i, q, k: _prepare(p, m, i, q, k, cfg))
        for f in files:
            c = load_training_clip(f, layout.name)
            T = len(c.keypoints)
            if T < config.context:
                continue
            key = (c.height_m, c.mass_kg)
            if key not in buckets:
                buckets[key] = len(self.models)
                self.models.append(character(*key))
            L = int(np.ceil(T / 32) * 32)  # a few padded lengths: a few compilations
            inputs = ClipInputs.from_clip(c, L)

            def pad(a, extra=L - T):
                a = np.asarray(a, np.float32)
                return np.concatenate([a, np.repeat(a[-1:], extra, 0)])

            out = prepare(params, self.models[buckets[key]], inputs, pad(c.gt_q), pad(c.gt_keypoints3d))
            clip = {k: np.asarray(v, np.float32)[:T] for k, v in out.items()}
            clip.update(model=buckets[key], T=T, intrinsics=np.asarray(inputs.intrinsics),
                        image_size=np.asarray(inputs.image_size), fps=np.float32(c.fps),
                        gt_q=np.asarray(c.gt_q, np.float32), gt_contacts=np.asarray(c.gt_contacts, np.float32))
            self.clips.append(clip)
        if not self.clips:
            raise ValueError(f"{path}: no clip has {config.context} frames")

    def sample(self, rng: np.random.Generator, batch: int, frames: int):
        picks = []
        for _ in range(batch):
            c = self.clips[rng.integers(len(self.clips))]
            s = int(rng.integers(0, c["T"] - frames + 1))
            item = {k: c[k][s : s + frames] for k in ("q_cam", "p_rr", "logits", "q_world", "contacts", "track", "gt_q", "gt_q_cam",
                                                         "gt_kp_cam", "gt_2d", "gt_contacts", "gt_omega", "gt_accel")}
            for k in ("intrinsics", "image_size", "fps"):
                item[k] = c[k]
            picks.append((c["model"], item))
        model = jax.tree.map(lambda *xs: np.stack(xs), *[self.models[m] for m, _ in picks])
        data = {k: np.stack([it[k] for _, it in picks]) for k in picks[0][1]}
        return model, data


def _velocity(model: Model, q: jnp.ndarray, fps) -> jnp.ndarray:
    return P.finite_difference_velocity(model, q, fps)


def window_loss(net: dict, model: Model, d: dict, key, cfg: D.DnDConfig, warmup: int, weights: dict):
    """Weighted loss of one sample and its named terms."""
    dtype = d["q_cam"].dtype
    T = d["q_cam"].shape[0]
    mask = jnp.ones(T, bool)
    init = D.Initial(d["q_cam"], d["p_rr"], d["logits"], d["q_world"], d["contacts"])
    E = d["track"]
    x = D.features(model, init, E[0, :3, :3] @ jnp.asarray(model.gravity, dtype), mask)
    phys = D.physical_properties(net, model, x, cfg)
    ctrl = D.pd_control(net, model, x, init.q_cam, cfg)
    b = D.contact_sample(phys.contact_logits, key, cfg, train=True)
    inputs = ClipInputs(jnp.zeros((T, 1, 3), dtype), d["intrinsics"], d["image_size"], E[0], d["fps"], mask, E)
    frames = D.frame_inputs(model, inputs, init, phys, ctrl, b, cfg)
    frames = jax.tree.map(lambda a: a[warmup:], frames)
    s = warmup
    qd_cam = _velocity(model, d["gt_q_cam"][s - 1 : s + 1], d["fps"])[1]
    qd_w = _velocity(model, d["gt_q"][s - 1 : s + 1], d["fps"])[1]
    state0 = D.State(d["gt_q_cam"][s], qd_cam, E[s, :3, :3], d["gt_q"][s, 0:3], qd_w[0:3])
    _, states, reports = D.simulate(model, state0, frames, d["fps"], cfg)
    layout = get_layout(cfg.layout)
    kp = jax.vmap(lambda q: P.keypoints(model, q, layout))(states.q)
    gt_kp = d["gt_kp_cam"][s:]
    cam = Camera(d["intrinsics"], d["image_size"], jnp.eye(4, dtype=dtype))
    uv = project(cam, kp)
    weight = S.body_weight(model, dtype)
    p = jax.nn.sigmoid(phys.contact_logits)
    bce = -(d["gt_contacts"] * jax.nn.log_sigmoid(phys.contact_logits)
            + (1 - d["gt_contacts"]) * jax.nn.log_sigmoid(-phys.contact_logits))
    entropy = -(p * jnp.log(p + 1e-6) + (1 - p) * jnp.log(1 - p + 1e-6))
    terms = {
        "3d": jnp.mean(jnp.abs(kp - gt_kp)),
        "2d": jnp.mean(jnp.clip(jnp.abs(uv - d["gt_2d"][s:]) / d["image_size"], 0.0, 2.0)),
        "trans": jnp.mean(jnp.abs(states.pos - d["gt_q"][s:, 0:3])),
        "con": jnp.mean(bce),
        "reg": jnp.mean(jnp.sum((phys.eta / weight) ** 2, -1)) + jnp.mean(entropy),
        "cam": jnp.mean(jnp.abs(phys.omega - d["gt_omega"])) + jnp.mean(jnp.abs(phys.accel - d["gt_accel"])) / 10.0,
        "impulse": jnp.mean(jnp.sum(reports.impulse**2, -1)),
    }
    if cfg.camera_motion == "none":
        terms["cam"] = jnp.zeros((), dtype)
    total = sum(weights[k] * terms[k] for k in weights)
    return total, terms


def make_step(cfg: D.DnDConfig, optimizer, warmup: int, weights: dict):
    def batch_loss(net, model, data, key):
        keys = jax.random.split(key, data["q_cam"].shape[0])
        tot, terms = jax.vmap(lambda m, d, k: window_loss(net, m, d, k, cfg, warmup, weights))(model, data, keys)
        return jnp.mean(tot), jax.tree.map(jnp.mean, terms)

    @jax.jit
    def step(net, opt_state, model, data, key):
        (loss, terms), g = jax.value_and_grad(batch_loss, has_aux=True)(net, model, data, key)
        updates, opt_state = optimizer.update(g, opt_state, net)
        return optax.apply_updates(net, updates), opt_state, loss, terms, optax.global_norm(g)

    return step


def train(config: DnDTrainConfig, params: dict, base: D.DnDConfig, *, progress: bool = True) -> dict:
    """Run (or resume) the training; returns D&D's network parameters (``params["dnd"]``)."""
    from jmocap.methods import resolve

    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    _, changes = resolve(config.variant)
    cfg = base.replace(**changes)
    (out / "config.json").write_text(json.dumps({"train": asdict(config), "cycle": _cfg_dict(cfg)}, indent=2))
    key = jax.random.PRNGKey(config.seed)
    net = D.init_params(key, character(), cfg)["dnd"]  # the networks' shapes do not depend on the subject
    schedule = optax.cosine_decay_schedule(config.lr, config.steps, alpha=0.05)
    # a step whose gradient is not finite is skipped (counted in the log), not applied
    optimizer = optax.apply_if_finite(
        optax.chain(optax.clip_by_global_norm(config.clip_grad_norm), optax.adam(schedule)), max_consecutive_errors=50)
    opt_state = optimizer.init(net)
    rng = np.random.default_rng(config.seed)
    start = 0
    ckpt = out / "checkpoint.msgpack"
    if ckpt.exists():
        r = serialization.msgpack_restore(ckpt.read_bytes())
        net = serialization.from_state_dict(net, r["net"])
        opt_state = serialization.from_state_dict(opt_state, r["opt_state"])
        start, key = int(r["step"]), jnp.asarray(r["key"])
        rng.bit_generator.state = json.loads(r["rng"])
    if start >= config.steps:  # a finished run
        return net
    data = DnDData(config.data, config, params, cfg, progress)
    step = make_step(cfg, optimizer, config.warmup, config.weights)
    log = open(out / "log.jsonl", "a")
    t0 = time.time()
    for it in range(start, config.steps):
        model, batch = data.sample(rng, config.batch, config.context)
        key, sub = jax.random.split(key)
        net, opt_state, loss, terms, gnorm = step(net, opt_state, model, batch, sub)
        if (it + 1) % config.log_every == 0 or it + 1 == config.steps:
            rec = {"step": it + 1, "loss": float(loss), "grad_norm": float(gnorm), "time_s": round(time.time() - t0, 1),
                   **{k: float(v) for k, v in terms.items()}}
            rec["skipped_steps"] = int(opt_state.total_notfinite)
            if not np.isfinite(float(gnorm)) and int(opt_state.notfinite_count) >= 50:
                raise FloatingPointError(f"50 non-finite gradients in a row at step {it + 1}: {rec}")
            log.write(json.dumps(rec) + "\n")
            log.flush()
            if progress:
                print(json.dumps(rec), flush=True)
        if (it + 1) % config.checkpoint_every == 0 or it + 1 == config.steps:
            payload = {"net": serialization.to_state_dict(jax.tree.map(np.asarray, net)),
                       "opt_state": serialization.to_state_dict(jax.tree.map(np.asarray, opt_state)),
                       "step": it + 1, "key": np.asarray(key), "rng": json.dumps(rng.bit_generator.state)}
            atomic_write(ckpt, serialization.msgpack_serialize(payload))
            atomic_write(out / "dnd_params.msgpack", serialization.msgpack_serialize(jax.tree.map(np.asarray, net)))
    log.close()
    return net


def _cfg_dict(cfg) -> dict:
    from jmocap.methods import config_dict

    return config_dict(cfg)


__all__ = ["DnDData", "DnDTrainConfig", "LOSS_WEIGHTS", "make_step", "train", "window_loss"]
