"""``jmocap export`` and ``jmocap view`` on result files: every format written, results without
force estimates handled (no force files), a bad file reported by name with exit status 1 while
the others are still exported."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jmocap.cli import main
from jmocap.results import load_result, write_result

DEMO = Path(__file__).resolve().parents[1] / "src/jmocap/assets/demo/ground_truth/demo_walk.npz"


def _write(path: Path, name: str, forces: bool, frames: int = 12) -> None:
    with np.load(DEMO) as z:
        arrays = {
            "format": np.array("jmocap-result-1"), "name": np.array(name),
            "method": np.array("pip" if forces else "kinematic"),
            "q": z["gt_q"][:frames].astype(np.float32), "fps": np.array(float(z["fps"])),
            "height_m": np.array(float(z["height_m"])), "mass_kg": np.array(float(z["mass_kg"])),
            "contact_prob": z["gt_contacts"][:frames].astype(np.float32),
            "keypoints3d": z["gt_keypoints3d"][:frames].astype(np.float32), "layout": np.array("body25"),
            "forces_estimated": np.array(forces), "assumed": np.array("[]"),
        }
        if forces:
            arrays.update(grf=z["gt_grf"][:frames].astype(np.float32), tau=z["gt_tau"][:frames].astype(np.float32))
    write_result(path, arrays)


def test_export_all_formats_and_skip_absent_forces(tmp_path, capsys):
    res = tmp_path / "results"
    res.mkdir()
    _write(res / "walk.npz", "walk", forces=True)
    _write(res / "kin.npz", "kin", forces=False)
    out = tmp_path / "export"
    assert main(["export", str(res), str(out)]) == 0
    names = {p.name for p in out.iterdir()}
    for stem in ("walk", "kin"):
        assert {f"{stem}.osim", f"{stem}_coordinates.mot", f"{stem}_markers.trc", f"{stem}.glb",
                f"{stem}.bvh"} <= names
    assert {"walk_grf.mot", "walk_grf.xml"} <= names
    assert not any(n.startswith("kin_grf") for n in names), "no forces estimated: no force files"
    assert "2 of 2 results" in capsys.readouterr().out
    # one format only
    assert main(["export", str(res / "walk.npz"), str(tmp_path / "glb"), "--glb"]) == 0
    assert sorted(p.name for p in (tmp_path / "glb").iterdir()) == ["walk.glb"]


def test_export_reports_a_bad_file_and_goes_on(tmp_path, capsys):
    res = tmp_path / "results"
    res.mkdir()
    _write(res / "walk.npz", "walk", forces=True)
    (res / "broken.npz").write_bytes(b"not a zip file")
    out = tmp_path / "export"
    assert main(["export", str(res), str(out), "--bvh"]) == 1
    err = capsys.readouterr().err
    assert "broken.npz" in err
    assert (out / "walk.bvh").is_file()
    assert main(["export", str(tmp_path / "missing"), str(out)]) == 1


def test_view_writes_one_page_for_a_folder(tmp_path, capsys):
    res = tmp_path / "results"
    res.mkdir()
    _write(res / "walk.npz", "walk", forces=True)
    _write(res / "kin.npz", "kin", forces=False)
    assert main(["view", str(res)]) == 0
    page = (res / "viewer.html").read_text()
    clips = json.loads(page.split('id="jmocap-data">')[1].split("</script>")[0])
    assert sorted(c["name"] for c in clips) == ["kin", "walk"]
    assert {c["name"]: c["forces"] for c in clips} == {"kin": False, "walk": True}
    assert load_result(res / "kin.npz")["grf"] is None
    assert main(["view", str(res / "walk.npz"), "-o", str(tmp_path / "w.html")]) == 0
    assert (tmp_path / "w.html").is_file()
