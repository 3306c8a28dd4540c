"""How sparse goal rewards are trained on: a run's ``reward_convention``, recorded in its
config.json.

AntMaze data store D4RL's 0/1 rewards and carry a ``reward_offset`` (-1): they are the data this
applies to. The published code of the algorithms does not agree on what to train on:

- ``minus-one``: ``r - 1`` (0 at the goal, -1 elsewhere), the data's own offset, as CORL's
  ``modify_reward`` does;
- ``raw``: the stored 0/1;
- any convention an algorithm's file defines (``Algorithm.reward_conventions``: a rule applied
  to the 0/1 rewards), which a run of any algorithm may choose.

Each algorithm's default is its description's ``reward_convention`` (docs/algorithms.md names the
source of each); data without a reward offset (the MuJoCo datasets) are trained on as the
algorithm preprocesses them, whatever the setting.
"""

from __future__ import annotations

import dataclasses

from eabc.agents import ALGORITHMS
from eabc.agents.contract import Algorithm
from eabc.data.dataset import Dataset

RULES = {name: rule for a in ALGORITHMS.values() for name, rule in a.reward_conventions.items()}
"""The conventions that algorithms' files define, by name: ``rule(dataset) -> dataset``."""
CONVENTIONS = ("minus-one", "raw", *RULES)
LEGACY = "minus-one"
"""What every run trained on before the setting existed (its config.json has none)."""


def default(algo: str) -> str:
    """The reward convention ``algo`` trains on unless told otherwise."""
    return ALGORITHMS[algo].reward_convention if algo in ALGORITHMS else LEGACY


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
    convention = check(convention or algorithm.reward_convention)
    if convention == "minus-one":
        return dataset.training_view()  # the data's own offset, -1
    raw = dataclasses.replace(dataset, reward_offset=None)
    return raw if convention == "raw" else RULES[convention](raw)
