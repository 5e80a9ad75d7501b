#!/usr/bin/env bash
# Wheel smoke test: the package installs and runs without the source tree.
#
# 1. builds a wheel from a copy of the tree (the files git tracks or would track, as in a clean
#    clone) and fails on any setuptools warning in the build log;
# 2. checks that the wheel ships the character (MJCF), the default, contact and IMU weights and the demo sample;
# 3. installs it, NOT editable and with its core dependencies only, into a fresh venv;
# 4. from a directory outside the source tree: `import jmocap; jmocap.load_model()`,
#    `python -m jmocap --help`, and `jmocap demo` (results, BVH, OpenSim, GLB, the viewer page,
#    metrics; the video is skipped
#    with a message, as the core install has no viz extra), then checks the demo's files.
#
# Usage: .ci/wheel_smoke.sh   (PYTHON=python3.11 to choose the interpreter; KEEP=1 keeps the
# work folder). Called by .ci/run after `make test`; `make wheel-smoke` runs it alone.
set -euo pipefail
cd "$(dirname "$0")/.."
SRC=$(pwd)
PYTHON=${PYTHON:-python3}
WORK=$(mktemp -d "${TMPDIR:-/tmp}/jmocap-wheel-smoke.XXXXXX")
if [ "${KEEP:-0}" = 1 ]; then echo "wheel-smoke: work folder $WORK (kept)"; else trap 'rm -rf "$WORK"' EXIT; fi
t0=$(date +%s)
step() { echo "wheel-smoke [$(( $(date +%s) - t0 )) s]: $*"; }

# --- 1. build ---------------------------------------------------------------------------------
step "copying the tree (git-tracked and untracked-but-not-ignored files)"
mkdir "$WORK/src"
git ls-files -z --cached --others --exclude-standard \
  | while IFS= read -r -d '' f; do [ -e "$f" ] && printf '%s\0' "$f"; done \
  | tar --null -T - -cf - | tar -xf - -C "$WORK/src"
step "building the wheel (isolated build environment)"
if ! "$PYTHON" -m pip wheel --no-deps --verbose --wheel-dir "$WORK/dist" "$WORK/src" >"$WORK/build.log" 2>&1; then
  cat "$WORK/build.log"; echo "wheel-smoke: FAILED: the wheel did not build"; exit 1
fi
# (distutils' "byte-compiling is disabled" notes come from PYTHONDONTWRITEBYTECODE, not the project)
if grep -nE "SetuptoolsDeprecationWarning|SetuptoolsWarning|_DeprecatedInstaller|[Ww]arning: " "$WORK/build.log" \
    | grep -v "byte-compiling is disabled"; then
  echo "wheel-smoke: FAILED: the build printed the warnings above"; exit 1
fi
WHEEL=$(ls "$WORK"/dist/jmocap-*.whl)
step "built $(basename "$WHEEL")"

# --- 2. wheel contents ----------------------------------------------------------------------
"$PYTHON" - "$WHEEL" <<'EOF'
import sys, zipfile
names = set(zipfile.ZipFile(sys.argv[1]).namelist())
need = ["jmocap/__main__.py", "jmocap/assets/mjcf/humanoid.xml", "jmocap/assets/default_params.msgpack",
        "jmocap/assets/default_train_config.json", "jmocap/assets/contact_mlp.msgpack", "jmocap/assets/support_tcn.msgpack",
        "jmocap/assets/imu_kinematics.msgpack", "jmocap/assets/imu_kinematics.json"]
missing = [n for n in need if n not in names]
demo = [n for n in names if n.startswith("jmocap/assets/demo/")]
gt = [n for n in demo if n.startswith("jmocap/assets/demo/ground_truth/") and n.endswith(".npz")]
inp = [n for n in demo if n.startswith("jmocap/assets/demo/input/")]
if missing or not gt or not inp:
    sys.exit(f"wheel-smoke: FAILED: the wheel lacks {missing or ''} {'' if gt else 'demo ground truth'} "
             f"{'' if inp else 'demo input'}")
print(f"wheel-smoke: the wheel ships the MJCF, the default weights and the demo sample "
      f"({len(gt)} clips, {len(demo)} files)")
EOF

# --- 3. install into a fresh venv -------------------------------------------------------------
step "installing the wheel (not editable) into a fresh venv"
"$PYTHON" -m venv "$WORK/venv"
VPY="$WORK/venv/bin/python"
"$VPY" -m pip install --quiet "$WHEEL"

# --- 4. run it outside the source tree ----------------------------------------------------------
mkdir "$WORK/run"
cd "$WORK/run"
step "import jmocap; jmocap.load_model()"
"$VPY" - "$SRC" <<'EOF'
import importlib.util, sys
from pathlib import Path

import jmocap

src = Path(sys.argv[1]).resolve()
where = Path(jmocap.__file__).resolve()
if src in where.parents:
    sys.exit(f"wheel-smoke: FAILED: jmocap imported from the source tree ({where})")
m = jmocap.load_model()
if m.mjx is not None:
    sys.exit("wheel-smoke: FAILED: load_model() built the MJX model without being asked")
lean = [p for p in ("matplotlib", "imageio", "imageio_ffmpeg", "clarabel", "qpax", "pytest")
        if importlib.util.find_spec(p) is not None]
if lean:
    sys.exit(f"wheel-smoke: FAILED: the core install pulled in {lean} (extras only)")
models = [where.parent / "assets" / "blazepose" / f for f in ("pose_detection.tflite", "pose_landmark_full.tflite")]
if not all(p.is_file() and p.stat().st_size > 1_000_000 for p in models):
    sys.exit(f"wheel-smoke: FAILED: the wheel lacks the vendored BlazePose models of `jmocap video`: {models}")
if importlib.util.find_spec("ai_edge_litert") is not None:
    sys.exit("wheel-smoke: FAILED: the core install pulled in ai-edge-litert (the video extra only)")
print(f"wheel-smoke: jmocap {jmocap.__version__} from {where.parent}; humanoid nq={m.nq} nv={m.nv}, "
      f"{m.total_mass:.1f} kg; core install without viz/test/bench packages")
EOF
"$VPY" -m jmocap --help >/dev/null
step "jmocap demo --out $WORK/demo"
"$WORK/venv/bin/jmocap" demo --out "$WORK/demo" --quiet --cache-dir "$WORK/xla" 2>&1 | tee "$WORK/demo.log"
grep -q "pip install 'jmocap\[viz\]'" "$WORK/demo.log" \
  || { echo "wheel-smoke: FAILED: the demo did not say that the video needs the viz extra"; exit 1; }
"$VPY" - "$WORK/demo" <<'EOF'
import json, sys
from pathlib import Path

out = Path(sys.argv[1])
npz = sorted((out / "results").glob("*.npz"))
bvh = sorted((out / "results").glob("*.bvh"))
rows = json.loads((out / "metrics.json").read_text())
glb = sorted((out / "export").glob("*.glb"))
osim = sorted((out / "export").glob("*.osim"))
if len(npz) < 3 or len(bvh) < 3 or set(rows) != {p.stem for p in npz} or not (out / "metrics.md").is_file():
    sys.exit(f"wheel-smoke: FAILED: demo outputs incomplete: {npz}, {bvh}, metrics for {sorted(rows)}")
if len(glb) < 3 or len(osim) < 3 or not (out / "viewer.html").is_file():
    sys.exit(f"wheel-smoke: FAILED: demo exports incomplete: {glb}, {osim}, viewer.html")
print(f"wheel-smoke: demo wrote {len(npz)} results, {len(bvh)} BVH files, {len(glb)} GLB, {len(osim)} OpenSim "
      f"models, viewer.html, metrics for {sorted(rows)}")
EOF
step "OK"
