"""Hostile or clumsy input, below the batch engine: limits, plausibility checks, the scanner,
archive manifests, extraction and crash-safe writing (issue 16). Fast: no reconstruction here
(tests/test_batch.py and tests/test_fuzz.py run the engine end to end).

References are hand-worked: the field of view of a pinhole (2 atan(w / 2 f)), the camera
centre -R^T t, byte counts of names, the mode 0o666 & ~umask that ``open()`` gives.
"""

from __future__ import annotations

import json
import math
import os
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from jmocap.camera import default_extrinsics
from jmocap.data import limits as L
from jmocap.data import save_clip
from jmocap.data.archive import MANIFEST, Archive, ArchiveError, ArchiveWriter
from jmocap.data.clip import Clip, FormatError
from jmocap.data.sources import open_sources, scan_folder
from jmocap.data.validate import check_name, check_reconstructable, frame_ranges
from jmocap.io import atomic_write, remove_stale_temporaries


def person_clip(T: int = 12, name: str = "walk", **changes) -> Clip:
    """A BODY_25 clip: 25 joints spread over a 200 x 600 px box in a 1000 x 1000 image."""
    rng = np.random.default_rng(0)
    xy = np.stack([rng.uniform(400, 600, (T, 25)), rng.uniform(200, 800, (T, 25))], -1)
    kp = np.concatenate([xy, np.full((T, 25, 1), 0.9)], -1)
    base = dict(name=name, layout="body25", fps=30.0, keypoints=kp, intrinsics=[1000.0, 1000.0, 500.0, 500.0],
                image_size=[1000, 1000], extrinsics=default_extrinsics(1.0, 4.0), height_m=1.75, mass_kg=70.0)
    base.update(changes)
    return Clip(**base)


# --- limits -------------------------------------------------------------------------------


def test_limits_parse_sizes_and_refuse_nonsense():
    lim = L.Limits.parse(["max_file_bytes=2M", "max-frames=5000", "max_extract_bytes=1.5G"])
    assert lim.max_file_bytes == 2 * 2**20 and lim.max_frames == 5000
    assert lim.max_extract_bytes == int(1.5 * 2**30)
    for bad in (["max_files"], ["nope=3"], ["max_files=-1"], ["max_files=x"]):
        with pytest.raises(ValueError, match="--limit"):
            L.Limits.parse(bad)
    with L.use(lim):
        assert L.current().max_frames == 5000
        with pytest.raises(L.LimitError, match=r"clip\.json: frame 100000: .*max_frame_gap = 10000"):
            L.check_frame_gap(8, 100000, "clip.json")
    assert L.current() == L.Limits()


def test_npz_members_are_checked_before_decompressing(tmp_path):
    """A small .npz whose member inflates past max_file_bytes is refused from its directory
    entry: nothing is decompressed."""
    p = tmp_path / "bomb.npz"
    with zipfile.ZipFile(p, "w", zipfile.ZIP_DEFLATED) as z:
        with z.open("keypoints.npy", "w", force_zip64=True) as f:
            chunk = bytes(1 << 20)
            for _ in range(8):
                f.write(chunk)
    assert p.stat().st_size < 100_000
    with L.use(L.Limits(max_file_bytes=4 << 20)), pytest.raises(L.LimitError, match="field 'keypoints'.*max_file_bytes"):
        L.load_npz(p, str(p))


# --- plausibility -------------------------------------------------------------------------


def test_a_plausible_clip_passes_without_warnings():
    assert check_reconstructable(person_clip(), "walk.npz") == []


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(fps=1e-9), "field 'fps'"),
        (dict(fps=1e9), "field 'fps'"),
        (dict(height_m=100.0), "field 'height_m'"),
        (dict(mass_kg=1e6), "field 'mass_kg'"),
        (dict(image_size=[100_000, 1000], intrinsics=[1000.0, 1000.0, 500.0, 500.0]), "field 'image_size'"),
        (dict(intrinsics=[1e7, 1e7, 500.0, 500.0]), "field 'intrinsics'.*field of view"),
        (dict(intrinsics=[1000.0, 100.0, 500.0, 500.0]), "field 'intrinsics'.*fx / fy"),
        (dict(intrinsics=[1000.0, 1000.0, 5000.0, 500.0]), "field 'intrinsics'.*principal point"),
    ],
)
def test_absurd_values_fail_naming_the_field(changes, match):
    with pytest.raises(FormatError, match=r"^walk\.npz: " + match):
        check_reconstructable(person_clip(**changes), "walk.npz")


def test_field_of_view_limits_are_the_pinhole_formula():
    """fov = 2 atan(w / 2 fx): 170 deg on a 1000 px image is fx = 500 / tan(85 deg) = 43.7 px."""
    fx_edge = 500.0 / math.tan(math.radians(85.0))
    ok = person_clip(intrinsics=[fx_edge * 1.01, fx_edge * 1.01, 500.0, 500.0])
    check_reconstructable(ok, "w")
    with pytest.raises(FormatError, match="field of view"):
        check_reconstructable(person_clip(intrinsics=[fx_edge * 0.99, fx_edge * 0.99, 500.0, 500.0]), "w")


def _camera_at(centre) -> np.ndarray:
    """A level camera looking along +y from ``centre`` (world -> camera, t = -R c)."""
    E = default_extrinsics(1.0, 4.0)
    E[:3, 3] = -E[:3, :3] @ np.asarray(centre, float)
    return E


def test_camera_placement():
    with pytest.raises(FormatError, match=r"field 'extrinsics'.*1e\+06 m from the world origin"):
        check_reconstructable(person_clip(extrinsics=_camera_at([0.0, -1e6, 1.0])), "w")
    with pytest.raises(FormatError, match="field 'extrinsics'.*0.5 m below the floor"):
        check_reconstructable(person_clip(extrinsics=_camera_at([0.0, -4.0, -0.5])), "w")
    w = check_reconstructable(person_clip(extrinsics=_camera_at([0.0, -300.0, 1.0])), "w")
    assert any("far away" in x for x in w)
    assert any("extrinsics" in x for x in check_reconstructable(person_clip(extrinsics=None), "w"))


def test_visibility_rules():
    kp = person_clip().keypoints.copy()
    faint = kp.copy()
    faint[..., 2] = 1e-30  # "detected" with no confidence at all
    with pytest.raises(FormatError, match="field 'keypoints': 0 of 12 frames have a usable detection"):
        check_reconstructable(person_clip(keypoints=faint), "w")
    one = np.zeros_like(kp)
    one[4, 0] = kp[4, 0]  # one visible joint in one frame
    with pytest.raises(FormatError, match="field 'keypoints'"):
        check_reconstructable(person_clip(keypoints=one), "w")
    gaps = kp.copy()
    gaps[[0, 1, 5, 6, 7, 11]] = 0.0
    (w,) = check_reconstructable(person_clip(keypoints=gaps), "w")
    assert "6 of 12 frames" in w and "frames 0-1, 5-7, 11" in w and "3 of them extrapolated" in w
    far = kp.copy()
    far[3, 2, 0] = 1e9
    with pytest.raises(FormatError, match=r"^w: frame 3: field 'keypoints'.*beyond"):
        check_reconstructable(person_clip(keypoints=far), "w")


def test_names_must_make_file_names():
    check_name("a" * 251, "w")  # + ".npz" = 255 bytes, the limit of a file name
    with pytest.raises(FormatError, match="field 'name'.*252 bytes"):
        check_name("a" * 252, "w")
    with pytest.raises(FormatError, match="field 'name'.*256 bytes"):
        check_name("sub/" + "é" * 128, "w")  # bytes, not characters
    for bad in ("../x", "/abs", "a/./b", "a\\b"):
        with pytest.raises(FormatError, match="field 'name'"):
            check_name(bad, "w")
    assert frame_ranges(np.array([0, 1, 2, 7])) == "0-2, 7"


# --- writing --------------------------------------------------------------------------------


def test_atomic_write_long_names_umask_and_stale_temporaries(tmp_path):
    long = tmp_path / ("n" * 251 + ".npz")
    old = os.umask(0o077)
    try:
        atomic_write(long, b"data")
    finally:
        os.umask(old)
    assert long.read_bytes() == b"data" and long.stat().st_mode & 0o777 == 0o600
    atomic_write(tmp_path / "b", b"x")
    assert (tmp_path / "b").stat().st_mode & 0o777 == 0o666 & ~old
    left = [tmp_path / ".jmocap-xyz.tmp", tmp_path / "d" / ".walk.npz.ab12.tmp"]
    for p in left:
        p.parent.mkdir(exist_ok=True)
        p.write_bytes(b"")
    keep = tmp_path / ".hidden_notes"
    keep.write_text("user's")
    assert sorted(remove_stale_temporaries(tmp_path)) == sorted(left)
    assert keep.exists() and long.exists()


# --- the scanner ------------------------------------------------------------------------------


def test_scan_lists_what_it_skips_and_survives_links(tmp_path):
    root = tmp_path / "in"
    (root / "a").mkdir(parents=True)
    save_clip(root / "a" / "walk.npz", person_clip())
    save_clip(root / "run.npz", person_clip(name="run"))
    (root / "notes.json").write_text(json.dumps({"author": "me", "date": "2026"}))
    (root / "readme.txt").write_text("hello")
    (root / "self").symlink_to(".")  # a loop
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    save_clip(outside / "secret.npz", person_clip(name="secret"))
    (root / "out_link").symlink_to(outside)
    (root / "file_link.npz").symlink_to(outside / "secret.npz")
    found = scan_folder(root)
    assert sorted(s.name for s in found) == ["a/walk", "run"]
    reasons = {Path(d["path"]).name: d["reason"] for d in found.skipped}
    assert "not OpenPose, COCO or MMPose" in reasons["notes.json"]
    assert "suffix '.txt'" in reasons["readme.txt"]
    assert "outside the input" in reasons["out_link"] and "outside the input" in reasons["file_link.npz"]
    assert "already scanned" in reasons["self"]


def test_stray_keypoints_file_and_nested_archives(tmp_path):
    """A stray ``*_keypoints.json`` at the top no longer hides the clips in sub-folders; a clip
    archive inside a folder of loose files contributes its clips; a results folder is skipped."""
    root = tmp_path / "in"
    for i in range(3):
        (root / f"take{i}").mkdir(parents=True)
        save_clip(root / f"take{i}" / "clip.npz", person_clip(name=f"t{i}"))
    (root / "stray_000000000000_keypoints.json").write_text(json.dumps({"version": 1.3, "people": []}))
    with ArchiveWriter(root / "arch", {"engine": "jmocap.data.synthetic"}) as w:
        w.add(person_clip(name="s0"))
        w.add(person_clip(name="s1"))
    with ArchiveWriter(root / "old_out", {"engine": "jmocap.batch"}) as w:
        w.add_failure("x", "an old failure")
    names = sorted(s.name for s in scan_folder(root))
    assert names == ["arch/s0", "arch/s1", "in", "take0/clip", "take1/clip", "take2/clip"]
    src = {s.name: s for s in scan_folder(root)}
    assert src["arch/s1"].load().name == "s1"
    assert any("results folder" in d["reason"] for d in scan_folder(root).skipped)
    # a zip of the same folder: the nested manifest does not make the whole zip an "archive"
    z = tmp_path / "in.zip"
    with zipfile.ZipFile(z, "w") as zf:
        for p in sorted(root.rglob("*")):
            if p.is_file():
                zf.write(p, p.relative_to(tmp_path).as_posix())
    with open_sources(z) as sources:
        assert sorted(s.name for s in sources) == ["in", "in/arch/s0", "in/arch/s1", "in/take0/clip",
                                                  "in/take1/clip", "in/take2/clip"]


def test_an_unreadable_folder_is_a_failing_source(tmp_path, monkeypatch):
    """A folder the scan cannot list (permission denied; simulated, since tests may run as
    root) is a source that fails naming it: not a traceback, not silently nothing."""
    root = tmp_path / "in"
    (root / "locked").mkdir(parents=True)
    save_clip(root / "ok.npz", person_clip())
    iterdir = Path.iterdir

    def guarded(self):
        if self.name == "locked":
            raise PermissionError(13, "Permission denied", str(self))
        return iterdir(self)

    monkeypatch.setattr(Path, "iterdir", guarded)
    src = {s.name: s for s in scan_folder(root)}
    assert set(src) == {"locked", "ok"}
    with pytest.raises(FormatError, match="locked: cannot read the folder: Permission denied"):
        src["locked"].load()


def test_scan_stops_at_max_files(tmp_path):
    for i in range(12):
        save_clip(tmp_path / f"c{i}.npz", person_clip(name=f"c{i}"))
    with L.use(L.Limits(max_files=10)), pytest.raises(ArchiveError, match="max_files"):
        scan_folder(tmp_path)


# --- archives --------------------------------------------------------------------------------


def test_manifest_paths_stay_inside_the_archive(tmp_path):
    arch = tmp_path / "arch"
    with ArchiveWriter(arch) as w:
        w.add(person_clip(name="good"))
    save_clip(tmp_path / "outside.npz", person_clip(name="outside"))
    with open(arch / MANIFEST, "a") as f:
        for name, file in (("up", "../outside.npz"), ("abs", str(tmp_path / "outside.npz")), ("nofile", None)):
            line = {"name": name, "status": "ok"}
            if file is not None:
                line["file"] = file
            f.write(json.dumps(line) + "\n")
    (arch / "link.npz").symlink_to(tmp_path / "outside.npz")
    with open(arch / MANIFEST, "a") as f:
        f.write(json.dumps({"name": "link", "file": "link.npz", "status": "ok"}) + "\n")
    with open_sources(arch) as sources:
        src = {s.name: s for s in sources}
        assert src["good"].load().name == "good"
        for name in ("up", "abs", "link"):
            with pytest.raises(ArchiveError, match="field 'file' points outside the archive"):
                src[name].load()
        with pytest.raises(ArchiveError, match="field 'file' must be a file name"):
            src["nofile"].load()
    with open(arch / MANIFEST, "a") as f:
        f.write(json.dumps({"name": "dot", "file": ".", "status": "ok"}) + "\n")
        f.write(json.dumps({"name": "dir", "file": "sub", "status": "ok"}) + "\n")
    (arch / "sub").mkdir()
    with open_sources(arch) as sources:
        src = {s.name: s for s in sources}
        with pytest.raises(ArchiveError, match="field 'file' must name a file of the archive"):
            src["dot"].load()
        with pytest.raises(ArchiveError, match="field 'file' names a folder"):
            src["dir"].load()


def test_a_manifest_that_is_not_utf8_is_one_line(tmp_path):
    arch = tmp_path / "arch"
    arch.mkdir()
    (arch / MANIFEST).write_bytes(b'{"name": "\xff"}\n')
    with pytest.raises(ArchiveError, match=r"manifest.jsonl: not UTF-8 text \(byte 10\)$"):
        Archive(arch)
    with zipfile.ZipFile(tmp_path / "a.zip", "w") as zf:
        zf.writestr(MANIFEST, b"\xfe\n")
    with pytest.raises(ArchiveError, match=r"a.zip:manifest.jsonl: not UTF-8 text \(byte 0\)"):
        Archive(tmp_path / "a.zip")


def test_a_clip_name_too_long_for_a_sidecar_has_none(tmp_path):
    """A 251-byte name is a valid file name; its sidecar name (+ '.camera.json') is not: no
    sidecar (ENAMETOOLONG is not an error), the clip loads."""
    name = "n" * 247
    save_clip(tmp_path / f"{name}.npz", person_clip(name=name))
    with open_sources(tmp_path) as sources:
        (src,) = list(sources)
        assert src.load().name == name


def test_damaged_containers_are_one_line_archive_errors(tmp_path):
    (tmp_path / "junk.zip").write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(ArchiveError, match="junk.zip"), open_sources(tmp_path / "junk.zip"):
        pass
    t = tmp_path / "links.tar"
    with tarfile.open(t, "w") as tf:
        info = tarfile.TarInfo("evil")
        info.type = tarfile.SYMTYPE
        info.linkname = "/etc/passwd"
        tf.addfile(info)
    with pytest.raises(ArchiveError, match="links.tar: member 'evil' refused"), open_sources(t):
        pass
    z = tmp_path / "bomb.zip"
    with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("clip.npy", "w", force_zip64=True) as f:
            for _ in range(4):
                f.write(bytes(1 << 20))
    with L.use(L.Limits(max_file_bytes=1 << 20)), pytest.raises(ArchiveError, match="max_file_bytes"), open_sources(z):
        pass
    with L.use(L.Limits(max_extract_bytes=1 << 20)), pytest.raises(ArchiveError, match="max_extract_bytes"), open_sources(z):
        pass
    with pytest.raises(ArchiveError, match="not valid JSON"):
        bad = tmp_path / "arch"
        bad.mkdir()
        (bad / MANIFEST).write_text("")
        (bad / "archive.json").write_text("{")
        Archive(bad)
