"""How sparse goal rewards are trained on: a run's ``reward_convention``, recorded in its
config.json.

AntMaze data store D4RL's 0/1 rewards and carry a ``reward_offset`` (-1): they are the data this
applies to. The published code of the algorithms does not agree on what to train on:

- ``minus-one``: ``r - 1`` (0 at the goal, -1 elsewhere), IQL's ``train_offline.py``
  (``dataset.rewards -= 1.0`` for AntMaze) and CORL's ``modify_reward``;
- ``raw``: the stored 0/1, what the authors' TD3+BC code trains on (``TD3_BC/main.py`` changes no
  reward; it has no AntMaze rule);
- ``iql-scale``: IQL's MuJoCo rule, the rewards times ``1000 / (max - min episode return)``
  (:func:`eabc.agents.iql.preprocess`), applied to the 0/1 rewards.

Each algorithm's default is :data:`DEFAULTS` (docs/algorithms.md names the source of each); data
without a reward offset (the MuJoCo datasets) are trained on as the algorithm preprocesses them,
whatever the setting.
"""

from __future__ import annotations

import dataclasses

from eabc.agents import iql
from eabc.agents.contract import Algorithm
from eabc.data.dataset import Dataset

CONVENTIONS = ("minus-one", "raw", "iql-scale")
LEGACY = "minus-one"
"""What every run trained on before the setting existed (its config.json has none)."""
DEFAULTS = {
    "iql": "minus-one",
    "td3bc": "raw",
    "td3": "raw",
    "eabc": "raw",
    "eabc-ln": "raw",
    "eabc-trust": "raw",
    "eabc-robust": "raw",
    "eabc-auto": "raw",
    "eabc-quantile": "raw",
    "bc": "raw",
}
"""Each algorithm's default where its published code (or the code it is built on) says; the
others keep :data:`LEGACY` (see docs/algorithms.md)."""


def default(algo: str) -> str:
    """The reward convention ``algo`` trains on unless told otherwise."""
    return DEFAULTS.get(algo, LEGACY)


def check(convention: str) -> str:
    if convention not in CONVENTIONS:
        raise ValueError(
            f"reward_convention must be one of {', '.join(CONVENTIONS)}, got {convention!r}"
        )
    return convention


def apply(algorithm: Algorithm, dataset: Dataset, convention: str | None = None) -> Dataset:
    """The data as ``algorithm`` trains on them under ``convention`` (None: its default)."""
    if dataset.reward_offset is None:
        return dataset if algorithm.preprocess is None else algorithm.preprocess(dataset)
    convention = check(convention or default(algorithm.name))
    if convention == "minus-one":
        return dataset.training_view()  # the data's own offset, -1
    raw = dataclasses.replace(dataset, reward_offset=None)
    return raw if convention == "raw" else iql.preprocess(raw)
