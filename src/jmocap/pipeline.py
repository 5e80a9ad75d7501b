"""The compute core of batch reconstruction: any registered method, chunked, ``jit(vmap)``-ed and
sharded over the local devices.

:func:`reconstruct_chunk` runs one fixed-length chunk of one clip with the method's state carried
in and out, so a clip of any length runs in bounded memory as a sequence of chunks;
:func:`reconstruct_chunks` is its ``jax.jit(jax.vmap(...))`` over a batch of clips (one
compilation per method, config and chunk shape; the characters are arguments).
:class:`Reconstructor` groups clips of equal chunk plans and shards each batch over every local
device.

An archive run has one config, so the engine compiles it in: the config's traced parameters
(gains, friction, ...) become constants of the program, which XLA may fold. This is the fastest
form, and it keeps batch results bit-identical to those made before the parameters became
traceable (``methods.<name>.reconstruct`` under a user's ``jax.jit`` traces them instead: the two
agree to float32 rounding). Use the methods' functions directly to change or differentiate
the parameters without recompiling.

Chunking is exact. A method needs ``method.history(config)`` frames of keypoints before a chunk
(TPNet's receptive field: C_T reads a window of per-frame features that include C_P's pose,
whose own window reaches further back, so frame t depends on frames ``t - 2(W - 1) .. t``; one
more frame serves the backward-difference velocity). Before a clip's first frame the first frame
is repeated, which is what :func:`jmocap.methods.stages.causal_windows` does for a whole clip;
the dynamic state is carried from chunk to chunk. A method with a fixed latency also reads
``method.lookahead(config)`` frames after the chunk (after a clip's last frame the last frame is
repeated, marked not real). Chunked and whole-clip reconstructions agree to float32 rounding
(tests/test_pipeline.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jmocap import methods
from jmocap import physics as P
from jmocap.constants import DEFAULT_HEIGHT_M
from jmocap.data.clip import Clip
from jmocap.inputs import ClipInputs
from jmocap.inputs import stack as stack_inputs
from jmocap.model import Model, character
from jmocap.motion import Motion

Array = jnp.ndarray



@struct.dataclass
class ChunkResult:
    """Per-frame results of one chunk (a batch adds a leading axis)."""

    motion: Motion  # (L, ...)
    keypoints3d: Array  # (L, J, 3) world-frame joints of motion.q in the config's layout


def reconstruct_chunk(params, model: Model, inputs: ClipInputs, carry, first, config, *, method: str,
                      history: int) -> tuple[Any, ChunkResult]:
    """One chunk of one clip with ``method`` (a registered name): ``inputs`` holds
    ``history + L + lookahead`` frames, the chunk's L frames preceded by the ``history`` frames
    before them and followed by the method's ``lookahead(config)`` frames after them
    (``inputs.mask[history:history + L]`` marks the real chunk frames). ``carry`` is the method's state at
    the end of the previous chunk; where ``first`` is True (the clip's first chunk) the method
    starts afresh. Returns the state after the chunk's last real frame and the chunk's results."""
    m = methods.get_method(method)
    carry, motion = m.reconstruct_chunk(params, model, inputs, carry, first, config, history)
    kp3d = jax.vmap(lambda q: P.keypoints(model, q, config.layout))(motion.q)
    return carry, ChunkResult(motion, kp3d)


#: clips per tile of a batch (:func:`reconstruct_chunks`): measured fastest on a 2-core CPU for
#: ``pip`` (16-32) and faster than one ``vmap`` over 128 clips for ``physcap`` too
#: (docs/performance.md, "Tiles")
TILE = 32


@partial(jax.jit, static_argnames=("config", "method", "history", "tile", "groups"))
def reconstruct_chunks(params, models: Model, inputs: ClipInputs, carry, first, *, config, method: str,
                       history: int, tile: int = TILE, groups: int = 1) -> tuple[Any, ChunkResult]:
    """:func:`reconstruct_chunk` over a batch of clips (leading axis of everything but
    ``params``); ``config`` is compiled in (hashable: Python numbers, see :func:`constant_config`).

    The batch is ``groups`` equal groups of consecutive clips (one per device the batch is
    sharded over), each run in tiles of ``tile`` clips (``lax.map`` over the tiles, ``vmap``
    within one; 0: one ``vmap`` over the group): the same results, and on a CPU faster,
    because a tile's working set stays in cache. The groups are ``vmap``-ed, so a group's tiles
    run on its own device."""
    def one(m, i, c, f):
        return reconstruct_chunk(params, m, i, c, f, config, method=method, history=history)

    return tiled_vmap(one, (models, inputs, carry, first), tile, groups)


def tiled_vmap(fn, args: tuple, tile: int, groups: int = 1):
    """``jax.vmap(fn)(*args)`` (leading axis B of every leaf of ``args``), computed as ``groups``
    equal groups of consecutive rows, ``vmap``-ed (so a batch sharded over ``groups`` devices
    keeps each group on its device), each in tiles of ``tile`` rows (``lax.map``, a sequential
    loop over tiles with ``vmap`` within one). The same values; on a CPU a tile's working set
    stays in cache, which for the reconstruction methods is faster than one ``vmap`` over
    hundreds of clips (docs/performance.md, "Tiles"). ``tile`` 0 or at least B / groups: one ``vmap``."""
    B = jax.tree.leaves(args)[0].shape[0]
    if groups < 1 or B % groups:
        raise ValueError(f"a batch of {B} rows cannot be split into {groups} equal groups")
    if not 0 < tile < B // groups:
        return jax.vmap(fn)(*args)
    split = jax.tree.map(lambda x: x.reshape(groups, B // groups, *x.shape[1:]), args)
    out = jax.vmap(lambda a: jax.lax.map(lambda r: fn(*r), a, batch_size=tile))(split)
    return jax.tree.map(lambda x: x.reshape(B, *x.shape[2:]), out)


def constant_config(config):
    """``config`` with every traced leaf as a Python number (hashable, so it can be a static jit
    argument and is compiled in as constants)."""
    return jax.tree.map(lambda x: float(np.asarray(x)) if np.ndim(x) == 0 else x, config)


def chunk_plan(num_frames: int, chunk: int, bucket: int) -> tuple[int, ...]:
    """The padded chunk lengths of a clip: full chunks of ``chunk`` frames, then the rest
    rounded up to a multiple of ``bucket`` (at most ``chunk``)."""
    if num_frames < 1 or chunk < 1 or bucket < 1:
        raise ValueError(f"need num_frames, chunk, bucket >= 1, got {num_frames}, {chunk}, {bucket}")
    full, rest = divmod(num_frames, chunk)
    last = (min(chunk, -(-rest // bucket) * bucket),) if rest else ()
    return (chunk,) * full + last


def set_host_devices(n: int) -> bool:
    """Ask for ``n`` host CPU devices (0: one per core) before JAX starts its backends.

    XLA's CPU backend runs one device's program on one thread, so the batch engine, which shards
    its clips over every local device, uses all cores only with several host devices. Returns
    whether the setting took effect: not when a backend is already running (e.g. the command is
    called from a process that has used JAX, or ``XLA_FLAGS`` already force a device count and
    ``n`` is 0); an explicit ``n > 1`` that cannot be applied raises ``ValueError``.
    """
    import os

    if n == 0 and "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return False  # the user's XLA_FLAGS already say how many
    want = n or (os.cpu_count() or 1)
    if want <= 1:
        return False
    try:
        jax.config.update("jax_num_cpu_devices", want)
    except RuntimeError as e:  # backends already initialised in this process
        if n > 1 and len(jax.devices("cpu")) != want:
            raise ValueError(f"--host-devices {n}: JAX is already running in this process ({e})") from e
        return False
    return True


def clip_plan(method, num_frames: int, chunk: int, bucket: int) -> tuple[int, ...]:
    """The chunk lengths of a clip of ``num_frames`` for ``method`` (a registered
    :class:`~jmocap.methods.base.Method` or its name): a causal method's chunks
    (:func:`chunk_plan`); a non-causal one (``trajopt``) sees its whole clip at once, padded to a
    multiple of ``bucket`` (it splits long clips into windows itself). Clips with one plan are
    batched together (one compilation per plan)."""
    method = methods.get_method(method) if isinstance(method, str) else method
    if not method.causal:
        return (-(-num_frames // bucket) * bucket,)
    return chunk_plan(num_frames, chunk, bucket)


def chunk_frames(num_frames: int, start: int, length: int, history: int,
                 lookahead: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Frame indices (history + length + lookahead,) of the chunk starting at ``start`` (clamped
    to the clip: the first frame repeats before it, the last after it) and which of them are
    real frames."""
    idx = np.arange(start - history, start + length + lookahead)
    return np.clip(idx, 0, num_frames - 1), (idx >= 0) & (idx < num_frames)


def _stack(trees):
    return jax.tree.map(lambda *xs: np.stack(xs), *trees)


def subject(clip: Clip) -> tuple[float | None, float | None]:
    """The ``(height_m, mass_kg)`` a clip is reconstructed with (``None``: the nominal character)."""
    return clip.height_m, clip.mass_kg


def subject_model(clip: Clip) -> Model:
    """The character a clip is reconstructed (and scored) with: jmocap's humanoid scaled to the
    clip's height and mass when it gives them (:func:`jmocap.model.character`)."""
    return character(*subject(clip))


def subject_height(clip: Clip) -> float:
    """The height (m) of the character of a clip."""
    return DEFAULT_HEIGHT_M if clip.height_m is None else float(clip.height_m)


def padded_length(frames: int) -> int:
    """The length a whole clip is padded to for a one-off pass over it (the floor estimate): the
    smallest of 64, 96, 128, 192, 256, 384, ... (powers of two and their 1.5 multiples) that holds
    it, so an archive of any lengths compiles a few programs and pads by less than half."""
    n = 64
    while True:
        for cand in (n, n + n // 2):
            if cand >= frames:
                return cand
        n *= 2


#: where a clip's extrinsics came from (the result's ``extrinsics_source``)
EXTRINSICS_SOURCES = ("input", "estimated", "default")


class FloorEstimator:
    """The camera of clips without extrinsics, estimated from their 2D keypoints
    (:mod:`jmocap.methods.floor`: the floor seen from the person, TPNet and the per-frame fit in
    the camera frame).

    ``params`` and ``config`` are a video method's (its TPNet weights, layout and network sizes).
    :meth:`resolve` gives a clip without extrinsics the estimated camera, or the default camera
    (:func:`jmocap.camera.default_extrinsics`) where the estimate is not usable, and records which
    in ``meta["extrinsics_source"]`` (:data:`EXTRINSICS_SOURCES`) and the estimate in
    ``meta["camera_estimate"]``. One compilation per padded length (:func:`padded_length`)."""

    def __init__(self, params: dict, config, floor=None):
        from jmocap.methods import floor as F

        self.params = {"tpnet": params["tpnet"]}
        self.config = config
        self.floor = floor or F.FloorConfig()
        self._fn = jax.jit(F.estimate_floor)

    def estimate(self, clip: Clip):
        """The :class:`jmocap.methods.floor.FloorEstimate` of a clip (numpy), whatever its own
        extrinsics (they are not read)."""
        length = padded_length(clip.num_frames)
        inputs = ClipInputs.from_clip(clip.replace(extrinsics=None), length)
        est = self._fn(self.params, subject_model(clip), inputs, self.config, self.floor)
        return jax.device_get(est)

    def resolve(self, clip: Clip) -> Clip:
        """The clip with extrinsics: its own, else the estimate, else the default camera."""
        if clip.extrinsics is not None:
            return clip.replace(meta={**clip.meta, "extrinsics_source": "input"})
        est = self.estimate(clip)
        report = {
            "pitch_deg": round(float(est.pitch_deg), 3), "roll_deg": round(float(est.roll_deg), 3),
            "height_m": round(float(est.height_m), 4), "support": round(float(est.support), 4),
            "frames": int(est.frames),
        }
        if bool(est.usable):
            meta = {**clip.meta, "extrinsics_source": "estimated", "camera_estimate": report}
            return clip.replace(extrinsics=np.asarray(est.extrinsics, np.float64), meta=meta)
        report["reason"] = "the estimate is not usable (too few frames, or the fitted floor is implausible)"
        return clip.replace(meta={**clip.meta, "extrinsics_source": "default", "camera_estimate": report})


class Reconstructor:
    """Reconstructs clips with one method in batches of ``batch`` clips per device, chunk by chunk.

    ``params``, ``method`` and ``config`` are fixed for the life of the object (the compiled code
    is cached per chunk shape by :func:`reconstruct_chunks`); each clip gets its own character
    (:func:`subject_model`), passed as an array argument (no recompilation per subject).
    A device's ``batch`` clips run in tiles of ``tile`` (:func:`tiled_vmap`).
    """

    def __init__(
        self,
        params: dict,
        config,
        *,
        method: str = methods.DEFAULT_METHOD,
        chunk: int = 256,
        bucket: int = 64,
        batch: int = 8,
        devices: Sequence[jax.Device] | None = None,
        tile: int = TILE,
    ):
        if min(chunk, bucket, batch) < 1 or tile < 0:
            raise ValueError(f"chunk, bucket and batch must be >= 1 and tile >= 0, got {chunk}, {bucket}, "
                             f"{batch}, {tile}")
        self.method = methods.get_method(method)
        if not isinstance(config, self.method.config_type):
            raise TypeError(f"method {self.method.name!r} needs a {self.method.config_type.__name__}, "
                            f"got {type(config).__name__}")
        self.config = config
        self.chunk, self.bucket, self.batch, self.tile = int(chunk), int(bucket), int(batch), int(tile)
        self.devices = list(devices) if devices is not None else jax.devices()
        mesh = Mesh(np.array(self.devices), ("clips",))
        self._rows = NamedSharding(mesh, PartitionSpec("clips"))
        self.params = jax.device_put(params, NamedSharding(mesh, PartitionSpec()))
        self._config = constant_config(config)
        self.group_size = self.batch * len(self.devices)
        self.history = self.method.history(config)
        self.lookahead = self.method.lookahead(config)

    def plan(self, clip: Clip) -> tuple[int, ...]:
        """The clip's chunk lengths (:func:`clip_plan`)."""
        return clip_plan(self.method, clip.num_frames, self.chunk, self.bucket)

    def run(self, clips: Sequence[Clip]) -> list[dict[str, np.ndarray]]:
        """Results of any clips (in their order): grouped by chunk plan, ``group_size`` at a time."""
        out: list[dict | None] = [None] * len(clips)
        groups: dict[tuple[int, ...], list[int]] = {}
        for i, c in enumerate(clips):
            groups.setdefault(self.plan(c), []).append(i)
        for idx in groups.values():
            for s in range(0, len(idx), self.group_size):
                part = idx[s : s + self.group_size]
                for i, res in zip(part, self.run_group([clips[i] for i in part]), strict=True):
                    out[i] = res
        return out

    def run_group(self, clips: Sequence[Clip]) -> list[dict[str, np.ndarray]]:
        """Results of up to ``group_size`` clips sharing one chunk plan: per clip a dict of the
        :data:`MOTION_FIELDS` as (T, ...) float32 arrays. The batch is filled up with copies of
        the first clip (their results are dropped), so every call has the same shape."""
        if not 0 < len(clips) <= self.group_size:
            raise ValueError(f"a group has 1..{self.group_size} clips, got {len(clips)}")
        plan = self.plan(clips[0])
        if any(self.plan(c) != plan for c in clips):
            raise ValueError("the clips of a group must share one chunk plan")
        if self.method.host is not None:
            return self._run_host(clips, plan[0])
        rows = list(clips) + [clips[0]] * (self.group_size - len(clips))
        H, A, G = self.history, self.lookahead, self.group_size
        # every row's keypoints over the whole plan at once, history in front and lookahead
        # behind; chunk c is then the slice [start_c, start_c + H + L_c + A) (chunk_frames of
        # each chunk)
        kp, real, track = [], [], []
        for c in rows:
            idx, r = chunk_frames(c.num_frames, 0, sum(plan), H, A)
            kp.append(np.asarray(c.keypoints, np.float32)[idx])
            real.append(r)
            track.append(ClipInputs.from_clip(c).camera_track[idx])  # every frame's camera
        kp, real, track = np.stack(kp), np.stack(real), np.stack(track)
        whole = stack_inputs([ClipInputs.from_clip(c).replace(keypoints=None, mask=None, camera_track=None) for c in rows])
        models = _stack([subject_model(c) for c in rows])
        zero = self.method.init_carry(subject_model(rows[0]), self.config)
        carry = jax.tree.map(lambda a: np.zeros((G, *np.shape(a)), np.float32), zero)
        models, whole, carry = jax.device_put((models, whole, carry), self._rows)
        fetched, pending, start = [], None, 0
        for c, length in enumerate(plan):
            window = slice(start, start + H + length + A)
            keypoints, mask, cams, first = jax.device_put(
                (kp[:, window], real[:, window], track[:, window], np.full(G, c == 0)), self._rows
            )
            carry, res = reconstruct_chunks(
                self.params, models, whole.replace(keypoints=keypoints, mask=mask, camera_track=cams), carry, first,
                config=self._config, method=self.method.name, history=H, tile=self.tile, groups=len(self.devices),
            )
            if pending is not None:  # fetch the previous chunk while this one runs
                fetched.append(_fields(jax.device_get(pending)))
            pending, start = res, start + length
        fetched.append(_fields(jax.device_get(pending)))
        out = []
        for i, c in enumerate(clips):
            res = {k: np.concatenate([f[k][i] for f in fetched])[: c.num_frames] for k in fetched[0] if k != "diagnostics"}
            if "diagnostics" in fetched[-1]:  # per-clip scalars of the clip's last chunk
                res["diagnostics"] = {k: float(v[i]) for k, v in fetched[-1]["diagnostics"].items()}
            out.append(res)
        return out

    def _run_host(self, clips: Sequence[Clip], length: int) -> list[dict[str, np.ndarray]]:
        """A host-simulated method's (``Method.host``: ``mocon``) results of a group, whole clips
        padded to ``length``: no filler rows (the host runs clip by clip), keypoints in jitted JAX."""
        inputs = stack_inputs([ClipInputs.from_clip(c, length) for c in clips])
        models = [subject_model(c) for c in clips]
        motion = self.method.host(self.params, models, inputs, self.config)
        kp3d = _host_keypoints(_stack(models), jnp.asarray(motion.q), self.config.layout)
        res = jax.device_get(ChunkResult(motion, kp3d))
        fields = _fields(res)
        out = []
        for i, c in enumerate(clips):
            r = {k: np.asarray(v[i])[: c.num_frames] for k, v in fields.items() if k != "diagnostics"}
            if "diagnostics" in fields:
                r["diagnostics"] = {k: float(v[i]) for k, v in fields["diagnostics"].items()}
            out.append(r)
        return out


@partial(jax.jit, static_argnames=("layout",))
def _host_keypoints(models: Model, q: Array, layout: str) -> Array:
    return jax.vmap(lambda m, qs: jax.vmap(lambda x: P.keypoints(m, x, layout))(qs))(models, q)


def _fields(res: ChunkResult) -> dict[str, np.ndarray]:
    m = res.motion
    return dict(
        q=m.q, qd=m.qd, tau=m.tau, grf=m.grf, contact_prob=m.contact_prob, target_q=m.target_q,
        keypoints3d=res.keypoints3d,
        **({} if m.certified is None else {"certified": m.certified}),
        **({} if m.diagnostics is None else {"diagnostics": m.diagnostics}),
        **({} if m.camera_track is None else {"camera_track_estimated": m.camera_track}),
    )


__all__ = [
    "EXTRINSICS_SOURCES",
    "ChunkResult",
    "FloorEstimator",
    "padded_length",
    "set_host_devices",
    "Reconstructor",
    "TILE",
    "tiled_vmap",
    "chunk_frames",
    "chunk_plan",
    "clip_plan",
    "constant_config",
    "reconstruct_chunk",
    "reconstruct_chunks",
    "subject_height",
    "subject_model",
]
