"""Resource limits on input: what a hostile or clumsy archive may cost before it is refused.

Every reader and the archive scanner check the :class:`Limits` in force (:func:`current`), so a
zip bomb, a symlink loop or a stray frame file numbered 100000 fails with an error that names the
file and the limit (and the ``--limit NAME=VALUE`` that raises it) instead of filling the disk,
the memory or the run. The limits are process-wide (set by :func:`use` for the duration of a
run; read on the reader threads too); the defaults fit every real dataset we know of with a wide
margin (docs/formats.md, "Limits").
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import os
import sys
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_MiB = 1 << 20


class FormatError(ValueError):
    """A file (or object) that does not follow its format; the message names file, frame, field.

    Defined here, the lowest module of ``jmocap.data``, and re-exported by ``jmocap.data.clip``.
    """


class LimitError(FormatError):
    """An input over one of the :class:`Limits` (the message names the file and the limit)."""


@dataclass(frozen=True)
class Limits:
    """Limits on one run's input (all positive integers)."""

    max_extract_bytes: int = 4096 * _MiB  # bytes extracted from one .zip / .tar input in all
    max_file_bytes: int = 512 * _MiB  # one input file, or one member of an .npz, uncompressed
    max_files: int = 200_000  # files under INPUT (members of a .zip / .tar input)
    max_frames: int = 1_000_000  # frames of one clip
    max_frame_gap: int = 10_000  # frame numbers missing in a row in a numbered frame sequence
    max_symlink_depth: int = 8  # symbolic links followed on one path below INPUT
    max_json_depth: int = 64  # nesting of a JSON file's arrays / objects

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
                raise ValueError(f"limit {f.name} must be a positive integer, got {v!r}")

    def replace(self, **changes) -> Limits:
        return dataclasses.replace(self, **changes)

    @classmethod
    def parse(cls, items: list[str] | None, base: Limits | None = None) -> Limits:
        """``["max_frames=50000", ...]`` (``--limit`` arguments; sizes take K/M/G suffixes,
        binary) on top of ``base`` (default: the defaults). Raises ``ValueError``."""
        out = base or cls()
        names = [f.name for f in dataclasses.fields(cls)]
        for item in items or []:
            key, sep, value = item.partition("=")
            key = key.strip().replace("-", "_")
            if not sep or key not in names:
                raise ValueError(f"--limit {item!r}: expected NAME=VALUE with NAME one of {names}")
            out = out.replace(**{key: _parse_size(value, item)})
        return out


def _parse_size(text: str, item: str) -> int:
    text = text.strip().upper().removesuffix("B").removesuffix("I")
    scale = 1
    if text and text[-1] in "KMG":
        scale = 1 << (10 * (" KMG".index(text[-1])))
        text = text[:-1]
    try:
        v = int(float(text) * scale)
    except ValueError:
        raise ValueError(f"--limit {item!r}: {text!r} is not a number") from None
    if v <= 0:
        raise ValueError(f"--limit {item!r}: must be positive")
    return v


_CURRENT = Limits()


def current() -> Limits:
    """The limits in force (process-wide)."""
    return _CURRENT


@contextlib.contextmanager
def use(limits: Limits | None) -> Iterator[Limits]:
    """Put ``limits`` in force for the duration of the block (None: leave them as they are)."""
    global _CURRENT
    old = _CURRENT
    if limits is not None:
        _CURRENT = limits
    try:
        yield _CURRENT
    finally:
        _CURRENT = old


def _flag(name: str) -> str:
    return f"--limit {name}=..."


def check_file_size(path: str | os.PathLike, where: str | None = None) -> int:
    """The size of ``path`` in bytes; :class:`LimitError` when over ``max_file_bytes``."""
    size = os.stat(path).st_size
    lim = current().max_file_bytes
    if size > lim:
        raise LimitError(
            f"{where or path}: {size} bytes, over the limit max_file_bytes = {lim} ({_flag('max_file_bytes')})"
        )
    return size


def check_frames(num_frames: int, where: str) -> None:
    """:class:`LimitError` when a clip has more than ``max_frames`` frames."""
    lim = current().max_frames
    if num_frames > lim:
        raise LimitError(
            f"{where}: {num_frames} frames, over the limit max_frames = {lim} ({_flag('max_frames')})"
        )


def check_frame_gap(previous: int, frame: int, where: str) -> None:
    """:class:`LimitError` when frame number ``frame`` follows ``previous`` with more than
    ``max_frame_gap`` numbers missing between them (a stray file would make a huge clip)."""
    lim = current().max_frame_gap
    gap = frame - previous - 1
    if gap > lim:
        raise LimitError(
            f"{where}: frame {frame}: frame number {frame} follows {previous} with {gap} frame numbers "
            f"missing, over the limit max_frame_gap = {lim} ({_flag('max_frame_gap')}); a stray file?"
        )


def check_npz_members(z: zipfile.ZipFile, where: str) -> None:
    """:class:`LimitError` when a member of an .npz (a zip) would decompress to more than
    ``max_file_bytes`` (checked before anything is decompressed; zipfile stops at the declared
    size, so a member cannot exceed it)."""
    lim = current().max_file_bytes
    total = 0
    for info in z.infolist():
        total += info.file_size
        if info.file_size > lim or total > lim:
            raise LimitError(
                f"{where}: field {info.filename.removesuffix('.npy')!r}: decompresses to "
                f"{max(info.file_size, total)} bytes, over the limit max_file_bytes = {lim} "
                f"({_flag('max_file_bytes')})"
            )


def check_npy_header(fp, where: str, field: str | None = None) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Read the header of the ``.npy`` stream ``fp`` (at its start; left just after the header)
    and return ``(shape, fortran_order, dtype)``, without reading any data.

    Checked: the magic string and a header numpy can parse (format versions 1.0, 2.0, 3.0), a
    shape of non-negative integers, and that the array it declares, ``prod(shape) * itemsize``
    bytes, is within ``max_file_bytes`` (:class:`LimitError`; numpy would allocate that much
    before reading). Anything else wrong: :class:`FormatError` naming ``where`` and ``field``.
    """
    from numpy.lib import format as npformat

    label = where if field is None else f"{where}: field {field!r}"
    try:
        version = npformat.read_magic(fp)
        if version == (1, 0):
            shape, fortran, dtype = npformat.read_array_header_1_0(fp)
        elif version == (2, 0):
            shape, fortran, dtype = npformat.read_array_header_2_0(fp)
        elif version == (3, 0) and hasattr(npformat, "_read_array_header"):
            shape, fortran, dtype = npformat._read_array_header(fp, version)
        else:
            raise ValueError(f"unsupported .npy format version {version[0]}.{version[1]}")
    except (ValueError, EOFError, OSError, SyntaxError, TypeError, zipfile.BadZipFile) as e:
        raise FormatError(f"{label}: not a readable .npy array header: {e}") from None
    if not all(isinstance(n, int) and n >= 0 for n in shape):
        raise FormatError(f"{label}: shape {shape} is not a tuple of non-negative integers")
    nbytes = math.prod(shape) * dtype.itemsize
    lim = current().max_file_bytes
    if nbytes > lim:
        raise LimitError(
            f"{label}: an array of shape {shape} ({dtype}) takes {nbytes} bytes, over the limit "
            f"max_file_bytes = {lim} ({_flag('max_file_bytes')})"
        )
    return shape, bool(fortran), dtype


def load_npy(path: str | os.PathLike, where: str | None = None) -> np.ndarray:
    """The array of a ``.npy`` file, without pickle, after :func:`check_file_size` and
    :func:`check_npy_header`. An array of Python objects (pickled) is a :class:`FormatError`;
    other read problems raise what numpy raises (callers turn those into their format's error)."""
    where = where or str(path)
    check_file_size(path, where)
    with open(path, "rb") as f:
        _shape, _fortran, dtype = check_npy_header(f, where)
        if dtype.hasobject:
            raise FormatError(f"{where}: holds Python objects (pickled data), which are not read; expected numbers")
        f.seek(0)
        return np.lib.format.read_array(f, allow_pickle=False)


def load_npz(source: str | os.PathLike | bytes, where: str) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` (a path, or its bytes), without pickle, after checking
    :func:`check_npz_members`, that every member is a ``.npy`` and every member's header
    (:func:`check_npy_header`; an array of Python objects is refused, never unpickled). Raises
    :class:`LimitError` or whatever reading a damaged file raises (callers turn those into their
    format's error)."""
    f = io.BytesIO(source) if isinstance(source, bytes) else source
    if not isinstance(source, bytes):
        check_file_size(source, where)
    with zipfile.ZipFile(f) as z:
        check_npz_members(z, where)
        for info in z.infolist():
            if not info.filename.endswith(".npy"):  # numpy would return its raw bytes
                raise FormatError(f"{where}: member {info.filename!r} is not an array (.npy)")
            field = info.filename.removesuffix(".npy")
            with z.open(info) as member:
                _shape, _fortran, dtype = check_npy_header(member, where, field)
            if dtype.hasobject:
                raise FormatError(
                    f"{where}: field {field!r}: holds Python objects (pickled data), which are "
                    "not read; expected numbers or strings"
                )
    if isinstance(f, io.BytesIO):
        f.seek(0)
    with np.load(f, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def parse_json(text: str | bytes, where: str):
    """``json.loads(text)``, every problem a one-line :class:`FormatError` naming ``where``:
    invalid JSON, an integer of more digits than Python converts, nesting too deep for Python's
    parser or over ``max_json_depth`` (:class:`LimitError`, :func:`check_json_depth`), memory."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise FormatError(f"{where}: not valid JSON: {e}") from None
    except UnicodeDecodeError as e:
        raise FormatError(f"{where}: not a UTF-8 text: {e}") from None
    except RecursionError:
        lim = current().max_json_depth
        raise LimitError(
            f"{where}: JSON nested too deeply to parse, over the limit max_json_depth = {lim} "
            f"({_flag('max_json_depth')})"
        ) from None
    except (ValueError, OverflowError) as e:  # e.g. an integer of more than 4300 digits
        if "digits" in str(e):
            raise FormatError(f"{where}: not readable JSON: a number of more than "
                              f"{sys.get_int_max_str_digits()} digits") from None
        raise FormatError(f"{where}: not readable JSON: {e}") from None
    except MemoryError:
        raise FormatError(f"{where}: not readable JSON: out of memory while parsing") from None
    check_json_depth(data, where)
    return data


def check_json_depth(data, where: str) -> None:
    """:class:`LimitError` when parsed JSON ``data`` nests arrays / objects more than
    ``max_json_depth`` deep (checked iteratively, so any depth Python could parse is safe)."""
    lim = current().max_json_depth
    stack = [(data, 1)]
    while stack:
        obj, depth = stack.pop()
        if isinstance(obj, dict):
            children = obj.values()
        elif isinstance(obj, list):
            children = obj
        else:
            continue
        if depth > lim:
            raise LimitError(
                f"{where}: JSON nests arrays / objects more than {lim} deep, over the limit "
                f"max_json_depth = {lim} ({_flag('max_json_depth')})"
            )
        stack.extend((c, depth + 1) for c in children if isinstance(c, (dict, list)))


def check_path_inside(root: Path, path: Path, where: str) -> Path:
    """``path`` resolved, when it is inside ``root`` (resolved); else :class:`LimitError`."""
    r, p = root.resolve(), path.resolve()
    if not p.is_relative_to(r):
        raise LimitError(f"{where}: points outside the input folder ({p} is not under {r})")
    return p


__all__ = [
    "LimitError",
    "Limits",
    "check_file_size",
    "check_frame_gap",
    "check_frames",
    "check_json_depth",
    "check_npy_header",
    "check_npz_members",
    "check_path_inside",
    "current",
    "load_npy",
    "load_npz",
    "parse_json",
    "use",
]
