"""Using a trained policy outside the training loop."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eabc import networks
from eabc.agents import get_algorithm
from eabc.data.dataset import Normalizer
from eabc.training import checkpoint
from eabc.training.checkpoint import read_config


class Policy:
    """A deterministic policy from raw observations to actions (normalisation inside). NumPy only."""

    def __init__(
        self,
        actor: dict[str, np.ndarray],
        normalizer: Normalizer,
        max_action: float,
        gaussian: bool = False,
    ):
        self.normalizer = normalizer
        self._act = networks.numpy_actor(actor, max_action, gaussian)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return self._act(self.normalizer(np.asarray(observation, np.float32)))


def load_policy(run_dir: str | Path) -> Policy:
    """The policy of the latest checkpoint in ``run_dir``.

    The observation normaliser stored in the checkpoint is applied inside, so the callable takes
    raw environment observations.
    """
    run_dir = Path(run_dir)
    config = read_config(run_dir)
    raw = checkpoint.load_raw(run_dir)
    actor = {k: np.asarray(v) for k, v in raw["agent"]["actor"].items()}
    normalizer = Normalizer(
        np.asarray(raw["normalizer"]["mean"]), np.asarray(raw["normalizer"]["std"])
    )
    gaussian = get_algorithm(config["train"]["algo"]).gaussian_actor
    return Policy(actor, normalizer, config["max_action"], gaussian)
