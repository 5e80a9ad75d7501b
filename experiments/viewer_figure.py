"""docs/figures/viewer.svg: the viewer page's canvases drawn by the page's own script.

    .venv/bin/jmocap demo                                 # writes demo_out/viewer.html
    .venv/bin/python experiments/viewer_figure.py demo_out/viewer.html --frame 40

Runs the page's drawing core (``jmocap-core``) under Node.js with a 2D context that records
its calls as SVG (paths, rectangles, arcs, text), for the 3D view and the plots of the first
clip at one frame: the figure is what the page draws, without a browser (none is installed on
the machines this was made on).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
from pathlib import Path

SHIM = r"""
const fs = require("fs");
const html = fs.readFileSync(process.argv[2], "utf8");
const frame = parseInt(process.argv[3], 10);
const grab = (id) => html.split(`id="${id}">`)[1].split("</script>")[0];
const JM = new Function("module", grab("jmocap-core") + "; return JM;")(undefined);
const clips = JSON.parse(grab("jmocap-data"));
const esc = (s) => String(s).replace(/&/g, "&amp;").replace(/</g, "&lt;");
function svgContext(out, dy) {
  let d = "";
  const c = { strokeStyle: "#000", fillStyle: "#000", lineWidth: 1, lineCap: "butt", font: "12px sans-serif" };
  const f = (v) => v.toFixed(1);
  Object.assign(c, {
    beginPath() { d = ""; },
    moveTo(x, y) { d += `M${f(x)} ${f(y + dy)}`; },
    lineTo(x, y) { d += `L${f(x)} ${f(y + dy)}`; },
    closePath() { d += "Z"; },
    arc(x, y, r) { d += `M${f(x + r)} ${f(y + dy)}A${r} ${r} 0 1 0 ${f(x - r)} ${f(y + dy)}A${r} ${r} 0 1 0 ${f(x + r)} ${f(y + dy)}`; },
    stroke() { out.push(`<path d="${d}" fill="none" stroke="${c.strokeStyle}" stroke-width="${c.lineWidth}" stroke-linecap="${c.lineCap}"/>`); },
    fill() { out.push(`<path d="${d}" fill="${c.fillStyle}"/>`); },
    fillRect(x, y, w, h) { out.push(`<rect x="${x}" y="${y + dy}" width="${w}" height="${h}" fill="${c.fillStyle}"/>`); },
    strokeRect(x, y, w, h) { out.push(`<rect x="${x}" y="${y + dy}" width="${w}" height="${h}" fill="none" stroke="${c.strokeStyle}"/>`); },
    clearRect(x, y, w, h) { out.push(`<rect x="${x}" y="${y + dy}" width="${w}" height="${h}" fill="#fff"/>`); },
    fillText(t, x, y) { out.push(`<text x="${x}" y="${y + dy}" fill="${c.fillStyle}" font-family="sans-serif" font-size="${parseInt(c.font)}">${esc(t)}</text>`); },
  });
  return c;
}
const out = [];
const c = JM.load(clips[0]); const cam = JM.camera(c); const t = Math.min(frame, c.T - 1);
out.push('<clipPath id="v"><rect width="720" height="480"/></clipPath><g clip-path="url(#v)">');
JM.drawFrame(svgContext(out, 0), c, t, cam, 720, 480);
out.push("</g>");
const p = svgContext(out, 490);
if (c.f) JM.plot(p, 0, 0, 720, 146, "vertical GRF per foot", "% body weight",
                 [["left", "#1f77b4", JM.footForce(c)[0]], ["right", "#d62728", JM.footForce(c)[1]]], t, c.T);
const cols = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"];
if (c.tq) JM.plot(p, 0, 150, 720, 146, "joint torques", "N m / kg",
                  c.torque_names.map((n, j) => [n.replace("_y", ""), cols[j], JM.torqueSeries(c, j)]), t, c.T);
console.log(`<svg xmlns="http://www.w3.org/2000/svg" width="720" height="790" viewBox="0 0 720 790">` + out.join("") + "</svg>");
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("page", help="a viewer page (jmocap view / jmocap demo)")
    ap.add_argument("--frame", type=int, default=40)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs/figures/viewer.svg"))
    args = ap.parse_args()
    if shutil.which("node") is None:
        raise SystemExit("viewer_figure: needs Node.js (node) on PATH")
    with tempfile.TemporaryDirectory() as tmp:
        js = Path(tmp) / "shim.js"
        js.write_text(SHIM)
        svg = subprocess.run(["node", str(js), args.page, str(args.frame)], capture_output=True, text=True,
                             check=True).stdout
    Path(args.out).write_text(svg)
    print(f"wrote {args.out} ({len(svg) // 1024} kB)")


if __name__ == "__main__":
    main()
