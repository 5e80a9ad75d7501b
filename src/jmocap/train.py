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

Training is resumable: a checkpoint (parameters, optimiser state, stage, step, random key, the
window sampler's and the validation state) is written atomically through orbax every
``checkpoint_every`` steps and at the end of each stage into ``out/checkpoint/``
(:class:`Checkpoints`; runs started before resume from their ``out/checkpoint.msgpack``), and a
JSON line per logged step into ``out/log.jsonl``.

Training is data-parallel over all devices (:class:`DataParallel`), also across processes and
hosts (:func:`initialize_distributed` in each process, then :func:`train` in each): every process
draws the same global batch and feeds its devices' rows, so a run's windows, losses and
parameters do not depend on the number of processes (up to float rounding), and it can resume on
another number of processes than the one that wrote its checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from flax import serialization
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jmocap import losses as Lo
from jmocap import physics as P
from jmocap.camera import Camera, project
from jmocap.constants import FLOOR_NORMAL, NUM_CONTACTS
from jmocap.inputs import ClipInputs
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


def make_step(stage: StageConfig, config: PhysCapConfig, optimizer, truncate: bool = True, mesh: Mesh | None = None):
    """The jitted training step ``(params, opt_state, model, data, key) -> (params, opt_state,
    loss, terms, grad_norm)``: the loss terms' means over the batch's rows and their gradient.

    With a ``mesh`` of several devices (:class:`DataParallel`; rows sharded over its ``"batch"``
    axis, everything else replicated) each device sums the losses and gradients of its own rows
    and one all-reduce of them all (a single flat vector) gives the batch's means, which every
    device then applies to its copy of the parameters."""

    def row_losses(params, model, data, keys):
        return jax.vmap(lambda m, d, k: stage_loss(params, m, d, k, stage.name, config, truncate))(model, data, keys)

    def batch_loss(params, model, data, key):
        total, terms = row_losses(params, model, data, jax.random.split(key, data["mask"].shape[0]))
        return jnp.mean(total), jax.tree.map(jnp.mean, terms)

    def update(params, opt_state, loss, terms, grads):
        updates, opt_state = optimizer.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        return params, opt_state, loss, terms, optax.global_norm(grads)

    if mesh is None or mesh.size == 1:

        @jax.jit
        def step(params, opt_state, model, data, key):
            (loss, terms), grads = jax.value_and_grad(batch_loss, has_aux=True)(params, model, data, key)
            return update(params, opt_state, loss, terms, grads)

        return step

    def local_sums(params, model, data, keys):
        def loss(params):
            total, terms = row_losses(params, model, data, keys)
            return jnp.sum(total), jax.tree.map(jnp.sum, terms)

        (total, terms), grads = jax.value_and_grad(loss, has_aux=True)(params)
        flat, unflatten = ravel_pytree((total, terms, grads))
        return unflatten(jax.lax.psum(flat, "batch"))

    rows, whole = PartitionSpec("batch"), PartitionSpec()
    sums = jax.shard_map(local_sums, mesh=mesh, in_specs=(whole, rows, rows, rows), out_specs=whole,
                         check_vma=False)

    @partial(jax.jit, out_shardings=NamedSharding(mesh, whole))
    def step(params, opt_state, model, data, key):
        n = data["mask"].shape[0]
        total, terms, grads = sums(params, model, data, jax.random.split(key, n))
        mean = partial(jax.tree.map, lambda x: x / n)
        return update(params, opt_state, total / n, mean(terms), mean(grads))

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
# data parallelism across devices and processes
# ---------------------------------------------------------------------------------------


def initialize_distributed(coordinator: str | None = None, num_processes: int | None = None,
                           process_id: int | None = None) -> None:
    """Join a multi-process (multi-host) run: a thin wrapper of :func:`jax.distributed.initialize`,
    to be called in every process before anything else uses JAX; :func:`train` then runs
    data-parallel over all the processes' devices.

    ``coordinator`` (``HOST:PORT``: process 0's host and a free port there), ``num_processes``
    and ``process_id`` (0 .. num_processes - 1) are given together, or all left out: JAX then
    reads them from the cluster environment (SLURM, Open MPI, ...). On CPU the processes
    exchange gradients through gloo, jax's default CPU collectives (no setting needed in jax 0.10).
    """
    given = [a is not None for a in (coordinator, num_processes, process_id)]
    if not any(given):
        jax.distributed.initialize()
        return
    if not all(given):
        raise ValueError("initialize_distributed: give coordinator, num_processes and process_id together, "
                         "or none of them (read from the cluster environment)")
    if num_processes < 1 or not 0 <= process_id < num_processes:
        raise ValueError(f"initialize_distributed: process_id {process_id} is not in 0..{num_processes - 1}")
    jax.distributed.initialize(coordinator, num_processes, process_id)


class DataParallel:
    """The data-parallel layout of a run: one ``"batch"`` mesh axis over every device of every
    process (each process's devices side by side), parameters and optimiser state replicated,
    the rows of a batch split over the devices.

    Every process draws the same global batch (one sampler state, the same in every process, so
    the windows do not depend on the number of processes), keeps the rows of its own devices and
    assembles the global arrays from them (:func:`jax.make_array_from_process_local_data`); the
    jitted step's means over the batch are then those of a single-device run, up to the order of
    the float additions. One process with one device is the plain single-device run."""

    def __init__(self) -> None:
        devices = sorted(jax.devices(), key=lambda d: (d.process_index, d.id))
        self.mesh = Mesh(np.array(devices), ("batch",))
        self.replicated = NamedSharding(self.mesh, PartitionSpec())
        self.rows = NamedSharding(self.mesh, PartitionSpec("batch"))
        self.primary = jax.process_index() == 0

    def check(self, stages) -> None:
        """A clear error for a stage whose batch the devices cannot share evenly."""
        n = self.mesh.size
        for s in stages:
            if s.batch % n:
                raise ValueError(f"stage {s.name!r}: batch {s.batch} is not divisible by the {n} devices of the "
                                 f"data-parallel run ({jax.process_count()} process(es)); use a multiple of {n}")

    def replicate(self, tree):
        """Host values, the same in every process, as arrays replicated over the mesh."""
        return jax.tree.map(
            lambda x: jax.make_array_from_process_local_data(self.replicated, np.asarray(x), np.shape(x)), tree)

    def split_rows(self, tree):
        """A global batch that every process holds whole as arrays sharded by rows over the mesh:
        each process hands over the (contiguous) rows of its own devices."""
        n = np.shape(jax.tree.leaves(tree)[0])[0]
        spans = [idx[0].indices(n)[:2] for idx in self.rows.addressable_devices_indices_map((n,)).values()]
        lo, hi = min(a for a, _ in spans), max(b for _, b in spans)
        return jax.tree.map(
            lambda x: jax.make_array_from_process_local_data(self.rows, np.asarray(x)[lo:hi], np.shape(x)), tree)


def _host(tree):
    """Replicated arrays as numpy arrays (each process reads its own copy)."""
    return jax.tree.map(np.asarray, tree)


# ---------------------------------------------------------------------------------------
# checkpoints and the loop
# ---------------------------------------------------------------------------------------


class Checkpoints:
    """A run's checkpoints in ``out/checkpoint/<n>/`` through orbax, the latest two kept: the
    training state (item ``state``: parameters, optimiser state or None at a stage's end, the
    jax key) and its bookkeeping as JSON (item ``meta``: the next stage and step, the window
    sampler's state, the validation state).

    Orbax writes a checkpoint into a temporary folder and renames it once complete, so an
    interrupted save leaves the previous checkpoint intact. Every process calls :meth:`save`
    (orbax synchronises them; the replicated arrays and the JSON are written once), so ``out``
    must be a folder all processes share. :meth:`restore` reads host (numpy) values, which the
    caller places on its own mesh: a run resumes on any number of processes.

    Runs started before the orbax checkpoints resume from their ``out/checkpoint.msgpack`` (flax
    msgpack of the same fields) when ``out/checkpoint/`` holds none; their next checkpoint is an
    orbax one."""

    KEEP = 2

    def __init__(self, out: Path) -> None:
        self.legacy = out / "checkpoint.msgpack"
        self.manager = ocp.CheckpointManager(
            (out / "checkpoint").absolute(),
            options=ocp.CheckpointManagerOptions(max_to_keep=self.KEEP, create=True, enable_async_checkpointing=False),
            item_handlers={"state": ocp.PyTreeCheckpointHandler(), "meta": ocp.JsonCheckpointHandler()},
        )

    def save(self, stage_step: tuple[int, int], params, opt_state, key, rng: np.random.Generator,
             vstate: dict) -> None:
        latest = self.manager.latest_step()
        state = {
            "params": serialization.to_state_dict(params),
            "opt_state": None if opt_state is None else serialization.to_state_dict(opt_state),
            "key": np.asarray(key),
        }
        meta = {"stage": stage_step[0], "step": stage_step[1], "rng": rng.bit_generator.state, "val": vstate}
        self.manager.save(0 if latest is None else latest + 1,
                          args=ocp.args.Composite(state=ocp.args.PyTreeSave(state), meta=ocp.args.JsonSave(meta)))

    def restore(self) -> dict | None:
        """The latest checkpoint as host values: ``stage``, ``step``, ``params`` and
        ``opt_state`` (state dicts; ``opt_state`` None at a stage's start), ``key``, ``rng`` and
        ``val`` (the sampler's and the validation state, None where not recorded); None when
        there is no checkpoint."""
        latest = self.manager.latest_step()
        if latest is None:
            return self._restore_legacy() if self.legacy.exists() else None
        saved = self.manager.item_metadata(latest)["state"].tree
        as_numpy = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), saved)
        got = self.manager.restore(latest, args=ocp.args.Composite(
            state=ocp.args.PyTreeRestore(restore_args=as_numpy), meta=ocp.args.JsonRestore()))
        meta = got["meta"]
        return {"stage": int(meta["stage"]), "step": int(meta["step"]), "rng": meta["rng"], "val": meta["val"],
                **got["state"]}

    def _restore_legacy(self) -> dict:
        raw = serialization.msgpack_restore(self.legacy.read_bytes())
        return {"stage": int(raw["stage"]), "step": int(raw["step"]), "params": raw["params"],
                "opt_state": raw["opt_state"], "key": np.asarray(raw["key"]),
                "rng": json.loads(raw["rng"]) if raw.get("rng") else None,
                "val": json.loads(raw["val"]) if raw.get("val") else None}

    def close(self) -> None:
        self.manager.close()


def train(config: TrainConfig, *, progress: bool = True, data: TrainingSet | None = None) -> dict:
    """Run (or resume) the staged training; returns the final parameters (numpy arrays).

    In a multi-process run (:func:`initialize_distributed` first) every process calls this with
    the same config and archives; process 0 alone writes the log, the config, the parameter
    files and shows progress, all of them write the checkpoints together (:class:`Checkpoints`)."""
    dp = DataParallel()
    dp.check(config.stages)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    if dp.primary:
        (out / "config.json").write_text(json.dumps(config.to_json(), indent=2))
    data = TrainingSet.load(config.data, config) if data is None else data
    val = TrainingSet.load(config.val_data, config) if config.val_data else None
    validate = make_validation(config.cycle) if val is not None else None
    checkpoints = Checkpoints(out)
    log = open(out / "log.jsonl", "a") if dp.primary else None
    try:
        return _train_loop(config, dp, checkpoints, log, data, val, validate, progress)
    finally:
        checkpoints.close()
        if log is not None:
            log.close()


def _train_loop(config: TrainConfig, dp: DataParallel, checkpoints: Checkpoints, log, data, val, validate,
                progress: bool) -> dict:
    out = Path(config.out)
    restored = checkpoints.restore()
    key = jax.random.PRNGKey(config.seed)
    params = init_params(key, data.models[0], config.cycle)
    if config.init is not None and restored is None:
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
    state = {"stage": 0, "step": 0, "opt_state": None}
    if restored is not None:
        state.update(stage=restored["stage"], step=restored["step"], opt_state=restored["opt_state"])
        params = serialization.from_state_dict(params, restored["params"])
        key = restored["key"]
    # the window sampler's state is checkpointed, so a resumed run draws exactly the windows an
    # uninterrupted one would have (checkpoints without it: reseeded from the stage and step)
    rng = np.random.default_rng(config.seed + 1000 * state["stage"] + state["step"])
    if restored is not None and restored["rng"]:
        rng.bit_generator.state = restored["rng"]
    # validation bookkeeping (best MPJPE and its stage/step, checks without improvement)
    vstate = {"best": None, "stage": None, "step": None, "bad": 0}
    if restored is not None and restored["val"]:
        vstate = restored["val"]
    best = {}  # the best parameters validated by this process (host values), for an early stop
    params = dp.replicate(params)
    key = jnp.asarray(key)

    def write_log(rec: dict) -> None:
        if log is not None:
            log.write(json.dumps(rec) + "\n")
            log.flush()

    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover
        tqdm = None
    for si in range(state["stage"], len(config.stages)):
        stage = config.stages[si]
        optimizer = make_optimizer(stage, params, config.clip_grad_norm)
        opt_state = optimizer.init(_host(params))
        start = 0
        if si == state["stage"] and state["opt_state"] is not None:
            opt_state = serialization.from_state_dict(opt_state, state["opt_state"])
            start = state["step"]
        opt_state = dp.replicate(opt_state)
        stage_cycle = dataclasses.replace(config.cycle, **stage.cycle)
        step_fn = make_step(stage, stage_cycle, optimizer, config.truncate_gradient, mesh=dp.mesh)
        show = progress and dp.primary
        bar = tqdm(total=stage.steps, initial=start, desc=stage.name, disable=not show) if tqdm else None
        t0 = time.time()
        checks = validate is not None and "tpnet" in STAGE_TRAINS[stage.name]
        vbatches = _validation_windows(val, config.val_windows, stage.batch, stage.frames) if checks else []

        def check(params, step, vbatches=vbatches, stage=stage):
            """Validate (every process, on its own copy of the parameters); returns True when the
            stage should stop early."""
            host = _host(params)
            tot = [validate(host, m, d) for m, d in vbatches]
            mpjpe = 1000.0 * float(sum(a for a, _ in tot)) / max(float(sum(b for _, b in tot)), 1.0)
            if vstate["best"] is None or mpjpe < vstate["best"]:
                vstate.update(best=mpjpe, stage=stage.name, step=step, bad=0)
                best["params"] = host
                if dp.primary:
                    save_params(out / "params_best.msgpack", host)
            else:
                vstate["bad"] += 1
            write_log({"stage": stage.name, "step": step, "val_mpjpe_mm": round(mpjpe, 3),
                       "best_mm": round(vstate["best"], 3)})
            return config.patience > 0 and vstate["bad"] >= config.patience

        if start == 0:
            vstate["bad"] = 0
            if checks:  # the starting point (a fine-tuning run's init, or the previous stage's end)
                check(params, 0)
        for it in range(start, stage.steps):
            model, batch = dp.split_rows(data.sample(rng, stage.batch, stage.frames))
            key, sub = jax.random.split(key)
            params, opt_state, loss, terms, gnorm = step_fn(params, opt_state, model, batch, dp.replicate(sub))
            if (it + 1) % config.log_every == 0 or it + 1 == stage.steps:
                rec = {"stage": stage.name, "step": it + 1, "loss": float(loss), "grad_norm": float(gnorm),
                       "time_s": round(time.time() - t0, 2), **{k: float(v) for k, v in terms.items()}}
                if not np.isfinite(rec["loss"]):
                    raise FloatingPointError(f"non-finite loss at stage {stage.name} step {it + 1}: {rec}")
                write_log(rec)
                if bar:
                    bar.set_postfix(loss=f"{rec['loss']:.4g}")
            if bar:
                bar.update(1)
            last = it + 1 == stage.steps
            if checks and ((it + 1) % config.val_every == 0 or last) and check(params, it + 1) and not last:
                last = True  # early stop: go on from the best parameters (of before a resume: their file)
                kept = best.get("params") or load_params(out / "params_best.msgpack")
                params = dp.replicate(serialization.from_state_dict(_host(params), kept))
                write_log({"stage": stage.name, "step": it + 1, "early_stop": True, "best_step": vstate["step"]})
            if (it + 1) % config.checkpoint_every == 0 or last:
                nxt = (si + 1, 0) if last else (si, it + 1)
                checkpoints.save(nxt, params, None if last else opt_state, key, rng, vstate)
            if last:
                break
        if bar:
            bar.close()
        if dp.primary:
            save_params(out / f"params_{stage.name}.msgpack", params)
    if dp.primary:
        save_params(out / "params.msgpack", params)
    return _host(params)
