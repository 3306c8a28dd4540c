"""Using a trained policy outside the training loop: :func:`load_policy` reads a run directory.

It sits above the training layer (it reads the training's checkpoints); the policy itself,
:class:`eabc.evaluation.Policy`, is NumPy only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eabc import pytree
from eabc.agents import get_algorithm
from eabc.data.dataset import Normalizer
from eabc.evaluation import Policy
from eabc.training import checkpoint
from eabc.training.checkpoint import read_config


def load_policy(run_dir: str | Path) -> Policy:
    """The policy of the latest checkpoint in ``run_dir``.

    The observation normaliser stored in the checkpoint is applied inside, so the callable takes
    raw environment observations.
    """
    run_dir = Path(run_dir)
    config = read_config(run_dir)
    algorithm = get_algorithm(config["train"]["algo"])
    raw = checkpoint.check_layout(
        checkpoint.load_raw(run_dir), run_dir, algorithm.name, algorithm.state_layout
    )
    actor = {k: np.asarray(v) for k, v in pytree.find(raw["agent"], "actor").items()}
    normalizer = Normalizer(
        np.asarray(raw["normalizer"]["mean"]), np.asarray(raw["normalizer"]["std"])
    )
    return Policy(actor, normalizer, config["max_action"], algorithm.gaussian_actor)
