"""``jmocap eval`` on an archive of six-IMU clips: PIP (:mod:`jmocap.methods.pip_imu`), the
kinematics module alone and the paper's two ablations, against the clips' ground truth, with the
metrics of PIP's paper (:mod:`jmocap.metrics`: SIP and angular error, positional error, the
mesh-error stand-in, jitter, translation error) and the physical rows of the video evaluation
(residual, GRF errors, skate, non-penetration, contact F1). docs/evaluation.md, "PIP on six IMUs".
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jmocap import metrics as M
from jmocap import physics as P
from jmocap.data.archive import Archive
from jmocap.data.imu import IMUClip
from jmocap.io import atomic_write
from jmocap.methods import pip_imu as PI
from jmocap.methods.pip_imu import N
from jmocap.model import character

PAD = 320
#: the rows: method name -> label (the kinematics module alone, the method, the paper's two
#: ablations of its Tab. 2, the archive's own motion)
METHODS = {
    "pip_imu_kinematics": "kinematics",
    "pip_imu": "pip",
    "pip_imu_single_pd": "pip, single PD",
    "pip_imu_zero_init": "pip, zero initial state",
    "ground_truth": "ground truth",
}
ROWS = tuple(METHODS.values())
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


@jax.jit
def geometry(model, q):
    """Per frame of ``q`` (T, nq): world body positions (T, nbody, 3) and orientations (T, nbody,
    3, 3), and the contact sites (T, 4, 3), in one compiled forward-kinematics pass."""
    kin = jax.vmap(lambda x: P.forward_kinematics(model, x))(q)
    feet = jax.vmap(lambda x: P.site_positions(model, x, model.topo.contact_sites))(q)
    return kin.xpos, kin.xmat, feet


def clip_geometry(model, q, length: int):
    """:func:`geometry` of the first ``len(q)`` frames, computed edge-padded to ``length`` frames
    (one compile per padded length, not per clip length)."""
    T = len(q)
    q = np.concatenate([np.asarray(q, np.float32), np.repeat(np.asarray(q[-1:], np.float32), length - T, 0)])
    return tuple(np.asarray(a)[:T] for a in geometry(model, jnp.asarray(q)))


def clip_metrics(model, q, grf, tau, prob, clip, mask, gt_geometry=None) -> dict[str, float]:
    """One clip's metrics of a motion ``q`` (T, nq) (``grf``, ``tau``, ``prob`` may be None);
    ``gt_geometry``: :func:`clip_geometry` of the clip's ``gt_q`` (computed when None)."""
    T = clip.num_frames
    n = int(np.ceil(T / PAD) * PAD)
    q, gq = np.asarray(q[:T], np.float32), np.asarray(clip.gt_q, np.float32)
    xpos, xmat, feet = clip_geometry(model, q, n)
    gxpos, gxmat, _ = clip_geometry(model, gq, n) if gt_geometry is None else gt_geometry
    bodies = np.asarray(N.body_indices(model)["bodies"])  # the root (pelvis) first
    sip = np.asarray([model.body_id(b) for b in M.SIP_BODIES])
    R, gR = xmat[:, bodies[0]], gxmat[:, bodies[0]]
    out = {
        "sip_deg": float(M.sip_error(xmat[:, sip], gxmat[:, sip])),
        "ang_deg": float(M.angular_error(xmat[:, 1:], gxmat[:, 1:])),
        "mesh_mm": float(M.mpjpe_root_frame(xpos[:, bodies], gxpos[:, bodies], R, gR)),
        "trans_m": float(M.mean_translation_error(q[:, :3], gq[:, :3])),
    }
    pred = {"keypoints3d": xpos[:, bodies], "feet": feet,
            "grf": None if grf is None else grf[:T], "tau": None if tau is None else tau[:T],
            "contact_prob": None if prob is None else prob[:T]}
    gt = {"keypoints3d": gxpos[:, bodies], "contacts": clip.gt_contacts, "grf": clip.gt_grf, "tau": clip.gt_tau}
    # the estimate's character is the clip's subject (else the nominal one); the ground truth's weight
    # is the clip's mass where it has one
    vals = M.evaluate_arrays(pred, gt, fps=float(clip.fps), mask=np.asarray(mask[:T]), pred_mass=model.total_mass,
                             gt_mass=clip.mass_kg if clip.mass_kg is not None else model.total_mass)
    for k, _, _ in COLS:  # the table's other columns, from the shared metrics
        out.setdefault(k, float(vals.get(k, np.nan)))
    return out


def run(archive, params_path=None, max_clips: int | None = None, changes: dict | None = None, rows=ROWS,
        log=lambda s: print(s, flush=True)) -> tuple[dict[str, dict[str, float]], dict[str, list[dict[str, float]]], list[str], int]:
    """Every row of ``rows`` (labels of :data:`METHODS`) on the clips of the IMU archive
    ``archive`` (the first ``max_clips``): ``(means per row, per-clip values per row, clip names,
    frames)``. ``changes``: fields of the physics config (:class:`jmocap.methods.pip.PIPConfig`).
    A clip without ground-truth forces (a kinematic archive) has no force rows (NaN)."""
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
            if not isinstance(clip, IMUClip) or clip.gt_q is None:
                raise ValueError(f"{archive}/{name}: not an IMU clip with ground truth (gt_q)")
            model = character(clip.height_m, clip.mass_kg)
            n = int(np.ceil(clip.num_frames / PAD) * PAD)
            inputs = PI.IMUInputs.from_clip(clip, model, n)
            frames += clip.num_frames
            gt_geo = clip_geometry(model, clip.gt_q, n)  # once per clip, for every row
            for row, (cfg, zero) in variants.items():
                m = rec(params, model, PI.zero_init(inputs) if zero else inputs, cfg)
                forces = cfg.physics
                per[row].append(clip_metrics(model, np.asarray(m.q), np.asarray(m.grf) if forces else None,
                                             np.asarray(m.tau) if forces else None, np.asarray(m.contact_prob),
                                             clip, np.asarray(inputs.mask), gt_geo))
            if "ground truth" in rows:
                per["ground truth"].append(clip_metrics(model, clip.gt_q, clip.gt_grf, clip.gt_tau,
                                                        clip.gt_contacts.astype(np.float32), clip,
                                                        np.ones(clip.num_frames, bool), gt_geo))
            if "pip" in rows and log is not None:
                log(f"{name}: pip MPJPE {per['pip'][-1]['mpjpe_mm']:.1f} mm, residual "
                    f"{per['pip'][-1]['root_residual_pct_bw']:.2f} % BW")
    with warnings.catch_warnings():  # a metric no clip defines (e.g. ballistic GRF without flight) is NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        means = {r: {k: float(np.nanmean([p[k] for p in ps])) for k, _, _ in COLS} for r, ps in per.items()}
    return means, per, list(names), frames


def table(means, rows=ROWS) -> str:
    """The markdown table of :func:`run`'s means (– where undefined)."""
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


def cmd_eval(args) -> int:
    """``jmocap eval IMU_ARCHIVE``: ``OUT/metrics.md`` (the table) and ``OUT/metrics.json`` (means
    and per-clip values per method)."""
    import sys

    try:
        methods = args.methods or list(METHODS)
        unknown = [m for m in methods if m not in METHODS]
        if unknown:
            raise ValueError(f"{args.archive} holds IMU clips: methods are {', '.join(METHODS)}; not {unknown}")
        rows = tuple(METHODS[m] for m in methods)
        log = None if args.quiet else (lambda s: print(s, file=sys.stderr, flush=True))
        means, per, names, frames = run(args.archive, args.params, args.max_clips, rows=rows, log=log)
    except (OSError, ValueError) as e:
        print(f"jmocap eval: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    text = f"# {args.archive}: {len(names)} IMU clips, {frames} frames\n\n" + table(means, rows) + "\n"
    atomic_write(out / "metrics.md", text.encode())
    label = {v: k for k, v in METHODS.items()}
    doc = {"archive": str(args.archive), "clips": names, "frames": frames,
           "means": {label[r]: v for r, v in means.items()},
           "per_clip": {label[r]: dict(zip(names, ps, strict=True)) for r, ps in per.items()}}
    atomic_write(out / "metrics.json", (json.dumps(doc, indent=1, allow_nan=True) + "\n").encode())
    print(text)
    print(f"wrote {out / 'metrics.md'} and metrics.json")
    return 0


__all__ = ["COLS", "METHODS", "ROWS", "clip_metrics", "cmd_eval", "run", "table"]
