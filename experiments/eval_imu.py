"""PIP on six IMUs (``jmocap.methods.pip_imu``) on a held-out synthetic IMU archive, with the
paper's ablations.

    .venv/bin/jmocap data synth --imu --physics --out data/imu_test_phys --clips 32 --seed 3
    .venv/bin/python experiments/eval_imu.py [--archive data/imu_test_phys] [--params P] [--no-docs]

Rows (each clip from its known first pose, as PIP's evaluation, unless said):

* ``kinematics``: the kinematics module alone (root translated by the integrated velocity);
* ``pip``: + the dual PD controller and the motion-tracking QP (the method);
* ``pip, single PD``: rotations-only PD (the paper's ablation, Tab. 2);
* ``pip, zero initial state``: every network from zero (the paper's ablation, Tab. 2);
* ``ground truth``: the archive's own motion and forces (what the metrics give on it).

Metrics (``jmocap.metrics``, means over clips): SIP error and angular error (global, deg), the
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

import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- imu:begin -->", "<!-- imu:end -->"
PAD = 320
ROWS = ("kinematics", "pip", "pip, single PD", "pip, zero initial state", "ground truth")
COLS = (  # key, header, format
    ("sip_deg", "SIP error (deg)", "{:.2f}"),
    ("ang_deg", "angular error (deg)", "{:.2f}"),
    ("mpjpe_mm", "positional error, root aligned (mm)", "{:.1f}"),
    ("mesh_mm", "root position + orientation aligned (mm)", "{:.1f}"),
    ("jitter_km_s3", "jitter (km/s^3)", "{:.3f}"),
    ("trans_m", "mean translation error (m)", "{:.3f}"),
    ("root_residual_pct_bw", "residual root force (% BW)", "{:.2f}"),
    ("grf_err_pct_bw", "net GRF error (% BW)", "{:.1f}"),
    ("grf_ballistic_pct_bw", "ballistic GRF (% BW)", "{:.1f}"),
    ("skate_pct", "foot skate (%)", "{:.2f}"),
    ("pnp_pct", "non-penetration (%)", "{:.2f}"),
    ("contact_f1_pct", "contact F1 (%)", "{:.1f}"),
)


def clip_metrics(model, q, grf, tau, prob, clip, mask) -> dict[str, float]:
    """One clip's metrics of a motion ``q`` (T, nq) (``grf``, ``tau``, ``prob`` may be None)."""
    from jmocap import metrics as M
    from jmocap import physics as P
    from jmocap.methods.pip_imu import N

    T = clip.num_frames
    q, gq = jnp.asarray(q[:T]), jnp.asarray(clip.gt_q, jnp.float32)
    bodies = tuple(N.body_indices(model)["bodies"])  # the root (pelvis) first
    kin = jax.vmap(lambda x: P.forward_kinematics(model, x))(q)
    gkin = jax.vmap(lambda x: P.forward_kinematics(model, x))(gq)
    sip = np.asarray([model.body_id(n) for n in M.SIP_BODIES])
    R, gR = kin.xmat[:, bodies[0]], gkin.xmat[:, bodies[0]]
    out = {
        "sip_deg": float(M.sip_error(kin.xmat[:, sip], gkin.xmat[:, sip])),
        "ang_deg": float(M.angular_error(kin.xmat[:, 1:], gkin.xmat[:, 1:])),
        "mesh_mm": float(M.mpjpe_root_frame(kin.xpos[:, bodies], gkin.xpos[:, bodies], R, gR)),
        "trans_m": float(M.mean_translation_error(q[:, :3], gq[:, :3])),
    }
    feet = jax.vmap(lambda x: P.site_positions(model, x, model.topo.contact_sites))(q)
    pred = {"keypoints3d": kin.xpos[:, bodies], "feet": feet,
            "grf": None if grf is None else grf[:T], "tau": None if tau is None else tau[:T],
            "contact_prob": None if prob is None else prob[:T]}
    gt = {"keypoints3d": gkin.xpos[:, bodies], "contacts": clip.gt_contacts, "grf": clip.gt_grf, "tau": clip.gt_tau}
    vals = M.evaluate_arrays(pred, gt, fps=float(clip.fps), mask=np.asarray(mask[:T]), pred_mass=clip.mass_kg,
                             gt_mass=clip.mass_kg)
    for k in ("mpjpe_mm", "jitter_km_s3", "root_residual_pct_bw", "grf_err_pct_bw", "grf_ballistic_pct_bw",
              "skate_pct", "pnp_pct", "contact_f1_pct"):
        out[k] = float(vals.get(k, np.nan))
    return out


def run(archive: str, params_path: str | None, max_clips: int | None, changes: dict | None = None,
        rows=ROWS) -> tuple[dict[str, dict[str, float]], int, int]:
    from jmocap.data.archive import Archive
    from jmocap.methods import pip_imu as PI
    from jmocap.model import character

    params, net = PI.load_params(params_path) if params_path else PI.load_params()
    base = PI.PIPIMUConfig(net=net)
    base = base.replace(pip=base.pip.replace(**(changes or {})))
    variants = {
        "kinematics": (base.replace(physics=False), False),
        "pip": (base, False),
        "pip, single PD": (PI.single_pd(base), False),
        "pip, zero initial state": (base, True),
    }
    variants = {k: v for k, v in variants.items() if k in rows}
    rec = jax.jit(PI.reconstruct)
    per: dict[str, list[dict[str, float]]] = {r: [] for r in rows}
    frames = 0
    with Archive(archive) as a:
        names = a.names()[:max_clips] if max_clips else a.names()
        for name in names:
            clip = a.load(name)
            if clip.gt_grf is None:
                raise SystemExit(f"{archive}/{name}: no ground-truth forces (make the archive with --physics)")
            model = character(clip.height_m, clip.mass_kg)
            n = int(np.ceil(clip.num_frames / PAD) * PAD)
            inputs = PI.IMUInputs.from_clip(clip, model, n)
            frames += clip.num_frames
            for row, (cfg, zero) in variants.items():
                m = rec(params, model, PI.zero_init(inputs) if zero else inputs, cfg)
                forces = cfg.physics
                per[row].append(clip_metrics(model, np.asarray(m.q), np.asarray(m.grf) if forces else None,
                                             np.asarray(m.tau) if forces else None, np.asarray(m.contact_prob),
                                             clip, np.asarray(inputs.mask)))
            if "ground truth" in rows:
                per["ground truth"].append(clip_metrics(model, clip.gt_q, clip.gt_grf, clip.gt_tau,
                                                        clip.gt_contacts.astype(np.float32), clip,
                                                        np.ones(clip.num_frames, bool)))
            if "pip" in rows:
                print(f"{name}: pip MPJPE {per['pip'][-1]['mpjpe_mm']:.1f} mm, residual "
                      f"{per['pip'][-1]['root_residual_pct_bw']:.2f} % BW", flush=True)
    means = {r: {k: float(np.nanmean([p[k] for p in ps])) for k, _, _ in COLS} for r, ps in per.items()}
    return means, len(names), frames


def table(means, rows=ROWS) -> str:
    head = "| row | " + " | ".join(h for _, h, _ in COLS) + " |"
    sep = "|---|" + "---:|" * len(COLS)
    lines = [head, sep]
    for r in rows:
        cells = []
        for k, _, fmt in COLS:
            v = means[r][k]
            cells.append("–" if not np.isfinite(v) else fmt.format(v))
        lines.append(f"| {'**pip**' if r == 'pip' else r} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


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
    from jmocap.methods.pip import PIPConfig

    defaults = PIPConfig()
    changes = {k: type(getattr(defaults, k))(float(v)) for k, v in (s.split("=", 1) for s in args.set)}
    command = "python experiments/eval_imu.py" + "".join(
        " " + shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    t0 = time.time()
    means, clips, frames = run(args.archive, args.params, args.max_clips, changes, tuple(args.rows))
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
