"""PIP on six IMUs (``jmocap.methods.pip_imu``) on a held-out synthetic IMU archive, with the
paper's ablations.

    .venv/bin/jmocap data synth --imu --physics --controller sampling --out data/imu_test_phys --clips 32 --seed 3
    .venv/bin/python experiments/eval_imu.py [--archive data/imu_test_phys] [--params P] [--no-docs]

Rows (each clip from its known first pose, as PIP's evaluation, unless said):

* ``kinematics``: the kinematics module alone (root translated by the integrated velocity);
* ``pip``: + the dual PD controller and the motion-tracking QP (the method);
* ``pip, single PD``: rotations-only PD (the paper's ablation, Tab. 2);
* ``pip, zero initial state``: every network from zero (the paper's ablation, Tab. 2);
* ``ground truth``: the archive's own motion and forces (what the metrics give on it).

The rows and metrics are :mod:`jmocap.evaluate_imu`'s (``jmocap eval IMU_ARCHIVE`` runs the same);
this script adds ``--set`` (physics config changes) and the docs section. Metrics
(``jmocap.metrics``, means over clips): SIP error and angular error (global, deg), the
positional error (root-aligned, on the character's body origins, mm), the mesh-error stand-in
(root position and orientation aligned, mm), jitter (km/s^3), the mean translation error (m,
PIP Fig. 3's curve averaged over 1-7 m), and the physical rows as for video input: residual
root force, net GRF error against the simulated ground truth and ballistic GRF (% BW), foot
skate and non-penetration (%), contact F1 (%). Prints the table and writes it into
docs/evaluation.md between ``<!-- imu:begin -->`` and ``<!-- imu:end -->`` (unless
``--no-docs``).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from jmocap.evaluate_imu import ROWS, run, table

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- imu:begin -->", "<!-- imu:end -->"


def write_docs(text: str, doc: Path) -> None:
    s = doc.read_text()
    block = f"{BEGIN}\n{text}\n{END}"
    if BEGIN in s and END in s:
        s = s[: s.index(BEGIN)] + block + s[s.index(END) + len(END):]
    else:
        s = s.rstrip("\n") + "\n\n" + block + "\n"
    doc.write_text(s)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default=str(ROOT / "data/imu_test_phys"))
    ap.add_argument("--params", help="kinematics-module weights (default: the shipped ones)")
    ap.add_argument("--max-clips", type=int)
    ap.add_argument("--doc", default=str(ROOT / "docs/evaluation.md"))
    ap.add_argument("--no-docs", action="store_true")
    ap.add_argument("--rows", nargs="+", choices=ROWS, default=list(ROWS), help="rows to run (default: all)")
    ap.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE",
                    help="physics config fields (jmocap.methods.pip.PIPConfig's), e.g. kp_anchor=50 smoothing_radius=6")
    args = ap.parse_args(argv)
    # the experiments' one "name=value" parser (this script's folder is on sys.path)
    from ablate_pip import parse_set
    from jmocap.methods.pip import PIPConfig

    changes = parse_set(args.set, PIPConfig())
    command = "python experiments/eval_imu.py" + "".join(
        " " + shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    t0 = time.time()
    means, _, names, frames = run(args.archive, args.params, args.max_clips, changes, tuple(args.rows))
    clips = len(names)
    shown = Path(args.archive).resolve()
    shown = shown.relative_to(ROOT) if shown.is_relative_to(ROOT) else shown
    text = (f"- Archive: `{shown}` ({clips} clips, {frames} frames); command: `{command}` "
            f"({(time.time() - t0) / 60:.1f} min on this 2-core CPU).\n\n" + table(means, tuple(args.rows)))
    print(text)
    if not args.no_docs:
        write_docs(text, Path(args.doc))
        print(f"wrote {args.doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
