"""One process of a multi-process training run, started by tests/test_train_distributed.py:

    python tests/distributed_worker.py CONFIG.json RESULT.npz \\
        --coordinator HOST:PORT --num-processes N --process-id I [--stop-after K]

Joins the run (:func:`jmocap.train.initialize_distributed`), trains the TrainConfig of
CONFIG.json and writes the parameters this process ends with to RESULT.npz (the leaves in tree
order, ``leaf_0``, ``leaf_1``, ...). With ``--stop-after K`` the run is interrupted before its
(K+1)-th batch (the sampler raises, in every process at the same step), as a run killed after its
last checkpoint would be; RESULT.npz is then not written and the exit status is 3.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import numpy as np

from jmocap.train import TrainConfig, TrainingSet, initialize_distributed, train
from test_train import (  # (this script runs from tests/: an interruption mid-stage)
    _Interrupted,
    _StopAfter,
)

INTERRUPTED = 3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("config")
    ap.add_argument("result")
    ap.add_argument("--coordinator", required=True)
    ap.add_argument("--num-processes", type=int, required=True)
    ap.add_argument("--process-id", type=int, required=True)
    ap.add_argument("--stop-after", type=int)
    args = ap.parse_args(argv)
    initialize_distributed(args.coordinator, args.num_processes, args.process_id)
    config = TrainConfig.from_json(json.loads(Path(args.config).read_text()))
    data = TrainingSet.load(config.data, config)
    if args.stop_after is not None:
        data = _StopAfter(data, args.stop_after)
    try:
        params = train(config, progress=False, data=data)
    except _Interrupted:
        return INTERRUPTED
    np.savez(args.result, **{f"leaf_{i}": x for i, x in enumerate(jax.tree.leaves(params))})
    return 0


if __name__ == "__main__":
    sys.exit(main())
