"""Crash-safe file writing, the one implementation used by every writer in jmocap.

A file is written to a temporary file in its destination folder, flushed and fsynced, then
renamed over the destination (``os.replace``, atomic on POSIX and Windows): a reader never sees
a half-written file, and a crash leaves the previous version (or nothing) in place.
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


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """A temporary path next to ``path`` for writers that open files by name (matplotlib, video
    encoders; ``suffix`` defaults to ``path``'s own, which they read the format from, named
    ``.<name>.<random><suffix>``); on a clean exit it is fsynced and renamed to ``path``, on an
    exception removed (``path`` untouched). The destination's folder is created if missing."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix if suffix is None else suffix,
                               dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file next to ``path`` for writing; on a clean exit it is flushed,
    fsynced and renamed to ``path``; on an exception it is removed and ``path`` is untouched.
    The temporary file is ``.<name>.<random>.tmp``."""
    with atomic_path(path, ".tmp") as tmp, open(tmp, mode) as f:
        yield f


def atomic_write(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write ``data`` (bytes, or text as UTF-8) to ``path`` atomically. Returns the path."""
    path = Path(path)
    with atomic_writer(path) as f:
        f.write(data.encode("utf-8") if isinstance(data, str) else data)
    return path


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


__all__ = ["atomic_path", "atomic_write", "atomic_write_npz", "atomic_writer", "npz_bytes"]
