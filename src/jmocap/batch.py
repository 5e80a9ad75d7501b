"""Batch reconstruction of clip archives: ``jmocap reconstruct INPUT OUTPUT``.

The functional core is :func:`reconstruct_chunk`: one fixed-length chunk of one clip, with the
dynamic state (:class:`~jmocap.cycle.CycleState`) carried in and out, so that a clip of any
length runs in bounded memory as a sequence of chunks. :func:`reconstruct_chunks` is its
``jax.jit(jax.vmap(...))`` over a batch of clips; the batch axis is sharded over every local
device. Everything else in this module is host-side orchestration around it:

* **inputs** (:func:`open_sources`): a jmocap clip archive (folder / ``.zip`` / ``.tar`` with
  ``manifest.jsonl``), or a folder / ``.zip`` / ``.tar`` of loose files in any format that
  :func:`jmocap.data.formats.read_clip` reads (jmocap clip ``.npz``, OpenPose JSON folders,
  COCO / MMPose JSON, VideoPose3D ``.npz`` - one clip per sequence - and keypoint arrays), each
  with its camera sidecar when there is one;
* **batching** (:func:`chunk_plan`, :class:`Reconstructor`): a clip of T frames runs as chunks
  of ``chunk`` frames, the last one padded up to a multiple of ``bucket`` (the frame mask marks
  padding); clips with the same chunk plan are batched together, ``batch`` clips per device, so
  every call has one of a few shapes and each shape compiles once;
* **outputs** (:class:`ResultWriter`): one ``.npz`` per clip (schema ``jmocap-result-1``,
  docs/formats.md), written atomically, then its line in ``manifest.jsonl`` (flushed and
  fsynced); a re-run skips the clips whose line says ``ok`` and whose file is there with the
  recorded size. Clips that cannot be read, or whose reconstruction is not finite, get a
  ``failed`` line naming file, frame and field, and the run goes on.

Chunking is exact. TPNet is causal with a window of ``W = config.nets.window`` frames, but its
receptive field is longer: C_T reads a window of per-frame features that include C_P's pose,
and C_P's pose at each of those frames has a window of its own, so frame t depends on the
keypoints of frames ``t - 2(W - 1) .. t``. Each chunk is therefore given the ``2W - 1`` frames
of keypoints before it as history (one more than the receptive field, for the
backward-difference velocity of the kinematic mode), and the history's outputs are dropped.
Before the first frame of a clip the first frame is repeated, which is what
:func:`jmocap.cycle.causal_windows` does for a whole clip; the dynamic state is carried from
chunk to chunk. Chunked and whole-clip reconstructions therefore agree to float32 rounding
(tests/test_batch.py).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import sys
import tarfile
import tempfile
import time
import zipfile
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache, partial
from pathlib import Path, PurePosixPath
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec

import jmocap
from jmocap import physics as P
from jmocap.cycle import (
    ClipInputs,
    CycleConfig,
    CycleState,
    finite_difference_velocity,
    init_params,
    simulate,
    target_pose,
)
from jmocap.data import formats
from jmocap.data.archive import (
    ARCHIVE_META,
    MANIFEST,
    Archive,
    ArchiveError,
    ArchiveWriter,
    _atomic_write,
    _sha256,
    npz_bytes,
)
from jmocap.data.clip import Clip, FormatError
from jmocap.model import DEFAULT_MODEL_PATH, Model, load_model
from jmocap.motion import Motion

Array = jnp.ndarray

RESULT_FORMAT = "jmocap-result-1"
SUMMARY = "summary.json"
DEFAULT_HEIGHT_M = 1.75  # the nominal height of models/mjcf/humanoid.xml (load_model() unscaled)
#: per-frame result fields, (T, ...) float32
MOTION_FIELDS = ("q", "qd", "tau", "grf", "contact_prob", "target_q", "keypoints3d")


class ReconstructionError(ValueError):
    """A reconstruction that produced non-finite values (never written as a result)."""


# =========================================================================================
# the functional core
# =========================================================================================


def history_length(config: CycleConfig) -> int:
    """Frames of keypoints a chunk needs before its first frame: TPNet's receptive field
    ``2 (W - 1)`` plus one (see the module docstring)."""
    return 2 * config.nets.window - 1


@struct.dataclass
class ChunkResult:
    """Per-frame results of one chunk (a batch adds a leading axis)."""

    motion: Motion  # (L, ...)
    keypoints3d: Array  # (L, J, 3) world-frame joints of motion.q in the config's layout


def reconstruct_chunk(
    params: dict,
    model: Model,
    inputs: ClipInputs,
    carry: CycleState,
    first: Array,
    config: CycleConfig,
    history: int,
) -> tuple[CycleState, ChunkResult]:
    """One chunk of one clip: ``inputs`` holds ``history + L`` frames, the chunk's L frames
    preceded by the ``history`` frames before them (``inputs.mask[history:]`` marks the real
    chunk frames). ``carry`` is the dynamic state at the end of the previous chunk; where
    ``first`` is True (the clip's first chunk) the state starts at rest at the first target pose,
    as in :func:`jmocap.cycle.reconstruct`. Returns the state after the chunk's last real frame
    and the chunk's L frames of results.
    """
    H = history
    tp = target_pose(params, model, inputs, config)
    q_hat = tp.q_hat[H:]
    prob = jax.nn.sigmoid(tp.contact_logits[H:])
    mask = jnp.asarray(inputs.mask)[H:]
    if config.kinematic_only:
        qd = finite_difference_velocity(model, tp.q_hat, inputs.fps)[H:]
        zeros = jnp.zeros_like(qd)
        motion = Motion(q_hat, qd, zeros, jnp.zeros((*prob.shape, 3), qd.dtype), prob, q_hat, mask)
        state = carry
    else:
        fresh = CycleState(q_hat[0], jnp.zeros_like(carry.qd), jnp.zeros_like(carry.grf))
        init = jax.tree.map(lambda a, b: jnp.where(first, a, b), fresh, carry)
        state, out = simulate(params, model, q_hat, prob, mask, inputs.fps, config, init=init)
        motion = Motion(out.q, out.qd, out.tau, out.grf, prob, q_hat, mask)
    kp3d = jax.vmap(lambda q: P.keypoints(model, q, config.layout))(motion.q)
    return state, ChunkResult(motion, kp3d)


@partial(jax.jit, static_argnames=("config", "history"))
def reconstruct_chunks(
    params: dict,
    models: Model,
    inputs: ClipInputs,
    carry: CycleState,
    first: Array,
    *,
    config: CycleConfig,
    history: int,
) -> tuple[CycleState, ChunkResult]:
    """:func:`reconstruct_chunk` over a batch of clips (leading axis of everything but
    ``params``): one compilation per chunk shape."""
    return jax.vmap(lambda m, i, c, f: reconstruct_chunk(params, m, i, c, f, config, history))(
        models, inputs, carry, first
    )


def chunk_plan(num_frames: int, chunk: int, bucket: int) -> tuple[int, ...]:
    """The padded chunk lengths of a clip: full chunks of ``chunk`` frames, then the rest
    rounded up to a multiple of ``bucket`` (at most ``chunk``)."""
    if num_frames < 1 or chunk < 1 or bucket < 1:
        raise ValueError(f"need num_frames, chunk, bucket >= 1, got {num_frames}, {chunk}, {bucket}")
    full, rest = divmod(num_frames, chunk)
    last = (min(chunk, -(-rest // bucket) * bucket),) if rest else ()
    return (chunk,) * full + last


def chunk_frames(num_frames: int, start: int, length: int, history: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame indices (history + length,) of the chunk starting at ``start`` (clamped to the clip:
    the first frame repeats before it, the last after it) and which of them are real frames."""
    idx = np.arange(start - history, start + length)
    return np.clip(idx, 0, num_frames - 1), (idx >= 0) & (idx < num_frames)


def _stack(trees):
    return jax.tree.map(lambda *xs: np.stack(xs), *trees)


# =========================================================================================
# the engine: groups of clips on all local devices
# =========================================================================================


class Reconstructor:
    """Reconstructs clips in batches of ``batch`` clips per device, chunk by chunk.

    ``params`` and ``config`` are fixed for the life of the object (the compiled code is cached
    per chunk shape by :func:`reconstruct_chunks`); characters are scaled to each clip's
    ``height_m`` (rounded to ``height_bucket_m``; :data:`DEFAULT_HEIGHT_M` when the clip has
    none), loaded once per height.
    """

    def __init__(
        self,
        params: dict,
        config: CycleConfig,
        *,
        chunk: int = 256,
        bucket: int = 64,
        batch: int = 8,
        height_bucket_m: float = 0.01,
        devices: Sequence[jax.Device] | None = None,
    ):
        if min(chunk, bucket, batch) < 1:
            raise ValueError(f"chunk, bucket and batch must be >= 1, got {chunk}, {bucket}, {batch}")
        self.config = config
        self.chunk, self.bucket, self.batch = int(chunk), int(bucket), int(batch)
        self.height_bucket_m = float(height_bucket_m)
        self.devices = list(devices) if devices is not None else jax.devices()
        mesh = Mesh(np.array(self.devices), ("clips",))
        self._rows = NamedSharding(mesh, PartitionSpec("clips"))
        self.params = jax.device_put(params, NamedSharding(mesh, PartitionSpec()))
        self.group_size = self.batch * len(self.devices)
        self.history = history_length(config)

    def model_height(self, clip: Clip) -> float:
        """The height (m) of the character a clip is reconstructed with."""
        if clip.height_m is None:
            return DEFAULT_HEIGHT_M
        step = self.height_bucket_m
        return round(round(clip.height_m / step) * step, 6) if step > 0 else float(clip.height_m)

    def model(self, height_m: float) -> Model:
        return _character(height_m)

    def plan(self, clip: Clip) -> tuple[int, ...]:
        return chunk_plan(clip.num_frames, self.chunk, self.bucket)

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
        rows = list(clips) + [clips[0]] * (self.group_size - len(clips))
        H, G = self.history, self.group_size
        # every row's keypoints over the whole plan at once, history in front; chunk c is then
        # the slice [start_c, start_c + H + L_c) (chunk_frames of each chunk)
        kp, real = [], []
        for c in rows:
            idx, r = chunk_frames(c.num_frames, 0, sum(plan), H)
            kp.append(np.asarray(c.keypoints, np.float32)[idx])
            real.append(r)
        kp, real = np.stack(kp), np.stack(real)
        whole = _stack([ClipInputs.from_clip(c).replace(keypoints=None, mask=None) for c in rows])
        models, whole = jax.device_put(
            (_stack([self.model(self.model_height(c)) for c in rows]), whole), self._rows
        )
        nq, nv = models.qpos0.shape[1], models.dof_armature.shape[1]
        carry = jax.device_put(
            CycleState(np.zeros((G, nq), np.float32), np.zeros((G, nv), np.float32),
                       np.zeros((G, 4, 3), np.float32)),
            self._rows,
        )
        fetched, pending, start = [], None, 0
        for c, length in enumerate(plan):
            window = slice(start, start + H + length)
            keypoints, mask, first = jax.device_put(
                (kp[:, window], real[:, window], np.full(G, c == 0)), self._rows
            )
            carry, res = reconstruct_chunks(
                self.params, models, whole.replace(keypoints=keypoints, mask=mask), carry, first,
                config=self.config, history=H,
            )
            if pending is not None:  # fetch the previous chunk while this one runs
                fetched.append(_fields(jax.device_get(pending)))
            pending, start = res, start + length
        fetched.append(_fields(jax.device_get(pending)))
        return [
            {k: np.concatenate([f[k][i] for f in fetched])[: c.num_frames] for k in MOTION_FIELDS}
            for i, c in enumerate(clips)
        ]


@lru_cache(maxsize=256)
def _character(height_m: float) -> Model:
    """The humanoid scaled to ``height_m`` (immutable, so shared by every engine)."""
    return load_model(height_m=None if height_m == DEFAULT_HEIGHT_M else height_m, with_mjx=False)


def _fields(res: ChunkResult) -> dict[str, np.ndarray]:
    m = res.motion
    return dict(
        q=m.q, qd=m.qd, tau=m.tau, grf=m.grf, contact_prob=m.contact_prob, target_q=m.target_q,
        keypoints3d=res.keypoints3d,
    )


# =========================================================================================
# checks, identities and the result file
# =========================================================================================


def check_clip(clip: Clip, config: CycleConfig, where: str) -> None:
    """What the pipeline needs beyond a valid clip (raises :class:`FormatError`)."""
    if clip.layout != config.layout:
        raise FormatError(
            f"{where}: field 'layout': the clip's keypoints are {clip.layout!r}, the parameters "
            f"were trained on {config.layout!r}"
        )
    if not (clip.keypoints[..., 2] > 0).any():
        raise FormatError(
            f"{where}: field 'keypoints': confidence is 0 for every joint of every frame "
            f"(nothing detected in {clip.num_frames} frames)"
        )


def check_finite(result: dict[str, np.ndarray], where: str) -> None:
    """Raise :class:`ReconstructionError` naming the first non-finite field and frame."""
    for k in MOTION_FIELDS:
        a = result[k]
        bad = ~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
        if bad.any():
            raise ReconstructionError(
                f"{where}: frame {int(np.argmax(bad))}: field {k!r}: the reconstruction is not "
                f"finite ({int(bad.sum())} of {a.shape[0]} frames); no result written"
            )


def params_sha256(params) -> str:
    """Identity of a parameter pytree: sha256 over its leaf paths, shapes and float32 values."""
    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        a = np.ascontiguousarray(np.asarray(leaf, np.float32))
        h.update(f"{jax.tree_util.keystr(path)}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def model_sha256(path: str | os.PathLike = DEFAULT_MODEL_PATH) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def check_params(params, config: CycleConfig) -> None:
    """Raise ``ValueError`` when ``params`` do not have the shapes ``config`` implies."""
    model = load_model(with_mjx=False)
    want = jax.eval_shape(lambda: init_params(jax.random.PRNGKey(0), model, config))
    got_leaves = {jax.tree_util.keystr(p): np.shape(x) for p, x in jax.tree_util.tree_flatten_with_path(params)[0]}
    for p, x in jax.tree_util.tree_flatten_with_path(want)[0]:
        k = jax.tree_util.keystr(p)
        if k not in got_leaves:
            raise ValueError(f"the parameters have no {k} (shape {x.shape}) that the config needs")
        if tuple(got_leaves[k]) != tuple(x.shape):
            raise ValueError(
                f"the parameters do not fit the config: {k} has shape {tuple(got_leaves[k])}, "
                f"the config needs {tuple(x.shape)} (pass the config they were trained with: --config)"
            )


def config_json(config: CycleConfig) -> str:
    return json.dumps(dataclasses.asdict(config), sort_keys=True)


def result_arrays(
    clip: Clip,
    result: dict[str, np.ndarray],
    *,
    height_m: float,
    identity: dict[str, str],
    source: str,
    assumed: Sequence[str] = (),
) -> dict[str, np.ndarray]:
    """The arrays of a ``jmocap-result-1`` file (docs/formats.md)."""
    extr = ClipInputs.from_clip(clip).extrinsics  # the clip's, or the default camera
    out = {
        "format": np.array(RESULT_FORMAT),
        "name": np.array(clip.name),
        "source": np.array(source),
        **{k: np.asarray(result[k], np.float32) for k in MOTION_FIELDS},
        "keypoints2d": np.asarray(clip.keypoints, np.float32),
        "fps": np.array(clip.fps, np.float64),
        "height_m": np.array(height_m, np.float64),
        "layout": np.array(clip.layout),
        "intrinsics": np.asarray(clip.intrinsics, np.float64),
        "image_size": np.asarray(clip.image_size, np.int64),
        "extrinsics": np.asarray(extr, np.float64),
        "assumed": np.array(json.dumps(list(assumed))),
    }
    out.update({k: np.array(v) for k, v in identity.items()})
    return out


def assumed_fields(clip: Clip) -> list[str]:
    """Which camera / subject values of a clip are defaults rather than data."""
    out = list(clip.meta.get("assumed", []))
    if clip.meta.get("assumed_image_size"):
        out.append("image_size")
    if clip.extrinsics is None:
        out.append("extrinsics")
    if clip.height_m is None:
        out.append("height_m")
    return out


class ResultWriter(ArchiveWriter):
    """The output folder: result files plus the archive manifest and settings
    (:class:`jmocap.data.archive.ArchiveWriter`'s crash-safe appends and resume)."""

    def done(self, name: str, *, bvh: bool = False) -> bool:
        """Whether ``name`` has a finished result: an ``ok`` line whose file exists with the
        recorded size (and, with ``bvh``, its BVH file). Failed clips are retried."""
        e = self.entries.get(name)
        if e is None or e["status"] != "ok":
            return False
        path = self.root / e["file"]
        if not path.is_file() or path.stat().st_size != e.get("bytes"):
            return False
        return not bvh or bool(e.get("bvh")) and (self.root / e["bvh"]).is_file()

    def add_result(self, name: str, arrays: dict[str, np.ndarray], **extra: Any) -> dict[str, Any]:
        """Write ``<name>.npz`` atomically, then its manifest line; returns the line."""
        parts = PurePosixPath(name).parts
        if not parts or name.startswith("/") or any(p in ("..", ".") for p in parts):
            raise ArchiveError(f"clip name {name!r} cannot be a file name under the output folder")
        data = npz_bytes(arrays)
        rel = f"{name}.npz"
        path = self.root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        _atomic_write(path, data)
        entry = {"name": name, "file": rel, "status": "ok", "bytes": len(data), "sha256": _sha256(data)}
        entry.update(extra)
        self._append(entry)
        return entry


# =========================================================================================
# inputs
# =========================================================================================


@dataclass(frozen=True)
class Source:
    """One clip of the input: ``name`` (the result's path stem under OUTPUT, and the resume
    key), ``where`` (for messages) and ``load`` (reads and validates it)."""

    name: str
    where: str
    load: Callable[[], Clip]


_CONTAINERS = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tar.xz")
_NOT_CLIPS = {"camera.json", ARCHIVE_META, SUMMARY}


def _is_container(path: Path) -> bool:
    return path.is_file() and path.name.lower().endswith(_CONTAINERS)


@contextmanager
def open_sources(
    path: str | os.PathLike,
    *,
    image_size: Sequence[int] | None = None,
    exclude: str | os.PathLike | None = None,
) -> Iterator[list[Source]]:
    """The clips of an input (a context manager: a ``.zip`` / ``.tar`` of loose files is
    extracted to a temporary folder for its duration).

    * a jmocap clip archive (``manifest.jsonl`` in the folder / zip / tar): its written clips;
    * a folder (or a zip / tar of one): every clip under it (:func:`scan_folder`);
    * a single clip file or OpenPose folder.

    ``image_size`` is the ``(width, height)`` assumed for clips whose file and sidecar give none;
    ``exclude``: a folder inside the input that holds no clips (the output).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(path)
    if (path.is_dir() and (path / MANIFEST).is_file()) or (_is_container(path) and _has_manifest(path)):
        with Archive(path) as archive:
            yield [
                Source(e["name"], f"{path}:{e['file']}", partial(archive.load, e["name"]))
                for e in archive.ok
            ]
        return
    if _is_container(path):
        with tempfile.TemporaryDirectory(prefix="jmocap-input-") as tmp:
            _extract(path, Path(tmp))
            yield scan_folder(Path(tmp), image_size=image_size, label=f"{path}:")
        return
    yield scan_folder(path, image_size=image_size, exclude=exclude)


def _has_manifest(path: Path) -> bool:
    if path.name.lower().endswith(".zip"):
        with zipfile.ZipFile(path) as z:
            return any(PurePosixPath(n).name == MANIFEST for n in z.namelist())
    with tarfile.open(path) as t:
        return any(PurePosixPath(n).name == MANIFEST for n in t.getnames())


def _extract(path: Path, dest: Path) -> None:
    """Extract a zip / tar, refusing members that would land outside ``dest``."""
    if path.name.lower().endswith(".zip"):
        with zipfile.ZipFile(path) as z:
            for n in z.namelist():
                if not (dest / n).resolve().is_relative_to(dest.resolve()):
                    raise ArchiveError(f"{path}: member {n!r} points outside the archive")
            z.extractall(dest)
    else:
        with tarfile.open(path) as t:
            t.extractall(dest, filter="data")


def scan_folder(
    root: str | os.PathLike,
    *,
    image_size: Sequence[int] | None = None,
    label: str | None = None,
    exclude: str | os.PathLike | None = None,
) -> list[Source]:
    """Every clip under ``root``, in sorted path order: a folder holding ``*_keypoints.json``
    files is one OpenPose clip; every other ``.npz`` / ``.npy`` / ``.json`` file is one clip
    (a VideoPose3D ``.npz`` one per sequence), except camera sidecars (``*.camera.json``,
    ``camera.json``) and ``archive.json`` / ``summary.json``. Hidden files are skipped.

    Names are paths relative to ``root`` without the suffix (``walk/take1.json`` ->
    ``walk/take1``); ``label`` replaces ``root`` in messages (e.g. the zip file's name).
    ``exclude`` is a folder not to look into (the output folder, when it is inside the input).
    """
    root = Path(root)
    skip = Path(exclude).resolve() if exclude is not None else None
    prefix = label if label is not None else ""
    found: list[tuple[str, Path]] = []

    def walk(d: Path):
        entries = sorted(d.iterdir())
        if any(p.is_file() and p.name.endswith("_keypoints.json") for p in entries):
            found.append((d.name if d == root else d.relative_to(root).as_posix(), d))
            return
        for p in entries:
            if p.name.startswith("."):
                continue
            if p.is_dir():
                if skip is None or p.resolve() != skip:
                    walk(p)
            elif p.suffix.lower() in (".npz", ".npy") or (
                p.suffix.lower() == ".json" and p.name not in _NOT_CLIPS and not p.name.endswith(".camera.json")
            ):
                found.append((p.relative_to(root).with_suffix("").as_posix(), p))

    if root.is_dir():
        walk(root)
    else:
        found.append((root.stem, root))
    counts: dict[str, int] = {}
    for name, _ in found:
        counts[name] = counts.get(name, 0) + 1
    sources: list[Source] = []
    vp3d = _LastFile()
    for name, p in found:
        if counts[name] > 1:  # walk.json and walk.npz: keep the suffix in the name
            name = p.relative_to(root).as_posix() if p != root else p.name
        if label is None:
            where, relabel = str(p), None
        else:
            where = prefix + (p.relative_to(root).as_posix() if p != root else p.name)
            relabel = partial(_relabel, old=str(root) + os.sep, new=prefix)
        seqs = _vp3d_sequences(p)
        if seqs is None:
            sources.append(Source(name, where, _guarded(partial(_load_path, p, image_size), relabel)))
        else:
            for seq in seqs:
                load = partial(vp3d.load, p, seq, image_size)
                sources.append(Source(f"{name}/{seq}", f"{where}[{seq}]", _guarded(load, relabel)))
    return sources


def _relabel(msg: str, old: str, new: str) -> str:
    return msg.replace(old, new)


def _guarded(load: Callable[[], Clip], relabel) -> Callable[[], Clip]:
    if relabel is None:
        return load

    def run():
        try:
            return load()
        except FormatError as e:
            raise type(e)(relabel(str(e))) from None

    return run


def _has_camera(path: Path) -> bool:
    return formats.sidecar_path(path).is_file() or (path.is_dir() and (path / "camera.json").is_file())


def _with_image_size(kp: formats.Keypoints2D, image_size) -> formats.Keypoints2D:
    if kp.image_size is not None or image_size is None:
        return kp
    return kp.replace(image_size=tuple(int(v) for v in image_size), meta={**kp.meta, "assumed_image_size": True})


def _load_path(path: Path, image_size) -> Clip:
    """:func:`jmocap.data.formats.read_clip`, with ``image_size`` assumed when neither the
    file nor a sidecar gives one."""
    if image_size is None or _has_camera(path) or (path.suffix == ".npz" and formats.is_clip_file(path)):
        return formats.read_clip(path)
    return _with_image_size(formats.read_keypoints(path), image_size).to_clip()


def _vp3d_sequences(path: Path) -> list[str] | None:
    """The sequence names of a VideoPose3D file, or None when ``path`` is not one (or is
    unreadable: then its single source reports the error)."""
    if path.suffix.lower() != ".npz" or not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as npz:
            if "positions_2d" not in npz.files:
                return None
        return [kp.name for kp in formats.iter_videopose3d(path)]
    except Exception:  # noqa: BLE001 - reported when the source is loaded
        return None


class _LastFile:
    """The sequences of the last VideoPose3D file read (sources of one file are consecutive)."""

    def __init__(self):
        self.path, self.seqs = None, {}

    def load(self, path: Path, seq: str, image_size) -> Clip:
        if self.path != path:
            self.path, self.seqs = None, {}  # (a failed read leaves nothing behind)
            self.seqs, self.path = {kp.name: kp for kp in formats.iter_videopose3d(path)}, path
        side = formats.sidecar_path(path)
        kp = self.seqs[seq]
        if side.is_file():
            return kp.to_clip(camera_json=side)
        return _with_image_size(kp, image_size).to_clip()


# =========================================================================================
# the archive run
# =========================================================================================


@dataclass(frozen=True)
class BatchOptions:
    """Options of :func:`reconstruct_archive` (see ``jmocap reconstruct --help``)."""

    chunk: int = 256  # frames per chunk (memory is bounded by batch x chunk frames)
    bucket: int = 64  # the last chunk of a clip is padded to a multiple of this
    batch: int = 8  # clips per device per call
    height_bucket_m: float = 0.01  # characters are scaled to heights on this grid
    image_size: tuple[int, int] | None = None  # assumed (width, height) when a clip has none
    bvh: bool = False  # also write <name>.bvh (jmocap.export.write_bvh)
    max_clips: int | None = None  # process at most this many clips this run
    pool: int = 0  # clips held while waiting for a full batch (0: 16 batches)


@dataclass
class _Item:
    source: Source
    clip: Clip
    seconds: float  # reading time


def run_identity(params, config: CycleConfig) -> dict[str, str]:
    return {
        "config": config_json(config),
        "params_sha256": params_sha256(params),
        "model_sha256": model_sha256(),
        "version": jmocap.__version__,
    }


def reconstruct_archive(
    input: str | os.PathLike,
    output: str | os.PathLike,
    params: dict,
    config: CycleConfig,
    options: BatchOptions = BatchOptions(),
    *,
    progress: Callable[[int], Any] | None = None,
    devices: Sequence[jax.Device] | None = None,
) -> dict[str, Any]:
    """Reconstruct every clip of ``input`` into ``output`` (resuming); returns the summary
    (also written to ``output/summary.json``).

    ``progress(total)`` makes a progress bar (``.update(clips, frames)``, ``.close()``).
    Raises :class:`~jmocap.data.archive.ArchiveError` when ``output`` holds results of other
    parameters / config.
    """
    t0 = time.perf_counter()
    identity = run_identity(params, config)
    settings = {
        "engine": "jmocap.batch",
        "format": RESULT_FORMAT,
        **{k: identity[k] for k in ("config", "params_sha256", "model_sha256")},
        "height_bucket_m": options.height_bucket_m,
        "image_size": list(options.image_size) if options.image_size else None,
    }
    write_bvh = _bvh_writer() if options.bvh else None
    engine = Reconstructor(
        params, config, chunk=options.chunk, bucket=options.bucket, batch=options.batch,
        height_bucket_m=options.height_bucket_m, devices=devices,
    )
    run = {"ok": 0, "failed": 0, "frames": 0}
    with (
        open_sources(input, image_size=options.image_size, exclude=output) as sources,
        ResultWriter(output, settings) as writer,
        ThreadPoolExecutor(1, thread_name_prefix="jmocap-write") as io,
    ):
        todo = [s for s in sources if not writer.done(s.name, bvh=options.bvh)]
        skipped = len(sources) - len(todo)
        if options.max_clips is not None:
            todo = todo[: options.max_clips]
        bar = progress(len(todo)) if progress is not None else None
        # Every manifest line, counter and progress update happens on the one `io` thread, in
        # submission order, so results are written while the next batch computes.
        inflight: deque[Future] = deque()

        def submit(fn, *args, **kwargs):
            inflight.append(io.submit(fn, *args, **kwargs))
            while len(inflight) > 2 * engine.group_size:  # bounded: at most ~2 batches queued
                inflight.popleft().result()

        def record_failure(source: Source, error: BaseException, seconds: float, **extra):
            writer.add_failure(source.name, _message(error, source.where), source=source.where,
                               seconds=round(seconds, 4), **extra)
            run["failed"] += 1
            if bar is not None:
                bar.update(1)

        def write_result(it: _Item, res: dict[str, np.ndarray], share: float):
            t = time.perf_counter()
            clip, src = it.clip, it.source
            try:
                check_finite(res, src.where)
                height = engine.model_height(clip)
                arrays = result_arrays(clip, res, height_m=height, identity=identity, source=src.where,
                                       assumed=assumed_fields(clip))
                extra = {}
                if write_bvh is not None:
                    extra["bvh"] = _write_bvh(write_bvh, writer.root, src.name, engine.model(height),
                                              res["q"], clip.fps)
                writer.add_result(
                    src.name, arrays, frames=clip.num_frames, fps=clip.fps, layout=clip.layout,
                    height_m=height, source=src.where, chunks=len(engine.plan(clip)),
                    seconds=round(it.seconds + share + time.perf_counter() - t, 4), **extra,
                )
            except Exception as e:  # noqa: BLE001 - a batch run records failures and goes on
                record_failure(src, e, it.seconds + share + time.perf_counter() - t, frames=clip.num_frames)
                return
            run["ok"] += 1
            run["frames"] += clip.num_frames
            if bar is not None:
                bar.update(1, clip.num_frames)

        def compute(group: list[_Item]):
            t = time.perf_counter()
            try:
                results = engine.run_group([it.clip for it in group])
            except Exception as e:  # noqa: BLE001
                share = (time.perf_counter() - t) / len(group)
                for it in group:
                    submit(record_failure, it.source, e, it.seconds + share, frames=it.clip.num_frames)
                return
            share = (time.perf_counter() - t) / len(group)
            for it, res in zip(group, results, strict=True):
                submit(write_result, it, res, share)

        pending: dict[tuple[int, ...], list[_Item]] = {}
        capacity = options.pool or 16 * engine.group_size
        for src, clip, seconds in _read_ahead(todo, config, depth=engine.group_size):
            if isinstance(clip, BaseException):
                submit(record_failure, src, clip, seconds)
                continue
            plan = engine.plan(clip)
            group = pending.setdefault(plan, [])
            group.append(_Item(src, clip, seconds))
            if len(group) == engine.group_size:
                compute(pending.pop(plan))
            elif sum(map(len, pending.values())) > capacity:  # bounded memory: run the fullest
                compute(pending.pop(max(pending, key=lambda k: len(pending[k]))))
        for plan in sorted(pending, key=lambda k: (len(k), k)):
            compute(pending[plan])
        while inflight:
            inflight.popleft().result()  # re-raises what could not even be recorded
        if bar is not None:
            bar.close()
        names = [s.name for s in sources]
        entries = [writer.entries[n] for n in names if n in writer.entries]
    elapsed = time.perf_counter() - t0
    ok = [e for e in entries if e["status"] == "ok"]
    summary = {
        "input": str(input),
        "output": str(output),
        "clips": len(names),
        "ok": len(ok),
        "failed": len(entries) - len(ok),
        "pending": len(names) - len(entries),
        "frames": int(sum(e.get("frames", 0) for e in ok)),
        "run": {
            **run,
            "skipped": skipped,
            "seconds": round(elapsed, 3),
            "clips_per_s": round((run["ok"] + run["failed"]) / elapsed, 4) if elapsed > 0 else None,
            "frames_per_s": round(run["frames"] / elapsed, 2) if elapsed > 0 else None,
        },
        "failures": [{"name": e["name"], "error": e.get("error")} for e in entries if e["status"] != "ok"][:100],
        "devices": [str(d) for d in engine.devices],
        "options": {**dataclasses.asdict(options), "image_size": settings["image_size"]},
        "params_sha256": identity["params_sha256"],
        "version": jmocap.__version__,
    }
    _atomic_write(Path(output) / SUMMARY, (json.dumps(summary, indent=2) + "\n").encode())
    return summary


def _read_ahead(sources: Sequence[Source], config: CycleConfig, depth: int):
    """``(source, clip or the exception that reading it raised, seconds)`` in order, read
    ``depth`` clips ahead on a thread (file reads and decompression overlap the compute)."""

    def load(src: Source):
        t = time.perf_counter()
        try:
            clip = src.load()
            check_clip(clip, config, src.where)
        except Exception as e:  # noqa: BLE001 - recorded as the clip's failure
            clip = e
        return clip, time.perf_counter() - t

    with ThreadPoolExecutor(1, thread_name_prefix="jmocap-read") as ex:
        queue: deque = deque()
        for src in sources:
            queue.append((src, ex.submit(load, src)))
            if len(queue) > depth:
                src0, fut = queue.popleft()
                yield (src0, *fut.result())
        while queue:
            src0, fut = queue.popleft()
            yield (src0, *fut.result())


def _message(error: BaseException, where: str) -> str:
    """A failure message that names the file (readers' errors already do)."""
    text = str(error)
    if isinstance(error, FormatError | ReconstructionError) or text.startswith(where):
        return text
    if isinstance(error, FileNotFoundError):
        return f"{where}: file not found: {error}"
    return f"{where}: {type(error).__name__}: {text}"


def _bvh_writer():
    try:
        from jmocap.export import write_bvh
    except ImportError as e:
        raise RuntimeError(f"--bvh needs jmocap.export.write_bvh, which is not available: {e}") from None
    return write_bvh


def _write_bvh(write_bvh, root: Path, name: str, model: Model, q: np.ndarray, fps: float) -> str:
    rel = f"{name}.bvh"
    write_bvh(root / rel, model, np.asarray(q), fps)  # atomic (temp file + os.replace)
    return rel


# =========================================================================================
# parameters and config
# =========================================================================================


def load_run_params(params_path: str | os.PathLike | None = None, config: str | None = None):
    """``(params, CycleConfig)``: the shipped weights or a msgpack file, with ``config`` (JSON
    text or a JSON file: CycleConfig fields, a training ``config.json`` or the shipped config
    file, all read as overrides) applied on top. Without ``config``, a params file gets the
    ``config.json`` next to it (a training run's folder) or the defaults."""
    from jmocap.weights import cycle_config_from_json, default_params, load_params

    if params_path is None:
        params, base = default_params()
    else:
        params = load_params(params_path)
        base = CycleConfig()
        beside = Path(params_path).with_name("config.json")
        if config is None and beside.is_file():
            config = str(beside)
    if config is not None:
        text = Path(config).read_text() if not config.lstrip().startswith("{") else config
        try:
            over = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"--config: not valid JSON: {e}") from None
        if not isinstance(over, dict):
            raise ValueError("--config: must be a JSON object")
        over = over.get("cycle", over)
        d = dataclasses.asdict(base)
        nets = {**d.pop("nets"), **over.pop("nets", {})}
        unknown = sorted(set(over) - set(d)) + sorted(set(nets) - {f.name for f in dataclasses.fields(base.nets)})
        if unknown:
            raise ValueError(f"--config: unknown CycleConfig fields {unknown}")
        base = cycle_config_from_json({**d, **over, "nets": nets})
    return params, base


# =========================================================================================
# command line (the parser is in jmocap.cli)
# =========================================================================================


def progress_bar(enabled: bool = True):
    """A factory ``total -> bar`` of text progress bars showing clips/s and frames/s."""
    from jmocap.cli import Progress

    class Bar(Progress):
        def _draw(self, now: float) -> None:
            el = max(now - self.t0, 1e-9)
            width = 24
            frac = self.n / self.total if self.total else 1.0
            eta = el / self.n * (self.total - self.n) if self.n else 0.0
            self.stream.write(
                f"\r{self.label} {self.n}/{self.total} [{'#' * int(round(frac * width)):<{width}}] "
                f"{self.n / el:.2f} clips/s {self.frames / el:.0f} frames/s {el:.0f}s ETA {eta:.0f}s "
            )
            self.stream.flush()

    return lambda total: Bar(total, "reconstruct", enabled=enabled)


def run_cli(args) -> int:
    """``jmocap reconstruct``: 0 when every clip has a result, 1 when some failed, 2 on bad
    arguments."""
    import dataclasses as dc

    if args.cache_dir and not jax.config.jax_compilation_cache_dir:
        jax.config.update("jax_compilation_cache_dir", args.cache_dir)
    try:
        params, config = load_run_params(args.params, args.config)
        if args.kinematic_only:
            config = dc.replace(config, kinematic_only=True)
        check_params(params, config)
        options = BatchOptions(
            chunk=args.chunk, bucket=args.bucket, batch=args.batch, image_size=args.image_size,
            bvh=args.bvh, max_clips=args.max_clips,
        )
        summary = reconstruct_archive(
            args.input, args.output, params, config, options, progress=progress_bar(not args.quiet)
        )
    except (FileNotFoundError, ValueError, RuntimeError) as e:  # ArchiveError is a ValueError
        print(f"jmocap reconstruct: {e}", file=sys.stderr)
        return 2
    r = summary["run"]
    print(
        f"jmocap reconstruct: {summary['ok']}/{summary['clips']} clips ok, {summary['failed']} failed "
        f"({r['ok']} done and {r['failed']} failed this run, {r['skipped']} already done); "
        f"{r['frames']} frames in {r['seconds']:.1f} s ({r['clips_per_s'] or 0:.2f} clips/s, "
        f"{r['frames_per_s'] or 0:.0f} frames/s) -> {args.output}"
    )
    for f in summary["failures"][:10]:
        print(f"  failed: {f['error']}", file=sys.stderr)
    return 0 if summary["failed"] == 0 and summary["pending"] == 0 else 1


__all__ = [
    "DEFAULT_HEIGHT_M",
    "MOTION_FIELDS",
    "RESULT_FORMAT",
    "BatchOptions",
    "ChunkResult",
    "ReconstructionError",
    "Reconstructor",
    "ResultWriter",
    "Source",
    "check_clip",
    "check_finite",
    "check_params",
    "chunk_frames",
    "chunk_plan",
    "history_length",
    "load_run_params",
    "open_sources",
    "params_sha256",
    "reconstruct_archive",
    "reconstruct_chunk",
    "reconstruct_chunks",
    "result_arrays",
    "run_cli",
    "scan_folder",
]
