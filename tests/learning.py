"""The learning check every algorithm passes: a short run on the Pendulum dataset beats the
untrained policy by a clear margin."""

from __future__ import annotations

import numpy as np

from eabc.training import lifecycle, trainer
from eabc.training.config import TrainConfig

MARGIN = 30.0
"""Normalised points the late evaluations must gain over the untrained policy."""


def late_gain(
    tmp_path, dataset, algo: str, overrides: dict, batch_size: int | None = None
) -> tuple[float, float, dict]:
    """``(untrained score, mean score at steps 2000 and 3000, every evaluation)`` of a 3000-step
    run with 64-64 networks, on batches of ``batch_size`` (None: the algorithm's own)."""
    config = TrainConfig(
        dataset="pendulum-swingup",
        algo=algo,
        batch_size=batch_size,
        steps=3000,
        log_interval=100,
        eval_interval=1000,
        checkpoint_interval=1000,
        eval_episodes=5,
        env="Pendulum-v1",
    )
    run = lifecycle.start(config, tmp_path / algo, {"hidden_dims": (64, 64), **overrides}, dataset)
    untrained = trainer.evaluate(run)["score"]
    trainer.train(run, progress=False)
    late = float(np.mean([run.state["evaluations"][s]["score"] for s in ("2000", "3000")]))
    return untrained, late, run.state["evaluations"]
