"""Train jmocap's shipped default weights from synthetic archives, reproducibly.

    python experiments/train_default.py [--config experiments/configs/default.json] [--ship]

1. Generates the config's training (and validation) archives if missing or short
   (deterministic for their seeds):
   data/contacts_train, 1013 clips of 60-150 frames tracked in MuJoCo simulation (seed 7,
   ``--physics --frames-per-clip 60:150``), the archive the contact estimator trains on
   (``experiments/train_contacts.py`` uses its first 1000); the shipped weights of 2026-12-03
   were trained on these 1013 (earlier weights: 300 kinematic clips of seed 1 and 40 physics
   clips of seed 2). ``configs/tpnet_extended.json`` fine-tunes the shipped weights on
   data/train_ext (800 clips of the extended generator, ``--extended``, seed 8, simulated)
   and validates on data/val_ext (48 kinematic clips of seed 78); ``configs/tpnet_mixed.json``
   continues that run on data/train_ext and data/train_classic (600 kinematic clips of the
   classic generator, seed 9), validated on data/val_ext and data/val; ``configs/tpnet_mixed2.json``
   continues it on those two and data/contacts_train (shipped from stop 37 to 41);
   ``configs/tpnet_mixed3.json`` continues those weights on data/train_classic and
   data/train_ext2 (1500 kinematic clips of the extended generator, seed 10), and
   ``configs/tpnet_mixed4.json`` continues that run (its runs/mixed3/params.msgpack) on those
   two and data/train_ext3 (1500 more, seed 11): the weights shipped since stop 42
   (docs/method.md, "Staged training").
2. Runs the staged training of the config (resumable: re-running continues from the orbax
   checkpoint in runs/default/checkpoint/, or a run's older checkpoint.msgpack; progress in
   runs/default/log.jsonl; on several hosts: ``jmocap train --config ... --coordinator ...``,
   docs/performance.md section 10). The shipped weights of
   2026-12-04 continued the first TPNet stage of a default.json run with
   ``--config experiments/configs/tpnet_finetune.json`` (its ``init``: that run's
   runs/default/params_tpnet.msgpack), i.e. default.json's later stages (docs/method.md).
3. With --ship, writes the result to src/jmocap/assets/default_params.msgpack (float16) and
   the config next to it (the training PhysCapConfig with the config's ``ship_cycle`` changes),
   which `jmocap.weights.default_params()` loads.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ARCHIVES = (
    ("data/contacts_train", 1013, 7, ["--physics", "--frames-per-clip", "60:150"]),
    # the extended generator's training and validation archives (configs/tpnet_extended.json)
    ("data/train_ext", 800, 8, ["--physics", "--extended", "--frames-per-clip", "60:150", "--workers", "2"]),
    ("data/val_ext", 48, 78, ["--extended", "--frames-per-clip", "60:150"]),
    # configs/tpnet_mixed.json: classic kinematic clips beside them, and the validation archive
    ("data/train_classic", 600, 9, ["--frames-per-clip", "60:150", "--workers", "2"]),
    ("data/val", 16, 77, ["--physics"]),
    # configs/tpnet_mixed3.json: more extended clips, kinematic (683-850 frames/s to make)
    ("data/train_ext2", 1500, 10, ["--extended", "--frames-per-clip", "60:150", "--workers", "2"]),
    # configs/tpnet_mixed4.json: 1500 more
    ("data/train_ext3", 1500, 11, ["--extended", "--frames-per-clip", "60:150", "--workers", "2"]),
)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(ROOT / "experiments/configs/default.json"))
    ap.add_argument("--ship", action="store_true", help="copy the trained weights into the package")
    args = ap.parse_args(argv)
    cfg_json = json.loads(Path(args.config).read_text())
    used = set(cfg_json.get("data", [])) | set(cfg_json.get("val_data", []))
    for folder, n, seed, extra in ARCHIVES:
        if folder not in used:
            continue
        if not (ROOT / folder / "manifest.jsonl").exists() or len(list((ROOT / folder).glob("*.npz"))) < n:
            cmd = [sys.executable, "-m", "jmocap.cli", "data", "synth", "--out", folder,
                   "--clips", str(n), "--seed", str(seed), "--quiet", *extra]
            print("+", " ".join(cmd), flush=True)
            subprocess.run(cmd, cwd=ROOT, check=True)

    from jmocap.train import TrainConfig, train
    from jmocap.weights import ship_params

    config = TrainConfig.from_json(cfg_json)
    params = train(config)
    if args.ship:
        shipped = config.cycle.replace(**config.ship_cycle)
        ship_params(params, shipped, source=args.config)
        shutil.copy(args.config, ROOT / "src/jmocap/assets/default_train_config.json")
        print("shipped default weights to src/jmocap/assets/")


if __name__ == "__main__":
    main()
