"""Staged training of TPNet, DyNet and GRFNet (paper Sec. 3.5-3.6) with optax.

Stages (each a :class:`StageConfig`; their order and lengths come from a :class:`TrainConfig`):

* ``tpnet`` — pre-training of C_P with L_3D + L_2D + L_ori + L_irr + L_b (eq. 17) and of C_T
  with L_CT (eq. 24); C_T's gradient does not reach C_P (they are separate pre-trainings).
* ``dynet`` — DyNet with L_Dyn (eq. 25) through the dynamic cycle, TPNet frozen.
* ``grfnet`` — GRFNet with L_GRF (eq. 12) through the dynamic cycle, the others frozen.
* ``joint`` — everything together: the sum of all objectives plus L_3D of the final pose.
* ``finetune2d`` — Sec. 3.6: the 2D reprojection loss only, against the detector keypoints.

Batches are random windows of clips from a jmocap archive (folder of clip .npz files, e.g.
``jmocap data synth``); each sample is simulated with a character scaled to its subject's
height (Model arrays are batched with the samples; the topology is shared, so one compile).

Training is resumable: a checkpoint (parameters, optimiser state, stage, step, random key)
is written atomically every ``checkpoint_every`` steps and at the end of each stage into
``out/checkpoint.msgpack``, and a JSON line per logged step into ``out/log.jsonl``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization

from jmocap import losses as Lo
from jmocap import physics as P
from jmocap.camera import Camera, project
from jmocap.constants import FLOOR_NORMAL, NUM_CONTACTS
from jmocap.inputs import ClipInputs
from jmocap.io import atomic_write
from jmocap.layouts import get_layout, through_layout
from jmocap.methods.physcap import CycleState, PhysCapConfig, init_params, simulate
from jmocap.methods.stages import body_weight, contact_probability, pd_error, target_pose
from jmocap.model import Model, character
from jmocap.physics.rotations import quat_to_mat
from jmocap.weights import load_params, save_params

NETS = ("tpnet", "dynet", "grfnet")
STAGE_TRAINS = {
    "tpnet": ("tpnet",),
    "dynet": ("dynet",),
    "grfnet": ("grfnet",),
    "joint": NETS,
    "finetune2d": NETS,
}


@dataclass(frozen=True)
class StageConfig:
    name: str  # tpnet | dynet | grfnet | joint | finetune2d
    steps: int
    lr: float
    batch: int
    frames: int  # window length in frames
    # PhysCapConfig fields changed for this stage only (e.g. {"use_dynet": false}: train GRFNet
    # under the fixed-gain PD that the shipped config runs)
    cycle: dict = field(default_factory=dict)
    # the learning rate over the stage: "constant" (lr throughout) or "cosine" (lr decayed to 0
    # over the stage's steps by a half cosine: a fine-tuning stage after a constant one)
    schedule: str = "constant"


@dataclass(frozen=True)
class TrainConfig:
    data: tuple[str, ...] = ("data/train",)  # archive folders of clip .npz files
    out: str = "runs/default"
    seed: int = 0
    stages: tuple[StageConfig, ...] = (
        StageConfig("tpnet", 3000, 1e-3, 16, 12),
        StageConfig("dynet", 300, 3e-4, 8, 6),
        StageConfig("grfnet", 300, 3e-4, 8, 6),
        StageConfig("joint", 200, 1e-4, 8, 6),
    )
    cycle: PhysCapConfig = field(default_factory=PhysCapConfig)
    max_clips: int | None = None
    log_every: int = 20
    checkpoint_every: int = 200
    clip_grad_norm: float = 1.0
    # truncated backpropagation through time: gradients stop at the state entering each frame
    truncate_gradient: bool = True
    # PhysCapConfig fields changed in the config shipped with the weights (inference only)
    ship_cycle: dict = field(default_factory=dict)
    # share of training windows whose keypoints are given as another layout's joints would be
    # (converted there and back, jmocap.layouts.conversion: e.g. no feet for coco17), so the
    # weights reconstruct clips of those layouts: {"coco17": 0.15, "h36m17": 0.15}
    layout_mix: dict = field(default_factory=dict)
    # a parameter file (msgpack, e.g. a previous run's params_tpnet.msgpack) whose networks
    # replace the fresh initialisation of those networks when a run starts (not when it resumes)
    init: str | None = None
    # validation: at the start of a stage that trains TPNet, every ``val_every`` steps and at its end,
    # TPNet's root-relative MPJPE (mm) on ``val_windows`` fixed windows of the ``val_data``
    # archives (clips never trained on), logged as ``val_mpjpe_mm``; the best parameters of the
    # run are kept in ``params_best.msgpack``; ``patience`` > 0 ends a stage early after that
    # many checks without improvement and goes on from the best parameters
    val_data: tuple[str, ...] = ()
    val_every: int = 250
    val_windows: int = 64
    patience: int = 0

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @staticmethod
    def from_json(d: dict) -> TrainConfig:
        d = dict(d)
        for k in ("data", "val_data"):
            if isinstance(d.get(k), str):
                d[k] = (d[k],)
            elif k in d:
                d[k] = tuple(d[k])
        if "stages" in d:
            d["stages"] = tuple(StageConfig(**s) for s in d["stages"])
        if "cycle" in d:
            from jmocap.methods import get_method

            d["cycle"] = get_method("physcap").make_config(d["cycle"])
        # older configs scaled subjects to a height grid; every subject now gets its exact
        # character (jmocap.model.character), the same as reconstruction and evaluation
        d.pop("height_bucket_m", None)
        return TrainConfig(**d)


# ---------------------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------------------


def load_training_clip(path, layout: str):
    """A clip of a training archive: in ``layout``, with the ground truth training needs
    (``gt_q``, ``gt_keypoints3d``, ``gt_contacts``); a clear error naming the file otherwise."""
    from jmocap.data.clip import load_clip

    c = load_clip(path)
    if c.layout != layout:
        raise ValueError(f"{path}: layout {c.layout!r}, training expects {layout!r}")
    if c.gt_q is None or c.gt_keypoints3d is None or c.gt_contacts is None:
        raise ValueError(f"{path}: training needs gt_q, gt_keypoints3d and gt_contacts")
    return c


@dataclass
class TrainingSet:
    """Clips of an archive held as numpy arrays, plus one character per subject (exact height
    and mass, :func:`jmocap.model.character`)."""

    clips: list[dict]
    models: list[Model]
    layout: str = "body25"
    layout_mix: tuple[tuple[str, float], ...] = ()

    @staticmethod
    def load(path: str | os.PathLike, config: TrainConfig) -> TrainingSet:

        paths = [path] if isinstance(path, str | os.PathLike) else list(path)
        files = sorted(f for p in paths for f in Path(p).glob("*.npz"))
        if config.max_clips:
            files = files[: config.max_clips]
        if not files:
            raise FileNotFoundError(f"no clip .npz files in {path}")
        layout = get_layout(config.cycle.layout)
        buckets: dict[tuple, int] = {}
        models: list[Model] = []
        clips = []
        for f in files:
            c = load_training_clip(f, layout.name)
            key = (c.height_m, c.mass_kg)
            if key not in buckets:
                buckets[key] = len(models)
                models.append(character(*key))
            inputs = ClipInputs.from_clip(c)
            clean = np.asarray(project(inputs.camera, np.asarray(c.gt_keypoints3d, np.float32)))
            clips.append(
                dict(
                    name=c.name,
                    model=buckets[key],
                    keypoints=inputs.keypoints,
                    intrinsics=inputs.intrinsics,
                    image_size=inputs.image_size,
                    extrinsics=inputs.extrinsics,
                    fps=np.float32(c.fps),
                    gt_q=np.asarray(c.gt_q, np.float32),
                    gt_qd=np.asarray(c.gt_qd, np.float32),
                    gt_kp3d=np.asarray(c.gt_keypoints3d, np.float32),
                    gt_contacts=np.asarray(c.gt_contacts, np.float32),
                    gt_2d=clean.astype(np.float32),
                )
            )
        return TrainingSet(clips, models, layout.name, tuple(sorted(config.layout_mix.items())))

    def sample(self, rng: np.random.Generator, batch: int, frames: int):
        """A batch of random windows: (batched Model, dict of (B, frames, ...) arrays)."""
        picks = []
        for _ in range(batch):
            c = self.clips[rng.integers(len(self.clips))]
            T = c["keypoints"].shape[0]
            L = min(frames, T)
            s = int(rng.integers(0, T - L + 1))
            item = {}
            for k in ("keypoints", "gt_q", "gt_qd", "gt_kp3d", "gt_contacts", "gt_2d"):
                a = c[k][s : s + L]
                pad = np.repeat(a[-1:], frames - L, 0)
                item[k] = np.concatenate([a, pad])
            item["mask"] = np.arange(frames) < L
            if self.layout_mix:
                u, acc = rng.random(), 0.0
                for other, share in self.layout_mix:
                    acc += share
                    if u < acc:
                        item["keypoints"] = through_layout(item["keypoints"], self.layout, other)
                        break
            for k in ("intrinsics", "image_size", "extrinsics", "fps"):
                item[k] = c[k]
            picks.append((c["model"], item))
        model = jax.tree.map(lambda *xs: np.stack(xs), *[self.models[m] for m, _ in picks])
        data = {k: np.stack([it[k] for _, it in picks]) for k in picks[0][1]}
        return model, data


# ---------------------------------------------------------------------------------------
# losses per sample
# ---------------------------------------------------------------------------------------


def _inputs(d) -> ClipInputs:
    return ClipInputs(d["keypoints"], d["intrinsics"], d["image_size"], d["extrinsics"], d["fps"], d["mask"])


def tpnet_losses(params, model, d, key, config: PhysCapConfig, detach: bool):
    layout = get_layout(config.layout)
    mask = d["mask"]
    tp = target_pose(params, model, _inputs(d), config, train=True, rngs={"dropout": key}, detach_pose=detach)
    E = d["extrinsics"]
    R, t = E[:3, :3], E[:3, 3]
    gt_q = d["gt_q"]
    rot_gt = jnp.matmul(R, quat_to_mat(gt_q[:, 3:7]))
    trans_gt = gt_q[:, :3] @ R.T + t
    p_rr_gt = (d["gt_kp3d"] - gt_q[:, None, :3]) @ R.T
    kp_world = jax.vmap(lambda q: P.keypoints(model, q, layout))(tp.q_hat)
    cam = Camera(d["intrinsics"], d["image_size"], E)
    hq = model.topo.hinge_qadr
    return tp, {
        "3d": Lo.loss_3d(tp.p_rr, p_rr_gt, mask),
        "2d": Lo.loss_2d(project(cam, kp_world), d["gt_2d"], d["image_size"], mask=mask),
        "ori": Lo.loss_ori(tp.rot_cam, rot_gt, mask),
        "irr": Lo.loss_irr(tp.q_hat[:, hq], model.q_lower[hq], model.q_upper[hq], mask),
        "b": Lo.loss_contact(tp.contact_logits, d["gt_contacts"], mask),
        "ct": Lo.loss_translation(tp.trans_cam, trans_gt, mask),
    }


def cycle_losses(params, model, d, tp, config: PhysCapConfig, truncate: bool = False):
    mask = d["mask"]
    q_hat = tp.q_hat
    prob = contact_probability(tp.contact_logits)
    dtype = q_hat.dtype
    init = CycleState(d["gt_q"][0], d["gt_qd"][0], jnp.zeros((NUM_CONTACTS, 3), dtype))
    _, out = simulate(params, model, q_hat, prob, mask, d["fps"], config, init=init, truncate_gradient=truncate)
    e = jax.vmap(lambda a, b: pd_error(model, a, b))(q_hat, out.q)
    steps = out.steps  # (T, k, ...)
    k = config.iterations
    step_mask = jnp.repeat(mask, k)
    flat = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), steps)
    grf_prev = jnp.concatenate([jnp.zeros((1, NUM_CONTACTS, 3), dtype), flat.grf[:-1]])
    weight = body_weight(model, dtype)
    normal = jnp.array(FLOOR_NORMAL, dtype)
    layout = get_layout(config.layout)
    kp = jax.vmap(lambda q: P.keypoints(model, q, layout))(out.q)
    return {
        "dyn": Lo.loss_dyn(e, steps.tau_pd.mean(1), mask),  # raw torques, phi = 1e-6 (eq. 25)
        "force": Lo.loss_force(flat.tau[:, :6], weight, step_mask),
        "smooth": Lo.loss_smooth(flat.grf, grf_prev, weight, step_mask),
        "cone": Lo.loss_cone(flat.grf_raw / weight, normal, config.mu, step_mask),
        "3d_final": Lo.loss_3d(kp, d["gt_kp3d"], mask),
    }


STAGE_WEIGHTS = {
    "tpnet": {"3d": 10.0, "2d": 10.0, "ori": 1.0, "irr": 1.0, "b": 0.1, "ct": 1.0},
    "dynet": {"dyn": 1.0},
    "grfnet": {"force": 1.0, "smooth": 1.0, "cone": 1.0},
    "joint": {"3d": 10.0, "2d": 10.0, "ori": 1.0, "irr": 1.0, "b": 0.1, "ct": 1.0, "dyn": 1.0,
              "force": 1.0, "smooth": 1.0, "cone": 1.0, "3d_final": 10.0},
    "finetune2d": {"2d": 10.0, "irr": 1.0},
}


def stage_loss(params, model, d, key, stage: str, config: PhysCapConfig, truncate: bool = False):
    """Weighted loss of one sample for a stage, and its named terms."""
    if stage == "finetune2d":  # 2D only: the detector keypoints are the pseudo ground truth
        d = dict(d, gt_2d=d["keypoints"][..., :2])
    tp, terms = tpnet_losses(params, model, d, key, config, detach=(stage == "tpnet"))
    if stage in ("dynet", "grfnet", "joint"):
        if stage != "joint":
            tp = jax.lax.stop_gradient(tp)
        terms.update(cycle_losses(params, model, d, tp, config, truncate))
    w = STAGE_WEIGHTS[stage]
    total = sum(w[k] * terms[k] for k in w)
    return total, terms


def make_validation(config: PhysCapConfig):
    """``f(params, model, data) -> (sum of per-frame MPJPE in m, frames)`` of TPNet (no
    dropout) over a batch of windows: the root-relative joint error of ``tpnet_losses``' L_3D
    (camera axes, all the layout's joints, the mask's frames)."""

    def one(params, model, d):
        tp = target_pose(params, model, _inputs(d), config, train=False)
        R = d["extrinsics"][:3, :3]
        p_rr_gt = (d["gt_kp3d"] - d["gt_q"][:, None, :3]) @ R.T
        err = jnp.linalg.norm(tp.p_rr - p_rr_gt, axis=-1).mean(-1)
        return jnp.sum(err * d["mask"]), jnp.sum(d["mask"])

    @jax.jit
    def batch(params, model, data):
        s, n = jax.vmap(lambda m, d: one(params, m, d))(model, data)
        return s.sum(), n.sum()

    return batch


def _validation_windows(val: TrainingSet, windows: int, batch: int, frames: int):
    """Fixed (seeded) validation batches of ``frames``-frame windows, BODY_25 as recorded."""
    rng = np.random.default_rng(20261204)
    plain = dataclasses.replace(val, layout_mix=())
    return [plain.sample(rng, batch, frames) for _ in range(max(1, -(-windows // batch)))]


def make_step(stage: StageConfig, config: PhysCapConfig, optimizer, truncate: bool = True):
    def batch_loss(params, model, data, key):
        keys = jax.random.split(key, data["mask"].shape[0])
        total, terms = jax.vmap(
            lambda m, d, k: stage_loss(params, m, d, k, stage.name, config, truncate)
        )(model, data, keys)
        return jnp.mean(total), jax.tree.map(jnp.mean, terms)

    @jax.jit
    def step(params, opt_state, model, data, key):
        (loss, terms), grads = jax.value_and_grad(batch_loss, has_aux=True)(params, model, data, key)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        gnorm = optax.global_norm(grads)
        return params, opt_state, loss, terms, gnorm

    return step


def learning_rate(stage: StageConfig):
    """The stage's learning rate: a constant or an optax schedule (by the stage's step count)."""
    if stage.schedule == "constant":
        return stage.lr
    if stage.schedule == "cosine":
        return optax.cosine_decay_schedule(stage.lr, max(stage.steps, 1))
    raise ValueError(f"stage {stage.name!r}: unknown schedule {stage.schedule!r} (constant, cosine)")


def make_optimizer(stage: StageConfig, params, clip: float):
    labels = {k: ("train" if k in STAGE_TRAINS[stage.name] else "freeze") for k in params}
    labels = {k: jax.tree.map(lambda _, v=v: v, params[k]) for k, v in labels.items()}
    return optax.multi_transform(
        {
            "train": optax.chain(optax.clip_by_global_norm(clip), optax.adam(learning_rate(stage))),
            "freeze": optax.set_to_zero(),
        },
        labels,
    )


# ---------------------------------------------------------------------------------------
# checkpoints and the loop
# ---------------------------------------------------------------------------------------


def train(config: TrainConfig, *, progress: bool = True, data: TrainingSet | None = None) -> dict:
    """Run (or resume) the staged training; returns the final parameters."""
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(config.to_json(), indent=2))
    data = TrainingSet.load(config.data, config) if data is None else data
    val = TrainingSet.load(config.val_data, config) if config.val_data else None
    validate = make_validation(config.cycle) if val is not None else None
    ckpt_path = out / "checkpoint.msgpack"
    key = jax.random.PRNGKey(config.seed)
    params = init_params(key, data.models[0], config.cycle)
    if config.init is not None and not ckpt_path.exists():
        start = load_params(config.init)
        unknown = set(start) - set(params)
        if unknown:
            raise ValueError(f"{config.init}: networks {sorted(unknown)} are not among {sorted(params)}")
        for name, tree in start.items():
            try:
                new = serialization.from_state_dict(params[name], tree)
                same = jax.tree.map(lambda a, b: np.shape(a) == np.shape(b), params[name], new)
            except (ValueError, KeyError, TypeError) as e:
                raise ValueError(f"{config.init}: network {name!r} does not match this config's: {e}") from e
            if not all(jax.tree.leaves(same)):
                raise ValueError(f"{config.init}: network {name!r} has other shapes than this config's")
            params[name] = new
    state = {"stage": 0, "step": 0, "params": params, "opt_state": None, "key": np.asarray(key)}
    if ckpt_path.exists():
        restored = serialization.msgpack_restore(ckpt_path.read_bytes())
        state["stage"], state["step"] = int(restored["stage"]), int(restored["step"])
        state["params"] = serialization.from_state_dict(params, restored["params"])
        state["key"] = np.asarray(restored["key"])
        state["opt_state"] = restored["opt_state"]
    log = open(out / "log.jsonl", "a")
    # the window sampler's state is checkpointed, so a resumed run draws exactly the windows an
    # uninterrupted one would have (checkpoints without it: reseeded from the stage and step)
    rng = np.random.default_rng(config.seed + 1000 * state["stage"] + state["step"])
    if ckpt_path.exists() and restored.get("rng"):
        rng.bit_generator.state = json.loads(restored["rng"])
    # validation bookkeeping (best MPJPE and its stage/step, checks without improvement)
    vstate = {"best": None, "stage": None, "step": None, "bad": 0}
    if ckpt_path.exists() and restored.get("val"):
        vstate = json.loads(restored["val"])
    params = state["params"]
    key = jnp.asarray(state["key"])
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover
        tqdm = None
    for si in range(state["stage"], len(config.stages)):
        stage = config.stages[si]
        optimizer = make_optimizer(stage, params, config.clip_grad_norm)
        opt_state = optimizer.init(params)
        start = 0
        if si == state["stage"] and state["opt_state"] is not None:
            opt_state = serialization.from_state_dict(opt_state, state["opt_state"])
            start = state["step"]
        stage_cycle = dataclasses.replace(config.cycle, **stage.cycle)
        step_fn = make_step(stage, stage_cycle, optimizer, config.truncate_gradient)
        bar = tqdm(total=stage.steps, initial=start, desc=stage.name, disable=not progress) if tqdm else None
        t0 = time.time()
        checks = validate is not None and "tpnet" in STAGE_TRAINS[stage.name]
        vbatches = _validation_windows(val, config.val_windows, stage.batch, stage.frames) if checks else []

        def check(params, step, vbatches=vbatches, stage=stage):
            """Validate; returns True when the stage should stop early."""
            tot = [validate(params, m, d) for m, d in vbatches]
            mpjpe = 1000.0 * float(sum(a for a, _ in tot)) / max(float(sum(b for _, b in tot)), 1.0)
            if vstate["best"] is None or mpjpe < vstate["best"]:
                vstate.update(best=mpjpe, stage=stage.name, step=step, bad=0)
                save_params(out / "params_best.msgpack", params)
            else:
                vstate["bad"] += 1
            log.write(json.dumps({"stage": stage.name, "step": step, "val_mpjpe_mm": round(mpjpe, 3),
                                  "best_mm": round(vstate["best"], 3)}) + "\n")
            log.flush()
            return config.patience > 0 and vstate["bad"] >= config.patience

        if start == 0:
            vstate["bad"] = 0
            if checks:  # the starting point (a fine-tuning run's init, or the previous stage's end)
                check(params, 0)
        for it in range(start, stage.steps):
            model, batch = data.sample(rng, stage.batch, stage.frames)
            key, sub = jax.random.split(key)
            params, opt_state, loss, terms, gnorm = step_fn(params, opt_state, model, batch, sub)
            if (it + 1) % config.log_every == 0 or it + 1 == stage.steps:
                rec = {"stage": stage.name, "step": it + 1, "loss": float(loss), "grad_norm": float(gnorm),
                       "time_s": round(time.time() - t0, 2), **{k: float(v) for k, v in terms.items()}}
                if not np.isfinite(rec["loss"]):
                    raise FloatingPointError(f"non-finite loss at stage {stage.name} step {it + 1}: {rec}")
                log.write(json.dumps(rec) + "\n")
                log.flush()
                if bar:
                    bar.set_postfix(loss=f"{rec['loss']:.4g}")
            if bar:
                bar.update(1)
            last = it + 1 == stage.steps
            if checks and ((it + 1) % config.val_every == 0 or last) and check(params, it + 1) and not last:
                last = True  # early stop: go on from the best parameters
                params = serialization.from_state_dict(params, load_params(out / "params_best.msgpack"))
                log.write(json.dumps({"stage": stage.name, "step": it + 1, "early_stop": True,
                                      "best_step": vstate["step"]}) + "\n")
                log.flush()
            if (it + 1) % config.checkpoint_every == 0 or last:
                nxt = (si + 1, 0) if last else (si, it + 1)
                _save_checkpoint(ckpt_path, nxt, params, None if last else opt_state, key, rng, vstate)
            if last:
                break
        if bar:
            bar.close()
        save_params(out / f"params_{stage.name}.msgpack", params)
    save_params(out / "params.msgpack", params)
    log.close()
    return params


def _save_checkpoint(path: Path, stage_step, params, opt_state, key, rng=None, vstate=None) -> None:
    payload = {
        "rng": "" if rng is None else json.dumps(rng.bit_generator.state),
        "val": "" if vstate is None else json.dumps(vstate),
        "stage": stage_step[0],
        "step": stage_step[1],
        "params": serialization.to_state_dict(jax.tree.map(np.asarray, params)),
        "opt_state": None if opt_state is None else serialization.to_state_dict(jax.tree.map(np.asarray, opt_state)),
        "key": np.asarray(key),
    }
    atomic_write(path, serialization.msgpack_serialize(payload))
