"""Archive runs on six-IMU clips: ``jmocap reconstruct IMU_ARCHIVE OUTPUT`` with PIP
(:mod:`jmocap.methods.pip_imu`), resumable like the 2D runs of :mod:`jmocap.batch`.

* **inputs**: every clip of a jmocap archive of IMU clips (``jmocap-imu-clip-1``, docs/formats.md
  "IMU clips"; e.g. ``jmocap data synth --imu``), read and validated by the archive's reader; a
  clip that cannot be read gets a ``failed`` line naming file and field, and the run goes on;
* **compute**: each clip on its subject's character (the clip's height and mass, else the
  nominal ones, recorded in ``assumed``), padded to a multiple of ``bucket`` frames (one compile
  per padded length), from its first ground-truth pose where it has one (PIP's calibration
  pose; else the zero initial state, recorded in ``warnings``);
* **outputs**: the same ``jmocap-result-1`` files as 2D runs (:mod:`jmocap.results`; 3D
  keypoints of the character's BODY_25 joints) without the camera and 2D input fields, plus
  ``input_kind = "imu6"``, written atomically with their manifest
  lines; a re-run skips the clips already done; ``summary.json`` at the end.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

import jmocap
from jmocap import physics as P
from jmocap.constants import DEFAULT_HEIGHT_M
from jmocap.data.archive import Archive, ArchiveError
from jmocap.data.imu import IMUClip
from jmocap.data.sources import SUMMARY
from jmocap.io import atomic_write
from jmocap.methods import pip_imu as PI
from jmocap.model import character
from jmocap.results import MOTION_FIELDS, RESULT_FORMAT, ResultWriter, check_finite

#: the method name IMU results record
METHOD = "pip_imu"
#: the layout of the results' 3D keypoints (``keypoints3d``: the character's BODY_25 joints)
LAYOUT = "body25"


def is_imu_archive(path) -> bool:
    """Whether ``path`` is a jmocap archive whose first clip is an IMU clip."""
    p = Path(path)
    if not (p.is_dir() and (p / "manifest.jsonl").is_file()):
        return False
    try:
        with Archive(p) as a:
            names = a.names()
            return bool(names) and isinstance(a.load(names[0]), IMUClip)
    except Exception:  # noqa: BLE001 - not readable as an IMU archive: the 2D path reports why
        return False


def result_arrays(clip: IMUClip, motion: dict[str, np.ndarray], *, height_m: float, mass_kg: float,
                  identity: dict[str, str], source: str, assumed, warnings) -> dict[str, np.ndarray]:
    """The arrays of an IMU run's ``jmocap-result-1`` file."""
    out = {
        "format": np.array(RESULT_FORMAT), "name": np.array(clip.name), "source": np.array(source),
        "method": np.array(METHOD), "input_kind": np.array("imu6"),
        **{k: np.asarray(motion[k], np.float32) for k in MOTION_FIELDS},
        "layout": np.array(LAYOUT),
        "certified": np.asarray(motion["certified"], bool),
        "fps": np.array(clip.fps, np.float64), "height_m": np.array(height_m, np.float64),
        "mass_kg": np.array(mass_kg, np.float64), "forces_estimated": np.array(True),
        "assumed": np.array(json.dumps(list(assumed))), "warnings": np.array(json.dumps(list(warnings))),
        "height_source": np.array("nominal" if "height_m" in assumed else "input"),
    }
    out.update({k: np.array(v) for k, v in identity.items()})
    return out


def reconstruct_imu_archive(input, output, params, config: PI.PIPIMUConfig, *, bucket: int = 64,
                            max_clips: int | None = None, bvh: bool = False, progress=None) -> dict[str, Any]:
    """Reconstruct every clip of the IMU archive ``input`` into ``output`` (module doc); returns
    the summary (also written as ``summary.json``). ``bvh``: also ``<name>.bvh`` per clip."""
    t0 = time.perf_counter()
    from jmocap.batch import (  # as the 2D runs'
        _bvh_writer,
        _output_folder,
        _write_bvh,
        run_identity,
        run_summary,
    )

    identity = run_identity(params, config, METHOD)
    settings = {"engine": "jmocap.batch_imu", "format": RESULT_FORMAT,
                **{k: identity[k] for k in ("method", "config", "params_sha256", "model_sha256")}}

    @jax.jit
    def rec(params, model, inputs, config):
        m = PI.reconstruct(params, model, inputs, config)
        return m, jax.vmap(lambda q: P.keypoints(model, q, LAYOUT))(m.q)

    run = {"ok": 0, "failed": 0, "frames": 0}
    write_bvh = _bvh_writer() if bvh else None

    with Archive(input) as archive, _output_folder(output) as root, ResultWriter(root, settings) as writer:
        names = archive.names()
        if not names:
            raise ArchiveError(f"{input}: no clips found")
        todo = [n for n in names if not writer.done(n, bvh=bvh)]
        skipped = len(names) - len(todo)
        if max_clips is not None:
            todo = todo[:max_clips]
        bar = progress(len(todo)) if progress is not None else None
        for name in todo:
            t = time.perf_counter()
            where = f"{input}/{name}"
            try:
                clip = archive.load(name)
                if not isinstance(clip, IMUClip):
                    raise ValueError(f"{where}: not an IMU clip (an archive mixes IMU and 2D clips)")
                assumed = [k for k in ("height_m", "mass_kg") if getattr(clip, k) is None]
                model = character(clip.height_m, clip.mass_kg)
                n = -(-clip.num_frames // bucket) * bucket
                inputs = PI.IMUInputs.from_clip(clip, model, n)
                warnings = [] if bool(inputs.has_first) else [
                    "no ground-truth first pose: the networks start from the zero state"]
                m, kp = jax.device_get(rec(params, model, inputs, config))
                T = clip.num_frames
                motion = {k: np.asarray(getattr(m, k))[:T] for k in
                          ("q", "qd", "tau", "grf", "contact_prob", "target_q", "certified")}
                motion["keypoints3d"] = np.asarray(kp)[:T]
                check_finite(motion, where)
                height = DEFAULT_HEIGHT_M if clip.height_m is None else float(clip.height_m)
                arrays = result_arrays(clip, motion, height_m=height, mass_kg=model.total_mass,
                                       identity=identity, source=where, assumed=assumed, warnings=warnings)
                extra = {"warnings": warnings} if warnings else {}
                if write_bvh is not None:
                    extra["bvh"] = _write_bvh(write_bvh, root, name, model, motion["q"], float(clip.fps))
                writer.add_result(name, arrays, frames=T, fps=float(clip.fps), input_kind="imu6",
                                  height_m=height, source=where,
                                  uncertified_frames=int(np.sum(~motion["certified"])),
                                  seconds=round(time.perf_counter() - t, 4), **extra)
                run["ok"] += 1
                run["frames"] += T
                if bar is not None:
                    bar.update(1, T)
            except Exception as e:  # noqa: BLE001 - a batch run records failures and goes on
                writer.add_failure(name, str(e) if str(e).startswith(str(input)) else f"{where}: {e}",
                                   source=where, seconds=round(time.perf_counter() - t, 4))
                run["failed"] += 1
                if bar is not None:
                    bar.update(1)
        if bar is not None:
            bar.close()
        entries = [writer.entries[n] for n in names if n in writer.entries]
    summary = {**run_summary(input, output, names, entries, run, skipped, time.perf_counter() - t0),
               "method": METHOD, "params_sha256": identity["params_sha256"], "version": jmocap.__version__}
    atomic_write(Path(output) / SUMMARY, (json.dumps(summary, indent=2) + "\n").encode())
    return summary


__all__ = ["METHOD", "is_imu_archive", "reconstruct_imu_archive", "result_arrays"]
