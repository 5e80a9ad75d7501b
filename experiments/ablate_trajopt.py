"""Ablations of ``trajopt`` on a few held-out clips: what each stage and each input contributes.

    .venv/bin/python experiments/ablate_trajopt.py --clips 0 1 4 6 17 28 35 --set w_pose=1
    .venv/bin/python experiments/ablate_trajopt.py --gt-contacts          # oracle contact labels
    .venv/bin/python experiments/ablate_trajopt.py --gt-flight            # oracle flight frames only
    .venv/bin/python experiments/ablate_trajopt.py --clean-2d             # oracle noise-free keypoints

Every clip is padded to one length (``--length``), so the fit compiles once; the config's
weights are traced (changing them with ``--set`` does not recompile; the static fields do).
Per clip and stage (TPNet's target, the kinematic fit, the physics fit) it prints the
reprojection error against the clean 2D (px), MPJPE (root-aligned), PA-MPJPE, the root error
and its part along the camera's viewing direction (depth), all in mm, and for the final fit the
contact F1 of the labels used. The XLA compilation cache is ~/.cache/jmocap/xla-dev.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jmocap import metrics as M
from jmocap import physics as P
from jmocap.camera import project, world_to_camera
from jmocap.data.clip import load_clip
from jmocap.inputs import ClipInputs
from jmocap.methods import stages as S
from jmocap.methods import trajopt as TO
from jmocap.pipeline import subject_model
from jmocap.weights import default_params


def scores(kp, gt, clip, roots):
    """Pose scores of joints (T, J, 3) against the ground truth (jmocap.metrics), and the root's
    error along the camera's viewing direction (depth, mm)."""
    roots = tuple(int(r) for r in roots)
    cam = clip.camera
    depth = world_to_camera(cam, kp[:, list(roots)].mean(1))[:, 2] - world_to_camera(cam, gt[:, list(roots)].mean(1))[:, 2]
    return dict(reproj=float(M.reprojection_error(kp, gt, cam)[0]), mpjpe=float(M.mpjpe(kp, gt, root=roots)),
                pa=float(M.mpjpe(kp, gt, align="procrustes", root=roots)),
                root=float(M.root_translation_error(kp, gt, root=roots)), depth=1e3 * float(np.mean(np.abs(depth))))


def clean_2d(clip):
    """The clip with the ground truth's exact projections as its keypoints (confidence 1)."""
    uv = np.asarray(project(clip.camera, clip.gt_keypoints3d))
    kp = np.concatenate([uv, np.ones_like(uv[..., :1])], -1).astype(clip.keypoints.dtype)
    return dataclasses.replace(clip, keypoints=kp)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/heldout")
    ap.add_argument("--clips", type=int, nargs="+", default=[0, 1, 4, 6, 17, 28, 35])
    ap.add_argument("--length", type=int, default=304)
    ap.add_argument("--set", nargs="*", default=[], help="config fields, name=value")
    ap.add_argument("--gt-contacts", action="store_true", help="the ground-truth contact labels")
    ap.add_argument("--gt-flight", action="store_true",
                    help="the estimated labels, cleared on the ground truth's flight frames (no foot in contact)")
    ap.add_argument("--clean-2d", action="store_true",
                    help="oracle: the ground truth's projection as the keypoints (confidence 1), no detector noise")
    ap.add_argument("--oracle-support", action="store_true",
                    help="oracle: the ground truth's net vertical force as the centre-of-mass prior's centre")
    ap.add_argument("--float64", action="store_true")
    ap.add_argument("--dump", default="", help="folder: save each clip's joints per stage (npz)")
    args = ap.parse_args()
    jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/jmocap/xla-dev"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    if args.float64:
        jax.config.update("jax_enable_x64", True)

    params, base = default_params("trajopt")
    # the experiments' one "name=value" parser (this folder is on sys.path)
    from ablate_pip import parse_set

    config = base.replace(**parse_set(args.set, base))
    from jmocap.layouts import get_layout

    roots = np.asarray(get_layout(config.layout).root_indices)

    @jax.jit
    def run(params, model, inputs, gt_contacts, use_gt, cap, config, oracle_support):
        tp = S.target_pose(params, model, inputs, config)
        mask = jnp.asarray(inputs.mask)
        prob_c = TO.contact_labels(params, inputs, S.contact_probability(tp.contact_logits), config)
        prob_c = jnp.where(use_gt, gt_contacts, jnp.minimum(prob_c, cap))
        q0 = TO.initial_trajectory(model, tp.q_hat, mask)
        support = TO.support_prior(params, inputs, config) if oracle_support is None else oracle_support
        prob = TO.problem(model, inputs, tp.q_hat, prob_c, config).replace(support=support)
        out = TO.fit(model, prob, q0, config)
        kp = lambda q: jax.vmap(lambda x: P.keypoints(model, x, config.layout))(q)  # noqa: E731
        feet = jax.vmap(lambda x: P.site_positions(model, x, model.topo.contact_sites))(out.q)
        report = TO.outputs(model, out.q, out.force, mask, inputs.fps)[3]
        return kp(q0), kp(out.q_kinematic), kp(out.q), out.contacts, {**out.diagnostics, **report}, out.force, feet

    rows = []
    for i in args.clips:
        clip = load_clip(Path(args.archive) / f"synth_{i:06d}.npz")
        T = clip.num_frames
        model = subject_model(clip)
        if args.clean_2d:
            clip = clean_2d(clip)
        inputs = ClipInputs.from_clip(clip, args.length)
        gtc = np.zeros((args.length, 4), np.float32)
        gtc[:T] = clip.gt_contacts
        cap = np.ones((args.length, 1), np.float32)
        if args.gt_flight:  # the estimator's labels with every ground-truth flight frame cleared
            cap[:T, 0] = np.any(clip.gt_contacts > 0.5, -1)
        oracle = None
        if args.oracle_support:
            from jmocap.methods.support import target

            oracle = np.ones(args.length, np.float32)
            oracle[:T] = target(clip.gt_grf, clip.mass_kg)
        t0 = time.perf_counter()
        k0, k1, k2, used, diag, force, feet = jax.block_until_ready(
            run(params, model, inputs, gtc, args.gt_contacts, cap, config, oracle))
        dt = time.perf_counter() - t0
        gt = clip.gt_keypoints3d
        w = float(np.sum(model.body_mass)) * 9.81
        gt_w = clip.mass_kg * 9.81 if clip.mass_kg else w
        grf = np.asarray(force[:T]).reshape(T, 4, 2, 3).sum(2)
        if args.dump:
            Path(args.dump).mkdir(parents=True, exist_ok=True)
            np.savez(Path(args.dump) / f"clip{i}.npz", init=k0[:T], kin=k1[:T], phys=k2[:T], gt=gt,
                     contacts=np.asarray(used[:T]), gt_contacts=clip.gt_contacts,
                     grf_bw=grf / w, gt_grf_bw=clip.gt_grf / gt_w)
        r = {"clip": i, "kind": clip.meta.get("kind", "?"), "s": dt}
        for name, k in (("init", k0), ("kin", k1), ("phys", k2)):
            for key, v in scores(np.asarray(k[:T], np.float64), gt, clip, roots).items():
                r[f"{name}_{key}"] = v
        # scored where the ground truth's contact forces explain its motion, as jmocap eval does
        explained = np.ones(T, bool) if clip.residual_percent_bw is None else clip.residual_percent_bw <= M.GT_MAX_RESIDUAL_PCT_BW
        r["grf_err"] = float(M.grf_error(grf, clip.gt_grf, w, gt_w, explained))
        flight = ~np.any(clip.gt_contacts > 0.5, -1)
        r["ballistic"] = float(M.grf_ballistic(grf, w, flight, explained))
        r["grf_max"] = float(100 * np.linalg.norm(grf.sum(1), axis=-1).max() / w)
        r["residual"] = float(100 * diag["residual_mean_bw"])
        r["jitter"] = float(M.jitter(np.asarray(k2[:T]), float(clip.fps)))
        r["pnp"] = float(M.non_penetration(np.asarray(feet[:T])))
        r["skate"] = float(M.foot_skate(np.asarray(feet[:T]), clip.gt_contacts))
        r["f1"] = float(M.contact_classification(np.asarray(used[:T]), clip.gt_contacts)["f1"])
        r["gnorm"] = float(diag["grad_norm"])
        rows.append(r)
        print(" ".join(f"{k}={v:.1f}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()), flush=True)
    keys = [k for k in rows[0] if k not in ("clip", "kind")]
    print("mean " + " ".join(f"{k}={np.nanmean([r[k] for r in rows]):.1f}" for k in keys))


if __name__ == "__main__":
    main()
