"""Using a trained policy outside the training loop: :func:`load_policy` reads a run directory.

It sits above the training layer (it reads the training's checkpoints); the policy itself,
:class:`eabc.evaluation.Policy`, is NumPy only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eabc import pytree
from eabc.data.dataset import Normalizer
from eabc.evaluation import Policy
from eabc.training.directory import read_checkpoint


def load_policy(run_dir: str | Path) -> Policy:
    """The policy of the latest checkpoint in ``run_dir``.

    The observation normaliser stored in the checkpoint is applied inside, so the callable takes
    raw environment observations. A checkpoint of another run (its recorded identity, or its
    actor's shapes, differ from the run's config.json) is refused.
    """
    config, algorithm, raw = read_checkpoint(run_dir)  # this run's own, of its layout and shapes
    actor = {k: np.asarray(v) for k, v in pytree.find(raw["agent"], "actor").items()}
    normalizer = Normalizer(
        np.asarray(raw["normalizer"]["mean"]), np.asarray(raw["normalizer"]["std"])
    )
    return Policy(actor, normalizer, config["max_action"], algorithm.gaussian_actor)
