"""Archive runs: ``jmocap reconstruct INPUT OUTPUT`` over thousands of clips, resumable.

Host-side orchestration around the compute core (:class:`jmocap.pipeline.Reconstructor`):

* **inputs** (:func:`jmocap.data.sources.open_sources`): every clip of a clip archive or a
  folder / ``.zip`` / ``.tar`` of loose files, read ahead on a thread, converted to the layout
  the parameters read (:func:`adapt_layout`: a COCO-17 or Human3.6M-17 clip reconstructs with
  BODY_25 weights, its missing joints marked missing) and validated (:func:`check_clip`);
* **batching**: clips with the same chunk plan are batched together, ``batch`` clips per device,
  so every call has one of a few shapes and each shape compiles once;
* **outputs** (:class:`jmocap.results.ResultWriter`): one ``.npz`` per clip (schema
  ``jmocap-result-1``, :mod:`jmocap.results`), written atomically, then its line in
  ``manifest.jsonl`` (flushed and fsynced); a re-run skips the clips whose line says ``ok`` and
  whose file is there with the recorded size. Clips that cannot be read, or whose reconstruction
  is not finite, get a ``failed`` line naming file, frame and field, and the run goes on.

Hostile or clumsy input (docs/formats.md, "Validation" and "Limits"): every clip is validated
completely before it joins a batch (:func:`check_clip`: the reader's checks, then
:func:`jmocap.data.validate.check_reconstructable`), and what is implausible but usable is
reconstructed with ``warnings`` in its manifest line and result; a batch that fails is retried
clip by clip, so only the culprit fails; input is read within :mod:`jmocap.data.limits`. The
output folder is locked for the run, a killed run's temporary files are removed when the next
starts, and SIGINT / SIGTERM (:class:`Interrupted`) end the run after the results already
computed are written, with ``summary.json`` saying so.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np

import jmocap
from jmocap import methods
from jmocap.data import limits as L
from jmocap.data.archive import ArchiveError
from jmocap.data.clip import Clip, FormatError
from jmocap.data.sources import SUMMARY, Source, open_sources
from jmocap.data.validate import check_reconstructable
from jmocap.io import atomic_write, remove_stale_temporaries
from jmocap.model import Model
from jmocap.pipeline import FloorEstimator, Reconstructor, subject_height, subject_model
from jmocap.results import (
    RESULT_FORMAT,
    ReconstructionError,
    ResultWriter,
    assumed_fields,
    check_finite,
    result_arrays,
)
from jmocap.subject import resolve_subject
from jmocap.weights import model_sha256, params_sha256


class Interrupted(BaseException):  # noqa: N818 - a signal, not an error (not caught by `except Exception`)
    """A run stopped by a signal (SIGINT: exit status 130, SIGTERM: 143)."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        self.exit_status = 128 + self.signum
        super().__init__(f"interrupted by {signal.Signals(self.signum).name}")


def adapt_layout(clip: Clip, config) -> tuple[Clip, list[str]]:
    """The clip in the layout the method's parameters read (``config.layout``): a clip in another
    layout is converted (:meth:`jmocap.data.clip.Clip.to_layout`: joints matched by the
    character's sites, midpoints derived, the rest missing), with a warning saying what was
    derived, absent and not used. Returns the clip and the warnings."""
    if clip.layout == config.layout:
        return clip, []
    converted = clip.to_layout(config.layout)
    from jmocap.layouts import conversion

    return converted, [conversion(clip.layout, config.layout).describe()]


def check_clip(clip: Clip, config, where: str) -> list[str]:
    """What the pipeline needs beyond a valid clip: raises :class:`FormatError` (file, frame,
    field) for a clip the method cannot take or that cannot give a meaningful reconstruction
    (:func:`~jmocap.data.validate.check_reconstructable`); returns the warnings."""
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
    return check_reconstructable(clip, where)


@dataclass(frozen=True)
class BatchOptions:
    """Options of :func:`reconstruct_archive` (see ``jmocap reconstruct --help``)."""

    chunk: int = 256  # frames per chunk (memory is bounded by batch x chunk frames)
    bucket: int = 64  # the last chunk of a clip is padded to a multiple of this
    batch: int = 8  # clips per device per call
    image_size: tuple[int, int] | None = None  # assumed (width, height) when a clip has none
    bvh: bool = False  # also write <name>.bvh (jmocap.export.write_bvh)
    max_clips: int | None = None  # process at most this many clips this run
    pool: int = 0  # clips held while waiting for a full batch (0: 16 batches)
    # the subject: a number (every clip), "auto" (the clip's own, else estimated from its 2D
    # evidence, else nominal) or "nominal" (the clip's own, else the 1.75 m character);
    # jmocap.subject.resolve_subject
    height_m: float | str = "auto"
    mass_kg: float | None = None  # every clip's mass (None: the clip's own, else nominal)
    # the camera of a clip without extrinsics: "estimate" (the floor seen from the person,
    # jmocap.methods.floor; the default camera where that is not usable) or "default"
    # (jmocap.camera.default_extrinsics); jmocap.pipeline.FloorEstimator
    camera: str = "estimate"
    # the terrain of every clip that carries none (jmocap.scene.Scene, in the world frame of the
    # clips' given extrinsics): a recording session's steps and platforms, measured once
    scene: Any = None


@dataclass
class _Item:
    source: Source
    clip: Clip
    seconds: float  # reading time
    warnings: list[str] = dataclasses.field(default_factory=list)


def run_identity(params, config, method: str) -> dict[str, str]:
    """What identifies a run's results: method, config, weights, character file, version."""
    return {
        "method": method,
        "config": json.dumps(methods.config_dict(config), sort_keys=True),
        "params_sha256": params_sha256(params),
        "model_sha256": model_sha256(),
        "version": jmocap.__version__,
    }


def run_settings(identity: dict[str, str], options: BatchOptions) -> dict[str, Any]:
    """The settings an output folder's ``archive.json`` records (a run with other settings is
    refused there): the result format, method, config, weights, character and the options that
    change results. Every engine (this one, :mod:`jmocap.batch_ray`) writes the same, so a run
    begun by one resumes with the other. Raises ValueError for an unknown ``options.camera``."""
    if options.camera not in ("estimate", "default"):
        raise ValueError(f"camera must be 'estimate' or 'default', got {options.camera!r}")
    settings = {
        "engine": "jmocap.batch",  # the output folder's layout (kept: folders written before resume)
        "format": RESULT_FORMAT,
        **{k: identity[k] for k in ("method", "config", "params_sha256", "model_sha256")},
        "image_size": list(options.image_size) if options.image_size else None,
    }
    # (only when not the default: output folders written before these options resume)
    if options.height_m != "auto":
        settings["height_m"] = options.height_m
    if options.mass_kg is not None:
        settings["mass_kg"] = options.mass_kg
    if options.camera != "estimate":
        settings["camera"] = options.camera
    if options.scene is not None:
        from jmocap.scene import scene_document

        settings["scene"] = scene_document(options.scene)
    return settings


def reconstruct_archive(
    input: str | os.PathLike,
    output: str | os.PathLike,
    params: dict,
    config,
    options: BatchOptions = BatchOptions(),
    *,
    method: str = methods.DEFAULT_METHOD,
    progress: Callable[[int], Any] | None = None,
    devices: Sequence[jax.Device] | None = None,
    limits: L.Limits | None = None,
) -> dict[str, Any]:
    """Reconstruct every clip of ``input`` into ``output`` with ``method`` (a registered method
    name; ``config`` its config) and ``params``, resuming; returns the summary (also written
    to ``output/summary.json``).

    ``progress(total)`` makes a progress bar (``.update(clips, frames)``, ``.close()``);
    ``limits`` bound what the input may cost (default: :class:`jmocap.data.limits.Limits`).
    Raises :class:`~jmocap.data.archive.ArchiveError` (one line) when ``input`` cannot be read
    as a whole or holds no clip, when ``output`` is not a writable folder, is being written by
    another run or holds results of other parameters / config; :class:`Interrupted` (or
    ``KeyboardInterrupt``) after a signal, once the finished results and ``summary.json`` are
    written.
    """
    with L.use(limits):
        return _reconstruct_archive(input, output, params, config, options, method=method,
                                    progress=progress, devices=devices)


def _reconstruct_archive(input, output, params, config, options, *, method, progress, devices):
    t0 = time.perf_counter()
    identity = run_identity(params, config, method)
    settings = run_settings(identity, options)
    write_bvh = _bvh_writer() if options.bvh else None
    engine = Reconstructor(
        params, config, method=method, chunk=options.chunk, bucket=options.bucket, batch=options.batch,
        devices=devices,
    )
    floor = FloorEstimator(engine.params, config) if options.camera == "estimate" else None
    run = {"ok": 0, "failed": 0, "frames": 0}
    interrupted: BaseException | None = None
    with contextlib.ExitStack() as stack:
        sources = stack.enter_context(open_sources(input, image_size=options.image_size, exclude=output))
        if not sources:  # before the output folder is made
            raise ArchiveError(
                f"{input}: no clips found"
                + (f" ({len(sources.skipped)} files skipped, e.g. {sources.skipped[0]['path']}: "
                   f"{sources.skipped[0]['reason']})" if getattr(sources, "skipped", None) else "")
            )
        writer = stack.enter_context(ResultWriter(stack.enter_context(_output_folder(output)), settings))
        io = stack.enter_context(ThreadPoolExecutor(1, thread_name_prefix="jmocap-write"))
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

        def record_failure_safely(source: Source, error: BaseException, seconds: float, **extra):
            # a failure must be recorded even when the message cannot be (e.g. a full disk)
            try:
                record_failure(source, error, seconds, **extra)
            except OSError as e:
                raise ArchiveError(f"{writer.root}: cannot write the manifest: {e}") from None

        def write_result(it: _Item, res: dict[str, np.ndarray], share: float):
            t = time.perf_counter()
            clip, src = it.clip, it.source
            try:
                arrays, extra = result_record(clip, res, engine, identity, src.where, it.warnings)
                if write_bvh is not None:
                    extra["bvh"] = _write_bvh(write_bvh, writer.root, src.name, subject_model(clip), res["q"], clip.fps)
                writer.add_result(src.name, arrays, seconds=round(it.seconds + share + time.perf_counter() - t, 4),
                                  **extra)
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
                if len(group) > 1:  # find the culprit: each clip alone, so only it fails
                    for it in group:
                        compute([it])
                    return
                share = time.perf_counter() - t
                submit(record_failure, group[0].source, e, group[0].seconds + share,
                       frames=group[0].clip.num_frames)
                return
            share = (time.perf_counter() - t) / len(group)
            for it, res in zip(group, results, strict=True):
                submit(write_result, it, res, share)

        pending: dict[tuple[int, ...], list[_Item]] = {}
        capacity = options.pool or 16 * engine.group_size
        try:
            with _signals_raise():
                for src, got, seconds in _read_ahead(todo, config, depth=engine.group_size, options=options,
                                                       floor=floor):
                    if isinstance(got, BaseException):
                        submit(record_failure_safely, src, got, seconds)
                        continue
                    clip, warnings = got
                    plan = engine.plan(clip)
                    group = pending.setdefault(plan, [])
                    group.append(_Item(src, clip, seconds, warnings))
                    if len(group) == engine.group_size:
                        compute(pending.pop(plan))
                    elif sum(map(len, pending.values())) > capacity:  # bounded memory: run the fullest
                        compute(pending.pop(max(pending, key=lambda k: len(pending[k]))))
                for plan in sorted(pending, key=lambda k: (len(k), k)):
                    compute(pending[plan])
        except (KeyboardInterrupt, Interrupted) as e:
            interrupted = e  # write what is computed, then the summary, then re-raise
        while inflight:
            inflight.popleft().result()  # re-raises what could not even be recorded
        if bar is not None:
            bar.close()
        names = [s.name for s in sources]
        entries = [writer.entries[n] for n in names if n in writer.entries]
        skipped_files = list(getattr(sources, "skipped", []))
    summary = archive_summary(input, output, names, entries, run, skipped, time.perf_counter() - t0,
                              skipped_files, interrupted, options, settings,
                              devices=[str(d) for d in engine.devices])
    atomic_write(Path(output) / SUMMARY, (json.dumps(summary, indent=2) + "\n").encode())
    if interrupted is not None:
        raise interrupted
    return summary


def result_record(clip: Clip, res: dict[str, np.ndarray], engine: Reconstructor, identity: dict[str, str],
                  where: str, warnings: Sequence[str]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A clip's result file arrays (:func:`jmocap.results.result_arrays`) and the fields of its
    manifest line (all but ``seconds`` and ``bvh``), from the engine's result ``res``; the result's
    method is the run's (``identity["method"]``: a variant's name, not its base method's). Raises
    :class:`~jmocap.results.ReconstructionError` (file, frame, field) for a non-finite result."""
    check_finite(res, where)
    height, model = subject_height(clip), subject_model(clip)
    arrays = result_arrays(
        clip, res, method=identity["method"], height_m=height, mass_kg=model.total_mass,
        forces_estimated=engine.method.estimates_forces, identity=identity, source=where,
        assumed=assumed_fields(clip), warnings=list(warnings),
        height_source=clip.meta.get("height_source"),
        extrinsics_source=clip.meta.get("extrinsics_source"),
    )
    extra: dict[str, Any] = {"frames": clip.num_frames, "fps": clip.fps, "layout": clip.layout,
                             "height_m": height, "source": where, "chunks": len(engine.plan(clip)),
                             "height_source": clip.meta.get("height_source"),
                             "extrinsics_source": clip.meta.get("extrinsics_source")}
    for key in ("camera_estimate", "layout_conversion", "height_estimate"):
        if clip.meta.get(key):
            extra[key] = clip.meta[key]
    if warnings:
        extra["warnings"] = list(warnings)
    if res.get("certified") is not None:  # per-frame QP certificates (e.g. ``pip``)
        extra["uncertified_frames"] = int(np.sum(~np.asarray(res["certified"], bool)))
    if res.get("diagnostics") is not None:  # a solver's per-clip report (e.g. ``trajopt``)
        extra["diagnostics"] = {k: round(float(v), 6) for k, v in res["diagnostics"].items()}
    return arrays, extra


def archive_summary(input, output, names, entries, run: dict, skipped: int, elapsed: float, skipped_files: list,
                    interrupted: BaseException | None, options: BatchOptions, settings: dict[str, Any],
                    **engine: Any) -> dict[str, Any]:
    """``summary.json`` of a 2D archive run (docs/formats.md): :func:`run_summary`, what the scan
    skipped, the signal that stopped it, its options and weights, then the ``engine``'s own
    fields (the local engine's ``devices``; :mod:`jmocap.batch_ray`'s ``engine`` and ``ray``)."""
    return {
        **run_summary(input, output, names, entries, run, skipped, elapsed),
        "skipped_files": len(skipped_files),
        "skipped": skipped_files[:100],
        "interrupted": None if interrupted is None else (
            "SIGINT" if isinstance(interrupted, KeyboardInterrupt) else signal.Signals(interrupted.signum).name
        ),
        **engine,
        "options": {**{f.name: getattr(options, f.name) for f in dataclasses.fields(options)},
                    "image_size": settings["image_size"], "scene": settings.get("scene")},
        "params_sha256": settings["params_sha256"],
        "version": jmocap.__version__,
    }


def run_summary(input, output, names, entries, run: dict, skipped: int, elapsed: float) -> dict[str, Any]:
    """The part of ``summary.json`` every archive run has (docs/formats.md): the counts over the
    input's clips ``names`` from the manifest ``entries``, this ``run``'s counts and rates
    (``skipped``: clips already done), the first 100 failures and the clips with warnings."""
    ok = [e for e in entries if e["status"] == "ok"]
    return {
        "input": str(input),
        "output": str(output),
        "clips": len(names),
        "ok": len(ok),
        "failed": len(entries) - len(ok),
        "pending": len(names) - len(entries),
        "frames": int(sum(e.get("frames", 0) for e in ok)),
        "uncertified_frames": int(sum(e.get("uncertified_frames", 0) for e in ok)),
        "run": {
            **run,
            "skipped": skipped,
            "seconds": round(elapsed, 3),
            "clips_per_s": round((run["ok"] + run["failed"]) / elapsed, 4) if elapsed > 0 else None,
            "frames_per_s": round(run["frames"] / elapsed, 2) if elapsed > 0 else None,
        },
        "failures": [{"name": e["name"], "error": e.get("error")} for e in entries if e["status"] != "ok"][:100],
        "warnings": sum(bool(e.get("warnings")) for e in ok),
    }


@contextlib.contextmanager
def _output_folder(output):
    """The output folder, created, checked writable and locked for the run (a second run on it
    fails at once); a killed run's temporary files in it are removed. Raises ArchiveError."""
    root = Path(output)
    if root.exists() and not root.is_dir():
        raise ArchiveError(f"{root}: the output exists and is not a folder")
    try:
        root.mkdir(parents=True, exist_ok=True)
        lock = open(root / ".jmocap.lock", "a+b")  # noqa: SIM115 - held for the run
    except OSError as e:
        raise ArchiveError(f"{root}: cannot write to the output folder: {e.strerror or e}") from None
    try:
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock
            fcntl = None
        if fcntl is not None:
            try:
                fcntl.flock(lock.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                raise ArchiveError(f"{root}: another jmocap run is writing to this folder") from None
        remove_stale_temporaries(root)
        if not os.access(root, os.W_OK | os.X_OK):
            raise ArchiveError(f"{root}: cannot write to the output folder (permission denied)")
        yield root
    finally:
        lock.close()


@contextlib.contextmanager
def _signals_raise():
    """SIGTERM raises :class:`Interrupted` in the main thread for the block (SIGINT already
    raises KeyboardInterrupt); outside the main thread nothing changes."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Interrupted(signum)

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def read_clip(src: Source, config, options: BatchOptions) -> tuple[Clip, list[str], list[str]]:
    """Read a source for a run: the clip with its subject resolved
    (:func:`jmocap.subject.resolve_subject`), in the parameters' layout (:func:`adapt_layout`),
    with ``options.scene`` where it has none, and checked (:func:`check_clip`). Returns the clip,
    the conversion's warnings and the check's; raises what reading or checking raises."""
    clip, warnings = adapt_layout(resolve_subject(src.load(), options.height_m, options.mass_kg), config)
    if options.scene is not None and clip.scene is None:
        if clip.extrinsics is None:
            raise FormatError(f"{src.where}: the scene given (--scene) is in the world frame of the "
                              "camera's extrinsics, and the clip has none (give its camera, or no scene)")
        clip = clip.replace(scene=options.scene)
    return clip, warnings, check_clip(clip, config, src.where)  # an unusable clip fails here, before any estimate


def place_camera(clip: Clip, config, floor: FloorEstimator | None, where: str,
                 checked: list[str]) -> tuple[Clip, list[str]]:
    """A read clip (:func:`read_clip`, its check's warnings ``checked``) with its camera: the
    floor estimated where it has no extrinsics and ``floor`` is given (checked again: the
    warnings of the estimated camera), else the input's or the default camera, recorded as the
    clip's ``extrinsics_source``."""
    if floor is not None and clip.extrinsics is None:
        clip = floor.resolve(clip)
        return clip, check_clip(clip, config, where)
    source = "input" if clip.extrinsics is not None else "default"
    return clip.replace(meta={**clip.meta, "extrinsics_source": source}), checked


def _read_ahead(sources: Sequence[Source], config, depth: int, options: BatchOptions = BatchOptions(),  # noqa: B008
                floor: FloorEstimator | None = None):
    """``(source, clip or the exception that reading it raised, seconds)`` in order, read
    ``depth`` clips ahead on a thread (file reads and decompression overlap the compute); each
    clip with its subject resolved (:func:`jmocap.subject.resolve_subject`), its camera (the
    floor estimated where it has no extrinsics, ``floor``; else the default camera) and checked."""

    def load(src: Source):
        t = time.perf_counter()
        try:
            clip, warnings, checked = read_clip(src, config, options)
            clip, checked = place_camera(clip, config, floor, src.where, checked)
            got = (clip, warnings + checked)
        except Exception as e:  # noqa: BLE001 - recorded as the clip's failure (RecursionError too)
            got = e
        return got, time.perf_counter() - t

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
    text = " ".join(str(error).split())  # one line
    if isinstance(error, FormatError | ReconstructionError | ArchiveError) and where.split("[")[0] in text:
        return text
    if text.startswith(where):
        return text
    if isinstance(error, FileNotFoundError):
        return f"{where}: file not found: {error.filename or text}"
    if isinstance(error, PermissionError):
        return f"{where}: permission denied: {error.filename or text}"
    if isinstance(error, MemoryError):
        return f"{where}: out of memory while reading or reconstructing the clip"
    if isinstance(error, FormatError | ReconstructionError | ArchiveError):
        return f"{where}: {text}"
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


__all__ = [
    "BatchOptions",
    "Interrupted",
    "adapt_layout",
    "archive_summary",
    "check_clip",
    "place_camera",
    "read_clip",
    "reconstruct_archive",
    "result_record",
    "run_identity",
    "run_settings",
]
