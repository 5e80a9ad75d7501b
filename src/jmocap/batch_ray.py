"""Archive runs on a Ray cluster: ``jmocap reconstruct INPUT OUTPUT --engine ray [--address ADDR]``.

The same run as :func:`jmocap.batch.reconstruct_archive`, its clips read and reconstructed by
Ray (an optional extra: ``pip install 'jmocap[ray]'``) on as many machines as the cluster has,
its results written by this process (the *driver*) exactly as the local engine writes them:

* **inputs**: the driver lists the input's clips (:func:`jmocap.data.sources.open_sources`) and
  drops those the output folder already has; the rest become a Ray Dataset of clip names. Reader
  actors (``readers``, one CPU each by default) open the same input by its path, read each clip
  and run the local engine's reading and checks (:func:`jmocap.batch.read_clip`: subject, layout,
  scene, :func:`~jmocap.batch.check_clip`) within the run's :mod:`~jmocap.data.limits`;
* **buckets**: the read clips are sorted by their chunk plan (:func:`jmocap.pipeline.clip_plan`),
  so each batch of ``batch`` clips the workers take shares one plan: the same shapes, and so the
  same compilations, as the local engine's groups;
* **compute**: worker actors (``workers``, each ``cpus_per_worker`` CPUs and ``gpus_per_worker``
  GPUs; on a shared GPU JAX's memory preallocation is switched off) each hold the method, its
  weights and jitted code (:class:`jmocap.pipeline.Reconstructor` over the worker's own devices):
  camera (:func:`jmocap.batch.place_camera`, the floor estimate where a clip has no extrinsics),
  reconstruction, and the result file's arrays and manifest fields
  (:func:`jmocap.batch.result_record`). A batch that fails is retried clip by clip, so only the
  culprit fails; a worker that dies is restarted by Ray and its batch run again;
* **outputs**: the driver writes each result as it arrives with the local engine's
  :class:`jmocap.results.ResultWriter` (atomic ``.npz``, then its fsynced ``manifest.jsonl``
  line) and the same ``archive.json`` settings (:func:`jmocap.batch.run_settings`). So a run
  begun by either engine resumes with either, and a clip's result file is the same bytes from
  both (tested). ``summary.json`` records ``"engine": "ray"``.

Every machine must see INPUT at the same path (a shared file system; the driver alone writes
OUTPUT) and have the same jmocap installed. docs/performance.md has the cluster set-up and the
scaling measured here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from jmocap import methods
from jmocap.batch import (
    BatchOptions,
    Interrupted,
    _message,
    _output_folder,
    _signals_raise,
    archive_summary,
    place_camera,
    read_clip,
    result_record,
    run_identity,
    run_settings,
)
from jmocap.data import limits as L
from jmocap.data.archive import ArchiveError
from jmocap.data.sources import SUMMARY, open_sources
from jmocap.io import atomic_write
from jmocap.results import ResultWriter

#: the sort key of a clip that could not be read (its failure passes through the workers)
_FAILED = ""


def _ray():
    try:
        import ray
    except ImportError:
        raise RuntimeError("--engine ray needs Ray: pip install 'jmocap[ray]'") from None
    return ray


@dataclasses.dataclass(frozen=True)
class RayOptions:
    """Where and how wide a Ray run is (see ``jmocap reconstruct --help``). A worker on CPUs only
    with ``cpus_per_worker`` >= 2 runs that many host devices (the local engine's
    ``--host-devices``)."""

    address: str | None = None  # a running cluster ("auto", "HOST:PORT", "ray://HOST:PORT"); None: a local one
    workers: int | None = None  # reconstruction actors (None: one per cpus_per_worker CPUs of the cluster)
    cpus_per_worker: float = 1.0
    gpus_per_worker: float = 0.0  # < 1: workers share a GPU (JAX's preallocation off)
    readers: int = 1  # reading actors (no CPU reserved: see _rows)


def _objects(items: list) -> np.ndarray:
    """A 1-D object array of ``items`` (tuples stay elements): a Ray Data column of Python objects."""
    out = np.empty(len(items), dtype=object)
    for i, x in enumerate(items):
        out[i] = x
    return out


def _plan_key(plan: tuple[int, ...]) -> str:
    """A sortable string of a chunk plan (equal plans, equal keys)."""
    return ",".join(f"{n:08d}" for n in plan)


class _Reader:
    """A Ray actor that reads clips by name (:func:`jmocap.batch.read_clip`) for the workers."""

    def __init__(self, input: str, exclude: str, cwd: str, config, options: BatchOptions, limits, method: str):
        # the driver's working directory, so that the input's path (and every message naming a
        # clip's file) is the one the user gave, as in the local engine
        if not os.path.isdir(cwd):
            raise FileNotFoundError(f"{input}: the run's folder {cwd} is not on this Ray node ({os.uname().nodename}): "
                                    "every node needs the input at the driver's path (a shared file system)")
        os.chdir(cwd)
        self._stack = contextlib.ExitStack()
        self._limits = limits
        with L.use(limits):
            sources = self._stack.enter_context(open_sources(input, image_size=options.image_size, exclude=exclude))
        self.sources = {s.name: s for s in sources}
        self.config, self.options = config, options
        self.method = methods.get_method(method)

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        from jmocap.pipeline import clip_plan

        keys, clips, errors, seconds = [], [], [], []
        for name in batch["name"]:
            src = self.sources[str(name)]
            t = time.perf_counter()
            try:
                with L.use(self._limits):
                    got = read_clip(src, self.config, self.options)
                keys.append(_plan_key(clip_plan(self.method, got[0].num_frames, self.options.chunk,
                                                self.options.bucket)))
                clips.append(got)
                errors.append("")
            except Exception as e:  # noqa: BLE001 - recorded as the clip's failure
                keys.append(_FAILED)
                clips.append(None)
                errors.append(_message(e, src.where))
            seconds.append(time.perf_counter() - t)
        return {"name": batch["name"], "where": batch["where"], "key": np.asarray(keys),
                "clip": _objects(clips), "error": np.asarray(errors), "seconds": np.asarray(seconds)}

    def __del__(self):
        with contextlib.suppress(Exception):
            self._stack.close()


class _Worker:
    """A Ray actor holding the method, its weights and compiled code: reconstructs a batch of
    read clips and returns each clip's result file arrays and manifest fields (or failure)."""

    def __init__(self, params, config, method: str, options: BatchOptions, identity: dict[str, str],
                 host_devices: int):
        if host_devices > 1:  # a CPU worker of several CPUs: one host device per CPU, as the local engine
            from jmocap.pipeline import set_host_devices

            set_host_devices(host_devices)
        from jmocap.pipeline import FloorEstimator, Reconstructor

        self.engine = Reconstructor(params, config, method=method, chunk=options.chunk, bucket=options.bucket,
                                    batch=options.batch)
        self.floor = FloorEstimator(self.engine.params, config) if options.camera == "estimate" else None
        self.config, self.options, self.identity = config, options, identity

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        n = len(batch["name"])
        out: dict[str, list] = {"status": [""] * n, "payload": [None] * n, "error": [""] * n,
                                "seconds": [float(s) for s in batch["seconds"]], "frames": [0] * n}
        groups: dict[str, list[tuple[int, Any, list[str], str]]] = {}
        for i in range(n):
            if batch["key"][i] == _FAILED:
                out["status"][i], out["error"][i] = "failed", str(batch["error"][i])
                continue
            t = time.perf_counter()
            clip, notes, checked = batch["clip"][i]  # (Ray carries Python objects between its actors)
            where = str(batch["where"][i])
            try:
                clip, checked = place_camera(clip, self.config, self.floor, where, checked)
            except Exception as e:  # noqa: BLE001 - a reading failure, as the local engine's (no frames)
                out["status"][i], out["error"][i] = "failed", _message(e, where)
                continue
            finally:
                out["seconds"][i] += time.perf_counter() - t
            out["frames"][i] = clip.num_frames
            groups.setdefault(str(batch["key"][i]), []).append((i, clip, notes + checked, where))
        for group in groups.values():
            for s in range(0, len(group), self.engine.group_size):
                self._compute(group[s:s + self.engine.group_size], out)
        return {"name": batch["name"], "status": np.asarray(out["status"]),
                "payload": _objects(out["payload"]), "error": np.asarray(out["error"]),
                "seconds": np.asarray(out["seconds"]), "frames": np.asarray(out["frames"])}

    def _compute(self, group, out) -> None:
        t = time.perf_counter()
        try:
            results = self.engine.run_group([clip for _, clip, _, _ in group])
        except Exception as e:  # noqa: BLE001
            if len(group) > 1:  # find the culprit: each clip alone, so only it fails
                for g in group:
                    self._compute([g], out)
                return
            i, _, _, where = group[0]
            out["status"][i], out["error"][i] = "failed", _message(e, where)
            out["seconds"][i] += time.perf_counter() - t
            return
        share = (time.perf_counter() - t) / len(group)
        for (i, clip, notes, where), res in zip(group, results, strict=True):
            t = time.perf_counter()
            try:
                arrays, extra = result_record(clip, res, self.engine, self.identity, where, notes)
                if self.options.bvh:
                    extra["bvh_bytes"] = _bvh_bytes(clip, res["q"])
                out["status"][i], out["payload"][i] = "ok", (arrays, extra)
            except Exception as e:  # noqa: BLE001
                out["status"][i], out["error"][i] = "failed", _message(e, where)
            out["seconds"][i] += share + time.perf_counter() - t


def _bvh_bytes(clip, q) -> bytes:
    """The clip's BVH file (:func:`jmocap.export.write_bvh`) as bytes, for the driver to write."""
    from jmocap.batch import _bvh_writer
    from jmocap.pipeline import subject_model

    write_bvh = _bvh_writer()
    with tempfile.TemporaryDirectory(prefix="jmocap-bvh-") as tmp:
        path = Path(tmp) / "clip.bvh"
        write_bvh(path, subject_model(clip), np.asarray(q), clip.fps)
        return path.read_bytes()


def reconstruct_archive_ray(
    input: str | os.PathLike,
    output: str | os.PathLike,
    params: dict,
    config,
    options: BatchOptions = BatchOptions(),  # noqa: B008
    ray_options: RayOptions = RayOptions(),  # noqa: B008
    *,
    method: str = methods.DEFAULT_METHOD,
    progress: Callable[[int], Any] | None = None,
    limits: L.Limits | None = None,
) -> dict[str, Any]:
    """:func:`jmocap.batch.reconstruct_archive` on a Ray cluster (module docstring): the same
    arguments, results, resume and errors, plus ``ray_options`` (where and how wide). Connects to
    ``ray_options.address`` (a running cluster) or starts a local one for the run. Returns the
    summary (also ``output/summary.json``, with ``"engine": "ray"`` and the cluster's resources).
    Raises RuntimeError (one line) when Ray itself fails mid-run (a lost node, a worker that died
    more often than Ray retries), after the finished results and the summary (its ``error``) are
    written: the same command resumes."""
    ray = _ray()
    t0 = time.perf_counter()
    identity = run_identity(params, config, method)
    settings = run_settings(identity, options)
    output = Path(output)
    run = {"ok": 0, "failed": 0, "frames": 0}
    interrupted: BaseException | None = None
    lost: BaseException | None = None
    started = False
    with contextlib.ExitStack() as stack:
        with L.use(limits):
            sources = stack.enter_context(open_sources(input, image_size=options.image_size, exclude=output))
        if not sources:
            raise ArchiveError(f"{input}: no clips found")
        writer = stack.enter_context(ResultWriter(stack.enter_context(_output_folder(output)), settings))
        todo = [s for s in sources if not writer.done(s.name, bvh=options.bvh)]
        skipped = len(sources) - len(todo)
        if options.max_clips is not None:
            todo = todo[: options.max_clips]
        where = {s.name: s.where for s in sources}
        bar = progress(len(todo)) if progress is not None else None
        if not ray.is_initialized():
            with warnings.catch_warnings():  # Ray starts its processes by fork + exec: no JAX state is shared
                warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
                ray.init(address=ray_options.address, include_dashboard=False, logging_level="warning")
            started = True
        resources = ray.cluster_resources()
        timing: dict[str, float] = {"start_s": round(time.perf_counter() - t0, 3)}
        try:
            if todo:
                with _signals_raise():
                    for row in _rows(ray, todo, input, output, params, config, method, options, ray_options,
                                     identity, limits, resources, timing):
                        timing.setdefault("first_result_s", round(time.perf_counter() - t0, 3))
                        _record(writer, row, where, options, run, bar)
        except (KeyboardInterrupt, Interrupted) as e:
            interrupted = e  # the results already written stay; the summary says so
        except ray.exceptions.RayError as e:  # the cluster itself failed (a node lost, retries spent)
            lost = e
        finally:
            if started:
                ray.shutdown()
        if bar is not None:
            bar.close()
        names = [s.name for s in sources]
        entries = [writer.entries[n] for n in names if n in writer.entries]
        skipped_files = list(getattr(sources, "skipped", []))
    # seconds from the run's start: Ray connected (start_s), the first result written
    # (first_result_s: reading, sorting, the workers' start and compilation); read_s: reading and sorting
    summary = archive_summary(
        input, output, names, entries, run, skipped, time.perf_counter() - t0, skipped_files, interrupted, options,
        settings, engine="ray", ray={**dataclasses.asdict(ray_options), "timing": timing, "cluster_resources": {
            k: v for k, v in resources.items() if k in ("CPU", "GPU", "memory")}},
    )
    if lost is not None:
        summary["error"] = " ".join(str(lost).split())[:2000]
    atomic_write(output / SUMMARY, (json.dumps(summary, indent=2) + "\n").encode())
    if interrupted is not None:
        raise interrupted
    if lost is not None:
        first = (str(lost).strip().splitlines() or [type(lost).__name__])[0]
        raise RuntimeError(f"{output}: the Ray run stopped ({type(lost).__name__}: {first}); the finished "
                           "results are written, run the same command again to resume") from None
    return summary


def _rows(ray, todo, input, output, params, config, method, options, ray_options, identity, limits,
          resources, timing: dict[str, float]):
    """The Ray Dataset pipeline (module docstring): names -> read clips -> sorted by plan -> results
    (``timing["read_s"]``: the seconds of reading and sorting)."""
    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False
    ctx.print_on_execution_start = False
    cpus = float(resources.get("CPU", 1.0))
    # (readers take no CPU of their own: reading is a small share, and it ends before the
    # compute starts, at the sort; a reader that waited for a CPU the workers hold would deadlock)
    workers = ray_options.workers or max(1, int(cpus // max(ray_options.cpus_per_worker, 1e-9)))
    if workers < 1 or ray_options.readers < 1:
        raise ValueError(f"workers and readers must be >= 1, got {workers}, {ray_options.readers}")
    names = [{"name": s.name, "where": s.where} for s in todo]
    ds = ray.data.from_items(names, override_num_blocks=max(1, min(len(names), 4 * ray_options.readers)))
    ds = ds.map_batches(
        _Reader, fn_constructor_kwargs=dict(input=str(input), exclude=str(output), cwd=os.getcwd(), config=config, options=options,
                                            limits=limits, method=method),
        batch_size=16, compute=ray.data.ActorPoolStrategy(size=ray_options.readers), num_cpus=0,
        batch_format="numpy",
    )
    # read and sorted to the end before a worker starts: the sort's tasks need CPUs that the
    # workers would otherwise hold (a deadlock on a cluster the workers fill)
    t = time.perf_counter()
    ds = ds.sort("key").materialize()
    timing["read_s"] = round(time.perf_counter() - t, 3)
    env = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"} if 0 < ray_options.gpus_per_worker < 1 else {}
    import jax

    if jax.config.jax_compilation_cache_dir:  # the driver's persistent compilation cache (--cache-dir), per node
        env["JAX_COMPILATION_CACHE_DIR"] = str(jax.config.jax_compilation_cache_dir)
    # (Ray Data restarts a worker that dies and runs its batch again: its actors' default
    # max_restarts / max_task_retries are -1)
    # a worker's devices: its GPUs, else one host device per CPU; each call fills them all
    # (options.batch clips per device, as the local engine's groups)
    gpus, host_devices = ray_options.gpus_per_worker, int(ray_options.cpus_per_worker)
    devices = max(1, int(gpus)) if gpus else max(1, host_devices)
    ds = ds.map_batches(
        _Worker, fn_constructor_kwargs=dict(params=params, config=config, method=method, options=options,
                                            identity=identity, host_devices=0 if gpus else host_devices),
        batch_size=options.batch * devices, compute=ray.data.ActorPoolStrategy(size=workers),
        num_cpus=ray_options.cpus_per_worker, num_gpus=ray_options.gpus_per_worker or None,
        runtime_env={"env_vars": env} if env else None, batch_format="numpy",
    )
    yield from ds.iter_rows()


def _record(writer: ResultWriter, row: dict, where: dict[str, str], options: BatchOptions, run: dict, bar) -> None:
    """Write one clip's outcome as the local engine does (result file, then manifest line)."""
    name = str(row["name"])
    seconds = round(float(row["seconds"]), 4)
    if row["status"] == "ok":
        arrays, extra = row["payload"]
        try:
            bvh = extra.pop("bvh_bytes", None)
            if bvh is not None:
                (writer.root / name).parent.mkdir(parents=True, exist_ok=True)
                atomic_write(writer.root / f"{name}.bvh", bvh)
                extra["bvh"] = f"{name}.bvh"
            writer.add_result(name, arrays, seconds=seconds, **extra)
        except OSError as e:
            raise ArchiveError(f"{writer.root}: cannot write the result of {name}: {e}") from None
        run["ok"] += 1
        run["frames"] += int(extra["frames"])
        if bar is not None:
            bar.update(1, int(extra["frames"]))
        return
    fields = {"frames": int(row["frames"])} if int(row["frames"]) else {}
    writer.add_failure(name, str(row["error"]), source=where[name], seconds=seconds, **fields)
    run["failed"] += 1
    if bar is not None:
        bar.update(1)


__all__ = ["RayOptions", "reconstruct_archive_ray"]
