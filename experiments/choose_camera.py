"""Which energy tells a still camera from a moving one: the measurement behind
``dnd_trajopt``'s choice between D&D's camera track and a still camera.

Reads two ``jmocap eval`` runs per archive, one per camera hypothesis: ``dnd_trajopt_estimated``
(trajopt under D&D's track) and ``trajopt --camera static`` (under the first frame's camera).
For every candidate criterion (trajopt's final energy, or one of its weighted terms) and margin
``m`` (the estimated track is taken when its criterion is below ``m`` times the still camera's),
prints the mean world root error of the chosen fits on moving and on still cameras and how many
clips of each kind chose the estimate. Recipe (docs/evaluation.md, "Offline D&D"):

    jmocap data synth --out data/val_moving --clips 40 --seed 77 --moving-camera handheld,pan,dolly,orbit,static
    jmocap data synth --out data/val_still --clips 20 --seed 78
    jmocap eval data/val_moving --methods dnd_trajopt_estimated --out out/val_moving_dte
    jmocap eval data/val_moving --methods trajopt --camera static --out out/val_moving_static
    jmocap eval data/val_still --methods dnd_trajopt_estimated --out out/val_still_dte
    jmocap eval data/val_still --methods trajopt --out out/val_still_static
    python experiments/choose_camera.py data/val_moving out/val_moving_dte out/val_moving_static \\
        data/val_still out/val_still_dte out/val_still_static
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from jmocap.methods import get_method
from jmocap.methods.trajopt import _weight

TERMS = ("reproj", "pose", "limits", "accel", "contact_height", "contact_still", "floor", "dynamics", "stay",
         "wrench_rate", "com_accel")
CRITERIA = {"total energy": ("total",), "kinematic stage's energy": ("kinematic",),
            **{t: (t,) for t in TERMS}, "contacts (still + height)": ("contact_still", "contact_height"),
            "physics (dynamics, wrench rate, CoM)": ("dynamics", "wrench_rate", "com_accel"),
            "reproj + dynamics": ("reproj", "dynamics"), "reproj + contacts still": ("reproj", "contact_still"),
            "reproj + stay": ("reproj", "stay")}


def per_clip(run: str) -> dict:
    d = json.loads((Path(run) / "metrics.json").read_text())["per_clip"]
    return d[next(iter(d))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", help="triples: ARCHIVE ESTIMATED_RUN STILL_RUN")
    args = ap.parse_args()
    if len(args.runs) % 3:
        ap.error("give triples ARCHIVE ESTIMATED_RUN STILL_RUN")
    config = get_method("trajopt").make_config()
    rows = []
    for archive, est, still in zip(*[iter(args.runs)] * 3, strict=True):
        kinds = {}
        for line in (Path(archive) / "manifest.jsonl").read_text().splitlines():
            r = json.loads(line)
            kinds[r["name"]] = r.get("camera") or "static"
        a, b = per_clip(est), per_clip(still)
        rows += [(kinds[k], a[k], b[k]) for k in a if k in b]

    def value(m: dict, term: str) -> float:
        if term == "total":
            return m["diag_objective_final"]
        if term == "kinematic":
            return m["diag_objective_kinematic"]
        return float(_weight(config, term)) * (m.get(f"diag_term_{term}") or 0.0)

    still = np.array([k == "static" for k, _, _ in rows])
    ra = np.array([a["root_err_mm"] for _, a, _ in rows])
    rb = np.array([b["root_err_mm"] for _, _, b in rows])
    print(f"{(~still).sum()} clips with moving cameras, {still.sum()} with still ones; world root error (mm)")
    print(f"always the estimate: moving {ra[~still].mean():.0f}, still {ra[still].mean():.0f}; "
          f"always still: moving {rb[~still].mean():.0f}, still {rb[still].mean():.0f}; "
          f"the better of the two per clip (oracle): moving {np.minimum(ra, rb)[~still].mean():.0f}")
    print("\n| criterion | margin | root err, moving | root err, still | still cameras given the estimate "
          "| moving cameras given the estimate |\n|---|---:|---:|---:|---:|---:|")
    for name, terms in CRITERIA.items():
        ea = np.array([sum(value(a, t) for t in terms) for _, a, _ in rows])
        eb = np.array([sum(value(b, t) for t in terms) for _, _, b in rows])
        for margin in (1.0, 0.8, 0.6):
            take = ea < margin * eb
            pick = np.where(take, ra, rb)
            print(f"| {name} | {margin:.1f} | {pick[~still].mean():.0f} | {pick[still].mean():.0f} | "
                  f"{take[still].sum()} / {still.sum()} | {take[~still].sum()} / {(~still).sum()} |")


if __name__ == "__main__":
    main()
