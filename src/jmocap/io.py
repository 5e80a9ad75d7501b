"""Crash-safe file writing, the one implementation used by every writer in jmocap.

A file is written to a temporary file in its destination folder, flushed and fsynced, then
renamed over the destination (``os.replace``, atomic on POSIX and Windows): a reader never sees
a half-written file, and a crash leaves the previous version (or nothing) in place.

Temporary files are named ``.jmocap-<random>.tmp`` (or ``<random><suffix>``), short whatever
the destination's name (a 251-byte name still fits the 255-byte limit of file names), so a
killed writer's leftovers are recognisable: :func:`remove_stale_temporaries` deletes them when a
run starts. Finished files get the mode a plain ``open()`` would give them (``0o666`` less the
umask), not ``mkstemp``'s ``0o600``.
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import numpy as np

_ZIP_DATE = (1980, 1, 1, 0, 0, 0)
TEMP_PREFIX = ".jmocap-"


def _umask() -> int:
    """The process umask (read without changing it where /proc allows; else set and restored)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """The mode a new file gets from ``open()``: ``0o666`` less the umask."""
    return 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """A temporary path next to ``path`` for writers that open files by name (matplotlib, video
    encoders; ``suffix`` defaults to ``path``'s own, which they read the format from, named
    ``.jmocap-<random><suffix>``); on a clean exit it is fsynced, given the umask's mode and
    renamed to ``path``, on an exception removed (``path`` untouched). The destination's folder
    is created if missing."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=TEMP_PREFIX, suffix=path.suffix if suffix is None else suffix,
                               dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
            os.fchmod(f.fileno(), file_mode())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file next to ``path`` for writing; on a clean exit it is flushed,
    fsynced and renamed to ``path``; on an exception it is removed and ``path`` is untouched.
    The temporary file is ``.jmocap-<random>.tmp``."""
    with atomic_path(path, ".tmp") as tmp, open(tmp, mode) as f:
        yield f


def atomic_write(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write ``data`` (bytes, or text as UTF-8) to ``path`` atomically. Returns the path."""
    path = Path(path)
    with atomic_writer(path) as f:
        f.write(data.encode("utf-8") if isinstance(data, str) else data)
    return path


def remove_stale_temporaries(root: str | os.PathLike) -> list[Path]:
    """Delete the temporary files a killed writer left under ``root`` (``.jmocap-*`` files, and
    ``.<name>.<random>.tmp`` ones of earlier versions); returns what was removed. Call it only
    while no other writer uses ``root`` (a run holds its output folder's lock)."""
    removed = []
    for dirpath, _dirs, files in os.walk(root):
        for name in files:
            if name.startswith(TEMP_PREFIX) or (name.startswith(".") and name.endswith(".tmp")):
                p = Path(dirpath) / name
                with contextlib.suppress(FileNotFoundError):
                    p.unlink()
                    removed.append(p)
    return removed


def npz_bytes(arrays: dict[str, np.ndarray], compressed: bool = True) -> bytes:
    """An .npz (as ``numpy.savez_compressed`` writes it) with fixed timestamps and sorted keys,
    so equal arrays give equal bytes. Arrays of Python objects are refused (never pickled)."""
    buf = io.BytesIO()
    method = zipfile.ZIP_DEFLATED if compressed else zipfile.ZIP_STORED
    with zipfile.ZipFile(buf, "w", compression=method) as zf:
        for key in sorted(arrays):
            arr = np.asanyarray(arrays[key])
            member = io.BytesIO()
            np.lib.format.write_array(member, arr, allow_pickle=False)
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_DATE)
            info.compress_type = method
            info.external_attr = 0o644 << 16
            zf.writestr(info, member.getvalue())
    return buf.getvalue()


def atomic_write_npz(path: str | os.PathLike, arrays: dict[str, np.ndarray], compressed: bool = True) -> Path:
    """Write ``arrays`` to ``path`` as .npz atomically (deterministic bytes, see :func:`npz_bytes`),
    creating the parent folder. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write(path, npz_bytes(arrays, compressed))


__all__ = [
    "TEMP_PREFIX",
    "atomic_path",
    "atomic_write",
    "atomic_write_npz",
    "atomic_writer",
    "file_mode",
    "npz_bytes",
    "remove_stale_temporaries",
]
