"""jmocap.export.viewer: the self-contained viewer page.

References: MuJoCo C kinematics (the geometry the page draws), a hand-written look-at camera
(the page's projection), and the page's own script run under Node.js with a recording 2D
context (skipped where ``node`` is not installed): the character is drawn where MuJoCo puts it,
and moving the time slider moves it. (A pixel screenshot in headless Chromium is not possible
on the machines this was written on: no browser is installed or downloadable.)
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
from pathlib import Path

import mujoco
import numpy as np
import pytest

from jmocap.constants import GRAVITY
from jmocap.export.viewer import TORQUE_JOINTS, clip_payload, viewer_html, write_viewer
from jmocap.results import result_model

DEMO = Path(__file__).resolve().parents[1] / "src/jmocap/assets/demo/ground_truth/demo_walk.npz"


def _result(frames: int = 24, forces: bool = True) -> dict:
    with np.load(DEMO) as z:
        r = {
            "name": "walk", "method": "ground_truth", "fps": float(z["fps"]), "height_m": float(z["height_m"]),
            "mass_kg": float(z["mass_kg"]), "q": z["gt_q"][:frames].astype(np.float32),
            "contact_prob": z["gt_contacts"][:frames].astype(np.float32), "forces_estimated": forces,
            "grf": z["gt_grf"][:frames].astype(np.float32) if forces else None,
            "tau": z["gt_tau"][:frames].astype(np.float32) if forces else None,
            "warnings": ["a warning"], "assumed": [],
        }
    return r


def _f32(b64: str, shape) -> np.ndarray:
    return np.frombuffer(base64.b64decode(b64), "<f4").reshape(shape)


def test_payload_is_the_mujoco_geometry_and_the_forces():
    r = _result()
    model = result_model(r)
    p = clip_payload(r)
    T, S = p["T"], p["S"]
    seg = _f32(p["segments"], (T, S, 2, 3))
    sites = _f32(p["sites"], (T, 4, 3))
    mj = model.mj
    d = mujoco.MjData(mj)
    caps = [g for g in range(mj.ngeom) if mj.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE]
    for t in (0, T // 2, T - 1):
        d.qpos[:] = r["q"][t]
        mujoco.mj_kinematics(mj, d)
        np.testing.assert_allclose(sites[t], d.site_xpos[list(model.topo.contact_sites)], atol=1e-5)
        # every capsule: a segment centred on the geom, along its z axis, as long as the capsule
        mids, dirs = seg[t].mean(1), seg[t, :, 1] - seg[t, :, 0]
        for g in caps:
            k = int(np.argmin(np.linalg.norm(mids - d.geom_xpos[g], axis=1)))
            np.testing.assert_allclose(mids[k], d.geom_xpos[g], atol=1e-5)
            np.testing.assert_allclose(np.abs(dirs[k] @ d.geom_xmat[g].reshape(3, 3)[:, 2]), 2 * mj.geom_size[g, 1],
                                       atol=1e-5)
    np.testing.assert_allclose(_f32(p["grf"], (T, 4, 3)), r["grf"], atol=1e-6)
    dofs = [int(mj.jnt_dofadr[mj.joint(n).id]) for n in TORQUE_JOINTS]
    np.testing.assert_allclose(_f32(p["torque"], (T, 6)), r["tau"][:, dofs] / model.total_mass, rtol=1e-6)
    w = model.total_mass * GRAVITY
    assert p["weight"] == pytest.approx(w, abs=1e-3)
    assert p["stats"]["residual_root_force_pct_bw"] == pytest.approx(
        100 * np.linalg.norm(r["tau"][:, :3], axis=1).mean() / w, abs=1e-3)
    assert p["stats"]["frames"] == T and p["warnings"] == ["a warning"]


def test_no_forces_means_no_force_data():
    p = clip_payload(_result(forces=False))
    assert p["forces"] is False and p["grf"] is None and p["torque"] is None
    assert "residual_root_force_pct_bw" not in p["stats"]
    assert "does not estimate them" in viewer_html([p])


def test_bad_input_names_the_field():
    r = _result()
    r["q"] = r["q"].copy()
    r["q"][3, 9] = np.nan
    with pytest.raises(ValueError, match="'q'"):
        clip_payload(r)
    r = _result()
    r["grf"] = r["grf"][:, :3]
    with pytest.raises(ValueError, match="'grf'"):
        clip_payload(r)
    r = _result()
    r["fps"] = 0.0
    with pytest.raises(ValueError, match="'fps'"):
        clip_payload(r)


def test_page_is_one_offline_file():
    page = viewer_html([clip_payload(_result())], title="a <title>")
    assert not re.search(r"https?://", page), "the page must not reach the network"
    assert not re.search(r"<(script|link|img)[^>]+(src|href)=", page), "no external files"
    assert "a &lt;title&gt;" in page
    data = page.split('id="jmocap-data">')[1].split("</script>")[0]
    clips = json.loads(data)
    assert clips[0]["name"] == "walk" and clips[0]["T"] == 24


def test_write_viewer_reads_a_folder_and_skips_what_is_not_a_result(tmp_path):
    from jmocap.results import write_result

    r = _result()
    arrays = {k: np.asarray(v) for k, v in r.items() if v is not None and k not in ("warnings", "assumed")}
    arrays["warnings"] = np.array(json.dumps(r["warnings"]))
    write_result(tmp_path / "walk.npz", arrays)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    out, skipped = write_viewer(tmp_path, tmp_path / "view.html")
    assert out.is_file() and len(skipped) == 1 and "junk.npz" in skipped[0]
    clips = json.loads(out.read_text().split('id="jmocap-data">')[1].split("</script>")[0])
    assert [c["name"] for c in clips] == ["walk"]
    with pytest.raises(ValueError, match="no readable result"):
        write_viewer(tmp_path / "junk.npz", tmp_path / "v2.html")


def _look_at_projection(cam, p, W, H):
    """The page's camera, written independently: an orbit eye about the target, z up."""
    eye = np.asarray(cam["target"]) + cam["dist"] * np.array(
        [np.cos(cam["pitch"]) * np.cos(cam["yaw"]), np.cos(cam["pitch"]) * np.sin(cam["yaw"]), np.sin(cam["pitch"])])
    f = np.asarray(cam["target"]) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    d = np.asarray(p) - eye
    s = cam["focal"] * min(W, H) / (d @ f)
    return np.array([W / 2 + s * (d @ r), H / 2 - s * (d @ u)])


NODE_SCRIPT = r"""
const fs = require("fs");
const html = fs.readFileSync(process.argv[2], "utf8");
const grab = (id) => html.split(`id="${id}">`)[1].split("</script>")[0];
const JM = new Function("module", grab("jmocap-core") + "; return JM;")(undefined);
const clips = JSON.parse(grab("jmocap-data"));
const frames = {}, cams = {};
const rec = [];
const ctx = new Proxy({}, { get: (o, k) => (k in o ? o[k] : (...a) => rec.push([k, ...a])),
                            set: (o, k, v) => { o[k] = v; return true; } });
const c = JM.load(clips[0]); const cam = JM.camera(c);
for (const t of [0, c.T - 1]) {
  rec.length = 0; JM.drawFrame(ctx, c, t, cam, 720, 480); frames[t] = rec.slice(); cams[t] = JM.view(cam, c, t);
}
const ff = JM.footForce(c);
console.log(JSON.stringify({cams, frames, left: Array.from(ff[0]), right: Array.from(ff[1]), T: c.T, S: c.S}));
"""


@pytest.mark.skipif(shutil.which("node") is None, reason="Node.js is not installed")
def test_page_script_draws_the_character_where_mujoco_puts_it(tmp_path):
    r = _result()
    p = clip_payload(r)
    page = tmp_path / "view.html"
    page.write_text(viewer_html([p]))
    script = tmp_path / "run.js"
    script.write_text(NODE_SCRIPT)
    run = subprocess.run(["node", str(script), str(page)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    T, S = out["T"], out["S"]
    seg = _f32(p["segments"], (T, S, 2, 3))
    sites = _f32(p["sites"], (T, 4, 3))
    drawn = {}
    for t in (0, T - 1):
        calls = out["frames"][str(t)]
        # the segments: moveTo(end 0) then lineTo(end 1 + 0.01 px), twice (outline, fill)
        pts = [(calls[i][1:3], calls[i + 1][1:3]) for i in range(len(calls) - 1)
               if calls[i][0] == "moveTo" and calls[i + 1][0] == "lineTo"]
        cam = out["cams"][str(t)]  # the orbit camera follows the character: its target is the sites' mean
        np.testing.assert_allclose(cam["target"][:2], sites[t, :, :2].mean(0), atol=1e-5)
        expect = [(_look_at_projection(cam, seg[t, s, 0], 720, 480),
                   _look_at_projection(cam, seg[t, s, 1], 720, 480)) for s in range(S)]
        for a, b in expect:  # each segment of MuJoCo's pose is drawn (outline and fill)
            hits = [1 for pa, pb in pts if np.allclose(pa, a, atol=0.05) and np.allclose(pb, b + [0.01, 0], atol=0.05)]
            assert len(hits) == 2, (t, a, b)
        drawn[t] = np.array(expect)  # (S, 2, 2): every segment was found drawn at these pixels
    assert np.abs(drawn[0] - drawn[T - 1]).max() > 5.0, "the time slider does not move the character"
    w = p["weight"]
    np.testing.assert_allclose(out["left"], 100 * r["grf"][:, :2, 2].sum(1) / w, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(out["right"], 100 * r["grf"][:, 2:, 2].sum(1) / w, rtol=1e-4, atol=1e-3)


UI_SCRIPT = r"""
const fs = require("fs");
const html = fs.readFileSync(process.argv[2], "utf8");
const grab = (id) => html.split(`id="${id}">`)[1].split("</script>")[0];
const ctx = new Proxy({}, { get: (o, k) => (k in o ? o[k] : () => {}), set: (o, k, v) => { o[k] = v; return true; } });
const els = {};
function el(id) {
  return els[id] = els[id] || { id, width: 720, height: 480, value: "0", max: "0", className: "",
    textContent: id === "jmocap-data" ? grab("jmocap-data") : "", rows: [],
    listeners: {}, addEventListener(t, f) { this.listeners[t] = f; }, getContext() { return ctx; },
    appendChild(c) { this.rows.push(c); } };
}
let n = 0;
global.document = { getElementById: el, querySelector: () => el("tbody"), querySelectorAll: () => [],
                    createElement: () => el("e" + (n++)), addEventListener() {} };
global.window = { addEventListener() {} };
let frames = 0;
global.requestAnimationFrame = (f) => { if (frames++ < 3) f(frames * 16); };
const JM = new Function("module", grab("jmocap-core") + "; return JM;")(undefined);
new Function("JM", grab("jmocap-ui"))(JM);
const out = { rows: els["tbody"].rows.length, max: els["time"].max };
els["time"].value = "10"; els["time"].listeners.input();
out.clock = els["clock"].textContent;
els["play"].listeners.click();
out.play = els["play"].textContent;
console.log(JSON.stringify(out));
"""


@pytest.mark.skipif(shutil.which("node") is None, reason="Node.js is not installed")
def test_page_wiring_runs_against_a_minimal_dom(tmp_path):
    """The page's UI script (clip list, slider, play button) runs against a minimal DOM: one row
    per clip, the slider spans the clip and moves the clock, the button toggles playing."""
    r = _result()
    page = tmp_path / "view.html"
    page.write_text(viewer_html([clip_payload(r), clip_payload(_result(forces=False), name="kin")]))
    script = tmp_path / "ui.js"
    script.write_text(UI_SCRIPT)
    run = subprocess.run(["node", str(script), str(page)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["rows"] == 2 and int(out["max"]) == len(r["q"]) - 1
    assert out["clock"] == f"{10 / r['fps']:.2f} s" and out["play"] == "pause"
