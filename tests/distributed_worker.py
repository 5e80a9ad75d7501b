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

INTERRUPTED = 3


class Interrupted(Exception):
    pass


class StopAfter:
    """A TrainingSet whose sampler raises after ``n`` batches."""

    def __init__(self, data: TrainingSet, n: int):
        self.data, self.n, self.models = data, n, data.models

    def sample(self, rng, batch, frames):
        if self.n == 0:
            raise Interrupted
        self.n -= 1
        return self.data.sample(rng, batch, frames)


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
        data = StopAfter(data, args.stop_after)
    try:
        params = train(config, progress=False, data=data)
    except Interrupted:
        return INTERRUPTED
    np.savez(args.result, **{f"leaf_{i}": x for i, x in enumerate(jax.tree.leaves(params))})
    return 0


if __name__ == "__main__":
    sys.exit(main())
