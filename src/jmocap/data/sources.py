"""The clips of an input: a jmocap clip archive, or a folder / ``.zip`` / ``.tar`` of loose files.

:func:`open_sources` lists every clip of an input as a :class:`Source` (a name, where it is,
and a function that reads and validates it), without reading the clips: batch runs read them
ahead on a thread, and a clip that cannot be read fails alone.

* a jmocap clip archive (folder / ``.zip`` / ``.tar`` with ``manifest.jsonl``): its written clips;
* a folder (or a zip / tar of one) of loose files in any format that
  :func:`jmocap.data.formats.read_clip` reads (jmocap clip ``.npz``, OpenPose JSON folders,
  COCO / MMPose JSON, VideoPose3D ``.npz`` - one clip per sequence - and keypoint arrays), each
  with its camera sidecar when there is one (:func:`scan_folder`);
* a single clip file or OpenPose folder.
"""

from __future__ import annotations

import os
import tarfile
import tempfile
import zipfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path, PurePosixPath

import numpy as np

from jmocap.data import formats
from jmocap.data.archive import ARCHIVE_META, MANIFEST, Archive, ArchiveError
from jmocap.data.clip import Clip, FormatError, is_clip_file

#: file names in an input folder that are never clips
SUMMARY = "summary.json"


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
    if image_size is None or _has_camera(path) or (path.suffix == ".npz" and is_clip_file(path)):
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


__all__ = ["SUMMARY", "Source", "open_sources", "scan_folder"]
