"""How well the floor of an uncalibrated static camera is estimated (``jmocap.methods.floor``).

For every clip of an archive with true extrinsics: the estimate from the 2D keypoints alone
(TPNet and the per-frame fit in the camera frame, the shipped weights) against the true camera, as the error of the
up direction (degrees; also split into pitch and roll) and of the camera's height above the
floor (cm and % of the true height); beside it the documented default camera (level, 1 m up),
which is what an uncalibrated clip got before. Rows for settings of ``FloorConfig`` with
``--set name=value`` (several allowed).

    .venv/bin/python experiments/eval_floor.py --archive data/heldout [--max-clips N] [--set tilt_sigma_deg=2]
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from jmocap.camera import default_extrinsics
from jmocap.evaluate import select_clips
from jmocap.inputs import ClipInputs
from jmocap.methods import floor as F
from jmocap.methods import stages as S
from jmocap.pipeline import subject_model
from jmocap.weights import default_params


def true_floor(E: np.ndarray) -> tuple[np.ndarray, float]:
    """(up in the camera frame, camera height above the floor) of a world -> camera transform."""
    R, t = E[:3, :3], E[:3, 3]
    return R[:, 2], float((-R.T @ t)[2])


def angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--archive", default="data/heldout")
    ap.add_argument("--max-clips", type=int, default=None)
    ap.add_argument("--method", default="trajopt", help="whose TPNet config (layout, network sizes)")
    ap.add_argument("--set", nargs="*", default=[], help="FloorConfig fields, name=value")
    ap.add_argument("--json", default=None, help="write per-clip results here")
    ap.add_argument("--tpnet-only", action="store_true",
                    help="TPNet's camera-frame pose as it is, without the per-frame fit (floor.fitted_frames)")
    ap.add_argument("--oracle", action="store_true",
                    help="the ground truth's own poses in the camera frame instead of TPNet's (an upper bound)")
    args = ap.parse_args(argv)
    changes = {k: float(v) for k, v in (s.split("=", 1) for s in args.set)}
    fcfg = F.FloorConfig(**changes)
    params, cfg = default_params(args.method)
    clips = select_clips(args.archive, args.max_clips)

    @jax.jit
    def run(model, inputs, gt_q):
        tp = S.target_pose(params, model, inputs, cfg)
        if args.oracle:  # the true pose seen from the camera
            from jmocap.physics.rotations import quat_to_mat
            E = inputs.extrinsics
            R, t = E[:3, :3], E[:3, 3]
            tp = tp.replace(q_hat=gt_q, trans_cam=gt_q[:, :3] @ R.T + t,
                            rot_cam=jnp.einsum("ij,tjk->tik", R, jax.vmap(quat_to_mat)(gt_q[:, 3:7])))
        if not (args.tpnet_only or args.oracle):
            tp = F.fitted_frames(model, tp, inputs, cfg)
        return F.floor_from_target(model, tp, inputs.mask, fcfg), tp.rot_cam

    rows = []
    t0 = time.time()
    for c in clips:
        c = c.to_layout(cfg.layout)
        T = -(-c.num_frames // 64) * 64
        inputs = ClipInputs.from_clip(c, T)
        gt_q = np.concatenate([c.gt_q, np.repeat(c.gt_q[-1:], T - c.num_frames, 0)]).astype(np.float32)
        est, _ = jax.device_get(run(subject_model(c), jax.tree.map(jnp.asarray, inputs), gt_q))
        up_true, h_true = true_floor(np.asarray(c.extrinsics))
        p_true, r_true = (float(v) for v in F.camera_angles(jnp.asarray(up_true)))
        up_def, h_def = true_floor(default_extrinsics())
        rows.append(dict(
            clip=c.name, kind=c.meta.get("kind", ""), usable=bool(est.usable), support=float(est.support),
            up_err=angle_deg(est.up, up_true), pitch_err=float(est.pitch_deg) - p_true,
            roll_err=float(est.roll_deg) - r_true, h_true=h_true, h_est=float(est.height_m),
            h_err_cm=100 * (float(est.height_m) - h_true), h_err_pct=100 * (float(est.height_m) / h_true - 1),
            up_err_default=angle_deg(up_def, up_true), h_err_default_cm=100 * (h_def - h_true),
            pitch_true=p_true,
        ))
    secs = time.time() - t0
    ok = [r for r in rows if r["usable"]]

    def stat(key, rs=rows, f=np.abs):
        v = f(np.array([r[key] for r in rs]))
        return f"{np.mean(v):.2f} (median {np.median(v):.2f}, max {np.max(v):.2f})"

    print(f"{args.archive}: {len(rows)} clips, {len(ok)} usable estimates, {secs:.0f} s; FloorConfig {changes or 'default'}")
    print(f"  up error deg:          estimate {stat('up_err')}   default camera {stat('up_err_default')}")
    print(f"  pitch error deg:       {stat('pitch_err')}   roll error deg: {stat('roll_err')}")
    print(f"  camera height err cm:  estimate {stat('h_err_cm')}   default camera {stat('h_err_default_cm')}")
    print(f"  camera height err %:   {stat('h_err_pct')}; signed mean {np.mean([r['h_err_pct'] for r in rows]):+.1f}")
    print(f"  support:               {stat('support', f=lambda x: x)}")
    bad = sorted(rows, key=lambda r: -r["up_err"])[:5]
    for r in bad:
        print(f"    worst: {r['clip']} {r['kind']}: up {r['up_err']:.1f} deg (pitch {r['pitch_err']:+.1f}, roll "
              f"{r['roll_err']:+.1f}; true pitch {r['pitch_true']:.1f}), height {r['h_est']:.2f} vs {r['h_true']:.2f} m, "
              f"support {r['support']:.2f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return {"rows": rows}


if __name__ == "__main__":
    main()
