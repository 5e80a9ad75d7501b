"""Clip archives: a folder of ``jmocap-clip-1`` (or ``jmocap-imu-clip-1``) .npz files plus
``manifest.jsonl``.

Layout of an archive folder::

    DIR/
      archive.json        settings the archive was written with (JSON object, optional)
      manifest.jsonl      one JSON object per line, one line per clip, in write order
      synth_000000.npz    the clips (compressed .npz, see jmocap.data.clip)
      ...

Every manifest line has ``name``, ``file`` (relative to the folder), ``status`` (``"ok"`` or
``"failed"``) and, for written clips, ``frames``, ``fps``, ``layout``, ``kind`` (motion
kind), ``height_m``, ``bytes`` and ``sha256`` (of the file), plus whatever the writer adds
(``index``, ``seed``, ``error`` of a failed clip, ...); IMU clips add ``format:
"jmocap-imu-clip-1"`` and are read back as :class:`~jmocap.data.imu.IMUClip`. A later line for
the same name supersedes an earlier one.

Writing is crash-safe: each clip file is written to a temporary file in the folder and renamed
into place (``os.replace``), then its manifest line is appended and flushed to disk. An
interrupted run therefore leaves complete clips, at most one truncated last manifest line
(ignored by the reader, cut off by the next writer) and possibly a clip file without a line
(rewritten when the run resumes). :class:`ArchiveWriter` resumes an existing archive: clips
already listed are skipped by the caller via :meth:`ArchiveWriter.has`.

Clip files are written deterministically (fixed zip timestamps), so the same clip gives the
same bytes and the same ``sha256``.

:class:`Archive` reads an archive from a folder, a ``.zip`` or a ``.tar`` (``.tar.gz``,
``.tgz``) file, by its manifest.
"""

from __future__ import annotations

import hashlib
import json
import os
import tarfile
import zipfile
from collections.abc import Iterator
from pathlib import Path, PurePosixPath
from typing import Any

from jmocap.data import limits as L
from jmocap.data.clip import Clip, ClipFormatError, FormatError, clip_from_arrays, clip_to_arrays
from jmocap.data.imu import FORMAT as IMU_FORMAT
from jmocap.data.imu import IMUClip, imu_clip_from_arrays, imu_clip_to_arrays
from jmocap.io import atomic_write, npz_bytes

MANIFEST = "manifest.jsonl"
ARCHIVE_META = "archive.json"


class ArchiveError(ValueError):
    """A malformed or inconsistent archive (the message names the file and line)."""


# --- files ---------------------------------------------------------------------------------


def _parse_manifest(text: str, where: str) -> list[dict[str, Any]]:
    """Manifest lines; a truncated (unparsable) *last* line is ignored, others are errors."""
    entries = []
    lines = text.split("\n")
    complete = text.endswith("\n")
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        last = i == len(lines) - 1 or (i == len(lines) - 2 and not lines[-1].strip())
        try:
            e = L.parse_json(line, f"{where}: line {i + 1}")
        except FormatError as err:
            if last and not complete:
                break  # an interrupted append
            raise ArchiveError(str(err)) from None
        if not isinstance(e, dict) or "name" not in e or "status" not in e:
            raise ArchiveError(f"{where}: line {i + 1} must be an object with 'name' and 'status'")
        if not isinstance(e["name"], str) or not e["name"]:
            raise ArchiveError(f"{where}: line {i + 1}: field 'name' must be a non-empty string, got {e['name']!r}")
        if last and not complete:
            break  # complete JSON but no newline: treat as interrupted too
        entries.append(e)
    return entries


def latest(entries: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The last entry per clip name, in first-appearance order."""
    out: dict[str, dict[str, Any]] = {}
    for e in entries:
        out[e["name"]] = e
    return out


# --- writer --------------------------------------------------------------------------------


class ArchiveWriter:
    """Append clips to an archive folder (created if needed), resuming an existing one.

    ``settings`` (JSON-serialisable) are stored in ``archive.json``; resuming an archive
    written with different settings raises :class:`ArchiveError` (it would mix two streams).
    """

    def __init__(self, root: str | os.PathLike, settings: dict[str, Any] | None = None):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.manifest_path = self.root / MANIFEST
        meta_path = self.root / ARCHIVE_META
        if settings is not None:
            settings = json.loads(json.dumps(settings, sort_keys=True))
            if meta_path.exists():
                try:
                    old = L.parse_json(meta_path.read_bytes(), str(meta_path))
                except FormatError as e:
                    raise ArchiveError(str(e)) from None
                if old != settings:
                    diff = sorted(k for k in set(old) | set(settings) if old.get(k) != settings.get(k))
                    raise ArchiveError(
                        f"{self.root}: the archive was written with different settings "
                        f"(differences in {diff}); use another folder or the same settings"
                    )
            else:
                atomic_write(meta_path, (json.dumps(settings, indent=2, sort_keys=True) + "\n").encode())
        self.entries: dict[str, dict[str, Any]] = {}
        if self.manifest_path.exists():
            try:
                text = self.manifest_path.read_text(encoding="utf-8")
            except UnicodeDecodeError as e:
                raise ArchiveError(f"{self.manifest_path}: not a UTF-8 text file: {e}") from None
            self.entries = latest(_parse_manifest(text, str(self.manifest_path)))
            if text and not text.endswith("\n"):
                # cut off the interrupted last line before appending
                keep = text[: text.rfind("\n") + 1]
                atomic_write(self.manifest_path, keep.encode())
        self._f = open(self.manifest_path, "a", encoding="utf-8")  # noqa: SIM115

    # -- state -------------------------------------------------------------------------------
    def has(self, name: str, verify: bool = False) -> bool:
        """Whether ``name`` is already in the archive (written, with its file present; or
        recorded as failed). ``verify`` also checks the file's sha256."""
        e = self.entries.get(name)
        if e is None:
            return False
        if e["status"] != "ok":
            return True
        path = self.root / e["file"]
        if not path.exists():
            return False
        return not verify or _sha256(path.read_bytes()) == e.get("sha256")

    # -- writing -----------------------------------------------------------------------------
    def _append(self, entry: dict[str, Any]) -> None:
        self._f.write(json.dumps(entry, sort_keys=True) + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())
        self.entries[entry["name"]] = entry

    def add(self, clip: Clip | IMUClip, **extra: Any) -> dict[str, Any]:
        """Write ``clip`` (a :class:`Clip` or an :class:`~jmocap.data.imu.IMUClip`, as
        ``<name>.npz``) and its manifest line; returns the line."""
        if not isinstance(clip, (Clip, IMUClip)):
            raise TypeError(f"ArchiveWriter.add expects a Clip or an IMUClip, got {type(clip).__name__}")
        fname = f"{clip.name}.npz"
        if "/" in clip.name or clip.name.startswith("."):
            raise ArchiveError(f"clip name {clip.name!r} cannot be a file name in the archive")
        imu = isinstance(clip, IMUClip)
        data = npz_bytes(imu_clip_to_arrays(clip) if imu else clip_to_arrays(clip))
        atomic_write(self.root / fname, data)
        entry = {
            "name": clip.name,
            "file": fname,
            "status": "ok",
            "frames": clip.num_frames,
            "fps": clip.fps,
            "layout": clip.layout,
            "kind": clip.meta.get("kind"),
            "height_m": clip.height_m,
            "bytes": len(data),
            "sha256": _sha256(data),
        }
        if imu:
            entry["format"] = IMU_FORMAT
        entry.update(extra)
        self._append(entry)
        return entry

    def add_failure(self, name: str, error: str, **extra: Any) -> dict[str, Any]:
        """Record a clip that could not be made (the run goes on)."""
        entry = {"name": name, "file": None, "status": "failed", "error": str(error)}
        entry.update(extra)
        self._append(entry)
        return entry

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()

    def __enter__(self) -> ArchiveWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _json_or_error(data: bytes, where: str):
    try:
        return L.parse_json(data, where)
    except FormatError as e:
        raise ArchiveError(str(e)) from None


def _decode(data: bytes, where: str) -> str:
    """A manifest's text: UTF-8, else an ArchiveError naming the file and the byte."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ArchiveError(f"{where}: not UTF-8 text (byte {e.start})") from None


def _reason(e: BaseException) -> str:
    """An exception's own words for a one-line message (never its class name or a traceback)."""
    text = " ".join(str(e).split())
    if isinstance(e, KeyError):
        return f"missing member {text}" if text else "a member is missing"
    if isinstance(e, EOFError):
        return "the file ends early"
    return text or "damaged or truncated"


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# --- reader --------------------------------------------------------------------------------


class Archive:
    """Read-only view of an archive in a folder, a ``.zip`` or a ``.tar[.gz]`` file.

    ``len(archive)`` and iteration cover the clips whose latest manifest status is ``ok``, in
    manifest order; :meth:`load` reads one by name; :attr:`manifest` has every latest line
    (failed clips included).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._kind = None
        try:
            self._open()
        except ArchiveError:
            self.close()
            raise
        except (OSError, zipfile.BadZipFile, tarfile.TarError, EOFError, UnicodeDecodeError, KeyError) as e:
            self.close()
            raise ArchiveError(f"{self.path}: cannot read the archive ({_reason(e)})") from None

    def _open(self) -> None:
        if self.path.is_dir():
            self._kind = "dir"
            mpath = self.path / MANIFEST
            if not mpath.exists():
                raise ArchiveError(f"{self.path}: no {MANIFEST} in the folder")
            text = _decode(mpath.read_bytes(), str(mpath))
            self._prefix = PurePosixPath("")
            meta = self.path / ARCHIVE_META
            self.settings = _json_or_error(meta.read_bytes(), str(meta)) if meta.exists() else None
        elif self._looks_like(self.path) == "zip":
            self._kind = "zip"
            self._zip = zipfile.ZipFile(self.path)
            names = self._zip.namelist()
            self._prefix = self._find_prefix(names)
            text = _decode(self._zip.read(str(self._prefix / MANIFEST)), f"{self.path}:{self._prefix / MANIFEST}")
            meta = str(self._prefix / ARCHIVE_META)
            self.settings = _json_or_error(self._zip.read(meta), f"{self.path}:{meta}") if meta in names else None
        elif self._looks_like(self.path) == "tar":
            self._kind = "tar"
            self._tar = tarfile.open(self.path)
            names = self._tar.getnames()
            self._prefix = self._find_prefix(names)
            text = _decode(self._tar.extractfile(str(self._prefix / MANIFEST)).read(),
                           f"{self.path}:{self._prefix / MANIFEST}")
            meta = str(self._prefix / ARCHIVE_META)
            self.settings = (
                _json_or_error(self._tar.extractfile(meta).read(), f"{self.path}:{meta}") if meta in names else None
            )
        else:
            raise ArchiveError(f"{self.path}: not an archive folder, .zip or .tar file")
        where = f"{self.path}:{self._prefix / MANIFEST}" if self._kind != "dir" else str(self.path / MANIFEST)
        if len(text) > L.current().max_file_bytes:
            raise L.LimitError(f"{where}: over the limit max_file_bytes (--limit max_file_bytes=...)")
        self.manifest = list(latest(_parse_manifest(text, where)).values())

    @staticmethod
    def _looks_like(path: Path) -> str | None:
        """'zip' / 'tar' by suffix, else by content (a tar of .npz files can contain a zip
        end-of-directory record, so tar is tried first when sniffing)."""
        if not path.is_file():
            return None
        name = path.name.lower()
        if name.endswith(".zip"):
            return "zip"
        if name.endswith((".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tar.xz")):
            return "tar"
        if tarfile.is_tarfile(path):
            return "tar"
        if zipfile.is_zipfile(path):
            return "zip"
        return None

    def _find_prefix(self, names) -> PurePosixPath:
        cands = [PurePosixPath(n) for n in names if PurePosixPath(n).name == MANIFEST]
        if not cands:
            raise ArchiveError(f"{self.path}: no {MANIFEST} inside")
        return min(cands, key=lambda p: len(p.parts)).parent

    @property
    def ok(self) -> list[dict[str, Any]]:
        return [e for e in self.manifest if e["status"] == "ok"]

    def __len__(self) -> int:
        return len(self.ok)

    def names(self) -> list[str]:
        return [e["name"] for e in self.ok]

    def _read(self, rel: str) -> bytes:
        """The bytes of the archive's file ``rel`` (a manifest's ``file``), which must stay
        inside the archive and within ``max_file_bytes`` (:mod:`jmocap.data.limits`)."""
        where = f"{self.path}:{rel}"
        if not isinstance(rel, str) or not rel:
            raise ArchiveError(f"{self.path}:{MANIFEST}: field 'file' must be a file name, got {rel!r}")
        pure = PurePosixPath(rel.replace("\\", "/"))
        if pure.is_absolute() or ".." in pure.parts or Path(rel).is_absolute():
            raise ArchiveError(f"{where}: field 'file' points outside the archive (not read)")
        if not pure.parts:
            raise ArchiveError(f"{where}: field 'file' must name a file of the archive, got {rel!r}")
        if self._kind == "dir":
            path = self.path / rel
            if not path.resolve().is_relative_to(self.path.resolve()):
                raise ArchiveError(f"{where}: field 'file' points outside the archive (a link; not read)")
            if path.exists() and not path.is_file():
                raise ArchiveError(f"{where}: field 'file' names a folder or special file, not a file")
            L.check_file_size(path, where)
            return path.read_bytes()
        member = str(self._prefix / pure)
        if self._kind == "zip":
            size = self._zip.getinfo(member).file_size
        else:
            info = self._tar.getmember(member)
            if not info.isfile():
                raise ArchiveError(f"{self.path}: member {member!r} is not a file")
            size = info.size
        if size > L.current().max_file_bytes:
            raise L.LimitError(
                f"{where}: {size} bytes, over the limit max_file_bytes = {L.current().max_file_bytes} "
                f"(--limit max_file_bytes=...)"
            )
        if self._kind == "zip":
            return self._zip.read(member)
        f = self._tar.extractfile(member)
        if f is None:
            raise ArchiveError(f"{self.path}: member {member!r} is not a file")
        return f.read()

    def load(self, name: str, verify: bool = False) -> Clip:
        """The clip called ``name``; ``verify`` checks the manifest's sha256 first."""
        entry = next((e for e in self.manifest if e["name"] == name), None)
        if entry is None or entry["status"] != "ok":
            raise KeyError(f"{self.path}: no written clip named {name!r}")
        return self._load(entry, verify)

    def _load(self, entry, verify):
        where = f"{self.path}:{entry.get('file')}"
        try:
            data = self._read(entry.get("file"))
        except (KeyError, FileNotFoundError):
            raise ArchiveError(f"{where}: listed in the manifest but missing") from None
        if verify and entry.get("sha256") and _sha256(data) != entry["sha256"]:
            raise ArchiveError(f"{where}: sha256 does not match the manifest")
        try:
            arrays = L.load_npz(data, where)
        except FormatError:  # over a limit, or an array jmocap does not read (names the field)
            raise
        except Exception as e:  # noqa: BLE001 - BadZipFile, zlib.error, truncated members, ...
            raise ClipFormatError(f"{where}: not a readable .npz file ({_reason(e)})") from None
        fmt = arrays.get("format")
        if fmt is not None and fmt.shape == () and fmt.dtype.kind in "US" and str(fmt) == IMU_FORMAT:
            return imu_clip_from_arrays(arrays, where)
        return clip_from_arrays(arrays, where)

    def __iter__(self) -> Iterator[Clip]:
        for e in self.ok:
            yield self._load(e, False)

    def iter_clips(self, verify: bool = False) -> Iterator[Clip]:
        for e in self.ok:
            yield self._load(e, verify)

    def close(self) -> None:
        for attr in ("_zip", "_tar"):
            f = getattr(self, attr, None)
            if f is not None:
                f.close()

    def __enter__(self) -> Archive:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def iter_clips(path: str | os.PathLike, verify: bool = False) -> Iterator[Clip]:
    """Iterate the written clips of an archive (folder, .zip or .tar) in manifest order."""
    with Archive(path) as a:
        yield from a.iter_clips(verify)


def read_manifest(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The latest manifest line of every clip of an archive."""
    with Archive(path) as a:
        return list(a.manifest)


def residual_summary(entries: list[dict[str, Any]]) -> str | None:
    """One line on where a physics archive's generator pushed the root (its manifest entries'
    ``residual_frame_share``, ``residual_force_mean`` and ``frames``; docs/data.md): the share of
    frames with a root residual, frame-weighted, overall and per kind (most frequent first), the
    clips without any, and the mean residual force (% body weight, mean over clips). None when no
    entry has a residual record (a kinematic archive)."""
    phys = [e for e in entries if "residual_frame_share" in e]
    if not phys:
        return None

    def share(es):
        pushed = sum(e["residual_frame_share"] * e.get("frames", 0) for e in es)
        return 100.0 * pushed / max(1, sum(e.get("frames", 0) for e in es))

    kinds: dict[str, int] = {}
    for e in phys:
        kinds[e.get("kind")] = kinds.get(e.get("kind"), 0) + 1
    by_kind = ", ".join(f"{k} {share([e for e in phys if e.get('kind') == k]):.1f} %"
                        for k in sorted(kinds, key=lambda k: -kinds[k]))
    free = sum(e["residual_frame_share"] == 0 for e in phys)
    force = 100.0 * sum(e.get("residual_force_mean", 0.0) for e in phys) / len(phys)
    return (f"root residual: {share(phys):.1f} % of frames ({by_kind}); {free} of {len(phys)} clips without; "
            f"mean force {force:.2f} % BW")


__all__ = [
    "ARCHIVE_META",
    "MANIFEST",
    "Archive",
    "ArchiveError",
    "ArchiveWriter",
    "iter_clips",
    "npz_bytes",
    "read_manifest",
    "residual_summary",
]
