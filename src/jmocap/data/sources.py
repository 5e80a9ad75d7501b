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

Nothing is silently skipped: files that are not clips (notes, unrelated JSON, symbolic links
that loop or point outside INPUT, a results folder) are listed with the reason in
:attr:`SourceList.skipped`; a folder that cannot be read becomes a source that fails with the
reason. Reading is bounded by :mod:`jmocap.data.limits` (files scanned, bytes extracted from a
.zip / .tar, symbolic-link depth), and a clip archive's manifest cannot point outside INPUT.
"""

from __future__ import annotations

import json
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
from jmocap.data import limits as L
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


class SourceList(list):
    """The :class:`Source` list of an input, plus ``skipped``: what was found but is not a clip,
    as ``{"path", "reason"}`` dicts (written to summary.json)."""

    def __init__(self, sources=(), skipped=()):
        super().__init__(sources)
        self.skipped: list[dict[str, str]] = list(skipped)


_CONTAINERS = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tar.xz")
_NOT_CLIPS = {"camera.json", ARCHIVE_META, SUMMARY, MANIFEST}
# words in the first bytes of a JSON file that mark one of the keypoint formats (OpenPose, COCO,
# MMPose); a valid JSON file without any of them is listed as skipped, not read as a clip
_JSON_MARKERS = (b'"people"', b'"instance_info"', b'"annotations"', b'"image_id"', b'"instances"',
                 b'"keypoint')
_SNIFF_BYTES = 1 << 16


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

    Yields a :class:`SourceList`. Raises :class:`ArchiveError` (one line) for an input that
    cannot be read as a whole: a damaged .zip / .tar, a member its safe extraction refuses, an
    input over the :mod:`~jmocap.data.limits`.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"input not found: {path}")
    if (path.is_dir() and (path / MANIFEST).is_file()) or (_is_container(path) and _has_manifest(path)):
        with Archive(path) as archive:
            yield SourceList(archive_sources(archive, str(path)))
        return
    if _is_container(path):
        with tempfile.TemporaryDirectory(prefix="jmocap-input-") as tmp:
            _extract(path, Path(tmp))
            yield scan_folder(Path(tmp), image_size=image_size, label=f"{path}:")
        return
    yield scan_folder(path, image_size=image_size, exclude=exclude)


def archive_sources(archive: Archive, label: str) -> list[Source]:
    """The written clips of a clip archive; a manifest line that names no file, or a file
    outside the archive, is a source that fails saying so (the other clips are unaffected)."""
    out = []
    for e in archive.ok:
        rel = e.get("file")
        where = f"{label}:{rel}" if isinstance(rel, str) else f"{label}:{MANIFEST}[{e['name']!r}]"
        out.append(Source(str(e["name"]), where, partial(_keypoint_clip, archive, e["name"], where)))
    return out


def _keypoint_clip(archive: Archive, name: str, where: str) -> Clip:
    """Clip ``name`` of ``archive``; an IMU clip (``jmocap-imu-clip-1``) is refused with a
    :class:`FormatError` (the methods here read 2D keypoints)."""
    clip = archive.load(name)
    if not isinstance(clip, Clip):
        raise FormatError(f"{where}: an IMU clip (jmocap-imu-clip-1); the reconstruction methods read "
                          f"2D keypoint clips")
    return clip


def _has_manifest(path: Path) -> bool:
    """Whether a .zip / .tar is a clip archive: ``manifest.jsonl`` at its top, or in its only
    top-level folder (a manifest deeper inside belongs to a sub-archive of a folder of loose files)."""
    try:
        if path.name.lower().endswith(".zip"):
            with zipfile.ZipFile(path) as z:
                names = z.namelist()
        else:
            with tarfile.open(path) as t:
                names = t.getnames()
    except (OSError, zipfile.BadZipFile, tarfile.TarError, EOFError) as e:
        raise ArchiveError(f"{path}: not a readable {'zip' if path.name.lower().endswith('.zip') else 'tar'} file: {e}") from None
    parts = [PurePosixPath(n).parts for n in names]
    if any(p == (MANIFEST,) for p in parts):
        return True
    tops = {p[0] for p in parts if p}
    return len(tops) == 1 and any(len(p) == 2 and p[1] == MANIFEST for p in parts)


def _extract(path: Path, dest: Path) -> None:
    """Extract a zip / tar into ``dest`` within the :mod:`~jmocap.data.limits` (member count,
    bytes per member and in all), refusing members that would land outside ``dest`` and, for a
    tar, whatever its ``"data"`` filter refuses (links out of the archive, devices, ...).
    Raises :class:`ArchiveError` naming the archive and the member."""
    lim = L.current()
    try:
        if path.name.lower().endswith(".zip"):
            with zipfile.ZipFile(path) as z:
                infos = z.infolist()
                sizes = [(i.filename, i.file_size) for i in infos]
                _check_members(path, sizes, lim)
                for n, _ in sizes:
                    if not (dest / n).resolve().is_relative_to(dest.resolve()):
                        raise ArchiveError(f"{path}: member {n!r} points outside the archive")
                z.extractall(dest)
        else:
            with tarfile.open(path) as t:
                members = t.getmembers()
                _check_members(path, [(m.name, m.size) for m in members if m.isfile()], lim, count=len(members))
                t.extractall(dest, filter="data")
    except ArchiveError:
        raise
    except tarfile.FilterError as e:
        raise ArchiveError(f"{path}: member {getattr(e, 'tarinfo', None) and e.tarinfo.name!r} refused: {e}") from None
    except (OSError, zipfile.BadZipFile, tarfile.TarError, EOFError, ValueError, RuntimeError) as e:
        raise ArchiveError(f"{path}: cannot extract: {type(e).__name__}: {e}") from None


def _check_members(path: Path, sizes, lim: L.Limits, count: int | None = None) -> None:
    n = len(sizes) if count is None else count
    if n > lim.max_files:
        raise ArchiveError(
            f"{path}: {n} members, over the limit max_files = {lim.max_files} (--limit max_files=...)"
        )
    total = 0
    for name, size in sizes:
        if size > lim.max_file_bytes:
            raise ArchiveError(
                f"{path}: member {name!r} extracts to {size} bytes, over the limit max_file_bytes = "
                f"{lim.max_file_bytes} (--limit max_file_bytes=...)"
            )
        total += size
        if total > lim.max_extract_bytes:
            raise ArchiveError(
                f"{path}: extracts to more than {lim.max_extract_bytes} bytes, over the limit "
                f"max_extract_bytes (--limit max_extract_bytes=...)"
            )


def scan_folder(
    root: str | os.PathLike,
    *,
    image_size: Sequence[int] | None = None,
    label: str | None = None,
    exclude: str | os.PathLike | None = None,
) -> SourceList:
    """Every clip under ``root``, in sorted path order:

    * a folder holding ``*_keypoints.json`` files is one OpenPose clip (its other files and
      sub-folders are scanned too);
    * a folder holding ``manifest.jsonl`` is a clip archive (its clips, named
      ``<folder>/<clip>``), or, with a jmocap results ``archive.json``, an output folder
      (skipped);
    * every other ``.npz`` / ``.npy`` / ``.json`` file is one clip (a VideoPose3D ``.npz`` one
      per sequence), except camera sidecars (``*.camera.json``, ``camera.json``),
      ``archive.json`` / ``summary.json`` and JSON files that are no keypoint format (skipped).

    Hidden files are ignored; other files, symbolic links that loop, point outside ``root`` or
    are nested deeper than ``max_symlink_depth``, and folders met twice are listed in
    ``skipped`` with the reason. A folder that cannot be read becomes a source that fails with
    the reason. More than ``max_files`` entries raise :class:`ArchiveError`.

    Names are paths relative to ``root`` without the suffix (``walk/take1.json`` ->
    ``walk/take1``; unique: a second ``walk`` keeps its suffix); ``label`` replaces ``root`` in
    messages (e.g. the zip file's name). ``exclude`` is a folder not to look into (the output
    folder, when it is inside the input).
    """
    root = Path(root)
    lim = L.current()
    skip = Path(exclude).resolve() if exclude is not None else None
    prefix = label if label is not None else ""
    real_root = root.resolve()
    found: list[tuple[str, Path, str]] = []  # (name, path, kind: file | openpose | unreadable | archive)
    skipped: list[dict[str, str]] = []
    seen_dirs: set[Path] = set()
    count = 0

    def rel(p: Path) -> str:
        return p.name if p == root else p.relative_to(root).as_posix()

    def shown(p: Path) -> str:
        return prefix + rel(p) if label is not None else str(p)

    def skip_it(p: Path, reason: str) -> None:
        skipped.append({"path": shown(p), "reason": reason})

    def walk(d: Path, links: int):
        nonlocal count
        real = d.resolve()
        if real in seen_dirs:
            skip_it(d, "a folder already scanned (a symbolic link loop or a second link to it)")
            return
        seen_dirs.add(real)
        try:
            entries = sorted(d.iterdir())
        except OSError as e:
            found.append((rel(d), d, "unreadable:" + (e.strerror or type(e).__name__)))
            return
        count += len(entries)
        if count > lim.max_files:
            raise ArchiveError(
                f"{shown(root)}: more than {lim.max_files} files, over the limit max_files "
                f"(--limit max_files=...)"
            )
        names = {p.name for p in entries}
        if MANIFEST in names and d != root:
            if _is_results_folder(d):
                skip_it(d, "a jmocap results folder (archive.json of jmocap.batch)")
            else:
                found.append((rel(d), d, "archive"))
            return
        if any(p.name.endswith("_keypoints.json") for p in entries if not p.name.startswith(".")):
            found.append((rel(d), d, "openpose"))
        for p in entries:
            if p.name.startswith("."):
                continue
            depth = links
            if p.is_symlink():
                depth += 1
                try:
                    target = p.resolve(strict=True)
                except (OSError, RuntimeError) as e:
                    skip_it(p, f"a broken or looping symbolic link ({type(e).__name__})")
                    continue
                if not target.is_relative_to(real_root):
                    skip_it(p, "a symbolic link to outside the input folder")
                    continue
                if depth > lim.max_symlink_depth:
                    skip_it(p, f"more than max_symlink_depth = {lim.max_symlink_depth} symbolic links on its path")
                    continue
            try:
                is_dir = p.is_dir()
            except OSError:
                is_dir = False
            if is_dir:
                if skip is None or p.resolve() != skip:
                    walk(p, depth)
                continue
            suffix = p.suffix.lower()
            if p.name.endswith("_keypoints.json"):
                continue  # a frame of this folder's OpenPose clip
            if suffix in (".npz", ".npy"):
                found.append((p.relative_to(root).with_suffix("").as_posix(), p, "file"))
            elif suffix == ".json":
                if p.name in _NOT_CLIPS or p.name.endswith(".camera.json"):
                    continue
                why = _not_keypoint_json(p)
                if why:
                    skip_it(p, why)
                else:
                    found.append((p.relative_to(root).with_suffix("").as_posix(), p, "file"))
            else:
                skip_it(p, f"not a clip file (suffix {p.suffix or 'none'!r})")

    if root.is_dir():
        walk(root, 0)
    else:
        found.append((root.stem, root, "file"))
    counts: dict[str, int] = {}
    for name, _, _ in found:
        counts[name] = counts.get(name, 0) + 1
    sources: list[Source] = []
    vp3d = _LastFile()
    for name, p, kind in found:
        if counts[name] > 1 and kind == "file":  # walk.json and walk.npz: keep the suffix in the name
            name = rel(p)
        where = shown(p)
        relabel = None if label is None else partial(_relabel, old=str(root) + os.sep, new=prefix)
        if kind.startswith("unreadable:"):
            sources.append(Source(name, where, partial(_unreadable, where, kind.split(":", 1)[1])))
            continue
        if kind == "archive":
            sources.extend(_sub_archive(p, name, where))
            continue
        seqs = _vp3d_sequences(p) if kind == "file" else None
        if seqs is None:
            sources.append(Source(name, where, _guarded(partial(_load_path, p, image_size), relabel)))
        else:
            for seq in seqs:
                load = partial(vp3d.load, p, seq, image_size)
                sources.append(Source(f"{name}/{seq}", f"{where}[{seq}]", _guarded(load, relabel)))
    return SourceList(_unique(sources), skipped)


def _unique(sources: list[Source]) -> list[Source]:
    """Sources with unique names (a later duplicate gets ``~2``, ``~3``, ...)."""
    taken = {s.name for s in sources}
    seen: set[str] = set()
    out = []
    for s in sources:
        name = s.name
        if name in seen:
            k = 2
            while f"{s.name}~{k}" in taken:
                k += 1
            name = f"{s.name}~{k}"
            taken.add(name)
            s = Source(name, s.where, s.load)
        seen.add(name)
        out.append(s)
    return out


def _unreadable(where: str, reason: str) -> Clip:
    raise FormatError(f"{where}: cannot read the folder: {reason}")


def _is_results_folder(d: Path) -> bool:
    try:
        meta = json.loads((d / ARCHIVE_META).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("engine") == "jmocap.batch"


def _sub_archive(d: Path, name: str, where: str) -> list[Source]:
    """The clips of a clip archive found inside a folder of loose files (``name/clip``)."""
    try:
        archive = Archive(d)
    except (ArchiveError, OSError, ValueError) as e:
        return [Source(name, where, partial(_raise, FormatError(f"{where}: not a readable clip archive: {e}")))]
    return [Source(f"{name}/{s.name}", s.where, s.load) for s in archive_sources(archive, where)]


def _raise(error: BaseException):
    raise error


def _not_keypoint_json(path: Path) -> str | None:
    """Why a ``.json`` file is not a keypoint file, or None when it may be one: its first bytes
    name a keypoint format's key, or it is not valid JSON (then reading it reports the error)."""
    try:
        with open(path, "rb") as f:
            head = f.read(_SNIFF_BYTES)
    except OSError:
        return None  # reading it reports the error
    if any(m in head for m in _JSON_MARKERS):
        return None
    try:
        L.check_file_size(path)
        data = json.loads(path.read_bytes())
    except (ValueError, RecursionError, OSError, FormatError):
        return None  # not JSON (or too big): the reader gives the error, as a failed clip
    if isinstance(data, list) and not data:
        return None  # an empty detection list: the reader says so
    return "a JSON file that is not OpenPose, COCO or MMPose keypoints"


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
    return formats.find_sidecar(path) is not None


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
        side = formats.find_sidecar(path)
        kp = self.seqs[seq]
        if side is not None:
            return kp.to_clip(camera_json=side)
        return _with_image_size(kp, image_size).to_clip()


__all__ = ["SUMMARY", "Source", "SourceList", "archive_sources", "open_sources", "scan_folder"]
