"""The ``jmocap`` command line: ``jmocap <command> ...``.

Each command is one function that configures its own ``argparse`` sub-parser and sets
``func`` (what runs, taking the parsed arguments, returning an exit status). Adding a command
is one decorated function::

    @command("demo", "run the demo")
    def _demo(p: argparse.ArgumentParser) -> None:
        p.add_argument("--frames", type=int, default=100)
        p.set_defaults(func=run_demo)     # run_demo(args) -> int | None

Commands: ``data synth`` (synthetic clip archives), ``data info`` (summarise an archive),
``reconstruct`` (batch reconstruction of an archive; ``--engine ray`` on a Ray cluster), ``train``
(the staged training of the networks, on one or several processes), ``eval`` (the metrics table of methods
over an archive with ground truth), ``render`` (video and force plots of a result), ``export``
(OpenSim, glTF and BVH files of results), ``view`` (a self-contained HTML viewer page),
``score`` (results against 3D ground truth with any subset of joints), ``video`` (from a video
file: 2D keypoints, reconstruction and an overlay video; the ``video`` extra) and ``demo`` (all
of it on the shipped sample).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable

from jmocap.progress import Progress

COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None]]] = {}


def command(name: str, help: str):
    """Register a top-level command: the decorated function configures its sub-parser."""

    def deco(fn):
        COMMANDS[name] = (help, fn)
        return fn

    return deco


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="jmocap", description="Physics-aware human motion capture from 2D keypoints."
    )
    sub = p.add_subparsers(dest="command", metavar="<command>", required=True)
    for name, (help_, configure) in COMMANDS.items():
        configure(sub.add_parser(name, help=help_, description=help_))
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jmocap`` script; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:  # before a command had its own handling in place
        print(f"\njmocap {args.command}: interrupted", file=sys.stderr)
        return 130


# =========================================================================================
# jmocap data ...
# =========================================================================================


def _frames_arg(text: str):
    """``N`` or ``MIN:MAX`` frames per clip."""
    try:
        if ":" in text:
            a, b = (int(x) for x in text.split(":", 1))
            if not 2 <= a <= b:
                raise ValueError
            return (a, b)
        n = int(text)
        if n < 2:
            raise ValueError
        return n
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N or MIN:MAX with 2 <= MIN <= MAX, got {text!r}") from None


def _kind_list(text: str, known: tuple[str, ...], what: str) -> tuple[str, ...]:
    """A comma-separated list of names, each one of ``known``, at least one."""
    kinds = tuple(k.strip() for k in text.split(",") if k.strip())
    bad = [k for k in kinds if k not in known]
    if bad or not kinds:
        raise argparse.ArgumentTypeError(f"unknown {what}(s) {bad}; known: {', '.join(known)}")
    return kinds


def _kinds_arg(text: str):
    from jmocap.data.synthetic import SEGMENTS

    return _kind_list(text, tuple(SEGMENTS), "motion kind")


def _camera_kinds_arg(text: str):
    from jmocap.data.synthetic import MOVING_KINDS

    return _kind_list(text, MOVING_KINDS + ("static",), "camera kind")


def _terrain_kinds_arg(text: str):
    from jmocap.data.synthetic.terrain import TERRAIN_KINDS

    return _kind_list(text, TERRAIN_KINDS + ("flat",), "terrain kind")


@command("data", "synthetic data and clip archives")
def _data(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="data_command", metavar="<data command>", required=True)
    s = sub.add_parser(
        "synth",
        help="generate an archive of synthetic clips",
        description=(
            "Generate synthetic clips (procedural motions on MuJoCo, random subject and camera, "
            "detector-like 2D keypoints) into an archive folder with manifest.jsonl. "
            "Deterministic for a seed; an interrupted run resumes where it stopped."
        ),
    )
    s.add_argument("--out", required=True, help="archive folder (created; resumed if it exists)")
    s.add_argument("--clips", type=int, required=True, help="number of clips")
    s.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    s.add_argument("--physics", action="store_true",
                   help="track each motion in MuJoCo simulation moved by contacts (gt_tau, gt_grf, "
                        "gt_residual, per-foot force, CoP, free moment; contact labels by force and floor)")
    s.add_argument("--controller", choices=["qp", "sampling"], default="qp",
                   help="with --physics: the simulation's controller: 'qp' (default) the QP tracker, with a "
                        "recorded root residual where the plan is infeasible; 'sampling' sampling-based "
                        "control (mujoco.rollout) whose samples the QP tracker's contact-respecting inverse "
                        "dynamics drives, a root force only in its rare rescues (recorded); the held-out "
                        "archive's, several times slower (docs/data.md)")
    s.add_argument("--frames-per-clip", type=_frames_arg, default=(150, 300), metavar="N|MIN:MAX",
                   help="clip length in frames (default 150:300)")
    s.add_argument("--layout", default="body25", choices=["body25", "coco17", "h36m17", "halpe26"],
                   help="2D keypoint layout (default body25)")
    s.add_argument("--fps", type=float, default=30.0, help="frame rate (default 30)")
    s.add_argument("--kinds", type=_kinds_arg, default=None, metavar="K1,K2",
                   help="motion kinds to draw from (default: all)")
    s.add_argument("--extended", action="store_true",
                   help="the extended generator: everyday motions (bend, crouch, reach) beside the classic "
                        "kinds, gestures and speed changes while walking, subjects 1.45-2.0 m, phone to "
                        "telephoto cameras 2-10 m away and 0.3-3 m high, occlusion bursts (docs/data.md)")
    s.add_argument("--moving-camera", type=_camera_kinds_arg, nargs="?", const=("handheld", "pan", "dolly", "orbit"),
                   default=(), metavar="K1,K2",
                   help="film each clip with a moving camera drawn from K1,K2 (default: handheld, pan, dolly, "
                        "orbit; 'static' may be one of them) and store its per-frame track (camera_track)")
    s.add_argument("--terrain", type=_terrain_kinds_arg, nargs="?",
                   const=("step_up", "step_down", "stairs_up", "stairs_down", "block", "ramp_up", "ramp_down"),
                   default=(), metavar="K1,K2",
                   help="walk on terrain drawn from K1,K2 (default: step_up, step_down, stairs_up, stairs_down, "
                        "block, ramp_up, ramp_down; 'flat' may be one of them): boxes placed under the "
                        "footsteps, simulated with --physics, stored as each clip's scene (docs/data.md)")
    s.add_argument("--no-corruption", action="store_true",
                   help="exact 2D projections, confidence 1 (with --imu: exact IMU signals)")
    s.add_argument("--imu", action="store_true",
                   help="write IMU clips (jmocap-imu-clip-1: six sensors on forearms, lower legs, head and "
                        "pelvis, with the same ground truth) instead of 2D keypoint clips")
    s.add_argument("--workers", type=int, default=1, help="parallel processes (default 1)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_data_synth)

    i = sub.add_parser("info", help="summarise a clip archive (folder, .zip or .tar)")
    i.add_argument("path")
    i.set_defaults(func=cmd_data_info)


def _synth_one(job):
    """Worker: (seed, index, config) -> (index, clip | None, error | None)."""
    from jmocap.data.synthetic import GenerationError, generate_clip
    from jmocap.data.synthetic.imu import IMUSynthConfig, generate_imu_clip

    seed, index, config = job
    try:
        if isinstance(config, IMUSynthConfig):
            return index, generate_imu_clip(seed, index, config), None
        return index, generate_clip(seed, index, config), None
    except GenerationError as e:
        return index, None, str(e)
    except Exception as e:  # a batch run records the failed clip and goes on (docs/DESIGN)
        return index, None, f"{type(e).__name__}: {e}"


def cmd_data_synth(args) -> int:
    import dataclasses

    from jmocap.data.archive import ArchiveWriter
    from jmocap.data.synthetic import Corruption, SynthConfig, clip_name

    if args.clips < 0:
        print("jmocap data synth: --clips must be >= 0", file=sys.stderr)
        return 2
    if args.controller != "qp" and not args.physics:
        print("jmocap data synth: --controller needs --physics", file=sys.stderr)
        return 2
    if args.imu and args.moving_camera:
        print("jmocap data synth: --moving-camera is for 2D keypoint clips, not --imu", file=sys.stderr)
        return 2
    if args.terrain and (args.imu or args.controller != "qp"):
        print("jmocap data synth: --terrain makes 2D keypoint clips simulated (with --physics) by the QP "
              "tracker: not with --imu or --controller sampling", file=sys.stderr)
        return 2
    from jmocap.data.synthetic.physics import PhysicsConfig

    fields = dict(frames=args.frames_per_clip, fps=args.fps, layout=args.layout, physics=args.physics,
                  kinds=args.kinds, physics_cfg=PhysicsConfig(controller=args.controller),
                  moving_camera=args.moving_camera, terrain=args.terrain)
    config = SynthConfig.extended_generator(**fields) if args.extended else SynthConfig(**fields)
    if args.no_corruption:
        config = dataclasses.replace(config, corruption=Corruption.none())
    if args.imu:
        from jmocap.data.synthetic.imu import IMUCorruption, IMUSynthConfig

        config = IMUSynthConfig(synth=dataclasses.replace(config, corruption=Corruption.none()),
                                corruption=IMUCorruption.none() if args.no_corruption else IMUCorruption())
    generator = "jmocap.data.synthetic.imu" if args.imu else "jmocap.data.synthetic"
    settings = {"generator": generator, "seed": args.seed, "config": config.to_json()}
    t0 = time.perf_counter()
    written = failed = skipped = frames = 0
    with ArchiveWriter(args.out, settings) as writer:
        todo = [i for i in range(args.clips) if not writer.has(clip_name(i))]
        skipped = args.clips - len(todo)
        bar = Progress(len(todo), "synth", enabled=not args.quiet)
        jobs = [(args.seed, i, config) for i in todo]
        if args.workers > 1 and len(jobs) > 1:
            import multiprocessing as mp

            ctx = mp.get_context("spawn")
            with ctx.Pool(min(args.workers, len(jobs))) as pool:
                results = pool.imap(_synth_one, jobs)
                written, failed, frames = _consume(results, writer, bar, args.seed)
        else:
            written, failed, frames = _consume(map(_synth_one, jobs), writer, bar, args.seed)
        bar.close()
    el = time.perf_counter() - t0
    print(
        f"jmocap data synth: {written} clips written, {failed} failed, {skipped} already there; "
        f"{frames} frames in {el:.1f} s ({frames / el if el > 0 else 0:.0f} frames/s) -> {args.out}"
    )
    return 1 if failed and not written else 0


def _consume(results, writer, bar, seed):
    from jmocap.data.synthetic import clip_name

    written = failed = frames = 0
    for index, clip, error in results:
        if clip is None:
            writer.add_failure(clip_name(index), error, index=index, seed=seed)
            failed += 1
            bar.update(1)
            continue
        extra = {"index": index, "seed": seed, "physics": bool(clip.meta.get("physics_variant"))}
        if "imu_generator" in clip.meta:
            extra["imu"] = True
            extra["filled_sensor_frames"] = int(clip.filled.sum()) if clip.filled is not None else 0
        if getattr(clip, "camera_track", None) is not None:  # a moving camera: its kind
            extra["camera"] = clip.meta.get("camera", {}).get("kind", "moving")
        phys = clip.meta.get("physics")
        if phys:
            extra["residual_force_mean"] = phys["residual_force_mean"]
            extra["residual_force_max"] = phys["residual_force_max"]
            extra["residual_frame_share"] = phys["residual_frame_share"]
        writer.add(clip, **extra)
        written += 1
        frames += clip.num_frames
        bar.update(1, clip.num_frames)
    return written, failed, frames


def cmd_data_info(args) -> int:
    from collections import Counter

    from jmocap.data.archive import Archive, ArchiveError, residual_summary

    try:
        with Archive(args.path) as a:
            ok = a.ok
            kinds = Counter(e.get("kind") for e in ok)
            print(f"{args.path}: {len(ok)} clips, {sum(e.get('frames', 0) for e in ok)} frames, "
                  f"{len(a.manifest) - len(ok)} failed")
            print("kinds: " + ", ".join(f"{k} {n}" for k, n in kinds.most_common()))
            cameras = Counter(e.get("camera", "static") for e in ok)
            if set(cameras) != {"static"}:  # an archive with moving cameras
                print("cameras: " + ", ".join(f"{k} {n}" for k, n in cameras.most_common()))
            line = residual_summary(ok)
            if line:  # a physics archive: where the generator pushed the root (docs/data.md)
                print(line)
            if a.settings:
                print("settings: " + json.dumps(a.settings, sort_keys=True))
    except (ArchiveError, FileNotFoundError) as e:
        print(f"jmocap data info: {e}", file=sys.stderr)
        return 1
    return 0


# =========================================================================================
# jmocap render ...
# =========================================================================================


def _size_arg(text: str):
    """``WxH`` pixels."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if not (8 <= w <= 4096 and 8 <= h <= 4096):
            raise ValueError
        return (w, h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH with 8..4096 pixels each, e.g. 320x240, got {text!r}") from None


@command("render", "render a reconstruction result: video (MP4/GIF) and force plots")
def _render(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Render a result .npz: the humanoid from the front and the side with ground reaction "
        "force arrows and contact feet marked, plus the input camera's view with the 2D "
        "keypoints when the result has them. Headless (EGL, else OSMesa)."
    )
    p.add_argument("result", help="result .npz of a reconstruction")
    p.add_argument("--out", help="video file, .mp4 or .gif (default: RESULT with .mp4)")
    p.add_argument("--plots", metavar="DIR", help="also write DIR/<name>_forces.png (GRF, torques)")
    p.add_argument("--size", type=_size_arg, default=(320, 240), metavar="WxH",
                   help="size of each view in pixels (default 320x240)")
    p.add_argument("--no-side", action="store_true", help="no side view")
    p.add_argument("--quality", choices=["fast", "high"], default="fast",
                   help="fast: no shadows/reflections/antialiasing (default); high: the model's own")
    p.set_defaults(func=cmd_render)


def cmd_render(args) -> int:
    from jmocap.viz import RenderError, render_result

    try:
        paths = render_result(args.result, args.out, plots=args.plots, size=args.size,
                              side=not args.no_side, quality=args.quality)
    except (ValueError, FileNotFoundError, RenderError, ImportError) as e:  # ImportError: no viz extra
        print(f"jmocap render: {e}", file=sys.stderr)
        return 1
    print("jmocap render: wrote " + ", ".join(str(p) for p in paths))
    return 0


# =========================================================================================
# jmocap export / jmocap score / jmocap view: results made earlier
# =========================================================================================

def _result_paths(path: str):
    """Result files of RESULTS (one .npz, or the .npz files of a results folder), sorted."""
    from pathlib import Path

    p = Path(path)
    if p.is_file():
        return [p]
    if p.is_dir():
        return sorted(f for f in p.glob("*.npz") if f.is_file())
    raise FileNotFoundError(f"no result file or folder at {p}")


@command("export", "export results to OpenSim (.osim/.mot/.xml/.trc), glTF (.glb) and BVH")
def _export(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Export reconstruction results (a result .npz or a results folder) to the files other tools "
        "open: OpenSim (the character as a .osim model, joint coordinates and per-foot ground reaction "
        "forces as .mot with their ExternalLoads .xml, keypoints as .trc markers), an animated glTF "
        "binary (.glb: Blender, three.js) and BVH (docs/formats.md). Without a format flag, all of them."
    )
    p.add_argument("results", help="result .npz, or a folder of them (jmocap reconstruct's OUTPUT)")
    p.add_argument("out", help="output folder (created)")
    from jmocap.export import EXPORT_FORMATS

    for f in EXPORT_FORMATS:
        p.add_argument(f"--{f}", action="store_true", help=f"write {f} files")
    p.add_argument("--no-forces", action="store_true", help="glb: no force arrows or contact markers")
    p.set_defaults(func=cmd_export)


def cmd_export(args) -> int:
    from jmocap.data.clip import FormatError
    from jmocap.export import EXPORT_FORMATS, export_result
    from jmocap.results import load_result

    formats = [f for f in EXPORT_FORMATS if getattr(args, f)] or list(EXPORT_FORMATS)
    try:
        files = _result_paths(args.results)
    except FileNotFoundError as e:
        print(f"jmocap export: {e}", file=sys.stderr)
        return 1
    if not files:
        print(f"jmocap export: no .npz result files in {args.results}", file=sys.stderr)
        return 1
    failed = 0
    n = 0
    for f in files:
        try:
            r = load_result(f)
            written = export_result(r, r.get("name") or f.stem, args.out, formats, forces=not args.no_forces)
        except (FormatError, ValueError, OSError) as e:
            failed += 1
            print(f"jmocap export: {f}: {e}", file=sys.stderr)
            continue
        n += len(written)
    print(f"jmocap export: {len(files) - failed} of {len(files)} results, {n} files in {args.out} "
          f"({', '.join(formats)})")
    return 1 if failed else 0


@command("score", "score results made earlier against 3D ground truth with any subset of named joints")
def _score(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Score result files against 3D ground truth that may have only some joints (a joint file: "
        "joint_names, joints3d, fps; or a jmocap clip with gt_keypoints3d; docs/formats.md): MPJPE, "
        "PA-MPJPE, absolute MPJPE, root error, smoothness and acceleration errors on the joints the "
        "ground truth has, and the result's jitter and foot metrics. Writes OUT/scores.md and .json."
    )
    p.add_argument("results", help="result .npz, or a folder of them")
    p.add_argument("gt", help="a ground-truth file, or a folder with <clip name>.npz / .json per clip")
    p.add_argument("--out", default="out/score", help="output folder (default out/score)")
    p.set_defaults(func=cmd_score)


def cmd_score(args) -> int:
    from jmocap.score import score_results, scores_table, write_scores

    try:
        rows, problems = score_results(args.results, args.gt)
    except (FileNotFoundError, ValueError) as e:
        print(f"jmocap score: {e}", file=sys.stderr)
        return 1
    for line in problems:
        print(f"jmocap score: {line}", file=sys.stderr)
    if not rows:
        print("jmocap score: nothing scored", file=sys.stderr)
        return 1
    files = write_scores(rows, args.out)
    print(scores_table(rows))
    print(f"jmocap score: {len(rows)} clips scored, {len(problems)} not -> " + ", ".join(str(f) for f in files))
    return 1 if problems else 0


@command("view", "write one self-contained HTML page that plays results (3D, forces, plots)")
def _view(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Write a single HTML file (opens offline from disk, no server) that plays a result or a "
        "results folder: the character in 3D with the floor, ground reaction force arrows and "
        "contacts, a time slider, the clip list with its numbers, and force/torque plots."
    )
    p.add_argument("results", help="result .npz, or a folder of them (jmocap reconstruct's OUTPUT)")
    p.add_argument("-o", "--out", help="the page (default: RESULTS/viewer.html for a folder, RESULT.html for a file)")
    p.add_argument("--max-clips", type=int, default=100, help="clips on the page (default 100; ~200 kB each)")
    p.set_defaults(func=cmd_view)


def cmd_view(args) -> int:
    from pathlib import Path

    from jmocap.export.viewer import write_viewer

    src = Path(args.results)
    out = args.out or (src / "viewer.html" if src.is_dir() else src.with_suffix(".html"))
    try:
        page, skipped = write_viewer(src, out, max_clips=args.max_clips)
    except (ValueError, FileNotFoundError, OSError) as e:
        print(f"jmocap view: {e}", file=sys.stderr)
        return 1
    for s in skipped:
        print(f"jmocap view: skipped {s}", file=sys.stderr)
    print(f"jmocap view: wrote {page}")
    return 0


# =========================================================================================
# jmocap eval
# =========================================================================================


@command("eval", "evaluate methods on an archive of clips with ground truth (one table of every metric)")
def _eval(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Reconstruct every clip of an archive with each method (the full pipeline, its ablations, "
        "the kinematic target and the ground truth itself) and write OUT/metrics.md, .csv and "
        ".json with every metric of jmocap.metrics per method (docs/evaluation.md)."
    )
    p.add_argument("archive", help="archive of clips with ground truth (folder, .zip or .tar)")
    p.add_argument("--methods", nargs="+", metavar="METHOD",
                   help=f"methods and variants (default: all): {_method_list()}, ground_truth; on an archive "
                        "of IMU clips: pip_imu, pip_imu_kinematics, pip_imu_single_pd, pip_imu_zero_init, ground_truth")
    p.add_argument("--params", help="parameters (.msgpack); default: the shipped weights")
    p.add_argument("--random-init", action="store_true",
                   help="freshly initialised parameters (seeded): smoke tests of the harness only")
    p.add_argument("--method-params", action="append", default=[], metavar="METHOD=PATH",
                   help="a method's own parameters, e.g. no_canonicalisation=runs/nocano/params.msgpack")
    p.add_argument("--out", default="out/eval", help="output folder (default out/eval)")
    p.add_argument("--max-clips", type=int, help="evaluate a seeded random subset of this many clips")
    p.add_argument("--seed", type=int, default=0, help="seed of the clip subset and random init (default 0)")
    p.add_argument("--batch-size", type=int, default=8, help="clips per compiled batch (default 8)")
    p.add_argument("--subject-height", choices=("given", "auto", "nominal"), default="given",
                   help="the height the estimates use: the clips' own (default), estimated from the 2D "
                        "evidence as for clips without one (jmocap.subject), or the nominal 1.75 m character; "
                        "the ground truth always uses the clips' own")
    p.add_argument("--camera", choices=("given", "static", "estimate", "default"), default="given",
                   help="the extrinsics the estimates use: the clips' own (default; a moving camera's track), "
                        "'static': a moving camera's first frame for every frame (the camera's motion ignored), "
                        "withheld and estimated from the 2D evidence as for an uncalibrated video "
                        "(jmocap.methods.floor), or withheld and replaced by the default camera; estimates are "
                        "scored in the true world")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_eval)


def cmd_eval(args) -> int:
    from jmocap.batch_imu import is_imu_archive

    if is_imu_archive(args.archive):  # six-IMU clips: PIP and its ablations (jmocap.evaluate_imu)
        from jmocap.evaluate_imu import cmd_eval as run_imu

        return run_imu(args)
    from jmocap.evaluate import cmd_eval as run

    return run(args)


# =========================================================================================
# jmocap reconstruct
# =========================================================================================


def _image_size_arg(text: str):
    """``WIDTHxHEIGHT`` pixels."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w > 0 and h > 0:
            return (w, h)
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 1920x1080, got {text!r}")


def _number_in(text: str, lo: float, hi: float) -> float | None:
    """``text`` as a number in [lo, hi], else None."""
    try:
        x = float(text)
    except ValueError:
        return None
    return x if lo <= x <= hi else None


def _height_arg(text: str):
    """``--height-m``: metres in [0.5, 2.5], ``auto`` or ``nominal``."""
    if text in ("auto", "nominal"):
        return text
    h = _number_in(text, 0.5, 2.5)
    if h is None:
        raise argparse.ArgumentTypeError(f"expected a height in metres in [0.5, 2.5], 'auto' or 'nominal', got {text!r}")
    return h


def _mass_arg(text: str) -> float:
    """``--mass-kg``: kilograms in [10, 300]."""
    m = _number_in(text, 10.0, 300.0)
    if m is None:
        raise argparse.ArgumentTypeError(f"expected a mass in kilograms in [10, 300], got {text!r}")
    return m


def _xla_cache_dir() -> str:
    import os

    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jmocap", "xla")


@command("reconstruct", "reconstruct 3D motion for every clip of a folder, .zip or .tar")
def _reconstruct(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Reconstruct every clip of INPUT (a jmocap archive, or a folder / .zip / .tar of clips in "
        "any supported 2D format) into OUTPUT: one result .npz per clip, manifest.jsonl and "
        "summary.json (docs/formats.md). Resumes: clips with a result are skipped; a bad clip is "
        "recorded as failed and the run goes on."
    )
    p.add_argument("input", help="jmocap archive, or folder / .zip / .tar of clips")
    p.add_argument("output", help="output folder (created; resumed if it exists)")
    p.add_argument("--params", help="parameters (.msgpack); default: the shipped weights")
    p.add_argument("--method", default=None, metavar="NAME",
                   help=f"reconstruction method or variant (default {_default_method()}): {_method_list()}")
    p.add_argument("--config", metavar="JSON",
                   help="config fields of the method (JSON text or file) overriding the parameters' config")
    p.add_argument("--kinematic-only", action="store_true", help="the same as --method kinematic")
    p.add_argument("--chunk", type=int, default=256, metavar="N", help="frames per chunk (default 256)")
    p.add_argument("--bucket", type=int, default=64, metavar="N",
                   help="a clip's last chunk is padded to a multiple of N frames (default 64)")
    p.add_argument("--batch", type=int, default=8, metavar="N",
                   help="clips per device per call (default 8; a larger batch runs in tiles of 32 clips, "
                        "docs/performance.md)")
    p.add_argument("--host-devices", type=int, default=0, metavar="N",
                   help="on a CPU-only machine, split each call over N host devices, one thread each "
                        "(default 0: one per CPU core; 1: a single device)")
    p.add_argument("--image-size", type=_image_size_arg, metavar="WxH",
                   help="image size assumed for clips whose file and camera sidecar give none")
    p.add_argument("--height-m", type=_height_arg, default="auto", metavar="H|auto|nominal",
                   help="the subject's height: H metres for every clip; 'auto' (default): the clip's or "
                        "its sidecar's height_m, else estimated from the 2D keypoints when the camera's "
                        "extrinsics are known, else the nominal 1.75 m character; 'nominal': no estimate. "
                        "The result's height_source says which")
    p.add_argument("--mass-kg", type=_mass_arg, default=None, metavar="M",
                   help="the subject's mass for every clip (default: the clip's or its sidecar's mass_kg, "
                        "else the character's nominal mass)")
    p.add_argument("--camera", choices=("estimate", "default"), default="estimate",
                   help="the camera of clips without extrinsics (no sidecar 'extrinsics'): 'estimate' "
                        "(default): its tilt and height above the floor estimated from the person "
                        "(jmocap.methods.floor), else the default camera; 'default': a level camera 1 m "
                        "above the floor. The result's extrinsics_source says which")
    p.add_argument("--scene", metavar="FILE",
                   help="the terrain (a jmocap-scene-1 JSON file: boxes for steps, stairs, platforms; "
                        "docs/formats.md 'Scenes') of every clip that carries none, in the world frame of "
                        "the clips' given extrinsics: trajopt fits the feet to it and the result keeps it")
    p.add_argument("--bvh", action="store_true", help="also write <name>.bvh per clip")
    p.add_argument("--max-clips", type=int, metavar="N", help="process at most N clips this run")
    p.add_argument("--cache-dir", default=_xla_cache_dir(), metavar="DIR",
                   help="persistent XLA compilation cache ('' for none; default %(default)s)")
    p.add_argument("--limit", action="append", metavar="NAME=VALUE", default=[],
                   help="raise or lower a limit on the input (repeatable; sizes take K/M/G): "
                        + ", ".join(f"{k}={v}" for k, v in _limit_defaults().items())
                        + " (docs/formats.md, 'Limits')")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    g = p.add_argument_group("cluster", "run on a Ray cluster (pip install 'jmocap[ray]'; docs/performance.md, "
                                        "'Archives larger than one machine')")
    g.add_argument("--engine", choices=("local", "ray"), default="local",
                   help="'local' (default): this process; 'ray': clips read and reconstructed by Ray actors, "
                        "results written here, the same files and manifest (either engine resumes the other)")
    g.add_argument("--address", metavar="ADDR",
                   help="with --engine ray: a running cluster ('auto', HOST:PORT or ray://HOST:PORT); default: "
                        "a local Ray instance started for the run")
    g.add_argument("--workers", type=int, metavar="N",
                   help="with --engine ray: reconstruction actors (default: the cluster's CPUs / --cpus-per-worker)")
    g.add_argument("--cpus-per-worker", type=float, default=1.0, metavar="C",
                   help="with --engine ray: CPUs per actor (default 1; C >= 2 on a CPU: C host devices)")
    g.add_argument("--gpus-per-worker", type=float, default=0.0, metavar="G",
                   help="with --engine ray: GPUs per actor (default 0; below 1 actors share a GPU, JAX's "
                        "memory preallocation off)")
    g.add_argument("--readers", type=int, default=1, metavar="N",
                   help="with --engine ray: actors reading and checking clips (default 1)")
    p.epilog = (
        "exit status: 0 every clip has a result; 1 some clips failed (listed in manifest.jsonl and "
        "summary.json); 2 bad arguments, or an input / output that cannot be used at all; 130 / 143 "
        "stopped by SIGINT / SIGTERM (finished results and summary.json are written)."
    )
    p.set_defaults(func=cmd_reconstruct)


def _limit_defaults() -> dict[str, int]:
    import dataclasses

    from jmocap.data.limits import Limits

    return dataclasses.asdict(Limits())


def set_host_devices(n: int) -> bool:
    """:func:`jmocap.pipeline.set_host_devices` (kept here: the commands' name for it)."""
    from jmocap.pipeline import set_host_devices as _set

    return _set(n)


def cmd_reconstruct(args) -> int:
    try:
        set_host_devices(args.host_devices)
    except ValueError as e:
        print(f"jmocap reconstruct: {e}", file=sys.stderr)
        return 2
    return run_reconstruct(args)


def run_reconstruct(args) -> int:
    """``jmocap reconstruct``: 0 when every clip has a result, 1 when some failed, 2 on bad
    arguments or an unusable input / output, 130 / 143 after SIGINT / SIGTERM."""
    import jax

    from jmocap.batch import BatchOptions, Interrupted, reconstruct_archive
    from jmocap.data.limits import Limits
    from jmocap.progress import progress_bar
    from jmocap.weights import check_params, load_run_params

    if args.cache_dir and not jax.config.jax_compilation_cache_dir:
        jax.config.update("jax_compilation_cache_dir", args.cache_dir)
    from jmocap.batch_imu import is_imu_archive

    if is_imu_archive(args.input):
        if getattr(args, "engine", "local") != "local":
            print("jmocap reconstruct: --engine ray reconstructs 2D keypoint clips; an IMU archive runs with "
                  "the local engine", file=sys.stderr)
            return 2
        return _reconstruct_imu(args)
    try:
        if args.kinematic_only and args.method not in (None, "kinematic"):
            raise ValueError(f"--kinematic-only contradicts --method {args.method}")
        method = "kinematic" if args.kinematic_only else (args.method or _default_method())
        params, config = load_run_params(args.params, args.config, method)
        check_params(params, config, method)
        limits = Limits.parse(getattr(args, "limit", None))
        if min(args.chunk, args.bucket, args.batch) < 1 or (args.max_clips is not None and args.max_clips < 0):
            raise ValueError("--chunk, --bucket and --batch must be >= 1, --max-clips >= 0")
        scene = None
        if getattr(args, "scene", None):
            from pathlib import Path

            from jmocap.scene import parse_scene

            scene = parse_scene(Path(args.scene).read_text(), args.scene)
        options = BatchOptions(
            chunk=args.chunk, bucket=args.bucket, batch=args.batch, image_size=args.image_size,
            bvh=args.bvh, max_clips=args.max_clips, height_m=getattr(args, "height_m", "auto"),
            mass_kg=getattr(args, "mass_kg", None), camera=getattr(args, "camera", "estimate"), scene=scene,
        )
        engine = getattr(args, "engine", "local")
        if engine == "local" and any(getattr(args, k, None) not in (None, d) for k, d in
                                     (("address", None), ("workers", None), ("cpus_per_worker", 1.0),
                                      ("gpus_per_worker", 0.0), ("readers", 1))):
            raise ValueError("--address, --workers, --cpus-per-worker, --gpus-per-worker and --readers need "
                             "--engine ray")
        if engine == "ray":
            from jmocap.batch_ray import RayOptions, reconstruct_archive_ray

            ray_options = RayOptions(address=args.address, workers=args.workers, cpus_per_worker=args.cpus_per_worker,
                                     gpus_per_worker=args.gpus_per_worker, readers=args.readers)
            summary = reconstruct_archive_ray(
                args.input, args.output, params, config, options, ray_options, method=method,
                progress=progress_bar("reconstruct", not args.quiet), limits=limits,
            )
        else:
            summary = reconstruct_archive(
                args.input, args.output, params, config, options, method=method,
                progress=progress_bar("reconstruct", not args.quiet), limits=limits,
            )
    except (KeyboardInterrupt, Interrupted) as e:
        status = e.exit_status if isinstance(e, Interrupted) else 130
        print(f"\njmocap reconstruct: interrupted ({'SIGINT' if status == 130 else 'SIGTERM'}); finished results "
              f"and summary.json are in {args.output}; run the same command again to resume", file=sys.stderr)
        return status
    except (OSError, ValueError, RuntimeError) as e:  # ArchiveError is a ValueError
        msg = " ".join(str(e).split()) or type(e).__name__
        print(f"jmocap reconstruct: {msg}", file=sys.stderr)
        return 2
    r = summary["run"]
    print(
        f"jmocap reconstruct: {summary['ok']}/{summary['clips']} clips ok, {summary['failed']} failed "
        f"({r['ok']} done and {r['failed']} failed this run, {r['skipped']} already done); "
        f"{r['frames']} frames in {r['seconds']:.1f} s ({r['clips_per_s'] or 0:.2f} clips/s, "
        f"{r['frames_per_s'] or 0:.0f} frames/s) -> {args.output}"
    )
    for f in summary["failures"][:10]:
        print(f"  failed: {f['error']}", file=sys.stderr)
    if summary.get("warnings"):
        print(f"  {summary['warnings']} clips reconstructed with warnings (manifest.jsonl 'warnings')", file=sys.stderr)
    if summary.get("skipped_files"):
        print(f"  {summary['skipped_files']} files are not clips and were skipped (summary.json 'skipped')",
              file=sys.stderr)
    return 0 if summary["failed"] == 0 and summary["pending"] == 0 else 1


def _reconstruct_imu(args) -> int:
    """``jmocap reconstruct`` on an archive of six-IMU clips: PIP (``jmocap.methods.pip_imu``)."""
    from jmocap.batch_imu import METHOD, reconstruct_imu_archive
    from jmocap.methods import pip_imu as PI
    from jmocap.progress import progress_bar

    try:
        if args.method not in (None, "pip", METHOD) or args.kinematic_only:
            raise ValueError(f"{args.input} holds IMU clips: their method is pip ({METHOD}), not "
                             f"{args.method or 'kinematic'}")
        if args.mass_kg is not None or args.height_m not in ("auto", "nominal") or args.image_size:
            raise ValueError(f"{args.input} holds IMU clips: each is reconstructed on its own subject (height_m, "
                             "mass_kg in the clip, else the nominal character); --height-m H, --mass-kg and "
                             "--image-size apply to 2D clips only")
        params, net = PI.load_params(args.params) if args.params else PI.load_params()
        config = PI.PIPIMUConfig(net=net)
        if args.config:
            from jmocap.weights import _config_overrides

            config = config.replace(pip=config.pip.replace(**_config_overrides(args.config)))
        summary = reconstruct_imu_archive(args.input, args.output, params, config, bucket=args.bucket,
                                          max_clips=args.max_clips, bvh=args.bvh,
                                          progress=progress_bar("reconstruct", not args.quiet))
    except KeyboardInterrupt:
        print(f"\njmocap reconstruct: interrupted (SIGINT); finished results are in {args.output}; run the same "
              "command again to resume", file=sys.stderr)
        return 130
    except (OSError, ValueError, RuntimeError, TypeError) as e:
        msg = " ".join(str(e).split()) or type(e).__name__
        print(f"jmocap reconstruct: {msg}", file=sys.stderr)
        return 2
    r = summary["run"]
    print(f"jmocap reconstruct ({METHOD}): {summary['ok']}/{summary['clips']} IMU clips ok, {summary['failed']} failed "
          f"({r['ok']} done and {r['failed']} failed this run, {r['skipped']} already done); {r['frames']} frames "
          f"in {r['seconds']:.1f} s -> {args.output}")
    for f in summary["failures"][:10]:
        print(f"  failed: {f['error']}", file=sys.stderr)
    return 0 if summary["failed"] == 0 and summary["pending"] == 0 else 1


def _default_method() -> str:
    from jmocap.methods import DEFAULT_METHOD

    return DEFAULT_METHOD


def _method_list() -> str:
    from jmocap.methods import method_names

    return ", ".join(method_names())


# =========================================================================================
# jmocap video
# =========================================================================================


def _positive_float(text: str) -> float:
    v = _number_in(text, 1e-6, 1e6)
    if v is None:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def _unit_float(text: str) -> float:
    v = _number_in(text, 0.0, 1.0)
    if v is None:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}")
    return v


def _count_arg(text: str) -> int:
    try:
        n = int(text)
        if n >= 0:
            return n
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")


def _person_arg(text: str) -> str:
    t = text.strip().lower()
    if t in ("largest", "all") or (t.isdigit()):
        return t
    raise argparse.ArgumentTypeError(f"expected 'largest', 'all' or a track number K >= 0, got {text!r}")


def _video_height_arg(text: str) -> float:
    h = _number_in(text, 0.5, 2.5)
    if h is None:
        raise argparse.ArgumentTypeError(f"expected a height in metres in [0.5, 2.5], got {text!r}")
    return h


@command("video", "from a video file: 2D keypoints (BlazePose), a reconstruction and an overlay video")
def _video(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Run a 2D pose detector (BlazePose, shipped with jmocap, on the CPU, offline) on every frame "
        "of VIDEO, track the people across frames (one clip per person, left/right flips repaired), "
        "and write into OUTPUT: keypoints/<video>_p<K>.npz (a BODY_25 jmocap clip) with its camera "
        "sidecar, results/ (jmocap reconstruct of those clips: result .npz, manifest.jsonl, "
        "summary.json), <video>_p<K>_overlay.mp4 (the reconstruction drawn over the video) and "
        "video.json (what was found). Needs the video extra: pip install 'jmocap[video]' "
        "(docs/formats.md, 'Video input')."
    )
    p.add_argument("video", help="a video file ffmpeg reads (.mp4, .mov, .avi, .mkv, ...)")
    p.add_argument("output", help="output folder (created; must be empty or a previous jmocap video output "
                                  "with --overwrite)")
    p.add_argument("--camera", metavar="FILE",
                   help="camera file in any form jmocap reads (K, dist, R/t, rvec/tvec, ...; docs/formats.md "
                        "'Camera sidecar'), for the video's image size; default: f = 1000 px, principal point at "
                        "the centre, recorded as assumed")
    p.add_argument("--person", type=_person_arg, default="largest", metavar="largest|all|K",
                   help="which tracked person to reconstruct: 'largest' (default: the one seen largest and longest, "
                        "the sum of its body size in pixels over its frames), 'all', or track K (numbered by first "
                        "frame, then left to right; video.json lists them)")
    p.add_argument("--method", default=None, metavar="NAME",
                   help=f"reconstruction method or variant (default {_default_method()}): {_method_list()}")
    p.add_argument("--params", help="parameters (.msgpack); default: the shipped weights")
    p.add_argument("--height", type=_video_height_arg, default=None, metavar="M",
                   help="the subject's height in metres (written into the clip; default: estimated from the 2D "
                        "keypoints when the camera file has extrinsics, else the nominal 1.75 m character)")
    p.add_argument("--fps", type=_positive_float, default=None,
                   help="frame rate (default: the camera file's, else the video's)")
    p.add_argument("--detect-every", type=_count_arg, default=15, metavar="N",
                   help="run the person detector every N frames to find new people (default 15; 0: only at the "
                        "start, while nobody is tracked and when a track is lost)")
    p.add_argument("--min-score", type=_unit_float, default=0.5, metavar="S",
                   help="detector score to accept a person (default 0.5, MediaPipe's)")
    p.add_argument("--min-presence", type=_unit_float, default=0.5, metavar="P",
                   help="pose-presence score below which a track is lost in a frame (default 0.5, MediaPipe's)")
    p.add_argument("--max-gap", type=_count_arg, default=15, metavar="N",
                   help="frames a lost track may miss and still continue (written as missing; default 15); a "
                        "longer gap splits it into two tracks")
    p.add_argument("--min-frames", type=_count_arg, default=10, metavar="N",
                   help="tracks with fewer frames with a pose are dropped (default 10)")
    p.add_argument("--no-flip-repair", action="store_true", help="keep the detector's left/right labels")
    p.add_argument("--no-overlay", action="store_true", help="no overlay video")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a previous jmocap video output in OUTPUT (its keypoints/, results/ and overlays)")
    p.add_argument("--host-devices", type=int, default=0, metavar="N",
                   help="as jmocap reconstruct --host-devices (default 0: one per CPU core)")
    p.add_argument("--cache-dir", default=_xla_cache_dir(), metavar="DIR",
                   help="persistent XLA compilation cache ('' for none; default %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.epilog = (
        "exit status: 0 every chosen person reconstructed (and drawn); 1 a reconstruction or an overlay "
        "failed; 2 bad arguments, or a video / camera file / OUTPUT that cannot be used (missing, not a "
        "video, nobody found); 130 / 143 stopped by SIGINT / SIGTERM."
    )
    p.set_defaults(func=cmd_video)


def _prepare_video_output(out, overwrite: bool) -> None:
    """OUTPUT must be absent, empty, or (with ``overwrite``) a previous ``jmocap video`` output,
    whose keypoints/, results/ and overlays are removed (nothing else is touched)."""
    import shutil
    from pathlib import Path

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: OUTPUT is a file, not a folder")
    if not out.exists() or not any(out.iterdir()):
        return
    summary = out / "video.json"
    if not summary.is_file():
        raise ValueError(f"{out}: OUTPUT is not empty and holds no jmocap video output (video.json); choose "
                         "an empty or new folder")
    if not overwrite:
        raise ValueError(f"{out}: OUTPUT holds a previous jmocap video output; pass --overwrite to replace it")
    try:
        previous = json.loads(summary.read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{summary}: unreadable ({e}); remove the folder yourself") from None
    for name in ("keypoints", "results"):
        if (out / name).is_dir():
            shutil.rmtree(out / name)
    for f in previous.get("overlays", []) if isinstance(previous, dict) else []:
        p = out / Path(str(f)).name
        if p.suffix == ".mp4" and p.is_file():
            p.unlink()
    summary.unlink()


def cmd_video(args) -> int:
    """``jmocap video``: 0 when every chosen person has a result (and an overlay), 1 when a
    reconstruction or an overlay failed, 2 on an unusable input, 130 / 143 after a signal."""
    from pathlib import Path

    from jmocap.data.clip import FormatError
    from jmocap.video import missing_video_packages
    from jmocap.video.extract import VideoOptions, extract_clips, write_overlays, write_summary
    from jmocap.video.reader import VideoError
    from jmocap.video.tracking import TrackOptions

    where = "jmocap video"
    missing = missing_video_packages()
    if missing:
        print(f"{where}: needs {', '.join(missing)}, not installed; video input is the optional video extra: "
              "pip install 'jmocap[video]'", file=sys.stderr)
        return 2
    try:
        set_host_devices(args.host_devices)
    except ValueError as e:
        print(f"{where}: {e}", file=sys.stderr)
        return 2
    out = Path(args.output)
    try:
        if args.camera is not None and not Path(args.camera).is_file():
            raise FileNotFoundError(f"{args.camera}: no such camera file")
        _prepare_video_output(out, args.overwrite)
        options = VideoOptions(
            person=args.person, fps=args.fps, camera=args.camera, height_m=args.height,
            track=TrackOptions(min_detection_score=args.min_score, min_presence=args.min_presence,
                               detect_every=args.detect_every, max_gap=args.max_gap, min_frames=args.min_frames),
            repair_flips=not args.no_flip_repair,
        )
        bars = []

        def progress(t, total):  # the bar starts with the first frame, when the video's length is known
            if not bars:
                bars.append(Progress(total or 0, "video: detect + track", enabled=not args.quiet, unit="frame"))
            bars[0].update(1)

        try:
            summary = extract_clips(args.video, out / "keypoints", options, progress=progress)
        finally:
            for b in bars:
                b.close()
    except KeyboardInterrupt:
        print(f"\n{where}: interrupted", file=sys.stderr)
        return 130
    except (FileNotFoundError, VideoError, FormatError, ValueError, OSError, ImportError) as e:
        print(f"{where}: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    write_summary(out / "video.json", summary)

    rec = argparse.Namespace(
        input=str(out / "keypoints"), output=str(out / "results"), params=args.params, method=args.method,
        config=None, kinematic_only=False, chunk=256, bucket=64, batch=8, host_devices=args.host_devices,
        image_size=None, height_m="auto", mass_kg=None, bvh=False, max_clips=None, cache_dir=args.cache_dir,
        limit=[], quiet=args.quiet,
    )
    status = run_reconstruct(rec)
    if status in (130, 143):
        return status
    overlays = []
    if not args.no_overlay:
        from jmocap.viz import RenderError

        try:
            overlays = write_overlays(args.video, summary["clips"], out / "results", out)
        except (RenderError, ImportError, ValueError, OSError) as e:
            print(f"{where}: overlay: {' '.join(str(e).split())}", file=sys.stderr)
            status = max(status, 1)
    summary["results"] = str(out / "results")
    summary["overlays"] = [str(p) for p in overlays]
    summary["reconstruct_status"] = status
    write_summary(out / "video.json", summary)
    tracks = summary["tracks"]
    chosen = [t for t in tracks if "clip" in t]
    print(
        f"{where}: {summary['frames']} frames ({summary['fps']:g} fps, {summary['ms_per_frame']:.0f} ms/frame detect + "
        f"track), {len(tracks)} track(s), {len(chosen)} person(s) reconstructed; flips repaired in "
        f"{sum(t['flipped_frames'] for t in chosen)} frames, {sum(t['frames_lost'] for t in chosen)} frames lost "
        f"(written as missing); camera {'assumed (f = 1000 px)' if summary['assumed'] else 'from ' + str(args.camera)} "
        f"-> {out}"
    )
    for t in tracks:
        print(f"  person {t['person']}: frames {t['start']}-{t['end']}, {t['frames_with_pose']} with a pose, "
              f"{t['frames_lost']} lost, {t['flipped_frames']} flipped, ~{t['size_px']:.0f} px"
              + (f" -> {t['clip']}" if "clip" in t else ""))
    if not args.no_overlay and len(overlays) < len(summary["clips"]):
        status = max(status, 1)
    return status


@command("demo", "reconstruct, score and render the sample shipped in the package")
def _demo(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Run the whole pipeline on the shipped sample (three synthetic clips as OpenPose JSON, "
        "with ground truth) with the shipped default weights: result .npz and BVH per clip, "
        "metrics against the ground truth (physionical vs kinematic), a video of the walking "
        "clip and its force plot, all in OUT."
    )
    p.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    p.add_argument("--params", help="parameters (.msgpack); default: the shipped weights")
    p.add_argument("--no-render", action="store_true", help="skip the video and the force plot")
    p.add_argument("--cache-dir", default=_xla_cache_dir(), metavar="DIR",
                   help="persistent XLA compilation cache ('' for none; default %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_demo)


def cmd_demo(args) -> int:
    import jax

    from jmocap.demo import run_demo

    if args.cache_dir and not jax.config.jax_compilation_cache_dir:
        jax.config.update("jax_compilation_cache_dir", args.cache_dir)
    run_demo(args.out, params_path=args.params, render=not args.no_render, progress=not args.quiet)
    return 0


# =========================================================================================
# jmocap train
# =========================================================================================


@command("train", "train TPNet, DyNet and GRFNet from a training config, on one or several processes")
def _train(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Run (or resume from OUT/checkpoint/) the staged training of a TrainConfig JSON "
        "(jmocap.train; e.g. experiments/configs/default.json). Several processes, e.g. one per "
        "host, train one data-parallel run: start this command in each with the same config, "
        "--coordinator HOST:PORT (process 0's host and a free port there), --num-processes N and "
        "its own --process-id I, or with --distributed to read them from the cluster environment "
        "(SLURM, Open MPI). OUT must be a folder all processes share; a run resumes on any number "
        "of processes."
    )
    p.add_argument("--config", required=True, metavar="JSON", help="TrainConfig as JSON")
    p.add_argument("--out", help="output folder (default: the config's out)")
    p.add_argument("--coordinator", metavar="HOST:PORT", help="process 0's host and a free port on it")
    p.add_argument("--num-processes", type=int, metavar="N", help="processes of the run")
    p.add_argument("--process-id", type=int, metavar="I", help="this process, 0 .. N-1")
    p.add_argument("--distributed", action="store_true",
                   help="a multi-process run whose processes JAX finds in the cluster environment (e.g. SLURM)")
    p.add_argument("--cache-dir", default=_xla_cache_dir(), metavar="DIR",
                   help="persistent XLA compilation cache ('' for none; default %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train)


def cmd_train(args) -> int:
    import dataclasses
    from pathlib import Path

    explicit = [a is not None for a in (args.coordinator, args.num_processes, args.process_id)]
    if any(explicit) and not all(explicit):
        print("jmocap train: give --coordinator, --num-processes and --process-id together (or none)", file=sys.stderr)
        return 2
    if any(explicit) and args.distributed:
        print("jmocap train: --distributed reads the processes from the environment; not with --coordinator",
              file=sys.stderr)
        return 2
    import jax

    from jmocap.train import TrainConfig, initialize_distributed, train

    try:
        if any(explicit) or args.distributed:  # before anything else uses JAX
            initialize_distributed(args.coordinator, args.num_processes, args.process_id)
        config = TrainConfig.from_json(json.loads(Path(args.config).read_text()))
    except (OSError, ValueError, TypeError) as e:
        print(f"jmocap train: {e}", file=sys.stderr)
        return 2
    if args.out:
        config = dataclasses.replace(config, out=args.out)
    if args.cache_dir and not jax.config.jax_compilation_cache_dir:
        jax.config.update("jax_compilation_cache_dir", args.cache_dir)
    try:
        train(config, progress=not args.quiet)
    except (FileNotFoundError, ValueError) as e:
        print(f"jmocap train: {e}", file=sys.stderr)
        return 2
    if jax.process_index() == 0:
        print(f"jmocap train: {len(config.stages)} stage(s) on {jax.process_count()} process(es), "
              f"{jax.device_count()} device(s) -> {config.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
