"""The viewer page: one self-contained HTML file that plays reconstruction results in a browser.

``jmocap view RESULTS -o viewer.html`` (:func:`write_viewer`) writes a single file that works
offline from disk (no server, no network, no JavaScript library: the page draws on a 2D canvas
with its own ~300 lines of script, so nothing needs vendoring or downloading). For a clip or a
whole results folder it shows:

* 3D playback of the character (its collision capsules and feet, in the result's own
  character), the floor grid, each contact site (filled while its contact probability is
  > 0.5) and the ground reaction force at each site as an arrow (1 body weight = 1 m);
  drag to orbit, wheel to zoom, the time slider to scrub, space to play or pause;
* the clip list with its numbers (method, frames, duration; where forces were estimated the
  mean residual root force and peak vertical GRF in % body weight, the share of frames whose
  QP was certified; warnings recorded with the result); click a row to open the clip;
* plots under the view: per-foot vertical GRF (% body weight) and the hip, knee and ankle
  flexion torques (N m / kg), with a cursor at the current frame. A result without force
  estimates (``forces_estimated`` False) says so instead of drawing zeros.

Data layout (``<script type="application/json" id="jmocap-data">``): a JSON list, one object
per clip, world positions in jmocap's frame (z up, metres) as base64 little-endian float32:
``segments`` (T, S, 2, 3) the end points of each geom's segment (a capsule's axis; a box's
longest axis) with ``radius`` (S,); ``sites`` (T, 4, 3) the contact sites; ``grf`` (T, 4, 3)
newtons or null; ``contact`` (T, 4) or null; ``torque`` (T, 6) N m / kg or null. The page's
script is split in a pure core (``id="jmocap-core"``: decoding, the camera, projection, drawing
on any 2D context) and the page wiring (``id="jmocap-ui"``), so the core runs (and is tested)
outside a browser.
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from jmocap.constants import GRAVITY, NUM_CONTACTS
from jmocap.export.bvh import check_q
from jmocap.io import atomic_write

__all__ = ["TORQUE_JOINTS", "clip_payload", "viewer_html", "write_viewer"]

#: the flexion dofs whose torques the page plots (N m / kg)
TORQUE_JOINTS = ("left_hip_y", "right_hip_y", "left_knee_y", "right_knee_y", "left_ankle_y", "right_ankle_y")


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a, "<f4").tobytes()).decode("ascii")


def _segments(mj: mujoco.MjModel, d: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
    """End points (S, 2, 3) and radii (S,) of the drawable geoms (capsules: their axis; boxes:
    their longest axis, radius the mean of the two other half sizes), world frame."""
    ends, radii = [], []
    for g in range(mj.ngeom):
        t = mj.geom_type[g]
        pos, R, size = d.geom_xpos[g], d.geom_xmat[g].reshape(3, 3), mj.geom_size[g]
        if t == mujoco.mjtGeom.mjGEOM_CAPSULE or t == mujoco.mjtGeom.mjGEOM_CYLINDER:
            half, r, axis = size[1], size[0], R[:, 2]
        elif t == mujoco.mjtGeom.mjGEOM_BOX:
            k = int(np.argmax(size[:3]))
            others = [i for i in range(3) if i != k]
            r = float(np.mean(size[others]))
            half, axis = max(size[k] - r, 0.0), R[:, k]
        elif t == mujoco.mjtGeom.mjGEOM_SPHERE:
            half, r, axis = 0.0, size[0], R[:, 2]
        else:  # the floor plane, meshes
            continue
        ends.append([pos - half * axis, pos + half * axis])
        radii.append(r)
    return np.asarray(ends, np.float64).reshape(-1, 2, 3), np.asarray(radii, np.float64)


def _num(v) -> float | None:
    v = float(v)
    return round(v, 3) if math.isfinite(v) else None


def clip_payload(result: dict[str, Any], model=None, *, name: str | None = None) -> dict[str, Any]:
    """The viewer's data for one result (:func:`jmocap.results.load_result` dict): geometry by
    MuJoCo C kinematics of ``q`` in the result's character (:func:`jmocap.results.result_model`),
    the forces when estimated, and the clip's numbers. Raises ``ValueError`` naming the field."""
    from jmocap.results import result_model

    model = result_model(result) if model is None else model
    where = f"viewer: {name or result.get('name') or 'result'}"
    q = check_q(model, result.get("q"), f"{where}: field 'q'")
    fps = float(result.get("fps") or 0.0)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"{where}: field 'fps' must be positive, got {result.get('fps')!r}")
    T = len(q)
    mj = model.mj
    d = mujoco.MjData(mj)
    segs, sites = [], []
    site_ids = list(model.topo.contact_sites)
    radius = None
    for x in q:
        d.qpos[:] = x
        mujoco.mj_kinematics(mj, d)
        e, radius = _segments(mj, d)
        segs.append(e)
        sites.append(d.site_xpos[site_ids].copy())
    weight = float(model.total_mass) * GRAVITY
    forces = bool(result.get("forces_estimated", True)) and result.get("grf") is not None
    grf = tau = None
    stats: dict[str, Any] = {"frames": T, "seconds": round(T / fps, 2)}
    if forces:
        grf = np.asarray(result["grf"], np.float64)
        if grf.shape != (T, NUM_CONTACTS, 3) or not np.all(np.isfinite(grf)):
            raise ValueError(f"{where}: field 'grf' must be finite (T={T}, {NUM_CONTACTS}, 3), got {grf.shape}")
        fz = grf[..., 2].sum(-1)
        stats["peak_vertical_grf_pct_bw"] = _num(100 * fz.max() / weight)
        if result.get("tau") is not None:
            t_all = np.asarray(result["tau"], np.float64)
            if t_all.shape != (T, model.nv) or not np.all(np.isfinite(t_all)):
                raise ValueError(f"{where}: field 'tau' must be finite (T={T}, nv={model.nv}), got {t_all.shape}")
            stats["residual_root_force_pct_bw"] = _num(100 * np.linalg.norm(t_all[:, :3], axis=1).mean() / weight)
            dofs = [int(mj.jnt_dofadr[mj.joint(n).id]) for n in TORQUE_JOINTS]
            tau = t_all[:, dofs] / float(model.total_mass)
    if result.get("certified") is not None:
        stats["certified_pct"] = _num(100 * np.mean(np.asarray(result["certified"], bool)))
    contact = result.get("contact_prob")
    if contact is not None:
        contact = np.asarray(contact, np.float64)
        if contact.shape != (T, NUM_CONTACTS):
            raise ValueError(f"{where}: field 'contact_prob' has shape {contact.shape}, expected ({T}, {NUM_CONTACTS})")
    warnings = result.get("warnings") or []
    return {
        "name": str(name or result.get("name") or "clip"),
        "method": str(result.get("method") or "?"),
        "fps": fps,
        "T": T,
        "S": int(len(radius)),
        "radius": [round(float(r), 4) for r in radius],
        "segments": _b64(np.asarray(segs)),
        "sites": _b64(np.asarray(sites)),
        "weight": round(weight, 3),
        "forces": forces,
        "grf": _b64(grf) if grf is not None else None,
        "contact": _b64(contact) if contact is not None else None,
        "torque": _b64(tau) if tau is not None else None,
        "torque_names": list(TORQUE_JOINTS),
        "stats": stats,
        "warnings": [str(w) for w in warnings],
    }


_CORE = r"""
var JM = (function () {
  "use strict";
  function decode(b64, shape) {
    if (b64 === null || b64 === undefined) return null;
    var bin = (typeof atob === "function") ? atob(b64) : Buffer.from(b64, "base64").toString("binary");
    var buf = new ArrayBuffer(bin.length), u8 = new Uint8Array(buf);
    for (var i = 0; i < bin.length; i++) u8[i] = bin.charCodeAt(i);
    return new Float32Array(buf);
  }
  function load(clip) {
    var c = Object.assign({}, clip);
    c.seg = decode(clip.segments); c.site = decode(clip.sites);
    c.f = decode(clip.grf); c.con = decode(clip.contact); c.tq = decode(clip.torque);
    // the scene's centre and size: the mean and spread of the sites and segment ends
    var n = c.site.length / 3, cx = 0, cy = 0;
    for (var i = 0; i < n; i++) { cx += c.site[3 * i]; cy += c.site[3 * i + 1]; }
    c.center = [cx / n, cy / n, 0.9];
    var r = 0;
    for (i = 0; i < n; i++) r = Math.max(r, Math.hypot(c.site[3 * i] - c.center[0], c.site[3 * i + 1] - c.center[1]));
    c.extent = r;
    return c;
  }
  function camera(c) {  // orbit camera: yaw/pitch (rad) about the character, distance (m)
    return { yaw: -2.2, pitch: 0.25, dist: 4.0, target: c.center.slice(), focal: 1.2 };
  }
  // the camera of frame t: the orbit camera's target follows the character (its contact sites'
  // mean, 0.9 m up)
  function view(cam, c, t) {
    var x = 0, y = 0;
    for (var k = 0; k < 4; k++) { x += c.site[(t * 4 + k) * 3] / 4; y += c.site[(t * 4 + k) * 3 + 1] / 4; }
    return { yaw: cam.yaw, pitch: cam.pitch, dist: cam.dist, focal: cam.focal, target: [x, y, 0.9] };
  }
  // world (z up) -> [x_px, y_px, depth]; depth <= 0: behind the camera
  function project(cam, p, W, H) {
    var cy = Math.cos(cam.yaw), sy = Math.sin(cam.yaw), cp = Math.cos(cam.pitch), sp = Math.sin(cam.pitch);
    var eye = [cam.target[0] + cam.dist * cp * cy, cam.target[1] + cam.dist * cp * sy, cam.target[2] + cam.dist * sp];
    var f = [cam.target[0] - eye[0], cam.target[1] - eye[1], cam.target[2] - eye[2]];
    var fl = Math.hypot(f[0], f[1], f[2]); f = [f[0] / fl, f[1] / fl, f[2] / fl];
    var r = [f[1], -f[0], 0]; var rl = Math.hypot(r[0], r[1]); r = [r[0] / rl, r[1] / rl, 0];
    var u = [r[1] * f[2] - r[2] * f[1], r[2] * f[0] - r[0] * f[2], r[0] * f[1] - r[1] * f[0]];
    var d = [p[0] - eye[0], p[1] - eye[1], p[2] - eye[2]];
    var z = d[0] * f[0] + d[1] * f[1] + d[2] * f[2];
    var s = cam.focal * Math.min(W, H) / Math.max(z, 1e-6);
    return [W / 2 + s * (d[0] * r[0] + d[1] * r[1] + d[2] * r[2]), H / 2 - s * (d[0] * u[0] + d[1] * u[1] + d[2] * u[2]), z];
  }
  function pt(a, k) { return [a[k], a[k + 1], a[k + 2]]; }
  function drawFrame(ctx, c, t, orbit, W, H) {
    var cam = view(orbit, c, t);
    ctx.fillStyle = "#f4f4f2"; ctx.fillRect(0, 0, W, H);
    // floor grid, 0.5 m, around the character
    ctx.strokeStyle = "#cfcfca"; ctx.lineWidth = 1;
    var g0x = Math.round(cam.target[0]) - 4, g0y = Math.round(cam.target[1]) - 4;
    for (var i = 0; i <= 16; i++) {
      var a = project(cam, [g0x + i * 0.5, g0y, 0], W, H), b = project(cam, [g0x + i * 0.5, g0y + 8, 0], W, H);
      if (a[2] > 0 && b[2] > 0) { ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke(); }
      a = project(cam, [g0x, g0y + i * 0.5, 0], W, H); b = project(cam, [g0x + 8, g0y + i * 0.5, 0], W, H);
      if (a[2] > 0 && b[2] > 0) { ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke(); }
    }
    // the body: segments as round-capped thick lines, far to near
    var S = c.S, base = t * S * 6, order = [], proj = [];
    for (var s = 0; s < S; s++) {
      var p = project(cam, pt(c.seg, base + 6 * s), W, H), q = project(cam, pt(c.seg, base + 6 * s + 3), W, H);
      proj.push([p, q]); order.push(s);
    }
    order.sort(function (x, y) { return (proj[y][0][2] + proj[y][1][2]) - (proj[x][0][2] + proj[x][1][2]); });
    ctx.lineCap = "round";
    order.forEach(function (s) {
      var p = proj[s][0], q = proj[s][1];
      if (p[2] <= 0 || q[2] <= 0) return;
      var scale = cam.focal * Math.min(W, H) / ((p[2] + q[2]) / 2);
      ctx.strokeStyle = "#4a4f5c"; ctx.lineWidth = Math.max(2 * c.radius[s] * scale, 1.5) + 2;
      ctx.beginPath(); ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0] + 0.01, q[1]); ctx.stroke();
      ctx.strokeStyle = "#c9a27e"; ctx.lineWidth = Math.max(2 * c.radius[s] * scale, 1.5);
      ctx.beginPath(); ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0] + 0.01, q[1]); ctx.stroke();
    });
    // contact sites and force arrows (1 body weight = 1 m)
    for (var k = 0; k < 4; k++) {
      var o = pt(c.site, (t * 4 + k) * 3), po = project(cam, o, W, H);
      if (po[2] <= 0) continue;
      var on = c.con ? c.con[t * 4 + k] > 0.5 : false;
      ctx.fillStyle = on ? (k < 2 ? "#1f77b4" : "#d62728") : "#ffffff";
      ctx.strokeStyle = k < 2 ? "#1f77b4" : "#d62728"; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.arc(po[0], po[1], 5, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
      if (c.f) {
        var fk = pt(c.f, (t * 4 + k) * 3), w = c.weight;
        var e = project(cam, [o[0] + fk[0] / w, o[1] + fk[1] / w, o[2] + fk[2] / w], W, H);
        if (e[2] > 0 && Math.hypot(e[0] - po[0], e[1] - po[1]) > 2) {
          ctx.beginPath(); ctx.moveTo(po[0], po[1]); ctx.lineTo(e[0], e[1]); ctx.stroke();
          var ang = Math.atan2(e[1] - po[1], e[0] - po[0]);
          ctx.beginPath(); ctx.moveTo(e[0], e[1]);
          ctx.lineTo(e[0] - 9 * Math.cos(ang - 0.4), e[1] - 9 * Math.sin(ang - 0.4));
          ctx.lineTo(e[0] - 9 * Math.cos(ang + 0.4), e[1] - 9 * Math.sin(ang + 0.4));
          ctx.closePath(); ctx.fillStyle = ctx.strokeStyle; ctx.fill();
        }
      }
    }
    ctx.fillStyle = "#333"; ctx.font = "13px sans-serif";
    ctx.fillText(c.name + "  (" + c.method + ")   frame " + t + " / " + (c.T - 1) + "   " + (t / c.fps).toFixed(2) + " s", 10, 18);
  }
  // a time-series plot: series = [[label, colour, values(T)]], cursor at frame t
  function plot(ctx, x0, y0, W, H, title, unit, series, t, T) {
    ctx.fillStyle = "#fff"; ctx.fillRect(x0, y0, W, H);
    ctx.strokeStyle = "#999"; ctx.strokeRect(x0, y0, W, H);
    var lo = 0, hi = 0;
    series.forEach(function (s) { for (var i = 0; i < T; i++) { lo = Math.min(lo, s[2][i]); hi = Math.max(hi, s[2][i]); } });
    if (hi - lo < 1e-9) hi = lo + 1;
    var X = function (i) { return x0 + 40 + (W - 50) * i / Math.max(T - 1, 1); };
    var Y = function (v) { return y0 + H - 18 - (H - 36) * (v - lo) / (hi - lo); };
    ctx.fillStyle = "#333"; ctx.font = "12px sans-serif";
    ctx.fillText(title + " (" + unit + ")", x0 + 40, y0 + 13);
    ctx.fillText(hi.toFixed(0), x0 + 2, Y(hi) + 4); ctx.fillText(lo.toFixed(0), x0 + 2, Y(lo) + 4);
    series.forEach(function (s, j) {
      ctx.strokeStyle = s[1]; ctx.lineWidth = 1.5; ctx.beginPath();
      for (var i = 0; i < T; i++) { if (i) ctx.lineTo(X(i), Y(s[2][i])); else ctx.moveTo(X(i), Y(s[2][i])); }
      ctx.stroke(); ctx.fillStyle = s[1]; ctx.fillText(s[0], x0 + W - 140 + 70 * (j % 2), y0 + 13 + 12 * Math.floor(j / 2));
    });
    ctx.strokeStyle = "#000"; ctx.beginPath(); ctx.moveTo(X(t), y0 + 2); ctx.lineTo(X(t), y0 + H - 2); ctx.stroke();
  }
  function footForce(c) {  // per-foot vertical GRF, % body weight
    var L = new Float32Array(c.T), R = new Float32Array(c.T);
    for (var t = 0; t < c.T; t++) {
      L[t] = 100 * (c.f[t * 12 + 2] + c.f[t * 12 + 5]) / c.weight;
      R[t] = 100 * (c.f[t * 12 + 8] + c.f[t * 12 + 11]) / c.weight;
    }
    return [L, R];
  }
  function torqueSeries(c, j) {
    var out = new Float32Array(c.T);
    for (var t = 0; t < c.T; t++) out[t] = c.tq[t * c.torque_names.length + j];
    return out;
  }
  return { decode: decode, load: load, camera: camera, view: view, project: project, drawFrame: drawFrame, plot: plot,
           footForce: footForce, torqueSeries: torqueSeries };
})();
if (typeof module !== "undefined") module.exports = JM;
"""

_UI = r"""
(function () {
  "use strict";
  var clips = JSON.parse(document.getElementById("jmocap-data").textContent);
  var view = document.getElementById("view"), plots = document.getElementById("plots");
  var slider = document.getElementById("time"), play = document.getElementById("play");
  var cur = null, cam = null, t = 0, playing = false, last = 0, acc = 0;
  function draw() {
    if (!cur) return;
    JM.drawFrame(view.getContext("2d"), cur, t, cam, view.width, view.height);
    var p = plots.getContext("2d"), W = plots.width, H = plots.height / 2;
    p.clearRect(0, 0, plots.width, plots.height);
    if (cur.f) {
      var ff = JM.footForce(cur);
      JM.plot(p, 0, 0, W, H - 4, "vertical GRF per foot", "% body weight",
              [["left", "#1f77b4", ff[0]], ["right", "#d62728", ff[1]]], t, cur.T);
    } else {
      p.fillStyle = "#333"; p.font = "14px sans-serif";
      p.fillText("No forces: the method '" + cur.method + "' does not estimate them.", 10, 30);
    }
    if (cur.tq) {
      var cols = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"];
      JM.plot(p, 0, H, W, H - 4, "joint torques", "N m / kg",
              cur.torque_names.map(function (n, j) { return [n.replace("_y", ""), cols[j], JM.torqueSeries(cur, j)]; }), t, cur.T);
    }
    slider.value = t;
    document.getElementById("clock").textContent = (t / cur.fps).toFixed(2) + " s";
  }
  function open(i) {
    cur = JM.load(clips[i]); cam = JM.camera(cur); t = 0;
    slider.max = cur.T - 1;
    document.querySelectorAll("#clips tbody tr").forEach(function (r, j) { r.className = j === i ? "sel" : ""; });
    draw();
  }
  function tick(now) {
    if (playing && cur) {
      acc += Math.min(now - last, 100) / 1000; last = now;
      var step = Math.floor(acc * cur.fps);
      if (step > 0) { acc -= step / cur.fps; t = (t + step) % cur.T; draw(); }
    } else { last = now; }
    requestAnimationFrame(tick);
  }
  slider.addEventListener("input", function () { t = parseInt(slider.value, 10); draw(); });
  play.addEventListener("click", function () { playing = !playing; play.textContent = playing ? "pause" : "play"; });
  document.addEventListener("keydown", function (e) { if (e.code === "Space") { e.preventDefault(); play.click(); } });
  var drag = null;
  view.addEventListener("mousedown", function (e) { drag = [e.clientX, e.clientY]; });
  window.addEventListener("mouseup", function () { drag = null; });
  window.addEventListener("mousemove", function (e) {
    if (!drag || !cam) return;
    cam.yaw -= (e.clientX - drag[0]) * 0.01;
    cam.pitch = Math.max(-0.1, Math.min(1.4, cam.pitch + (e.clientY - drag[1]) * 0.01));
    drag = [e.clientX, e.clientY]; draw();
  });
  view.addEventListener("wheel", function (e) { e.preventDefault(); if (cam) { cam.dist *= Math.exp(e.deltaY * 0.001); draw(); } });
  var body = document.querySelector("#clips tbody");
  clips.forEach(function (c, i) {
    var tr = document.createElement("tr"), s = c.stats;
    [c.name, c.method, s.frames, s.seconds, s.residual_root_force_pct_bw, s.peak_vertical_grf_pct_bw,
     s.certified_pct, c.warnings.length ? c.warnings.join("; ") : ""].forEach(function (v) {
      var td = document.createElement("td"); td.textContent = (v === undefined || v === null) ? "-" : v; tr.appendChild(td);
    });
    tr.addEventListener("click", function () { open(i); });
    body.appendChild(tr);
  });
  if (clips.length) open(0);
  requestAnimationFrame(tick);
})();
"""

_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>{title}</title>
<style>
body {{ font-family: sans-serif; margin: 12px; color: #222; }}
#main {{ display: flex; gap: 16px; align-items: flex-start; flex-wrap: wrap; }}
canvas {{ border: 1px solid #bbb; display: block; }}
#clips {{ border-collapse: collapse; font-size: 12px; }}
#clips td, #clips th {{ border: 1px solid #ddd; padding: 2px 6px; text-align: right; }}
#clips td:first-child, #clips td:nth-child(2), #clips td:last-child {{ text-align: left; }}
#clips tbody tr {{ cursor: pointer; }} #clips tr.sel {{ background: #dde8f5; }}
#bar {{ display: flex; gap: 8px; align-items: center; margin: 6px 0; }} #time {{ flex: 1; }}
</style></head><body>
<h3>{title}</h3>
<div id="main"><div>
<canvas id="view" width="720" height="480"></canvas>
<div id="bar"><button id="play">play</button><input id="time" type="range" min="0" max="0" value="0"><span id="clock"></span></div>
<canvas id="plots" width="720" height="300"></canvas>
<p style="font-size:12px">Drag to orbit, wheel to zoom, space to play. Arrows: ground reaction force per contact
site, 1 body weight = 1 m. Filled circles: contact probability &gt; 0.5. Made by jmocap {version}.</p>
</div><div><table id="clips"><thead><tr><th>clip</th><th>method</th><th>frames</th><th>s</th>
<th>residual %BW</th><th>peak GRF %BW</th><th>certified %</th><th>warnings</th></tr></thead><tbody></tbody></table></div></div>
<script type="application/json" id="jmocap-data">{data}</script>
<script id="jmocap-core">{core}</script>
<script id="jmocap-ui">{ui}</script>
</body></html>
"""


def viewer_html(payloads: Sequence[dict[str, Any]], *, title: str = "jmocap results") -> str:
    """The page for clip payloads (:func:`clip_payload`), as one HTML string."""
    import jmocap

    data = json.dumps(list(payloads), separators=(",", ":")).replace("</", "<\\/")
    return _PAGE.format(title=html.escape(title), data=data, core=_CORE, ui=_UI,
                        version=html.escape(str(getattr(jmocap, "__version__", ""))))


def _result_files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    if path.is_dir():
        return sorted(p for p in path.glob("*.npz") if p.is_file())
    raise FileNotFoundError(f"viewer: no result file or folder at {path}")


def write_viewer(results: str | os.PathLike | Sequence[str | os.PathLike], out: str | os.PathLike, *,
                 max_clips: int = 100, title: str | None = None) -> tuple[Path, list[str]]:
    """Write the viewer page ``out`` for result files (a file, a results folder, or a list of
    files), at most ``max_clips`` of them (the page holds every frame's geometry: ~200 kB per
    300-frame clip). Files that are not readable results are skipped and returned as
    ``"file: reason"`` lines. Returns (the page's path, skipped)."""
    from jmocap.data.clip import FormatError
    from jmocap.results import load_result

    if isinstance(results, (str, os.PathLike)):
        files = _result_files(Path(results))
        default_title = f"jmocap: {Path(results).name}"
    else:
        files = [Path(p) for p in results]
        default_title = "jmocap results"
    if max_clips < 1:
        raise ValueError(f"viewer: max_clips must be >= 1, got {max_clips}")
    payloads, skipped = [], []
    for f in files:
        if len(payloads) >= max_clips:
            skipped.append(f"{f}: beyond --max-clips {max_clips}")
            continue
        try:
            r = load_result(f)
            payloads.append(clip_payload(r, name=r.get("name") or f.stem))
        except (FormatError, ValueError, FileNotFoundError) as e:
            skipped.append(f"{f}: {e}")
    if not payloads:
        raise ValueError("viewer: no readable result among " + (", ".join(str(f) for f in files[:5]) or "no files")
                         + (f" ({skipped[0]})" if skipped else ""))
    out = Path(out)
    atomic_write(out, viewer_html(payloads, title=title or default_title).encode("utf-8"))
    return out, skipped
