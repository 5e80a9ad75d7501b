"""Corrupted inputs for ``jmocap reconstruct``: the cases of the fuzz suite (tests/test_fuzz.py).

Not a test module (pytest collects ``test_*.py`` only); ``tests/test_fuzz.py`` imports it.
Everything is deterministic: the valid clips are hand-made keypoints of a standing person who
squats a little and swings the arms, projected through a pinhole camera (pure numpy, no
synthetic generator, milliseconds per clip), and every random byte comes from a
``numpy.random.Generator`` seeded by the case's id.

Two kinds of cases:

* :class:`Case` (per clip): the files of one clip, in one of the input formats (jmocap clip
  ``.npz``, OpenPose JSON folder with and without a camera sidecar, COCO results / annotations
  JSON, MMPose JSON, VideoPose3D ``.npz``, plain ``.npy`` / ``.npz`` keypoint arrays, camera
  sidecars), valid or corrupted, written under ``INPUT/<case.id>...``. Many cases go into one
  folder (a *mixed archive*) and one ``jmocap reconstruct`` run; the case says what must happen
  to the clips it makes (their manifest names are ``case.id`` or start with ``case.id + "/"``
  or ``case.id + "."``):

  - ``ok``: a valid clip; it must get a result (in a run whose parameters are in the case's
    ``layout``; in a run with other parameters it must fail *only* because of the layout,
    ``field 'layout'``);
  - ``fail``: it must be recorded as failed, with a clean message: one line, naming the file
    (``case.id`` is in it: the path below INPUT, or the archive member) and a field
    (``field '...'``), a frame (``frame N``) or a limit (``max_...``), and, when ``mention`` is
    set, one of those strings;
  - ``either``: no traceback; if it fails, the message is clean as above.

  :func:`build_folder` writes a list of cases into a folder, :func:`pack` turns a folder into a
  ``.zip`` / ``.tar`` / ``.tar.gz`` input, :func:`build_clip_archive` writes the ``clip`` cases
  as a jmocap clip archive (``manifest.jsonl`` + members) in a folder, zip or tar.

* :class:`ArchiveCase` (per run): a whole INPUT / OUTPUT situation (OUTPUT is a file, INPUT
  missing, zip bomb, symlinks, manifest lines pointing outside INPUT, signals, ...) with the exit
  code(s) and outcome it must have; built by ``case.build(sandbox)`` into a :class:`RunSpec`.

The pickle payloads (:class:`Payload`) try to create :data:`MARKER` in the sandbox (``exec`` or
``os.system``, both harmless: they append a line to that file); the suite asserts that the file
never appears. The zip bombs are written by hand (:func:`raw_zip`) from a deflate stream of
zeros that is built once (:func:`deflated_zeros`): a 1.2 MB file that expands to 1.2 GiB, made
in about half a second, never materialised.
"""

from __future__ import annotations

import functools
import io
import json
import os
import pickle
import re
import shlex
import struct
import tarfile
import warnings
import zipfile
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data.clip import Clip, clip_to_arrays
from jmocap.data.formats import (
    write_camera_json,
    write_coco_results,
    write_mmpose_json,
    write_openpose_folder,
    write_videopose3d,
)
from jmocap.layouts import get_layout

SEED = 16  # issue 16
MARKER = "MARKER"  # the file the pickle payloads try to create, in the sandbox root
GIB = 1 << 30
BOMB_BYTES = 1000 * 300 * 4096  # 1.23e9 bytes (> 1 GiB) of zeros behind every bomb
OUTSIDE = "outside"  # sandbox folder with valid clips that manifest lines / symlinks point at

LAYOUT_OF_FORMAT = {"clip": "body25", "openpose": "body25", "coco": "coco17", "mmpose": "coco17",
                    "vp3d": "h36m17", "array": "h36m17"}

#: a failure message names a field, a frame or a limit
DETAIL_RE = r"field '[^']*'|field \"[^\"]*\"|\bframe -?\d+|\bmax_[a-z_]+"
#: or it says what is wrong with the file as a whole (then no field or frame applies)
FILE_LEVEL_RE = (r"not a readable (?:\.npz|numpy) file|not (?:valid|readable) JSON|not (?:a )?UTF-8|"
                 r"contains no frames|is an empty list|must be a JSON object|not an? [\w-]+ [\w ]*file|"
                 r"file name does not end in|none of the keypoint names|not an archive|cannot read the archive")
#: what a clean message never contains: a traceback, or a raw exception's ``Type: text``
UNCLEAN_RE = r"Traceback \(most recent call last\)|File \"[^\"]+\", line \d+|\b[A-Z]\w*(?:Error|Exception): "


def rng_for(*key: Any) -> np.random.Generator:
    """The random stream of one case: seeded by :data:`SEED` and the case's id."""
    return np.random.default_rng([SEED, zlib.crc32(repr(key).encode())])


# =========================================================================================
# valid clips: a standing person, squatting a little and swinging the arms
# =========================================================================================

_CENTRE = {"nose": (0.0, -0.10, 1.62), "neck": (0.0, 0.0, 1.48), "head_top": (0.0, -0.01, 1.76),
           "thorax": (0.0, 0.0, 1.42), "spine": (0.0, 0.0, 1.20), "mid_hip": (0.0, 0.0, 0.95)}
# left side (x > 0: the person faces -y, towards the camera); the right side is mirrored
_PAIRED = {"shoulder": (0.19, 0.0, 1.45), "elbow": (0.23, 0.02, 1.17), "wrist": (0.25, -0.04, 0.92),
           "hip": (0.10, 0.0, 0.93), "knee": (0.11, -0.03, 0.51), "ankle": (0.12, 0.02, 0.09),
           "eye": (0.035, -0.09, 1.66), "ear": (0.075, -0.01, 1.63), "big_toe": (0.14, -0.16, 0.02),
           "small_toe": (0.18, -0.13, 0.02), "heel": (0.12, 0.05, 0.03)}

DEFAULT_INTRINSICS = (1000.0, 1000.0, 960.0, 540.0)
DEFAULT_SIZE = (1920, 1080)
H36M_INTRINSICS = (1145.0494384765625, 1143.7811279296875, 512.54150390625, 515.4514770507812)
H36M_SIZE = (1000, 1002)


def _site_template() -> dict[str, np.ndarray]:
    sites = {f"kp_{k}": np.array(v) for k, v in _CENTRE.items()}
    for k, (x, y, z) in _PAIRED.items():
        sites[f"kp_left_{k}"] = np.array([x, y, z])
        sites[f"kp_right_{k}"] = np.array([-x, y, z])
    return sites


def person_world(layout: str, T: int, fps: float = 30.0) -> np.ndarray:
    """(T, J, 3) world positions (z up, metres) of ``layout``'s joints."""
    tmpl = _site_template()
    lay = get_layout(layout)
    t = np.arange(T) / fps
    squat = 0.06 * (1 - np.cos(2 * np.pi * 0.4 * t)) / 2
    swing = np.sin(2 * np.pi * 0.7 * t)
    sway = 0.05 * np.sin(2 * np.pi * 0.3 * t)
    out = np.zeros((T, lay.num_joints, 3))
    for j, site in enumerate(lay.sites):
        p = np.repeat(tmpl[site][None], T, axis=0)
        side = 1.0 if "_left_" in site else -1.0 if "_right_" in site else 0.0
        if any(k in site for k in ("knee",)):
            p[:, 2] -= squat / 2
            p[:, 1] -= squat / 2
        elif not any(k in site for k in ("ankle", "toe", "heel")):
            p[:, 2] -= squat
        if "elbow" in site:
            p[:, 1] += 0.10 * side * swing
        if "wrist" in site:
            p[:, 1] += 0.20 * side * swing
        p[:, 0] += sway
        out[:, j] = p
    return out


def look_at(eye: Sequence[float], target: Sequence[float] = (0.0, 0.0, 0.95)) -> np.ndarray:
    """World -> camera 4x4 (OpenCV axes: x right, y down, z forward), z-up world."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    E = np.eye(4)
    E[:3, :3] = np.stack([r, d, f])
    E[:3, 3] = -E[:3, :3] @ eye
    return E


def project(P: np.ndarray, E: np.ndarray, intr: Sequence[float]) -> np.ndarray:
    """(..., 3) world points -> (..., 2) pixels."""
    Pc = P @ E[:3, :3].T + E[:3, 3]
    fx, fy, cx, cy = intr
    return np.stack([fx * Pc[..., 0] / Pc[..., 2] + cx, fy * Pc[..., 1] / Pc[..., 2] + cy], -1)


@functools.cache
def _valid_clip(layout: str, T: int, camera: str, extrinsics: bool, subject: bool) -> Clip:
    rng = rng_for("valid", layout, T, camera)
    intr, size = (H36M_INTRINSICS, H36M_SIZE) if camera == "h36m" else (DEFAULT_INTRINSICS, DEFAULT_SIZE)
    E = look_at((0.4, -4.0, 1.3))
    uv = project(person_world(layout, T), E, intr) + rng.normal(0.0, 0.5, (T, get_layout(layout).num_joints, 2))
    conf = rng.uniform(0.7, 1.0, uv.shape[:2])
    kp = np.concatenate([uv, conf[..., None]], -1).astype(np.float32)
    return Clip(
        name="take", layout=layout, fps=30.0, keypoints=kp, intrinsics=np.asarray(intr, np.float64),
        image_size=np.asarray(size), extrinsics=E if extrinsics else None,
        height_m=1.75 if subject else None, mass_kg=70.0 if subject else None,
        meta={"kind": "fuzz", "layout": layout},
    )


def valid_clip(layout: str = "body25", T: int = 24, *, camera: str = "default", extrinsics: bool = True,
               subject: bool = True, name: str = "take") -> Clip:
    """A valid clip of ``T`` frames (16, 24 and 40 keep the compiled chunk shapes few)."""
    c = _valid_clip(layout, T, camera, extrinsics, subject)
    return c if name == "take" else c.replace(name=name)


# =========================================================================================
# writing helpers
# =========================================================================================


def npz_bytes(arrays: dict[str, Any], compressed: bool = False) -> bytes:
    """``np.savez`` of ``arrays`` (object arrays are pickled, as numpy does by default)."""
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return buf.getvalue()


def npy_bytes(a: Any) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=True)
    return buf.getvalue()


def write_bytes(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)


def write_json(path: Path, obj: Any) -> None:
    write_bytes(path, json.dumps(obj, allow_nan=True).encode())


def edit_json(path: Path, fn: Callable[[Any], Any]) -> None:
    """Edit the JSON in ``path``: ``fn(data)`` changes it in place (what it returns is ignored),
    or, when ``fn`` is marked by :func:`replaces`, returns the new document."""
    data = json.loads(path.read_text())
    new = fn(data)
    write_json(path, new if getattr(fn, "replaces", False) else data)


def replaces(fn: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """Mark a JSON edit that returns the new document (see :func:`edit_json`)."""
    fn.replaces = True
    return fn


def zip_entry(name: str) -> zipfile.ZipInfo:
    """A zip member with a fixed timestamp (deterministic bytes)."""
    info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
    info.external_attr = 0o644 << 16
    return info


def deep_json(levels: int = 100_000) -> str:
    return "[" * levels + "]" * levels


HUGE_INT = "1" + "0" * 5000  # over Python's 4300-digit int/str conversion limit
BIG_INT = 10**400  # parses, but does not fit a float
LATIN1 = '{"people": [], "note": "caf\xe9"}'.encode("latin-1")  # not UTF-8


class Payload:
    """Unpickling this runs code: ``exec`` or ``os.system`` appending ``tag`` to ``marker``."""

    def __init__(self, marker: Path, tag: str, how: str = "exec"):
        self.marker, self.tag, self.how = str(marker), tag, how

    def __reduce__(self):
        if self.how == "system":
            return (os.system, (f"echo {shlex.quote(self.tag)} >> {shlex.quote(self.marker)}",))
        return (exec, (f"open({self.marker!r}, 'a').write({self.tag!r} + '\\n')",))


# ---- zip bombs ---------------------------------------------------------------------------


@functools.cache
def deflated_zeros(prefix: bytes = b"", block: int = 300 * 4096, count: int = 1000) -> tuple[bytes, int, int]:
    """A raw deflate stream of ``prefix`` + ``block * count`` zero bytes, its CRC-32 and size.

    After a full flush the compressor's state is reset, so every block of zeros compresses to
    the same bytes: the stream is those bytes repeated (built without compressing 1 GiB)."""
    zeros = bytes(block)
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    head = c.compress(prefix) + c.flush(zlib.Z_FULL_FLUSH) if prefix else b""
    first = c.compress(zeros) + c.flush(zlib.Z_FULL_FLUSH)
    again = c.compress(zeros) + c.flush(zlib.Z_FULL_FLUSH)
    third = c.compress(zeros) + c.flush(zlib.Z_FULL_FLUSH)
    assert again == third, "zlib does not repeat itself after a full flush"
    stream = head + first + again * (count - 1) + c.flush()
    crc = zlib.crc32(prefix)
    for _ in range(count):
        crc = zlib.crc32(zeros, crc)
    return stream, crc, len(prefix) + block * count


def raw_zip(path: Path, members: Iterable[tuple[str, bytes | tuple[bytes, int, int]]],
            declared_size: dict[str, int] | None = None) -> None:
    """Write a zip by hand. A member is ``(name, data)`` (stored) or ``(name, (deflate stream,
    crc, size))`` (deflated, not recompressed); ``declared_size`` lies about a member's size."""
    path.parent.mkdir(parents=True, exist_ok=True)
    central = []
    with open(path, "wb") as f:
        for name, data in members:
            if isinstance(data, tuple):
                payload, crc, size = data
                method = zipfile.ZIP_DEFLATED
            else:
                payload, crc, size, method = data, zlib.crc32(data), len(data), zipfile.ZIP_STORED
            if declared_size and name in declared_size:
                size = declared_size[name]
            nb = name.encode()
            off = f.tell()
            f.write(struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, method, 0, 0x21, crc, len(payload),
                                size, len(nb), 0) + nb)
            f.write(payload)
            central.append(struct.pack("<4s6H3L5H2L", b"PK\x01\x02", 20, 20, 0, method, 0, 0x21, crc,
                                       len(payload), size, len(nb), 0, 0, 0, 0, 0o100644 << 16, off) + nb)
        start = f.tell()
        for c in central:
            f.write(c)
        f.write(struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, len(central), len(central),
                            f.tell() - start, start, 0))


def npy_header(shape: tuple[int, ...], descr: str = "<f4") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def bomb_npz(path: Path, clip_fields: bool = True) -> None:
    """A jmocap clip ``.npz`` whose ``keypoints.npy`` member expands to 1.2 GiB of zeros
    (4 096 000 frames; the file is ~1.2 MB)."""
    T = BOMB_BYTES // (25 * 3 * 4)
    stream = deflated_zeros(npy_header((T, 25, 3)))
    members: list = []
    if clip_fields:
        arrays = clip_to_arrays(valid_clip("body25", 16))
        for k, v in arrays.items():
            if k != "keypoints":
                members.append((f"{k}.npy", npy_bytes(v)))
    members.append(("keypoints.npy", stream))
    raw_zip(path, members)


# =========================================================================================
# per-clip cases
# =========================================================================================

Builder = Callable[[Path, Path], None]  # (INPUT root, marker path)


@dataclass(frozen=True)
class Case:
    """One clip's files, written under ``INPUT/<id>...`` by ``build(root, marker)``."""

    id: str
    format: str  # clip | openpose | coco | mmpose | vp3d | array
    category: str
    expect: str  # ok | fail | either
    build: Builder = field(repr=False, compare=False)
    layout: str = "body25"  # the layout of the clip when it reads
    clips: int | None = 1  # clips (manifest names) it makes; None: any number (at least 1 unless `either`)
    mention: tuple[str, ...] = ()  # a failure message contains one of these
    fast: bool = False  # in the default suite's mixed archive
    containers: bool = True  # can be packed into .zip / .tar inputs and clip archives
    distinct: bool = False  # its clips have different frame counts (names that collide must stay apart)
    note: str = ""

    def owns(self, name: str) -> bool:
        return name == self.id or name.startswith(self.id + "/") or name.startswith(self.id + ".")


class _Registry:
    def __init__(self):
        self.cases: list[Case] = []

    def add(self, fmt: str, name: str, category: str, expect: str, build: Builder, **kw) -> None:
        kw.setdefault("layout", LAYOUT_OF_FORMAT[fmt])
        if isinstance(kw.get("mention"), str):
            kw["mention"] = (kw["mention"],)
        assert "." not in name, f"{fmt}/{name}: no dots in case names (a name's suffix is its file type)"
        self.cases.append(Case(f"{fmt}/{name}", fmt, category, expect, build, **kw))


# ---- jmocap clip .npz ---------------------------------------------------------------------


def _clip_cases(reg: _Registry) -> None:
    def arrays(T=24, **kw) -> dict[str, np.ndarray]:
        return dict(clip_to_arrays(valid_clip("body25", T, **kw)))

    def add(name, category, expect, mutate=None, *, T=24, compressed=False, raw=None, clip_kw=None, **kw):
        """``mutate(arrays, marker)`` edits the arrays (returns None or new arrays); ``raw(bytes,
        rng)`` replaces the file's bytes."""

        def build(root: Path, marker: Path, name=name):
            a = arrays(T, **(clip_kw or {}))
            if mutate is not None:
                new = mutate(a, marker)
                a = a if new is None else new
            data = npz_bytes(a, compressed)
            if raw is not None:
                data = raw(data, rng_for("clip", name))
            write_bytes(root / "clip" / f"{name}.npz", data)

        reg.add("clip", name, category, expect, build, **kw)

    def setk(key, value):
        def m(a, marker):
            a[key] = value
        return m

    def drop(key):
        def m(a, marker):
            del a[key]
        return m

    def kp(fn):
        def m(a, marker):
            k = a["keypoints"].copy()
            out = fn(k)
            a["keypoints"] = k if out is None else out
        return m

    # valid
    add("valid_16", "valid", "ok", T=16, fast=True)
    add("valid_24", "valid", "ok")
    add("valid_40", "valid", "ok", T=40, fast=True)
    add("valid_compressed", "valid", "ok", compressed=True)
    add("valid_no_extrinsics", "valid", "ok", clip_kw={"extrinsics": False}, fast=True)
    add("valid_no_subject", "valid", "ok", clip_kw={"subject": False})
    add("valid_extra_keys", "valid", "ok", setk("unknown_extra", np.arange(5)))
    add("valid_layout_upper", "valid", "ok", setk("layout", np.array("BODY25")))
    add("valid_float16", "valid", "ok", kp(lambda k: k.astype(np.float16)))
    add("valid_float64", "valid", "ok", kp(lambda k: k.astype(np.float64)))
    add("valid_bigendian", "valid", "ok", kp(lambda k: k.astype(">f4")))
    add("valid_fortran", "valid", "ok", kp(lambda k: np.asfortranarray(k)))

    def undetected(k):
        k[5:9] = 0

    add("valid_undetected_frames", "valid", "ok", kp(undetected), fast=True)

    def missing_nonzero(k):
        k[:, 3, 2] = 0  # missing joint whose coordinates are not zero (normalised, not rejected)

    add("valid_missing_joint_coords", "valid", "ok", kp(missing_nonzero))
    add("valid_conf_one", "valid", "ok", kp(lambda k: k.__setitem__((..., 2), 1.0)))
    add("valid_name_differs", "valid", "ok", setk("name", np.array("another name")))
    add("valid_height_2p2", "subject", "ok", setk("height_m", np.array(2.2)))
    add("valid_mass_150", "subject", "ok", setk("mass_kg", np.array(150.0)))
    add("valid_coco17", "valid", "ok", mutate=lambda a, m: dict(clip_to_arrays(valid_clip("coco17", 24))),
        layout="coco17", fast=True)
    add("valid_h36m17", "valid", "ok", mutate=lambda a, m: dict(clip_to_arrays(valid_clip("h36m17", 24))),
        layout="h36m17")

    # truncated / random bytes / not an npz
    for frac in (0.0, 0.1, 0.5, 0.9):
        add(f"truncated_{int(frac * 100)}", "truncated", "fail", raw=lambda d, r, f=frac: d[: int(len(d) * f)],
            fast=frac == 0.5)
    add("truncated_22_bytes", "truncated", "fail", raw=lambda d, r: d[:22])
    add("truncated_last_byte", "truncated", "fail", raw=lambda d, r: d[:-1])
    add("random_1k", "random_bytes", "fail", raw=lambda d, r: r.bytes(1024), fast=True)
    add("random_64k", "random_bytes", "fail", raw=lambda d, r: r.bytes(65536))
    add("random_pk_header", "random_bytes", "fail", raw=lambda d, r: b"PK\x03\x04" + r.bytes(4000))

    def flip(d, r):
        b = bytearray(d)
        for i in r.integers(len(b) // 4, len(b) // 2, 8):
            b[i] ^= 0xFF
        return bytes(b)

    add("bit_flips", "random_bytes", "fail", raw=flip)
    add("json_named_npz", "wrong_type", "fail", raw=lambda d, r: b'{"people": []}')

    def as_tar(d, r):
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w") as t:
            info = tarfile.TarInfo("x.npz")
            info.size = len(d)
            t.addfile(info, io.BytesIO(d))
        return buf.getvalue()

    add("tar_named_npz", "wrong_type", "fail", raw=as_tar)
    add("npy_named_npz", "wrong_type", "fail", raw=lambda d, r: npy_bytes(np.zeros((24, 25, 3), np.float32)))

    # missing fields
    for key in ("name", "layout", "fps", "keypoints", "intrinsics", "image_size"):
        add(f"missing_{key}", "missing_field", "fail", drop(key), mention=f"'{key}'", fast=key == "fps")
    add("missing_format", "missing_field", "fail", drop("format"))  # then it is a keypoint array

    # wrong types
    add("format_int", "wrong_type", "fail", setk("format", np.array(1)), mention="field 'format'")
    add("format_other", "wrong_type", "fail", setk("format", np.array("jmocap-clip-9")), mention="field 'format'")
    add("name_int", "wrong_type", "fail", setk("name", np.array(5)), mention="field 'name'")
    add("layout_unknown", "wrong_type", "fail", setk("layout", np.array("body26")), mention="field 'layout'")
    add("layout_int", "wrong_type", "fail", setk("layout", np.array(25)), mention="field 'layout'")
    add("fps_string_number", "wrong_type", "either", setk("fps", np.array("30")))
    add("fps_string", "wrong_type", "fail", setk("fps", np.array("fast")), mention="field 'fps'", fast=True)
    add("fps_bytes", "wrong_type", "either", setk("fps", np.array(b"30")))
    add("fps_bool", "wrong_type", "either", setk("fps", np.array(True)))
    add("fps_vector", "wrong_shape", "fail", setk("fps", np.array([30.0, 30.0])), mention="field 'fps'")
    add("fps_complex", "wrong_type", "fail", setk("fps", np.array(30 + 1j)), mention="field 'fps'")
    add("fps_object", "pickle", "fail", setk("fps", np.array(30.0, dtype=object)))
    add("keypoints_strings", "wrong_type", "fail", kp(lambda k: np.full(k.shape, "abc")),
        mention="field 'keypoints'")
    add("keypoints_numeric_strings", "wrong_type", "either", kp(lambda k: k.astype(str)))
    add("keypoints_bool", "wrong_type", "either", kp(lambda k: k > 0.5))
    add("keypoints_complex", "wrong_type", "either", kp(lambda k: k.astype(np.complex64)))
    add("keypoints_structured", "wrong_type", "fail",
        kp(lambda k: np.zeros(k.shape[0], dtype=[("x", "f4"), ("y", "f4")])), mention="field 'keypoints'")
    add("intrinsics_strings", "wrong_type", "fail", setk("intrinsics", np.array(["a", "b", "c", "d"])),
        mention="field 'intrinsics'")
    add("image_size_fraction", "wrong_type", "fail", setk("image_size", np.array([1920.5, 1080.0])),
        mention="field 'image_size'")
    add("image_size_negative", "wrong_type", "fail", setk("image_size", np.array([-1920, 1080])),
        mention="field 'image_size'")
    add("image_size_zero", "wrong_type", "fail", setk("image_size", np.array([0, 0])),
        mention="field 'image_size'")
    add("meta_invalid_json", "wrong_type", "fail", setk("meta", np.array("{")), mention="field 'meta'")
    add("meta_json_list", "wrong_type", "fail", setk("meta", np.array("[1, 2]")), mention="field 'meta'")
    add("meta_deep_json", "json_depth", "fail", setk("meta", np.array(deep_json())),
        mention=("field 'meta'", "max_json_depth"), fast=True)
    add("height_string", "wrong_type", "fail", setk("height_m", np.array("tall")), mention="field 'height_m'")
    add("height_vector", "wrong_shape", "fail", setk("height_m", np.array([1.7, 1.8])),
        mention="field 'height_m'")

    # shapes
    T = 24
    add("keypoints_2d_array", "wrong_shape", "fail", kp(lambda k: k[..., 0]), mention="field 'keypoints'")
    add("keypoints_24_joints", "wrong_shape", "fail", kp(lambda k: k[:, :24]), mention="field 'keypoints'")
    add("keypoints_26_joints", "wrong_shape", "fail", kp(lambda k: np.concatenate([k, k[:, :1]], 1)),
        mention="field 'keypoints'")
    add("keypoints_4d", "wrong_shape", "fail", kp(lambda k: k[..., None]), mention="field 'keypoints'")
    add("keypoints_one_frame_2d", "wrong_shape", "fail", kp(lambda k: k[0]), mention="field 'keypoints'")
    add("keypoints_scalar", "wrong_shape", "fail", kp(lambda k: np.array(1.0)), mention="field 'keypoints'")
    add("keypoints_no_confidence", "wrong_shape", "fail", kp(lambda k: k[..., :2]), mention="field 'keypoints'")
    add("intrinsics_3", "wrong_shape", "fail", setk("intrinsics", np.array([1000.0, 1000.0, 960.0])),
        mention="field 'intrinsics'")
    add("intrinsics_matrix", "wrong_shape", "fail", setk("intrinsics", np.eye(4) * 1000),
        mention="field 'intrinsics'")
    add("image_size_3", "wrong_shape", "fail", setk("image_size", np.array([1920, 1080, 3])),
        mention="field 'image_size'")
    add("extrinsics_3x4", "wrong_shape", "fail", setk("extrinsics", np.eye(4)[:3]), mention="field 'extrinsics'")

    def ext(fn):
        def m(a, marker):
            E = np.array(a["extrinsics"], np.float64)
            out = fn(E)
            a["extrinsics"] = E if out is None else out
        return m

    add("extrinsics_scaled", "extrinsics", "fail", ext(lambda E: E.__setitem__(slice(0, 3), E[:3] * 2)),
        mention="field 'extrinsics'")
    add("extrinsics_mirror", "extrinsics", "fail", ext(lambda E: E.__setitem__((0, slice(None)), -E[0])),
        mention="field 'extrinsics'")
    add("extrinsics_last_row", "extrinsics", "fail", ext(lambda E: E.__setitem__((3, 0), 1.0)),
        mention="field 'extrinsics'")
    add("gt_q_wrong_frames", "wrong_shape", "fail", setk("gt_q", np.zeros((T + 3, 35), np.float32)),
        mention="field 'gt_q'")
    add("gt_contacts_half", "wrong_type", "fail", setk("gt_contacts", np.full((T, 4), 0.5, np.float32)),
        mention="field 'gt_contacts'")

    # non-finite values
    def at(f, j, c, v):
        def fn(k):
            k[f, j, c] = v
        return kp(fn)

    add("keypoints_nan_frame_5", "nonfinite", "fail", at(5, 3, 0, np.nan), mention="frame 5", fast=True)
    add("keypoints_inf_frame_7", "nonfinite", "fail", at(7, 0, 1, np.inf), mention="frame 7")
    add("confidence_nan_frame_2", "nonfinite", "fail", at(2, 4, 2, np.nan), mention="frame 2")
    add("intrinsics_nan", "nonfinite", "fail", setk("intrinsics", np.array([np.nan, 1000, 960, 540.0])),
        mention="field 'intrinsics'")
    add("image_size_nan", "nonfinite", "fail", setk("image_size", np.array([np.nan, 1080.0])),
        mention="field 'image_size'")
    add("extrinsics_inf", "nonfinite", "fail", ext(lambda E: E.__setitem__((0, 3), np.inf)),
        mention="field 'extrinsics'")
    add("fps_nan", "nonfinite", "fail", setk("fps", np.array(np.nan)), mention="field 'fps'")
    add("fps_inf", "nonfinite", "fail", setk("fps", np.array(np.inf)), mention="field 'fps'")
    add("height_nan", "nonfinite", "fail", setk("height_m", np.array(np.nan)), mention="field 'height_m'")
    add("mass_inf", "nonfinite", "fail", setk("mass_kg", np.array(np.inf)), mention="field 'mass_kg'")

    # fps
    for label, v, exp in (("1e-9", 1e-9, "fail"), ("1e9", 1e9, "fail"), ("0", 0.0, "fail"), ("negative", -30.0, "fail"),
                          ("0p5", 0.5, "fail"), ("5000", 5000.0, "fail"), ("1", 1.0, "either"),
                          ("1000", 1000.0, "either"), ("2p5", 2.5, "either")):
        add(f"fps_{label}", "fps", exp, setk("fps", np.array(v)), mention="field 'fps'",
            fast=label in ("1e-9", "1e9"))

    # intrinsics
    def intr(fx, fy, cx, cy):
        return setk("intrinsics", np.array([fx, fy, cx, cy], np.float64))

    add("fx_1e-12", "intrinsics", "fail", intr(1e-12, 1e-12, 960, 540), mention="field 'intrinsics'", fast=True)
    add("fx_1e12", "intrinsics", "fail", intr(1e12, 1e12, 960, 540), mention="field 'intrinsics'")
    add("fx_negative", "intrinsics", "fail", intr(-1000, 1000, 960, 540), mention="field 'intrinsics'")
    add("fx_zero", "intrinsics", "fail", intr(0, 1000, 960, 540), mention="field 'intrinsics'")
    add("cx_1e9", "intrinsics", "fail", intr(1000, 1000, 1e9, 540), mention="field 'intrinsics'")
    add("fx_fy_ratio_100", "intrinsics", "fail", intr(1000, 10, 960, 540), mention="field 'intrinsics'")
    add("image_1x1", "intrinsics", "fail", setk("image_size", np.array([1, 1])),
        mention=("field 'image_size'", "field 'intrinsics'"))
    add("image_1e9", "intrinsics", "fail", setk("image_size", np.array([10**9, 10**9])),
        mention=("field 'image_size'", "field 'intrinsics'"))
    add("principal_point_outside", "intrinsics", "either", intr(1000, 1000, -100, 540))

    # extrinsics: where the camera is
    def cam_at(eye, target=(0, 0, 0.95)):
        return setk("extrinsics", look_at(eye, target))

    add("camera_1000km", "extrinsics", "fail", cam_at((0, -1e6, 1.3)), mention="field 'extrinsics'", fast=True)
    add("camera_below_floor", "extrinsics", "fail", cam_at((0, -4, -5)), mention="field 'extrinsics'", fast=True)
    add("camera_999m", "extrinsics", "either", cam_at((0, -999, 1.3)))
    add("camera_upside_down", "extrinsics", "either",
        ext(lambda E: np.diag([-1.0, -1.0, 1.0, 1.0]) @ E))
    add("camera_inside_person", "extrinsics", "either", cam_at((0, 0, 1.0), (0, 1, 1.0)))

    # confidence
    def conf(v):
        return kp(lambda k: k.__setitem__((..., 2), v))

    add("confidence_1e-30", "confidence", "fail", conf(1e-30), mention="field 'keypoints'", fast=True)
    add("confidence_1p5", "confidence", "fail", conf(1.5), mention="field 'keypoints'")
    add("confidence_negative", "confidence", "fail", conf(-0.1), mention="field 'keypoints'")
    add("confidence_zero", "confidence", "fail", conf(0.0), mention="field 'keypoints'")
    add("confidence_0p049", "confidence", "fail", conf(0.049), mention="field 'keypoints'")
    add("confidence_0p05", "confidence", "either", conf(0.05))

    # visibility
    def only(k, frames, joints):
        keep = np.zeros(k.shape[:2], bool)
        keep[np.ix_(frames, joints)] = True
        k[~keep] = 0

    add("one_joint_one_frame", "visibility", "fail", kp(lambda k: only(k, [7], [1])), mention="field 'keypoints'",
        fast=True)
    add("one_usable_frame_of_40", "visibility", "fail", kp(lambda k: only(k, [20], list(range(25)))), T=40,
        mention="field 'keypoints'")
    add("four_joints_per_frame", "visibility", "fail", kp(lambda k: only(k, list(range(24)), [0, 1, 2, 5])),
        mention="field 'keypoints'")
    add("every_other_frame_empty", "visibility", "ok", kp(lambda k: k.__setitem__(slice(1, None, 2), 0)))
    add("first_30_of_40_empty", "visibility", "either", kp(lambda k: k.__setitem__(slice(0, 30), 0)), T=40)
    add("coords_1e7", "visibility", "fail", at(3, 0, 0, 1e7), mention=("field 'keypoints'", "frame 3"))
    add("coords_outside_image", "visibility", "either", kp(lambda k: k.__setitem__((..., 0), k[..., 0] - 3000)))
    add("all_joints_one_point", "visibility", "either",
        kp(lambda k: k.__setitem__((..., slice(0, 2)), np.array([960.0, 540.0], np.float32))))

    # subject
    for key, v, label in (("height_m", 100.0, "height_100"), ("mass_kg", 1e6, "mass_1e6"),
                          ("height_m", 0.01, "height_0p01"), ("mass_kg", 0.0, "mass_0"),
                          ("height_m", -1.75, "height_negative"), ("height_m", 2.6, "height_2p6"),
                          ("height_m", 0.4, "height_0p4"), ("mass_kg", 5.0, "mass_5")):
        add(label, "subject", "fail", setk(key, np.array(v)), mention=f"field '{key}'",
            fast=label in ("height_100", "mass_1e6"))

    # empty / tiny / huge
    add("empty_T0", "empty", "fail", kp(lambda k: k[:0]), mention="field 'keypoints'", fast=True)
    add("T1", "empty", "either", kp(lambda k: k[:1]))
    add("T2", "empty", "either", kp(lambda k: k[:2]))

    def claims_huge(d, r):
        # keypoints.npy's header says (10**9, 25, 3): 300 GB, the data is 24 frames
        arrays = dict(clip_to_arrays(valid_clip("body25", 24)))
        members = [(f"{k}.npy", npy_bytes(v)) for k, v in arrays.items() if k != "keypoints"]
        members.append(("keypoints.npy", npy_header((10**9, 25, 3)) + arrays["keypoints"].tobytes()))
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as z:
            for n, b in members:
                z.writestr(zip_entry(n), b)
        return buf.getvalue()

    add("header_claims_1e9_frames", "huge", "fail", raw=claims_huge, fast=True)

    def duplicate_member(d, r):
        buf = io.BytesIO(d)
        with zipfile.ZipFile(buf, "a") as z, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "Duplicate name"
            z.writestr(zip_entry("fps.npy"), npy_bytes(np.array(1e9)))
        return buf.getvalue()

    add("duplicate_member_fps", "wrong_type", "either", raw=duplicate_member)

    # pickles (never unpickled: clip files are read without pickle)
    add("meta_pickle", "pickle", "fail",
        lambda a, m: a.__setitem__("meta", np.array(Payload(m, "clip/meta_pickle"), dtype=object)),
        mention="field 'meta'", fast=True)
    add("keypoints_pickle", "pickle", "fail",
        lambda a, m: a.__setitem__("keypoints", np.array(Payload(m, "clip/keypoints_pickle", "system"),
                                                         dtype=object)),
        mention="field 'keypoints'")

    # zip bomb as a clip file
    def build_bomb(root: Path, marker: Path):
        bomb_npz(root / "clip" / "bomb.npz")

    reg.add("clip", "bomb", "bomb", "fail", build_bomb, mention="max_", fast=True,
            note="keypoints.npy expands to 1.2 GiB")

    # names
    def named(stem: str, *, raw_name: bytes | None = None) -> Builder:
        def build(root: Path, marker: Path):
            folder = root / "clip" / "names"
            folder.mkdir(parents=True, exist_ok=True)
            data = npz_bytes(arrays(16))
            if raw_name is not None:
                p = os.path.join(os.fsencode(folder), raw_name)
                with open(p, "wb") as f:
                    f.write(data)
            else:
                write_bytes(folder / f"{stem}.npz", data)
        return build

    reg.add("clip", "names/" + "n" * 240, "names", "ok", named("n" * 240), note="240-byte file stem")
    reg.add("clip", "names/" + "x" * 251, "names", "either", named("x" * 251), fast=True,
            note="a 251-byte clip name (the result file name is 255 bytes)")
    reg.add("clip", "names/caf\udce9", "names", "either", named("", raw_name=b"caf\xe9.npz"),
            containers=False, note="a file name that is not UTF-8")
    reg.add("clip", "names/sp ace;$(touch x)'q\"", "names", "ok", named("sp ace;$(touch x)'q\""),
            note="shell metacharacters in the file name")

    # twin: a clip file and an OpenPose folder with the same stem (names keep the suffix)
    def twin(root: Path, marker: Path):
        folder = root / "clip" / "twin"
        write_openpose_folder(valid_clip("body25", 16), folder / "twin", name="take")
        write_bytes(folder / "twin.npz", npz_bytes(arrays(16)))

    reg.add("clip", "twin/twin", "valid", "ok", twin, clips=2, fast=True,
            note="twin.npz next to the OpenPose folder twin/ (+ twin.camera.json)")


# ---- OpenPose folders -----------------------------------------------------------------------


def _frame(folder: Path, i: int, name: str = "take") -> Path:
    return folder / f"{name}_{i:012d}_keypoints.json"


def _openpose_cases(reg: _Registry) -> None:
    def add(name, category, expect, mutate=None, *, T=16, sidecar=True, first=0, **kw):
        """``mutate(folder, sidecar_path, marker)`` corrupts the written folder."""

        def build(root: Path, marker: Path, name=name):
            folder = root / "openpose" / name
            write_openpose_folder(valid_clip("body25", T), folder, name="take", first_frame=first,
                                  write_camera=sidecar)
            if mutate is not None:
                mutate(folder, folder.with_name(name + ".camera.json"), marker)

        reg.add("openpose", name, category, expect, build, **kw)

    def frame_bytes(i, data):
        return lambda f, s, m: write_bytes(_frame(f, i), data)

    def frame_edit(i, fn):
        return lambda f, s, m: edit_json(_frame(f, i), fn)

    def person_edit(i, fn):
        def edit(d):
            fn(d["people"][0])
        return frame_edit(i, edit)

    # valid
    add("valid_16", "valid", "ok", fast=True)
    add("valid_40", "valid", "ok", T=40)
    add("valid_start_1000", "valid", "ok", first=1000)

    def camera_inside(f, s, m):
        s.rename(f / "camera.json")

    add("valid_camera_json_inside", "valid", "ok", camera_inside)

    def unpadded(f, s, m):
        for p in sorted(f.glob("*_keypoints.json")):
            n = int(p.name.split("_")[1])
            p.rename(f / f"take_{n}_keypoints.json")

    add("valid_unpadded", "valid", "ok", unpadded)

    def gap(f, s, m):
        for i in (5, 6, 7):
            _frame(f, i).unlink()

    add("valid_gap_5_7", "frames", "ok", gap)

    def two_people(f, s, m):
        def edit(d):
            p = json.loads(json.dumps(d["people"][0]))
            p["pose_keypoints_2d"] = [v * 0.5 for v in p["pose_keypoints_2d"]]  # smaller, less confident
            d["people"].append(p)
        for i in range(16):
            edit_json(_frame(f, i), edit)

    add("valid_two_people", "valid", "ok", two_people)
    add("valid_person_id_int", "valid", "ok",
        lambda f, s, m: [edit_json(_frame(f, i), lambda d: d["people"][0].__setitem__("person_id", 3))
                         for i in range(16)])
    add("valid_empty_frame", "valid", "ok", frame_edit(4, lambda d: d.__setitem__("people", [])))
    add("valid_extra_files", "valid", "ok", lambda f, s, m: (f / "README.txt").write_text("notes"))
    add("valid_no_version", "valid", "ok", frame_edit(2, lambda d: d.pop("version")))
    add("valid_fifty_people", "valid", "either",
        lambda f, s, m: [edit_json(_frame(f, i), lambda d: d.__setitem__("people", d["people"] * 50))
                         for i in range(16)])
    add("no_sidecar", "camera", "fail", sidecar=False, fast=True, mention=("field 'image_size'",),
        note="no camera: no image size unless --image-size")

    # one frame file's bytes
    def trunc(i):
        return lambda f, s, m: write_bytes(_frame(f, i), _frame(f, i).read_bytes()[:57])

    add("frame_truncated", "truncated", "fail", trunc(3), mention="frame 3", fast=True)
    add("frame_random_bytes", "random_bytes", "fail",
        lambda f, s, m: write_bytes(_frame(f, 3), rng_for("op_rand").bytes(300)), mention="frame 3")
    add("frame_empty_file", "empty", "fail", frame_bytes(3, b""), mention="frame 3")
    add("frame_not_utf8", "encoding", "fail", frame_bytes(3, LATIN1), mention="frame 3", fast=True)
    add("frame_utf16", "encoding", "fail",
        lambda f, s, m: write_bytes(_frame(f, 3), _frame(f, 3).read_text().encode("utf-16")), mention="frame 3")
    add("frame_deep_json", "json_depth", "fail",
        frame_bytes(3, ('{"people": [{"pose_keypoints_2d": ' + deep_json() + "}]}").encode()),
        mention=("frame 3", "max_json_depth"), fast=True)
    add("frame_huge_int", "huge", "either",
        frame_bytes(3, ('{"people": [{"pose_keypoints_2d": [' + HUGE_INT + "]}]}").encode()))
    add("frame_int_1e400", "huge", "either",
        person_edit(3, lambda p: p["pose_keypoints_2d"].__setitem__(0, BIG_INT)), fast=True)
    add("frame_literal_1e400", "nonfinite", "ok",
        lambda f, s, m: write_bytes(_frame(f, 3), re.sub(r'("pose_keypoints_2d": \[)[^,]+', r"\g<1>1e400",
                                                         _frame(f, 3).read_text(), count=1).encode()),
        note="1e400 parses as inf: a missing joint")
    add("frame_nan", "nonfinite", "ok", person_edit(3, lambda p: p["pose_keypoints_2d"].__setitem__(0, float("nan"))))
    add("frame_infinity", "nonfinite", "ok",
        person_edit(3, lambda p: p["pose_keypoints_2d"].__setitem__(1, float("inf"))))

    # wrong types
    add("people_string", "wrong_type", "fail", frame_edit(3, lambda d: d.__setitem__("people", "nobody")),
        mention=("frame 3", "field 'people'"), fast=True)
    add("people_null", "wrong_type", "fail", frame_edit(3, lambda d: d.__setitem__("people", None)),
        mention="frame 3")
    add("people_missing", "wrong_type", "fail", frame_edit(3, lambda d: d.pop("people")), mention="frame 3")
    add("person_is_list", "wrong_type", "fail", frame_edit(3, lambda d: d.__setitem__("people", [[1, 2, 3]])),
        mention="frame 3")
    add("pose_string", "wrong_type", "fail", person_edit(3, lambda p: p.__setitem__("pose_keypoints_2d", "1,2,3")),
        mention="frame 3")
    add("pose_strings_inside", "wrong_type", "fail",
        person_edit(3, lambda p: p["pose_keypoints_2d"].__setitem__(4, "x")), mention="frame 3")
    add("pose_bools", "wrong_type", "either",
        person_edit(3, lambda p: p.__setitem__("pose_keypoints_2d", [True] * 75)))
    add("pose_nulls", "wrong_type", "ok", person_edit(3, lambda p: p.__setitem__("pose_keypoints_2d", [None] * 75)))
    add("pose_nested_triplets", "wrong_shape", "fail",
        person_edit(3, lambda p: p.__setitem__("pose_keypoints_2d",
                                               [p["pose_keypoints_2d"][k:k + 3] for k in range(0, 75, 3)])),
        mention="frame 3")
    add("pose_dict", "wrong_type", "fail", person_edit(3, lambda p: p.__setitem__("pose_keypoints_2d", {"x": 1})),
        mention="frame 3")
    add("pose_nested_lists_deep", "wrong_type", "fail",
        person_edit(3, lambda p: p.__setitem__("pose_keypoints_2d", [[[[1.0]]]] * 75)), mention="frame 3")
    add("top_level_list", "wrong_type", "fail", frame_bytes(3, b"[1, 2, 3]"), mention="frame 3")
    add("top_level_number", "wrong_type", "fail", frame_bytes(3, b"42"), mention="frame 3")
    add("top_level_string", "wrong_type", "fail", frame_bytes(3, b'"people"'), mention="frame 3")
    add("person_id_string", "wrong_type", "either", person_edit(3, lambda p: p.__setitem__("person_id", "abc")))
    add("person_id_huge", "huge", "either", person_edit(3, lambda p: p.__setitem__("person_id", [BIG_INT])))

    # wrong lengths
    for n in (74, 76, 54, 100):
        add(f"pose_{n}_values", "wrong_shape", "fail",
            person_edit(3, lambda p, n=n: p.__setitem__("pose_keypoints_2d", (p["pose_keypoints_2d"] * 2)[:n])),
            mention="frame 3", fast=n == 74)
    add("pose_empty_list", "wrong_shape", "ok", person_edit(3, lambda p: p.__setitem__("pose_keypoints_2d", [])))

    # frame numbers
    def duplicate(f, s, m):
        (f / "take_3_keypoints.json").write_bytes(_frame(f, 3).read_bytes())

    add("duplicate_frame_3", "frames", "fail", duplicate, mention="frame 3", fast=True)

    def stray(n):
        def m(f, s, marker):
            (f / f"take_{n}_keypoints.json").write_bytes(_frame(f, 2).read_bytes())
        return m

    add("stray_frame_100000", "frames", "fail", stray(100000), mention="max_frame_gap", fast=True)
    add("stray_frame_10_30", "frames", "fail", stray(10**30), mention="max_frame_gap")
    add("frame_number_missing", "frames", "fail",
        lambda f, s, m: (f / "take_keypoints.json").write_bytes(_frame(f, 2).read_bytes()))
    add("frame_number_negative_looking", "frames", "either",
        lambda f, s, m: _frame(f, 15).rename(f / "take_-15_keypoints.json"))
    add("single_frame", "empty", "either", T=1)

    def only_people(i_keep, joints):
        def m(f, s, marker):
            for i in range(16):
                def edit(d, i=i):
                    if i != i_keep:
                        d["people"] = []
                    else:
                        v = d["people"][0]["pose_keypoints_2d"]
                        d["people"][0]["pose_keypoints_2d"] = [
                            x if (k // 3) in joints else 0.0 for k, x in enumerate(v)]
                edit_json(_frame(f, i), edit)
        return m

    add("one_joint_one_frame", "visibility", "fail", only_people(6, {1}), mention="field 'keypoints'", fast=True)
    add("nobody_anywhere", "visibility", "fail", only_people(-1, set()), mention="field 'keypoints'")

    def confidences(v):
        def m(f, s, marker):
            for i in range(16):
                def edit(d):
                    p = d["people"][0]["pose_keypoints_2d"]
                    for k in range(2, 75, 3):
                        p[k] = v
                edit_json(_frame(f, i), edit)
        return m

    add("confidence_1e-30", "confidence", "fail", confidences(1e-30), mention="field 'keypoints'", fast=True)
    add("confidence_1p5", "confidence", "ok", confidences(1.5), note="clipped to 1")
    add("confidence_negative", "confidence", "fail", confidences(-1.0), mention="field 'keypoints'")

    # camera sidecar
    def side(fn):
        return lambda f, s, m: edit_json(s, fn)

    def side_bytes(data):
        return lambda f, s, m: write_bytes(s, data)

    def sset(key, value):
        return side(lambda d: d.__setitem__(key, value))

    add("sidecar_truncated", "camera", "fail", lambda f, s, m: write_bytes(s, s.read_bytes()[:40]), fast=True)
    add("sidecar_random", "camera", "fail", side_bytes(rng_for("sidecar").bytes(200)))
    add("sidecar_list", "camera", "fail", side_bytes(b"[1000, 1000, 960, 540]"))
    add("sidecar_empty_object", "camera", "fail", side_bytes(b"{}"), mention="field 'fx'")
    add("sidecar_not_utf8", "camera", "fail", side_bytes(b'{"fx": "\xff\xfe"}'))
    add("sidecar_deep", "json_depth", "fail", side_bytes(deep_json().encode()),
        mention=("max_json_depth", "field "))
    add("sidecar_missing_fx", "camera", "fail", side(lambda d: d.pop("fx")), mention="field 'fx'")
    add("sidecar_missing_width", "camera", "fail", side(lambda d: d.pop("width")), mention="field 'width'")
    add("sidecar_fx_string", "camera", "fail", sset("fx", "1000px"), mention="field 'fx'")
    add("sidecar_fx_null", "camera", "fail", sset("fx", None), mention="field 'fx'")
    add("sidecar_fx_list", "camera", "fail", sset("fx", [1000]), mention="field 'fx'")
    add("sidecar_fx_negative", "intrinsics", "fail", sset("fx", -1000.0), mention=("field 'fx'", "field 'intrinsics'"))
    add("sidecar_fx_1e-12", "intrinsics", "fail", sset("fx", 1e-12), mention=("field 'fx'", "field 'intrinsics'"),
        fast=True)
    add("sidecar_fx_1e300", "intrinsics", "fail", sset("fx", 1e300), mention=("field 'fx'", "field 'intrinsics'"))
    add("sidecar_fx_nan", "nonfinite", "fail", sset("fx", float("nan")), mention=("field 'fx'", "field 'intrinsics'"))
    add("sidecar_fx_inf", "nonfinite", "fail", sset("fx", float("inf")), mention=("field 'fx'", "field 'intrinsics'"))
    add("sidecar_fy_100x", "intrinsics", "fail", sset("fy", 100000.0), mention=("field 'fy'", "field 'intrinsics'"))
    add("sidecar_cx_1e9", "intrinsics", "fail", sset("cx", 1e9), mention=("field 'cx'", "field 'intrinsics'"))
    add("sidecar_fx_huge_int", "huge", "fail", sset("fx", BIG_INT))
    add("sidecar_width_0", "camera", "fail", sset("width", 0), mention=("field 'width'", "field 'image_size'"))
    add("sidecar_width_fraction", "camera", "fail", sset("width", 1920.5), mention=("field 'width'",))
    add("sidecar_width_1e9", "camera", "fail", sset("width", 10**9),
        mention=("field 'width'", "field 'image_size'", "field 'intrinsics'"))
    add("sidecar_width_huge_int", "huge", "fail", sset("width", 10**30),
        mention=("field 'width'", "field 'image_size'", "field 'intrinsics'"))
    add("sidecar_height_string", "camera", "fail", sset("height", "1080"), mention=("field 'height'", "field 'width'"))
    add("sidecar_width_bool", "camera", "either", sset("width", True))
    add("sidecar_extrinsics_3x3", "extrinsics", "fail", sset("extrinsics", np.eye(3).tolist()),
        mention="field 'extrinsics'")
    add("sidecar_extrinsics_strings", "extrinsics", "fail", sset("extrinsics", [["a"] * 4] * 4),
        mention="field 'extrinsics'")
    add("sidecar_extrinsics_ragged", "extrinsics", "fail", sset("extrinsics", [[1, 0, 0, 0], [0, 1], [0], []]),
        mention="field 'extrinsics'")
    add("sidecar_extrinsics_scaled", "extrinsics", "fail", sset("extrinsics", (np.eye(4) * 3).tolist()),
        mention="field 'extrinsics'")
    add("sidecar_camera_1000km", "extrinsics", "fail", sset("extrinsics", look_at((0, -1e6, 1.3)).tolist()),
        mention="field 'extrinsics'", fast=True)
    add("sidecar_camera_below_floor", "extrinsics", "fail", sset("extrinsics", look_at((0, -4, -5)).tolist()),
        mention="field 'extrinsics'")
    add("sidecar_fps_1e-9", "fps", "fail", sset("fps", 1e-9), mention="field 'fps'", fast=True)
    add("sidecar_fps_1e9", "fps", "fail", sset("fps", 1e9), mention="field 'fps'")
    add("sidecar_fps_0", "fps", "fail", sset("fps", 0), mention="field 'fps'")
    add("sidecar_fps_negative", "fps", "fail", sset("fps", -30), mention="field 'fps'")
    add("sidecar_fps_string", "fps", "fail", sset("fps", "30"), mention="field 'fps'")
    add("sidecar_fps_nan", "fps", "fail", sset("fps", float("nan")), mention="field 'fps'")
    add("sidecar_fps_null", "fps", "ok", sset("fps", None), note="default 30 fps")
    add("sidecar_fps_true", "fps", "either", sset("fps", True))
    add("sidecar_extra_keys", "camera", "ok", sset("distortion", [0.1, 0.0, 0.0, 0.0]))

    def sidecar_dir(f, s, m):
        s.unlink()
        s.mkdir()

    add("sidecar_is_a_folder", "camera", "either", sidecar_dir)

    def pickle_sidecar(f, s, m):
        write_bytes(s, pickle.dumps(Payload(m, "openpose/sidecar_pickle")))

    add("sidecar_pickle", "pickle", "fail", pickle_sidecar)


# ---- COCO results / annotations ------------------------------------------------------------------


def _coco_cases(reg: _Registry) -> None:
    def add(name, category, expect, mutate=None, *, T=24, sidecar=True, annotations=False, **kw):
        """``mutate(data)`` edits the loaded JSON (a results list or an annotations dict)."""

        def build(root: Path, marker: Path, name=name):
            path = root / "coco" / f"{name}.json"
            clip = valid_clip("coco17", T)
            path.parent.mkdir(parents=True, exist_ok=True)
            write_coco_results(clip, path)
            if annotations:
                res = json.loads(path.read_text())
                data = {
                    "images": [{"id": i, "width": 1920, "height": 1080, "file_name": f"{i:06d}.jpg"} for i in range(T)],
                    "annotations": [{"id": k, "image_id": r["image_id"], "category_id": 1,
                                     "keypoints": [v if j % 3 != 2 else 2 for j, v in enumerate(r["keypoints"])],
                                     "num_keypoints": 17} for k, r in enumerate(res)],
                    "categories": [{"id": 1, "name": "person"}],
                }
                write_json(path, data)
            if sidecar:
                write_camera_json(path.with_name(f"{name}.camera.json"), clip)
            if mutate is not None:
                if isinstance(mutate, bytes):
                    write_bytes(path, mutate)
                else:
                    edit_json(path, mutate)

        reg.add("coco", name, category, expect, build, **kw)

    def each(fn):
        def m(data):
            for r in data:
                fn(r)
        return m

    def entry(i, fn):
        return lambda data: fn(data[i])

    add("valid", "valid", "ok", fast=True)
    add("valid_annotations", "valid", "ok", sidecar=False, annotations=True)
    add("valid_start_500", "valid", "ok", each(lambda r: r.__setitem__("image_id", r["image_id"] + 500)))

    def second_person(data):
        extra = [dict(r, score=r["score"] * 0.1, keypoints=[v * 0.5 for v in r["keypoints"]]) for r in data]
        data.extend(extra)

    add("valid_two_people", "valid", "ok", second_person)
    add("valid_other_categories", "valid", "ok", lambda d: d.extend([dict(r, category_id=2) for r in d]))
    add("valid_gap", "frames", "ok", replaces(lambda d: [r for r in d if r["image_id"] not in (3, 4, 5)]))
    add("no_sidecar", "camera", "fail", sidecar=False, mention=("field 'image_size'",))
    def raw(name, category, expect, data_fn, **kw):
        """``data_fn(valid file bytes, rng)`` gives the file's bytes."""

        def build(root: Path, marker: Path, name=name):
            path = root / "coco" / f"{name}.json"
            clip = valid_clip("coco17", 24)
            path.parent.mkdir(parents=True, exist_ok=True)
            write_coco_results(clip, path)
            write_camera_json(path.with_name(f"{name}.camera.json"), clip)
            write_bytes(path, data_fn(path.read_bytes(), rng_for("coco", name)))

        reg.add("coco", name, category, expect, build, **kw)

    raw("truncated", "truncated", "fail", lambda d, r: d[: len(d) // 2], fast=True)
    raw("random_bytes", "random_bytes", "fail", lambda d, r: r.bytes(2000))
    raw("empty_file", "empty", "fail", lambda d, r: b"")
    raw("empty_list", "empty", "fail", lambda d, r: b"[]")
    raw("empty_object", "wrong_type", "either", lambda d, r: b"{}", clips=None,
        note="not recognisable as keypoints: may be skipped like notes.json")
    raw("not_utf8", "encoding", "fail", lambda d, r: d.replace(b'"image_id"', b'"image_\xe9d"', 1))
    raw("deep_json", "json_depth", "fail", lambda d, r: deep_json().encode(), mention="max_json_depth", fast=True)
    raw("huge_int", "huge", "either",
        lambda d, r: d.replace(b'"score": ', b'"big": ' + HUGE_INT.encode() + b', "score": ', 1))
    add("image_id_string", "wrong_type", "fail", entry(0, lambda r: r.__setitem__("image_id", "img0")),
        mention="field 'image_id'", fast=True)
    add("image_id_float", "wrong_type", "fail", entry(0, lambda r: r.__setitem__("image_id", 0.5)),
        mention="field 'image_id'")
    add("image_id_bool", "wrong_type", "fail", entry(0, lambda r: r.__setitem__("image_id", True)),
        mention="field 'image_id'")
    add("image_id_null", "wrong_type", "fail", entry(0, lambda r: r.__setitem__("image_id", None)),
        mention="field 'image_id'")
    add("image_id_huge", "frames", "fail", entry(0, lambda r: r.__setitem__("image_id", 10**30)),
        mention=("max_frame_gap", "field 'image_id'"))
    add("image_id_100000", "frames", "fail", entry(0, lambda r: r.__setitem__("image_id", 100000)),
        mention="max_frame_gap", fast=True)
    add("image_id_negative", "frames", "either", entry(0, lambda r: r.__setitem__("image_id", -1)))
    add("keypoints_string", "wrong_type", "fail", entry(2, lambda r: r.__setitem__("keypoints", "x")))
    add("keypoints_nested", "wrong_shape", "fail",
        entry(2, lambda r: r.__setitem__("keypoints", [r["keypoints"][k:k + 3] for k in range(0, 51, 3)])))
    add("keypoints_50_values", "wrong_shape", "fail", entry(2, lambda r: r["keypoints"].pop()), fast=True)
    add("keypoints_missing", "wrong_type", "fail", entry(2, lambda r: r.pop("keypoints")))
    add("keypoints_nulls", "wrong_type", "ok", entry(2, lambda r: r["keypoints"].__setitem__(0, None)))
    add("keypoints_int_1e400", "huge", "either", entry(2, lambda r: r["keypoints"].__setitem__(0, BIG_INT)))
    add("score_string", "wrong_type", "either", entry(2, lambda r: r.__setitem__("score", "high")))
    add("score_nan", "nonfinite", "either", entry(2, lambda r: r.__setitem__("score", float("nan"))))
    add("all_category_2", "empty", "fail", each(lambda r: r.__setitem__("category_id", 2)))
    add("entries_are_lists", "wrong_type", "either", replaces(lambda d: [[1, 2, 3] for _ in d]), clips=None,
        note="not recognisable as keypoints: may be skipped like notes.json")
    add("entry_null", "wrong_type", "fail", lambda d: d.__setitem__(3, None))

    def only(i_keep, joints, conf=None):
        def m(data):
            out = []
            for r in data:
                if r["image_id"] == i_keep:
                    kp = r["keypoints"]
                    r["keypoints"] = [v if (k // 3) in joints else 0 for k, v in enumerate(kp)]
                    out.append(r)
                elif i_keep < 0:
                    if conf is not None:
                        r["keypoints"] = [v if k % 3 != 2 else conf for k, v in enumerate(r["keypoints"])]
                    out.append(r)
            return out
        return replaces(m)

    add("confidence_1e-30", "confidence", "fail", only(-1, set(), conf=1e-30), mention="field 'keypoints'",
        fast=True)
    add("one_joint_one_frame", "visibility", "fail", only(5, {0}), mention="field 'keypoints'")
    add("annotations_width_0", "camera", "either",
        lambda d: [im.__setitem__("width", 0) for im in d["images"]], sidecar=False, annotations=True)
    add("annotations_sizes_disagree", "camera", "either",
        lambda d: d["images"][3].__setitem__("width", 640), sidecar=False, annotations=True)
    add("annotations_no_images", "wrong_type", "either", lambda d: d.pop("images"), sidecar=False,
        annotations=True)
    add("annotations_string", "wrong_type", "fail", lambda d: d.__setitem__("annotations", "none"),
        sidecar=False, annotations=True)


# ---- MMPose predictions ------------------------------------------------------------------------


def _mmpose_cases(reg: _Registry) -> None:
    def add(name, category, expect, mutate=None, *, T=24, sidecar=True, raw=None, **kw):
        def build(root: Path, marker: Path, name=name):
            path = root / "mmpose" / f"{name}.json"
            clip = valid_clip("coco17", T)
            path.parent.mkdir(parents=True, exist_ok=True)
            write_mmpose_json(clip, path)
            if sidecar:
                write_camera_json(path.with_name(f"{name}.camera.json"), clip)
            if mutate is not None:
                edit_json(path, mutate)
            if raw is not None:
                write_bytes(path, raw(path.read_bytes(), rng_for("mmpose", name)))

        reg.add("mmpose", name, category, expect, build, **kw)

    def inst(i, fn):
        return lambda d: fn(d[i]["instances"][0])

    def frame(i, fn):
        return lambda d: fn(d[i])

    add("valid", "valid", "ok", fast=True)
    add("valid_demo_format", "valid", "ok",
        replaces(lambda d: {"meta_info": {"dataset_name": "coco"}, "instance_info": d}))
    add("valid_track_ids", "valid", "ok", lambda d: [f["instances"][0].__setitem__("track_id", 0) for f in d])
    add("valid_gap", "frames", "ok", replaces(lambda d: [f for f in d if f["frame_id"] not in (4, 5)]))
    add("single_image", "empty", "either", replaces(lambda d: d[0]["instances"]))
    add("truncated", "truncated", "fail", raw=lambda d, r: d[: len(d) // 3], fast=True)
    add("random_bytes", "random_bytes", "fail", raw=lambda d, r: r.bytes(500))
    add("empty_list", "empty", "fail", raw=lambda d, r: b"[]")
    add("not_utf8", "encoding", "fail", raw=lambda d, r: b"\xff\xfe" + d)
    add("deep_json", "json_depth", "fail", raw=lambda d, r: deep_json().encode(), mention="max_json_depth")
    add("frame_id_string", "wrong_type", "fail", frame(2, lambda f: f.__setitem__("frame_id", "two")),
        mention=("field 'frame_id'",), fast=True)
    add("frame_id_float", "wrong_type", "fail", frame(2, lambda f: f.__setitem__("frame_id", 2.5)),
        mention="field 'frame_id'")
    add("frame_id_null", "wrong_type", "fail", frame(2, lambda f: f.__setitem__("frame_id", None)),
        mention="field 'frame_id'")
    add("frame_id_duplicate", "frames", "fail", frame(2, lambda f: f.__setitem__("frame_id", 1)), mention="frame 1")
    add("frame_id_100000", "frames", "fail", frame(23, lambda f: f.__setitem__("frame_id", 100000)),
        mention="max_frame_gap", fast=True)
    add("instances_not_list", "wrong_type", "fail", frame(2, lambda f: f.__setitem__("instances", {"a": 1})),
        mention="field 'instances'")
    add("instances_empty_everywhere", "visibility", "fail", lambda d: [f.__setitem__("instances", []) for f in d],
        mention="field 'keypoints'")
    add("keypoints_strings", "wrong_type", "fail", inst(2, lambda i: i.__setitem__("keypoints", [["a", "b"]] * 17)),
        mention="frame 2")
    add("keypoints_3d", "wrong_shape", "fail", inst(2, lambda i: i.__setitem__("keypoints", [[1.0, 2.0, 3.0]] * 17)),
        mention="frame 2")
    add("keypoints_16", "wrong_shape", "fail", inst(2, lambda i: i["keypoints"].pop()), mention="frame 2", fast=True)
    add("keypoints_ragged", "wrong_shape", "fail", inst(2, lambda i: i["keypoints"].__setitem__(3, [1.0])),
        mention="frame 2")
    add("keypoints_missing", "wrong_type", "fail", inst(2, lambda i: i.pop("keypoints")), mention="frame 2")
    add("scores_16", "wrong_shape", "fail", inst(2, lambda i: i["keypoint_scores"].pop()), mention="frame 2")
    add("scores_string", "wrong_type", "fail", inst(2, lambda i: i.__setitem__("keypoint_scores", "high")),
        mention="frame 2")
    add("scores_1e-30", "confidence", "fail",
        lambda d: [f["instances"][0].__setitem__("keypoint_scores", [1e-30] * 17) for f in d],
        mention="field 'keypoints'")
    add("scores_nan", "nonfinite", "fail",
        lambda d: [f["instances"][0].__setitem__("keypoint_scores", [float("nan")] * 17) for f in d],
        mention="field 'keypoints'")
    add("bbox_score_string", "wrong_type", "either", inst(2, lambda i: i.__setitem__("bbox_score", "x")))
    add("track_id_string", "wrong_type", "either", inst(2, lambda i: i.__setitem__("track_id", "t0")))
    add("meta_info_only", "wrong_type", "either", replaces(lambda d: {"meta_info": {}}), clips=None,
        note="not recognisable as keypoints: may be skipped like notes.json")
    add("instance_info_string", "wrong_type", "fail", replaces(lambda d: {"meta_info": {}, "instance_info": "x"}))


# ---- VideoPose3D --------------------------------------------------------------------------------


def _vp3d_kp(T: int = 24, layout: str = "h36m17", conf: bool = False) -> np.ndarray:
    c = valid_clip(layout, T, camera="h36m" if layout == "h36m17" else "default")
    return np.asarray(c.keypoints if conf else c.keypoints[..., :2], np.float32)


def _vp3d_cases(reg: _Registry) -> None:
    def add(name, category, expect, make, **kw):
        """``make(marker)`` returns the ``.npz``'s arrays (dict) or bytes."""

        def build(root: Path, marker: Path, name=name):
            path = root / "vp3d" / f"{name}.npz"
            out = make(marker)
            if isinstance(out, bytes):
                write_bytes(path, out)
            elif callable(out):
                path.parent.mkdir(parents=True, exist_ok=True)
                out(path)
            else:
                write_bytes(path, npz_bytes(out))

        reg.add("vp3d", name, category, expect, build, **kw)

    def written(seqs, layout="h36m17", video_metadata=None):
        return lambda m: (lambda p: write_videopose3d(p, seqs, layout=layout, video_metadata=video_metadata))

    meta = {"layout_name": "h36m", "num_joints": 17, "keypoints_symmetry": [[4, 5, 6], [1, 2, 3]]}

    def arrays(positions, metadata=None):
        return {"positions_2d": np.array(positions, dtype=object),
                "metadata": np.array(meta if metadata is None else metadata, dtype=object)}

    kp = _vp3d_kp()
    add("valid_s1", "valid", "ok", written({"S1": {"Walking": [kp]}}), fast=True)
    add("valid_4_cameras_2_actions", "valid", "ok",
        written({"S1": {"Walking": [kp] * 4, "Sitting 1": [kp[:16]] * 4}}), clips=8)
    add("valid_custom_video", "valid", "ok",
        written({"video1": {"custom": [kp]}}, video_metadata={"video1": {"w": 1000, "h": 1002}}))
    add("valid_with_confidence", "valid", "ok", written({"S1": {"Walking": [_vp3d_kp(conf=True)]}}))
    add("valid_coco", "valid", "ok",
        written({"clipA": {"custom": [_vp3d_kp(layout="coco17")]}}, layout="coco17",
                video_metadata={"clipA": {"w": 1920, "h": 1080}}), layout="coco17")
    add("collide_walk_1", "names", "ok", written({"S1": {"Walk 1": [kp], "Walk_1": [kp[:16]]}}), clips=2,
        distinct=True, fast=True, note="actions 'Walk 1' and 'Walk_1' both give S1_Walk_1_0: two distinct results")
    add("collide_slash", "names", "ok", written({"S1": {"a/b": [kp], "a_b": [kp[:16]]}}), clips=2,
        distinct=True)
    add("collide_subject", "names", "ok", written({"S 1": {"x": [kp]}, "S_1": {"x": [kp[:16]]}},
                                                  video_metadata={"S 1": {"w": 1000, "h": 1002},
                                                                  "S_1": {"w": 1000, "h": 1002}}), clips=2,
        distinct=True)
    # pickle payloads (VideoPose3D's positions_2d and metadata are pickled dicts by definition)
    add("pickle_positions", "pickle", "fail",
        lambda m: arrays(Payload(m, "vp3d/pickle_positions", "system")), fast=True)
    add("pickle_inside_positions", "pickle", "fail",
        lambda m: arrays({"S1": {"Walking": [Payload(m, "vp3d/pickle_inside_positions")]}}))
    add("pickle_metadata", "pickle", "fail",
        lambda m: arrays({"S1": {"Walking": [kp]}}, Payload(m, "vp3d/pickle_metadata")), fast=True)
    add("pickle_video_metadata", "pickle", "fail",
        lambda m: arrays({"S1": {"Walking": [kp]}}, dict(meta, video_metadata=Payload(m, "vp3d/pickle_vm"))))
    # corrupted
    add("positions_list", "wrong_type", "fail", lambda m: arrays([kp]), mention="field 'positions_2d'")
    add("positions_float_array", "wrong_type", "fail", lambda m: {"positions_2d": kp, "metadata": np.array(meta, dtype=object)},
        mention="field 'positions_2d'")
    add("layout_mpii", "wrong_type", "fail", lambda m: arrays({"S1": {"W": [kp]}}, dict(meta, layout_name="mpii")),
        mention="field 'metadata.layout_name'")
    add("num_joints_25", "wrong_type", "fail", lambda m: arrays({"S1": {"W": [kp]}}, dict(meta, num_joints=25)),
        mention="field 'metadata.num_joints'")
    add("metadata_list", "wrong_type", "fail", lambda m: arrays({"S1": {"W": [kp]}}, [1, 2]),
        mention="field 'metadata'")
    add("array_4_channels", "wrong_shape", "fail",
        lambda m: arrays({"S1": {"W": [np.concatenate([kp, kp], -1)]}}), mention="field ")
    add("array_16_joints", "wrong_shape", "fail", lambda m: arrays({"S1": {"W": [kp[:, :16]]}}), mention="field ")
    add("array_strings", "wrong_type", "fail", lambda m: arrays({"S1": {"W": [kp.astype(str)]}}), mention="field ")
    add("array_empty", "empty", "fail", lambda m: arrays({"S1": {"W": [kp[:0]]}}))
    add("array_all_nan", "nonfinite", "fail", lambda m: arrays({"S1": {"W": [np.full_like(kp, np.nan)]}}),
        mention="field 'keypoints'")
    add("actions_list", "wrong_type", "fail", lambda m: arrays({"S1": [kp]}))
    add("cameras_empty", "empty", "either", lambda m: arrays({"S1": {"W": []}}), clips=None)
    add("video_metadata_w0", "camera", "fail",
        lambda m: arrays({"v": {"W": [kp]}}, dict(meta, video_metadata={"v": {"w": 0, "h": 1002}})))
    add("video_metadata_w_string", "camera", "fail",
        lambda m: arrays({"v": {"W": [kp]}}, dict(meta, video_metadata={"v": {"w": "wide", "h": 1002}})))
    add("video_metadata_fps_1e9", "fps", "fail",
        lambda m: arrays({"v": {"W": [kp]}}, dict(meta, video_metadata={"v": {"w": 1000, "h": 1002, "fps": 1e9}})),
        mention="field 'fps'")
    add("truncated", "truncated", "fail",
        lambda m: npz_bytes(arrays({"S1": {"W": [kp]}}))[:300], fast=True)
    add("random_bytes", "random_bytes", "fail", lambda m: b"PK\x03\x04" + rng_for("vp3d").bytes(3000))


# ---- plain keypoint arrays ----------------------------------------------------------------------


def _array_cases(reg: _Registry) -> None:
    def add(name, category, expect, make, *, suffix=".npy", sidecar=True, **kw):
        """``make(kp (T, 17, 3) h36m17 pixels + confidence, marker)`` returns an array (saved
        as ``.npy``), a dict (saved as ``.npz``) or bytes."""

        def build(root: Path, marker: Path, name=name):
            clip = valid_clip("h36m17", 24)
            out = make(np.array(clip.keypoints), marker)
            path = root / "array" / f"{name}{suffix}"
            if isinstance(out, bytes):
                write_bytes(path, out)
            elif isinstance(out, dict):
                write_bytes(path, npz_bytes(out))
            else:
                write_bytes(path, npy_bytes(out))
            if sidecar:
                write_camera_json(path.with_name(f"{name}.camera.json"), clip)

        reg.add("array", name, category, expect, build, **kw)

    add("valid_xy", "valid", "ok", lambda k, m: k[..., :2])
    add("valid_xyc", "valid", "ok", lambda k, m: k, fast=True)
    add("valid_npz_with_camera", "valid", "ok",
        lambda k, m: {"keypoints": k, "fps": np.array(25.0), "image_size": np.array([1920, 1080]),
                      "intrinsics": np.array(DEFAULT_INTRINSICS)}, suffix=".npz", sidecar=False, fast=True)
    add("valid_npz_kp2d_key", "valid", "ok", lambda k, m: {"kp2d": k, "other": np.zeros(3)}, suffix=".npz")
    add("valid_float16", "valid", "ok", lambda k, m: k.astype(np.float16))
    add("valid_int", "valid", "ok", lambda k, m: np.rint(k[..., :2]).astype(np.int32))
    add("valid_fortran", "valid", "ok", lambda k, m: np.asfortranarray(k))
    add("no_sidecar", "camera", "fail", lambda k, m: k, sidecar=False, mention=("field 'image_size'",))
    add("body25_shape", "wrong_shape", "fail", lambda k, m: np.zeros((24, 25, 3), np.float32) + 5, fast=True)
    add("shape_T_17", "wrong_shape", "fail", lambda k, m: k[..., 0])
    add("shape_17_2", "wrong_shape", "fail", lambda k, m: k[0, :, :2])
    add("shape_4_channels", "wrong_shape", "fail", lambda k, m: np.concatenate([k, k[..., :1]], -1))
    add("scalar", "wrong_shape", "fail", lambda k, m: np.array(3.0))
    add("empty_T0", "empty", "fail", lambda k, m: k[:0], mention=("field ", "frame ", "no frames"))
    add("object_pickle", "pickle", "fail", lambda k, m: np.array([Payload(m, "array/object_pickle", "system")] * 3,
                                                                 dtype=object), fast=True)
    add("strings", "wrong_type", "fail", lambda k, m: k.astype(str))
    add("bools", "wrong_type", "fail", lambda k, m: k > 100)
    add("complex", "wrong_type", "fail", lambda k, m: k.astype(np.complex64))
    add("all_nan", "nonfinite", "fail", lambda k, m: np.full_like(k, np.nan), mention="field 'keypoints'")
    add("some_inf", "nonfinite", "ok", lambda k, m: k.__setitem__((3, 4, 0), np.inf) or k)
    add("confidence_7", "confidence", "fail", lambda k, m: k.__setitem__((..., 2), 7.0) or k, mention="frame 0")
    add("confidence_1e-30", "confidence", "fail", lambda k, m: k.__setitem__((..., 2), 1e-30) or k,
        mention="field 'keypoints'")
    add("npz_two_unknown_arrays", "wrong_type", "fail", lambda k, m: {"a": k, "b": k}, suffix=".npz")
    size = np.array(DEFAULT_SIZE)  # (no sidecar: its fps would win over the file's)
    add("npz_fps_string", "wrong_type", "fail", lambda k, m: {"keypoints": k, "fps": np.array("fast"), "image_size": size},
        suffix=".npz", sidecar=False, mention="field 'fps'")
    add("npz_fps_1e9", "fps", "fail", lambda k, m: {"keypoints": k, "fps": np.array(1e9), "image_size": size},
        suffix=".npz", sidecar=False, mention="field 'fps'")
    add("npz_fps_vector", "wrong_shape", "fail",
        lambda k, m: {"keypoints": k, "fps": np.array([25.0, 30.0]), "image_size": size}, suffix=".npz",
        sidecar=False, mention="field 'fps'")
    add("npz_image_size_3", "wrong_shape", "fail",
        lambda k, m: {"keypoints": k, "image_size": np.array([1920, 1080, 3])}, suffix=".npz", sidecar=False,
        mention="field 'image_size'")
    add("npz_image_size_nan", "nonfinite", "fail",
        lambda k, m: {"keypoints": k, "image_size": np.array([np.nan, 1080.0])}, suffix=".npz", sidecar=False,
        mention="field 'image_size'")
    add("npz_intrinsics_strings", "wrong_type", "fail",
        lambda k, m: {"keypoints": k, "image_size": np.array([1920, 1080]), "intrinsics": np.array(["a"] * 4)},
        suffix=".npz", sidecar=False, mention="field 'intrinsics'")
    add("npz_intrinsics_1e-12", "intrinsics", "fail",
        lambda k, m: {"keypoints": k, "image_size": np.array([1920, 1080]),
                      "intrinsics": np.array([1e-12, 1e-12, 960, 540])}, suffix=".npz", sidecar=False,
        mention="field 'intrinsics'")
    add("npz_pickle_fps", "pickle", "fail",
        lambda k, m: {"keypoints": k, "fps": np.array(Payload(m, "array/npz_pickle_fps"), dtype=object)},
        suffix=".npz")
    add("truncated", "truncated", "fail", lambda k, m: npy_bytes(k)[:200])
    add("random_bytes", "random_bytes", "fail", lambda k, m: rng_for("array").bytes(700))
    add("header_only", "truncated", "fail", lambda k, m: npy_header((24, 17, 3)))
    add("header_claims_1e9_frames", "huge", "fail", lambda k, m: npy_header((10**9, 17, 3)) + k.tobytes())
    add("header_garbage", "wrong_type", "fail",
        lambda k, m: b"\x93NUMPY\x01\x00\x20\x00{'descr': __import__('os') }    \n" + k.tobytes())


@functools.lru_cache(maxsize=1)
def _all_cases() -> tuple[Case, ...]:
    reg = _Registry()
    for fn in (_clip_cases, _openpose_cases, _coco_cases, _mmpose_cases, _vp3d_cases, _array_cases):
        fn(reg)
    ids = [c.id for c in reg.cases]
    dup = {i for i in ids if ids.count(i) > 1}
    assert not dup, f"duplicate case ids: {sorted(dup)}"
    for a in reg.cases:
        for b in reg.cases:
            assert a is b or not a.owns(b.id), f"case {a.id} would own {b.id}'s clips"
    return tuple(reg.cases)


def cases(*, fast: bool = False, formats: Sequence[str] | None = None,
          layout: str | None = None, containers: bool | None = None) -> list[Case]:
    """The per-clip cases (``fast``: only the default suite's), filtered."""
    out = []
    for c in _all_cases():
        if fast and not c.fast:
            continue
        if formats is not None and c.format not in formats:
            continue
        if layout is not None and c.layout != layout:
            continue
        if containers is not None and c.containers != containers:
            continue
        out.append(c)
    return out


def build_folder(root: Path, chosen: Iterable[Case], marker: Path) -> list[Case]:
    """Write ``chosen`` under ``root`` (created); returns them as a list."""
    root.mkdir(parents=True, exist_ok=True)
    chosen = list(chosen)
    for c in chosen:
        c.build(root, marker)
    return chosen


def _fixed_time(info: tarfile.TarInfo) -> tarfile.TarInfo:
    info.mtime, info.uid, info.gid, info.uname, info.gname = 0, 0, 0, "", ""
    return info


def pack(folder: Path, dest: Path) -> Path:
    """``folder``'s tree as a ``.zip``, ``.tar``, ``.tar.gz`` (by ``dest``'s suffix); paths
    relative to ``folder``. Symbolic links go into tars as links and are left out of zips."""
    name = dest.name.lower()
    dest.parent.mkdir(parents=True, exist_ok=True)
    if name.endswith(".zip"):
        with zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as z:
            for p in sorted(folder.rglob("*")):
                if p.is_file() and not p.is_symlink():
                    z.writestr(zip_entry(p.relative_to(folder).as_posix()), p.read_bytes(), zipfile.ZIP_DEFLATED)
    else:
        mode = "w:gz" if name.endswith((".tar.gz", ".tgz")) else "w"
        with tarfile.open(dest, mode) as t:
            for p in sorted(folder.rglob("*")):
                t.add(p, p.relative_to(folder).as_posix(), recursive=False, filter=_fixed_time)
    return dest


# =========================================================================================
# jmocap clip archives (manifest.jsonl)
# =========================================================================================


@dataclass(frozen=True)
class Member:
    """One manifest line of a built clip archive and what must happen to it."""

    name: str
    file: str
    expect: str
    layout: str = "body25"
    mention: tuple[str, ...] = ()
    case: str = ""


def build_clip_archive(dest: Path, kind: str, chosen: Iterable[Case], marker: Path,
                       staging: Path) -> tuple[Path, list[Member]]:
    """The ``clip`` cases of ``chosen`` as members of a jmocap clip archive (``kind``: ``folder``,
    ``zip``, ``tar``, ``tar.gz``): member ``m_<case>.npz`` named ``m_<case>`` in the manifest,
    plus lines the reader must take as they are (a status ``failed`` line, a name listed twice
    whose later line wins, and an interrupted last line without a newline, ignored).
    Returns the INPUT path and the members to expect."""
    staging.mkdir(parents=True, exist_ok=True)
    members: list[Member] = []
    lines: list[dict] = []
    files: dict[str, bytes] = {}
    for c in chosen:
        if c.format != "clip" or not c.containers or c.clips != 1 or "/" in c.id.removeprefix("clip/"):
            continue
        tmp = staging / "clip_cases"
        c.build(tmp, marker)
        src = tmp / "clip" / (c.id.removeprefix("clip/") + ".npz")
        stem = "m_" + c.id.removeprefix("clip/").replace(".", "_")
        files[f"{stem}.npz"] = src.read_bytes()
        members.append(Member(stem, f"{stem}.npz", c.expect, c.layout, c.mention, c.id))
        lines.append({"name": stem, "file": f"{stem}.npz", "status": "ok", "frames": 0})
    good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
    files["dup_second.npz"] = good
    lines.append({"name": "dup", "file": "missing_first.npz", "status": "ok"})
    lines.append({"name": "dup", "file": "dup_second.npz", "status": "ok"})
    members.append(Member("dup", "dup_second.npz", "ok", case="manifest/duplicate_name"))
    lines.append({"name": "was_failed", "file": None, "status": "failed", "error": "x"})
    text = "".join(json.dumps(e) + "\n" for e in lines) + '{"name": "interrupted", "file": "dup_'
    files["manifest.jsonl"] = text.encode()
    files["archive.json"] = json.dumps({"generator": "tests/fuzz_inputs.py"}).encode()
    return _write_container(dest, kind, files), members


def _write_container(dest: Path, kind: str, files: dict[str, bytes], prefix: str = "") -> Path:
    if kind == "folder":
        dest.mkdir(parents=True, exist_ok=True)
        for n, b in files.items():
            write_bytes(dest / n, b)
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    if kind == "zip":
        with zipfile.ZipFile(dest, "w") as z:
            for n, b in files.items():
                z.writestr(zip_entry(prefix + n), b)
        return dest
    with tarfile.open(dest, "w:gz" if kind == "tar.gz" else "w") as t:
        for n, b in files.items():
            info = tarfile.TarInfo(prefix + n)
            info.size = len(b)
            t.addfile(info, io.BytesIO(b))
    return dest


# =========================================================================================
# archive-level cases (one run each)
# =========================================================================================


@dataclass
class RunSpec:
    """What one archive-level case runs: ``jmocap reconstruct INPUT OUTPUT *args``."""

    input: Path
    output: Path
    args: list[str] = field(default_factory=list)
    # name -> ok | fail | either (clips that must be in the manifest, with that outcome)
    clips: dict[str, str] = field(default_factory=dict)
    # name -> strings one of which a failure message must contain
    mention: dict[str, tuple[str, ...]] = field(default_factory=dict)
    absent: tuple[str, ...] = ()  # names that must not be in the manifest
    skipped: tuple[str, ...] = ()  # substrings of summary["skipped"][*]["path"] that must be there
    untouched: tuple[Path, ...] = ()  # files that must not be read into a result / changed
    umask: int | None = None
    env: dict[str, str] = field(default_factory=dict)
    inprocess: bool = True  # may run in the test process (signals need a subprocess)
    # what the test checks besides: chmod (restore after), rerun, stale / keep (files in OUTPUT),
    # refused (a tar member), outside_links, exact_clips, max_tmp_bytes (TMPDIR's peak), signal
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ArchiveCase:
    id: str
    category: str
    build: Callable[[Path], RunSpec] = field(repr=False)  # (sandbox) -> RunSpec
    exit: frozenset[int] = frozenset({0})
    message: tuple[str, ...] = ()  # exit 2: the one-line message contains one of these
    fast: bool = False
    needs_non_root: bool = False
    needs_symlinks: bool = False
    note: str = ""


def _save_valid(path: Path, T: int = 16, name: str = "take") -> Path:
    write_bytes(path, npz_bytes(dict(clip_to_arrays(valid_clip("body25", T, name=name)))))
    return path


def _outside_clips(sandbox: Path) -> tuple[Path, Path]:
    a = _save_valid(sandbox / OUTSIDE / "x.npz")
    b = _save_valid(sandbox / OUTSIDE / "y.npz")
    return a, b


def _inp(sandbox: Path) -> Path:
    return sandbox / "in"


def _out(sandbox: Path) -> Path:
    # deep, so that a name with ../.. under it still lands inside the sandbox (and is seen)
    return sandbox / "a" / "b" / "out"


def _archive_cases() -> list[ArchiveCase]:
    out: list[ArchiveCase] = []

    def case(id, category, exit, *, message=(), fast=False, needs_non_root=False, needs_symlinks=False, note=""):
        def deco(fn):
            out.append(ArchiveCase(id, category, fn, frozenset(exit), tuple(message), fast, needs_non_root,
                                   needs_symlinks, note))
            return fn
        return deco

    # ---- arguments and paths
    @case("output_is_a_file", "arguments", {2}, message=("out",), fast=True)
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        o = _out(s)
        write_bytes(o, b"I am a file")
        return RunSpec(_inp(s), o, untouched=(o,))

    @case("output_read_only", "arguments", {2}, message=("out",), fast=True, needs_non_root=True)
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        o = _out(s)
        o.mkdir(parents=True)
        o.chmod(0o555)
        return RunSpec(_inp(s), o, extra={"chmod": [(o, 0o755)]})

    @case("output_parent_read_only", "arguments", {2}, message=("out",), needs_non_root=True)
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        o = _out(s)
        o.parent.mkdir(parents=True, exist_ok=True)
        o.parent.chmod(0o555)
        return RunSpec(_inp(s), o, extra={"chmod": [(o.parent, 0o755)]})

    @case("input_missing", "arguments", {2}, message=("in",), fast=True)
    def _(s):
        return RunSpec(s / "does_not_exist", _out(s))

    @case("input_empty_folder", "arguments", {2}, message=("clip", "no "), fast=True)
    def _(s):
        _inp(s).mkdir(parents=True)
        return RunSpec(_inp(s), _out(s))

    @case("input_only_non_clips", "arguments", {2}, message=("clip", "no "))
    def _(s):
        write_bytes(_inp(s) / "notes.txt", b"hello")
        write_bytes(_inp(s) / "take.camera.json", b"{}")
        write_bytes(_inp(s) / ".hidden.npz", b"")
        return RunSpec(_inp(s), _out(s))

    @case("input_empty_zip", "arguments", {2}, message=("clip", "no "))
    def _(s):
        p = s / "in.zip"
        with zipfile.ZipFile(p, "w"):
            pass
        return RunSpec(p, _out(s))

    @case("input_zip_random_bytes", "arguments", {2}, message=("in.zip",), fast=True)
    def _(s):
        p = s / "in.zip"
        write_bytes(p, rng_for("zip_random").bytes(5000))
        return RunSpec(p, _out(s))

    @case("input_tar_truncated", "arguments", {2}, message=("in.tar",))
    def _(s):
        folder = s / "staging"
        _save_valid(folder / "a.npz")
        _save_valid(folder / "b.npz")
        p = pack(folder, s / "in.tar")
        write_bytes(p, p.read_bytes()[:700])
        return RunSpec(p, _out(s))

    @case("input_is_a_text_file", "arguments", {1, 2})
    def _(s):
        p = s / "in.txt"
        write_bytes(p, b"hello")
        return RunSpec(p, _out(s))

    @case("input_equals_output", "arguments", {0, 1, 2})
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        return RunSpec(_inp(s), _inp(s), clips={}, extra={"output_inside_input": True})

    @case("output_inside_input_rerun", "arguments", {0})
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        _save_valid(_inp(s) / "sub" / "b.npz")
        return RunSpec(_inp(s), _inp(s) / "results", clips={"a": "ok", "sub/b": "ok"},
                       extra={"output_inside_input": True, "rerun": True})

    @case("bad_batch_0", "arguments", {2}, message=("batch",))
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        return RunSpec(_inp(s), _out(s), args=["--batch", "0"])

    @case("bad_chunk_negative", "arguments", {2}, message=("chunk",))
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        return RunSpec(_inp(s), _out(s), args=["--chunk", "-5"])

    @case("single_clip_file", "inputs", {0}, fast=True)
    def _(s):
        p = _save_valid(_inp(s) / "walk.npz")
        return RunSpec(p, _out(s), clips={"walk": "ok"})

    @case("single_openpose_folder", "inputs", {0})
    def _(s):
        write_openpose_folder(valid_clip("body25", 16), _inp(s) / "video01", name="video01")
        return RunSpec(_inp(s) / "video01", _out(s), clips={"video01": "ok"})

    @case("image_size_argument", "inputs", {0})
    def _(s):
        write_openpose_folder(valid_clip("body25", 16), _inp(s) / "nocam", name="nocam", write_camera=False)
        return RunSpec(_inp(s), _out(s), args=["--image-size", "1920x1080"], clips={"nocam": "ok"})

    # ---- zips
    @case("zip_bomb_input", "bomb", {2}, message=("max_",), fast=True,
          note="a zip input whose member expands to 1.2 GiB")
    def _(s):
        p = s / "in.zip"
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        raw_zip(p, [("a.npz", good), ("bomb/zeros.npy", deflated_zeros(npy_header((BOMB_BYTES // 300, 25, 3))))])
        return RunSpec(p, _out(s), extra={"max_tmp_bytes": 64 << 20})

    @case("zip_bomb_lying_size", "bomb", {1, 2}, message=("max_", "in.zip"),
          note="the member's header says 1000 bytes; the stream expands to 1.2 GiB")
    def _(s):
        p = s / "in.zip"
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        raw_zip(p, [("a.npz", good), ("liar.npy", deflated_zeros(npy_header((BOMB_BYTES // 300, 25, 3))))],
                declared_size={"liar.npy": 1000})
        return RunSpec(p, _out(s), clips={"a": "either"}, extra={"max_tmp_bytes": 64 << 20})

    @case("zip_many_members", "bomb", {0, 1, 2}, note="20 000 empty members")
    def _(s):
        p = s / "in.zip"
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        raw_zip(p, [("a.npz", good)] + [(f"junk/{i:05d}.txt", b"") for i in range(20000)])
        return RunSpec(p, _out(s), clips={"a": "either"})

    @case("zip_slip_member", "outside", {0, 2}, message=("..",), note="member '../../escaped.npz'")
    def _(s):
        p = s / "in.zip"
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        raw_zip(p, [("a.npz", good), ("../../escaped.npz", good)])
        return RunSpec(p, _out(s), clips={"a": "either"}, absent=("../../escaped",))

    @case("zip_absolute_member", "outside", {0, 2}, message=("/",))
    def _(s):
        p = s / "in.zip"
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        raw_zip(p, [("a.npz", good), (str(s / "abs_escaped.npz"), good)])
        return RunSpec(p, _out(s), clips={"a": "either"})

    @case("zip_nested_manifest", "manifest", {0, 1}, fast=True,
          note="loose clips plus sub/manifest.jsonl: the loose clips are reconstructed")
    def _(s):
        p = s / "in.zip"
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        files = {"a.npz": good, "takes/b.npz": good,
                 "sub/manifest.jsonl": b'{"name": "c", "file": "c.npz", "status": "ok"}\n', "sub/c.npz": good}
        staging = s / "staging"
        write_openpose_folder(valid_clip("body25", 16), staging / "op" / "walk", name="walk")
        for q in sorted((staging).rglob("*")):
            if q.is_file():
                files[q.relative_to(staging).as_posix()] = q.read_bytes()
        _write_container(p, "zip", files)
        return RunSpec(p, _out(s), clips={"a": "ok", "takes/b": "ok", "op/walk": "ok"})

    @case("zip_pickle_vp3d", "pickle", {1}, fast=True, note="a VideoPose3D file with a pickle payload, in a zip")
    def _(s):
        p = s / "in.zip"
        marker = s / MARKER
        evil = npz_bytes({"positions_2d": np.array({"S1": {"W": [Payload(marker, "zip_pickle", "system")]}},
                                                   dtype=object),
                          "metadata": np.array(Payload(marker, "zip_pickle_meta"), dtype=object)})
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        _write_container(p, "zip", {"a.npz": good, "data_2d_h36m_evil.npz": evil})
        return RunSpec(p, _out(s), clips={"a": "ok", "data_2d_h36m_evil": "fail"})

    # ---- tars
    def tar_with(s: Path, extra_members: Callable[[tarfile.TarFile], None], mode: str = "w") -> Path:
        p = s / ("in.tar" if mode == "w" else "in.tar.gz")
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        with tarfile.open(p, mode) as t:
            info = tarfile.TarInfo("a.npz")
            info.size = len(good)
            t.addfile(info, io.BytesIO(good))
            extra_members(t)
        return p

    def link(name, target, kind=tarfile.SYMTYPE):
        def add(t):
            info = tarfile.TarInfo(name)
            info.type = kind
            info.linkname = target
            t.addfile(info)
        return add

    @case("tar_member_dotdot", "outside", {0, 2}, message=("escaped",), fast=True,
          note="a member '../escaped.npz', refused by tarfile's 'data' filter")
    def _(s):
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))

        def add(t):
            info = tarfile.TarInfo("../escaped.npz")
            info.size = len(good)
            t.addfile(info, io.BytesIO(good))

        return RunSpec(tar_with(s, add), _out(s), clips={"a": "either"}, skipped=(), extra={"refused": "escaped"})

    @case("tar_symlink_absolute", "outside", {0, 2}, message=("passwd", "link"))
    def _(s):
        return RunSpec(tar_with(s, link("passwd.npz", "/etc/passwd")), _out(s), clips={"a": "either"},
                       extra={"refused": "passwd"})

    @case("tar_symlink_outside", "outside", {0, 2}, message=("link", "outside"))
    def _(s):
        x, _ = _outside_clips(s)
        # extracted under TMPDIR/<dir>/ (TMPDIR = sandbox/tmp): ../../outside/x.npz is the valid clip
        return RunSpec(tar_with(s, link("x.npz", "../../" + OUTSIDE + "/x.npz")), _out(s), clips={"a": "either"},
                       untouched=(x,), extra={"refused": "x.npz"})

    @case("tar_hardlink_outside", "outside", {0, 2}, message=("link", "outside"))
    def _(s):
        x, _ = _outside_clips(s)
        return RunSpec(tar_with(s, link("h.npz", str(x), tarfile.LNKTYPE)), _out(s), clips={"a": "either"},
                       untouched=(x,), extra={"refused": "h.npz"})

    @case("tar_fifo_member", "outside", {0, 1, 2}, message=("fifo", "special", "pipe"))
    def _(s):
        def add(t):
            info = tarfile.TarInfo("pipe.npz")
            info.type = tarfile.FIFOTYPE
            t.addfile(info)
        return RunSpec(tar_with(s, add), _out(s), clips={"a": "either"})

    @case("tar_gz_of_loose_files", "inputs", {0}, fast=False)
    def _(s):
        def add(t):
            good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 24))))
            info = tarfile.TarInfo("sub/b.npz")
            info.size = len(good)
            t.addfile(info, io.BytesIO(good))
        return RunSpec(tar_with(s, add, "w:gz"), _out(s), clips={"a": "ok", "sub/b": "ok"})

    # ---- clip archives: manifest lines
    def clip_archive(s: Path, lines: list[dict], files: dict[str, bytes], kind: str = "folder") -> Path:
        files = dict(files)
        files["manifest.jsonl"] = "".join(json.dumps(e) + "\n" for e in lines).encode()
        return _write_container(_inp(s) / ("arch" if kind == "folder" else f"arch.{kind}"), kind, files)

    def outside_lines(s: Path, kind: str) -> RunSpec:
        x, y = _outside_clips(s)
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        lines = [{"name": "a", "file": "a.npz", "status": "ok"},
                 {"name": "rel", "file": "../../" + OUTSIDE + "/x.npz", "status": "ok"},
                 {"name": "abs", "file": str(y), "status": "ok"},
                 {"name": "b", "file": "b.npz", "status": "ok"}]
        p = clip_archive(s, lines, {"a.npz": good, "b.npz": good}, kind)
        return RunSpec(p, _out(s), clips={"a": "ok", "b": "ok", "rel": "fail", "abs": "fail"},
                       mention={"rel": ("outside",), "abs": ("outside",)}, untouched=(x, y))

    for kind in ("folder", "zip", "tar"):
        case(f"manifest_outside_{kind}", "outside", {1}, fast=kind == "folder",
             note="lines '../../outside/x.npz' and an absolute path, where valid clips exist")(
            lambda s, kind=kind: outside_lines(s, kind))

    @case("manifest_line_without_file", "manifest", {1, 2}, message=("file",), fast=True)
    def _(s):
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        lines = [{"name": "a", "file": "a.npz", "status": "ok"}, {"name": "nofile", "status": "ok"}]
        return RunSpec(clip_archive(s, lines, {"a.npz": good}), _out(s), clips={"a": "ok", "nofile": "fail"},
                       mention={"nofile": ("'file'",)})

    @case("manifest_file_wrong_types", "manifest", {1, 2}, message=("file",))
    def _(s):
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        lines = [{"name": "a", "file": "a.npz", "status": "ok"}, {"name": "null", "file": None, "status": "ok"},
                 {"name": "int", "file": 7, "status": "ok"}, {"name": "list", "file": ["a.npz"], "status": "ok"},
                 {"name": "dir", "file": ".", "status": "ok"}]
        return RunSpec(clip_archive(s, lines, {"a.npz": good}), _out(s),
                       clips={"a": "ok", "null": "fail", "int": "fail", "list": "fail", "dir": "fail"})

    @case("manifest_names_escape", "outside", {1, 2}, message=("name",),
          note="names '../../escaped', an absolute path, '', '.', 'a/../../x': no file outside OUTPUT")
    def _(s):
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        names = ["../../escaped", str(s / "abs_escaped"), "", ".", "a/../../../x", "nul\x00name", "y" * 300]
        lines = [{"name": "ok1", "file": "a.npz", "status": "ok"}]
        lines += [{"name": n, "file": "a.npz", "status": "ok"} for n in names]
        return RunSpec(clip_archive(s, lines, {"a.npz": good}), _out(s),
                       clips={"ok1": "ok", **{n: "fail" for n in names}})

    @case("manifest_name_types", "manifest", {1, 2})
    def _(s):
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        lines = [{"name": "ok1", "file": "a.npz", "status": "ok"}, {"name": 5, "file": "a.npz", "status": "ok"},
                 {"name": None, "file": "a.npz", "status": "ok"}, {"name": ["x"], "file": "a.npz", "status": "ok"}]
        return RunSpec(clip_archive(s, lines, {"a.npz": good}), _out(s), clips={"ok1": "either"})

    @case("manifest_garbage_line", "manifest", {1, 2}, message=("manifest.jsonl", "line"))
    def _(s):
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        files = {"a.npz": good, "manifest.jsonl": b'{"name": "a", "file": "a.npz", "status": "ok"}\n{{{garbage\n'
                 b'{"name": "b", "file": "a.npz", "status": "ok"}\n'}
        return RunSpec(_write_container(_inp(s) / "arch", "folder", files), _out(s))

    @case("manifest_not_utf8", "manifest", {1, 2}, message=("manifest.jsonl",))
    def _(s):
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        files = {"a.npz": good, "manifest.jsonl": b'{"name": "a\xff", "file": "a.npz", "status": "ok"}\n'}
        return RunSpec(_write_container(_inp(s) / "arch", "folder", files), _out(s))

    @case("manifest_deep_json_line", "manifest", {1, 2}, message=("manifest.jsonl", "max_json_depth"))
    def _(s):
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        files = {"a.npz": good, "manifest.jsonl": b'{"name": "a", "file": "a.npz", "status": "ok"}\n'
                 + deep_json().encode() + b"\n"}
        return RunSpec(_write_container(_inp(s) / "arch", "folder", files), _out(s))

    @case("manifest_member_is_pickle_npz", "pickle", {1})
    def _(s):
        marker = s / MARKER
        evil = npz_bytes({**clip_to_arrays(valid_clip("body25", 16)),
                          "meta": np.array(Payload(marker, "manifest_member"), dtype=object)})
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        lines = [{"name": "a", "file": "a.npz", "status": "ok"}, {"name": "evil", "file": "evil.npz", "status": "ok"}]
        return RunSpec(clip_archive(s, lines, {"a.npz": good, "evil.npz": evil}, "zip"), _out(s),
                       clips={"a": "ok", "evil": "fail"})

    @case("manifest_bomb_member", "bomb", {1}, message=("max_",))
    def _(s):
        staging = s / "staging"
        bomb_npz(staging / "bomb.npz")
        good = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 16))))
        lines = [{"name": "a", "file": "a.npz", "status": "ok"}, {"name": "bomb", "file": "bomb.npz", "status": "ok"}]
        return RunSpec(clip_archive(s, lines, {"a.npz": good, "bomb.npz": (staging / "bomb.npz").read_bytes()}),
                       _out(s), clips={"a": "ok", "bomb": "fail"}, mention={"bomb": ("max_",)})

    # ---- folders: symlinks, strays, non-clips
    @case("symlink_self", "symlinks", {0}, fast=True, needs_symlinks=True,
          note="self -> . : each clip once, the link in summary['skipped']")
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        write_openpose_folder(valid_clip("body25", 16), _inp(s) / "op" / "walk", name="walk")
        (_inp(s) / "self").symlink_to(".")
        (_inp(s) / "op" / "up").symlink_to("..")
        return RunSpec(_inp(s), _out(s), clips={"a": "ok", "op/walk": "ok"}, skipped=("self",),
                       extra={"exact_clips": True})

    @case("symlinks_outside", "symlinks", {0}, fast=True, needs_symlinks=True,
          note="file and folder links to valid clips outside INPUT: not read")
    def _(s):
        x, y = _outside_clips(s)
        _save_valid(_inp(s) / "a.npz")
        (_inp(s) / "x.npz").symlink_to(x)
        (_inp(s) / "outdir").symlink_to(x.parent)
        (_inp(s) / "rel.npz").symlink_to(os.path.relpath(y, _inp(s)))
        return RunSpec(_inp(s), _out(s), clips={"a": "ok"}, absent=("outdir/x", "outdir/y"),
                       untouched=(x, y), extra={"outside_links": ["x", "rel", "outdir"]})

    @case("symlinks_inside", "symlinks", {0}, needs_symlinks=True,
          note="a link to a clip inside INPUT: that clip once, or twice under two names, never a failure")
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        (_inp(s) / "alias.npz").symlink_to("a.npz")
        return RunSpec(_inp(s), _out(s), clips={"a": "ok"})

    @case("symlink_loop", "symlinks", {0}, needs_symlinks=True)
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        (_inp(s) / "l1").symlink_to("l2")
        (_inp(s) / "l2").symlink_to("l1")
        (_inp(s) / "loop.npz").symlink_to("loop.npz")
        (_inp(s) / "deep").mkdir()
        (_inp(s) / "deep" / "back").symlink_to("../deep")
        return RunSpec(_inp(s), _out(s), clips={"a": "ok"})

    @case("symlink_dangling", "symlinks", {0, 1}, needs_symlinks=True)
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        (_inp(s) / "gone.npz").symlink_to("nowhere.npz")
        return RunSpec(_inp(s), _out(s), clips={"a": "ok"})

    @case("stray_top_level_keypoints", "openpose", {0, 1}, fast=True,
          note="a *_keypoints.json at the top next to subfolders of valid clips")
    def _(s):
        c = valid_clip("body25", 16)
        write_openpose_folder(c, _inp(s) / "walk", name="walk")
        write_openpose_folder(c, _inp(s) / "run", name="run")
        _save_valid(_inp(s) / "clips" / "a.npz")
        (_inp(s) / "stray_000000000000_keypoints.json").write_bytes(_frame(_inp(s) / "walk", 0, "walk").read_bytes())
        return RunSpec(_inp(s), _out(s), clips={"walk": "ok", "run": "ok", "clips/a": "ok"})

    @case("notes_json", "non_clips", {0}, fast=True, note="notes.json is not a clip: listed in summary['skipped']")
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        write_json(_inp(s) / "notes.json", {"author": "someone", "date": "2024-01-01"})
        write_json(_inp(s) / "sub" / "config.json", {"lr": 0.1})
        return RunSpec(_inp(s), _out(s), clips={"a": "ok"}, absent=("notes", "sub/config"),
                       skipped=("notes.json", "config.json"))

    @case("locked_folder", "permissions", {0, 1}, needs_non_root=True)
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        _save_valid(_inp(s) / "locked" / "b.npz")
        (_inp(s) / "locked").chmod(0)
        return RunSpec(_inp(s), _out(s), clips={"a": "ok"}, extra={"chmod": [(_inp(s) / "locked", 0o755)]})

    @case("unreadable_file", "permissions", {1}, needs_non_root=True)
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        p = _save_valid(_inp(s) / "b.npz")
        p.chmod(0)
        return RunSpec(_inp(s), _out(s), clips={"a": "ok", "b": "fail"}, extra={"chmod": [(p, 0o644)]})

    # ---- OUTPUT state
    @case("stale_temporaries", "output", {0}, fast=True,
          note="a killed run's .jmocap-*.tmp and .<name>.*.tmp are removed when the run starts")
    def _(s):
        _save_valid(_inp(s) / "a.npz")
        o = _out(s)
        stale = [o / ".jmocap-k2j3h4.tmp", o / ".a.npz.x8y7z6.tmp", o / "sub" / ".jmocap-77.tmp",
                 o / ".summary.json.abc.tmp"]
        for p in stale:
            write_bytes(p, b"partial")
        keep = [o / "keep.txt", o / ".hidden_user_file", o / "notes.tmp"]
        for p in keep:
            write_bytes(p, b"mine")
        return RunSpec(_inp(s), o, clips={"a": "ok"}, extra={"stale": stale, "keep": keep})

    for mask in (0o022, 0o027, 0o002):
        case(f"file_modes_umask_{mask:03o}", "output", {0}, fast=mask == 0o027,
             note="result files get 0o666 & ~umask")(
            lambda s, mask=mask: (_save_valid(_inp(s) / "a.npz"),
                                  RunSpec(_inp(s), _out(s), clips={"a": "ok"}, umask=mask))[1])

    # ---- signals
    for sig, code in (("SIGINT", 130), ("SIGTERM", 143)):
        case(f"signal_{sig}", "signals", {code}, fast=True,
             note=f"{sig} during a run: exit {code}, summary.json with interrupted: true")(
            lambda s, sig=sig: _signal_spec(s, sig))

    return out


def _signal_spec(s: Path, sig: str) -> RunSpec:
    inp = _inp(s)
    inp.mkdir(parents=True, exist_ok=True)
    data = npz_bytes(dict(clip_to_arrays(valid_clip("body25", 24))))  # the mixed runs' compiled shape
    for i in range(400):
        write_bytes(inp / f"c{i:03d}.npz", data)
    return RunSpec(inp, _out(s), inprocess=False, extra={"signal": sig})


@functools.lru_cache(maxsize=1)
def _archive_case_tuple() -> tuple[ArchiveCase, ...]:
    cs = _archive_cases()
    ids = [c.id for c in cs]
    assert len(ids) == len(set(ids)), "duplicate archive case ids"
    return tuple(cs)


def archive_cases(*, fast: bool = False) -> list[ArchiveCase]:
    """The archive-level cases (``fast``: only the default suite's)."""
    return [c for c in _archive_case_tuple() if c.fast or not fast]


def counts() -> dict[str, dict[str, int]]:
    """Case counts by format and category (per clip) and by category (archive level)."""
    out: dict[str, dict[str, int]] = {"format": {}, "category": {}, "expect": {}, "archive": {}}
    for c in _all_cases():
        out["format"][c.format] = out["format"].get(c.format, 0) + 1
        out["category"][c.category] = out["category"].get(c.category, 0) + 1
        out["expect"][c.expect] = out["expect"].get(c.expect, 0) + 1
    for a in _archive_case_tuple():
        out["archive"][a.category] = out["archive"].get(a.category, 0) + 1
    return out


__all__ = [
    "DETAIL_RE", "FILE_LEVEL_RE", "MARKER", "UNCLEAN_RE", "ArchiveCase", "Case", "Member", "Payload", "RunSpec",
    "archive_cases", "build_clip_archive", "build_folder", "cases", "counts", "deflated_zeros", "pack",
    "raw_zip", "valid_clip",
]


if __name__ == "__main__":  # python tests/fuzz_inputs.py: the counts
    print(json.dumps(counts(), indent=1))
    print(len(_all_cases()), "per-clip cases,", len(_archive_case_tuple()), "archive cases;",
          sum(c.fast for c in _all_cases()), "+", sum(c.fast for c in _archive_case_tuple()), "fast")
