"""The reconstruction result format ``jmocap-result-1``: one writer, one reader (docs/formats.md).

A result is one ``.npz`` per clip:

=================  =========  ============  ===========================================
field              dtype      shape         meaning
=================  =========  ============  ===========================================
format             str        ()            ``jmocap-result-1``
name, source       str        ()            the clip's name and where it was read from
method             str        ()            the registered method that made it
q, qd              float32    (T, nq/nv)    motion (MuJoCo conventions)
tau                float32    (T, nv)       generalised forces; residual root wrench in [:6]
                                            (only when ``forces_estimated``)
grf                float32    (T, 4, 3)     world-frame contact forces (N) per contact point
                                            (only when ``forces_estimated``)
contact_prob       float32    (T, 4)        contact probabilities
target_q           float32    (T, nq)       the kinematic target the dynamics tracked
keypoints3d        float32    (T, J, 3)     world-frame joints of ``q`` in ``layout``
keypoints2d        float32    (T, J, 3)     the input keypoints (pixels, confidence)
certified          bool       (T,)          optional, methods that solve a QP per frame: every
                                            solve of the frame passed its KKT check
diagnostics        str        ()            optional, JSON object of per-clip numbers a method
                                            reports about its solve (``trajopt``: objective
                                            before/after, terms, iterations, residual;
                                            ``pip``: ``resets``, tracking failures)
fps                float64    ()            frames per second
height_m, mass_kg  float64    ()            the character's height and mass
layout             str        ()            keypoint layout
intrinsics         float64    (4,)          fx, fy, cx, cy
image_size         int64      (2,)          width, height
extrinsics         float64    (4, 4)        world -> camera (a moving camera's first frame)
camera_track       float64    (T, 4, 4)     optional: a moving camera's world -> camera per frame
camera_track_      float64    (T, 4, 4)     optional: the world -> camera track a method
estimated                                   estimated (``dnd``, whose input is the first
                                            frame's camera only); ``jmocap render`` draws the
                                            camera view through it where ``camera_track`` is absent
scene              str        ()            optional: the input clip's terrain, a
                                            ``jmocap-scene-1`` document (jmocap.scene)
extrinsics_source  str        ()            where ``extrinsics`` came from: ``input`` (clip or
                                            sidecar), ``estimated`` (the floor seen from the
                                            person, jmocap.methods.floor), ``default``
                                            (jmocap.camera.default_extrinsics)
assumed            str        ()            JSON list of values that were defaults, not data
warnings           str        ()            JSON list of what was implausible but usable in the
                                            input (jmocap.data.validate; also in the manifest)
height_source      str        ()            where ``height_m`` came from: ``input``
                                            (clip or sidecar), ``argument`` (--height-m),
                                            ``estimated`` (jmocap.subject), ``nominal``
config             str        ()            JSON of the method's config
params_sha256,     str        ()            identity of the weights, the character file and
model_sha256,                               the package version
version
=================  =========  ============  ===========================================

``forces_estimated`` (bool) says whether the method estimates forces. Absent means absent: a
method that estimates none (``kinematic``) writes ``False`` and leaves ``tau`` and ``grf`` out of
the file (:func:`load_result` gives ``None`` for them), so no reader mistakes "not estimated" for
"0 N". Files written before 2026-12-03 hold zeros there with ``forces_estimated = False``;
:func:`load_result` reads those as absent too.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from jmocap.constants import NUM_CONTACTS
from jmocap.data.archive import ArchiveError, ArchiveWriter, _sha256
from jmocap.data.clip import Clip, FormatError
from jmocap.inputs import ClipInputs
from jmocap.io import atomic_write, npz_bytes

RESULT_FORMAT = "jmocap-result-1"
#: per-frame fields written from a reconstruction, (T, ...) float32
MOTION_FIELDS = ("q", "qd", "tau", "grf", "contact_prob", "target_q", "keypoints3d")
#: the fields only a method that estimates forces writes (``forces_estimated``)
FORCE_FIELDS = ("tau", "grf")

# key -> trailing shape (None = any size); time series have a leading T
_SERIES = {
    "q": (None,),
    "qd": (None,),
    "tau": (None,),
    "grf": (NUM_CONTACTS, 3),
    "contact_prob": (NUM_CONTACTS,),
    "target_q": (None,),
    "keypoints3d": (None, 3),
    "keypoints2d": (None, 3),
}
_STATIC = {"intrinsics": (4,), "image_size": (2,), "extrinsics": (4, 4)}
_SCALARS = ("fps", "height_m", "mass_kg")
_STRINGS = ("format", "name", "source", "method", "layout", "version", "config", "params_sha256",
            "model_sha256", "assumed", "warnings", "height_source", "extrinsics_source")
_BOOLS = ("forces_estimated",)


class ReconstructionError(ValueError):
    """A reconstruction that produced non-finite values (never written as a result)."""


def _scene_document(scene) -> dict:
    from jmocap.scene import scene_document

    return scene_document(scene)


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


def assumed_fields(clip: Clip) -> list[str]:
    """Which camera / subject values of a clip are defaults rather than data."""
    out = list(clip.meta.get("assumed", []))
    if clip.meta.get("assumed_image_size"):
        out.append("image_size")
    if clip.extrinsics is None:
        out.append("extrinsics")
    if clip.height_m is None:
        out.append("height_m")
    if clip.mass_kg is None:
        out.append("mass_kg")
    return out


def result_model(result: dict[str, Any]):
    """The character a result was reconstructed with (:func:`jmocap.model.character` of its
    height and mass, or the nominal ones where the result says they were assumed)."""
    from jmocap.model import character

    assumed = result.get("assumed") or []
    height = None if "height_m" in assumed or result.get("height_m") is None else result["height_m"]
    mass = None if "mass_kg" in assumed or result.get("mass_kg") is None else result["mass_kg"]
    return character(height, mass)


def result_arrays(
    clip: Clip,
    result: dict[str, np.ndarray],
    *,
    method: str,
    height_m: float,
    mass_kg: float,
    forces_estimated: bool,
    identity: dict[str, str],
    source: str,
    assumed: Sequence[str] = (),
    warnings: Sequence[str] = (),
    height_source: str | None = None,
    extrinsics_source: str | None = None,
) -> dict[str, np.ndarray]:
    """The arrays of a ``jmocap-result-1`` file (see the module docstring)."""
    extr = ClipInputs.from_clip(clip).extrinsics  # the clip's, or the default camera
    out = {
        "format": np.array(RESULT_FORMAT),
        "name": np.array(clip.name),
        "source": np.array(source),
        "method": np.array(method),
        **{k: np.asarray(result[k], np.float32) for k in MOTION_FIELDS
           if forces_estimated or k not in FORCE_FIELDS},
        "keypoints2d": np.asarray(clip.keypoints, np.float32),
        **({"certified": np.asarray(result["certified"], bool)} if result.get("certified") is not None else {}),
        **({"diagnostics": np.array(json.dumps({k: float(v) for k, v in result["diagnostics"].items()}))}
           if result.get("diagnostics") is not None else {}),
        "fps": np.array(clip.fps, np.float64),
        "height_m": np.array(height_m, np.float64),
        "mass_kg": np.array(mass_kg, np.float64),
        "forces_estimated": np.array(bool(forces_estimated)),
        "layout": np.array(clip.layout),
        "intrinsics": np.asarray(clip.intrinsics, np.float64),
        "image_size": np.asarray(clip.image_size, np.int64),
        "extrinsics": np.asarray(extr, np.float64),
        **({"camera_track": np.asarray(clip.camera_track, np.float64)} if clip.camera_track is not None else {}),
        **({"camera_track_estimated": np.asarray(result["camera_track_estimated"], np.float64)}
           if result.get("camera_track_estimated") is not None else {}),
        **({"scene": np.array(json.dumps(_scene_document(clip.scene)))} if clip.scene is not None else {}),
        "assumed": np.array(json.dumps(list(assumed))),
        "warnings": np.array(json.dumps(list(warnings))),
        "height_source": np.array(height_source if height_source is not None
                                  else ("input" if clip.height_m is not None else "nominal")),
        "extrinsics_source": np.array(extrinsics_source if extrinsics_source is not None
                                      else ("input" if clip.extrinsics is not None else "default")),
    }
    out.update({k: np.array(v) for k, v in identity.items()})
    return out


def write_result(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> bytes:
    """Write a result's arrays atomically (deterministic bytes); returns the bytes written."""
    data = npz_bytes(arrays)
    atomic_write(path, data)
    return data


def load_result(path: str | os.PathLike) -> dict[str, Any]:
    """Read a reconstruction result ``.npz`` into a dict.

    Required: ``q`` (T, nq) and ``fps`` (> 0). Every other field of the format is present in the
    dict, as ``None`` when the file lacks it (older or hand-made files; ``tau`` and ``grf`` also
    when ``forces_estimated`` is False: not estimated). Shapes are checked (time
    series must share T); numeric scalars become ``float``, 0-d strings ``str``, ``assumed`` a
    list; unknown extra keys are passed through as arrays. Raises
    :class:`jmocap.data.FormatError` (a ``ValueError``) naming the file and field.

    Read through :func:`jmocap.data.limits.load_npz` (file, member and declared array sizes
    within the limits, no pickle); the time series have at most ``max_frames`` frames; the JSON
    fields (``diagnostics``, ``assumed``, ``warnings``) are parsed within ``max_json_depth``.
    """
    from jmocap.data import limits

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"result file not found: {path}")
    try:
        data = limits.load_npz(path, str(path))
    except FormatError:
        raise
    except Exception as e:  # not a zip, truncated, pickled objects, ...
        raise FormatError(f"{path}: not a readable .npz result file ({e})") from None

    out: dict[str, Any] = {k: None for k in (*_SERIES, *_STATIC, *_SCALARS, *_STRINGS, *_BOOLS)}
    for key in ("q", "fps"):
        if key not in data:
            raise FormatError(f"{path}: missing field {key!r}")
    T = None
    for key, trailing in _SERIES.items():
        if key not in data:
            continue
        a = data[key]
        if a.dtype.kind not in "fiu" or a.ndim != 1 + len(trailing) or any(
            n is not None and s != n for s, n in zip(a.shape[1:], trailing, strict=True)
        ):
            want = "(T, " + ", ".join("*" if n is None else str(n) for n in trailing) + ")"
            raise FormatError(f"{path}: field {key!r} has shape {a.shape} ({a.dtype}), expected {want} numbers")
        if T is None:
            T = a.shape[0]
        elif a.shape[0] != T:
            raise FormatError(f"{path}: field {key!r} has {a.shape[0]} frames, 'q' has {T}")
        out[key] = a
    if T == 0:
        raise FormatError(f"{path}: field 'q' has no frames")
    limits.check_frames(T, f"{path}: field 'q'")
    out["certified"] = None
    if "certified" in data:
        a = data["certified"]
        if a.shape != (T,) or a.dtype.kind != "b":
            raise FormatError(f"{path}: field 'certified' has shape {a.shape} ({a.dtype}), expected ({T},) booleans")
        out["certified"] = a
    out["diagnostics"] = None
    if "diagnostics" in data:
        diag = limits.parse_json(str(data["diagnostics"]), f"{path}: field 'diagnostics'")
        if not isinstance(diag, dict) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in diag.values()
        ):
            raise FormatError(f"{path}: field 'diagnostics' is not a JSON object of numbers")
        out["diagnostics"] = diag
    out["scene"] = None
    if "scene" in data:
        from jmocap.scene import SceneError, parse_scene

        try:
            out["scene"] = parse_scene(limits.parse_json(str(data["scene"]), f"{path}: field 'scene'"),
                                       f"{path}: field 'scene'")
        except SceneError as e:
            raise FormatError(str(e)) from None
    for key in ("camera_track", "camera_track_estimated"):
        out[key] = None
        if key in data:
            a = data[key]
            if a.shape != (T, 4, 4) or a.dtype.kind not in "fiu":
                raise FormatError(f"{path}: field {key!r} has shape {a.shape} ({a.dtype}), expected ({T}, 4, 4) numbers")
            out[key] = a
    for key, shape in _STATIC.items():
        if key in data:
            a = data[key]
            if a.shape != shape or a.dtype.kind not in "fiu":
                raise FormatError(f"{path}: field {key!r} has shape {a.shape} ({a.dtype}), expected {shape} numbers")
            out[key] = a
    for key in _SCALARS:
        if key in data:
            a = data[key]
            if a.shape != () or a.dtype.kind not in "fiu":
                raise FormatError(f"{path}: field {key!r} must be a number, got shape {a.shape} ({a.dtype})")
            out[key] = float(a)
    if not (math.isfinite(out["fps"]) and out["fps"] > 0):
        raise FormatError(f"{path}: field 'fps' must be positive, got {out['fps']}")
    for key in _STRINGS:
        if key in data:
            a = data[key]
            if a.shape != () or a.dtype.kind not in "US":
                raise FormatError(f"{path}: field {key!r} must be a string, got shape {a.shape} ({a.dtype})")
            out[key] = str(a)
    for key in _BOOLS:
        if key in data:
            a = data[key]
            if a.shape != () or a.dtype.kind != "b":
                raise FormatError(f"{path}: field {key!r} must be a boolean, got shape {a.shape} ({a.dtype})")
            out[key] = bool(a)
    if out["forces_estimated"] is False:  # absent means absent (older files hold zeros there)
        for key in FORCE_FIELDS:
            out[key] = None
    for key in ("assumed", "warnings"):
        if out[key] is not None:
            value = limits.parse_json(out[key], f"{path}: field {key!r}")
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                raise FormatError(f"{path}: field {key!r} must be a JSON list of strings, got {out[key][:80]!r}")
            out[key] = value
    for key, a in data.items():
        if key not in out:
            out[key] = a
    return out


class ResultWriter(ArchiveWriter):
    """An output folder of results: result files plus the archive manifest and settings
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
        rel = f"{name}.npz"
        path = self.root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        data = write_result(path, arrays)
        entry = {"name": name, "file": rel, "status": "ok", "bytes": len(data), "sha256": _sha256(data)}
        entry.update(extra)
        self._append(entry)
        return entry


__all__ = [
    "MOTION_FIELDS",
    "RESULT_FORMAT",
    "ReconstructionError",
    "ResultWriter",
    "assumed_fields",
    "check_finite",
    "load_result",
    "result_arrays",
    "result_model",
    "write_result",
]
