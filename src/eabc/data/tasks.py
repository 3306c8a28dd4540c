"""What we know about D4RL's MuJoCo tasks: environments, reference returns, and the paper's p per dataset."""

from __future__ import annotations

import dataclasses
import re


@dataclasses.dataclass(frozen=True)
class EnvInfo:
    env_id: str
    """Gymnasium id used for evaluation (the closest match of D4RL's -v2 task)."""
    ref_min_score: float
    """D4RL's return of a random policy."""
    ref_max_score: float
    """D4RL's return of an expert policy."""


ENVS: dict[str, EnvInfo] = {
    "hopper": EnvInfo("Hopper-v4", -20.272305, 3234.3),
    "halfcheetah": EnvInfo("HalfCheetah-v4", -280.178953, 12135.0),
    "walker2d": EnvInfo("Walker2d-v4", 1.629008, 4592.3),
    "ant": EnvInfo("Ant-v4", -325.6, 3879.7),
}

KINDS = ("random", "medium", "expert", "medium-replay", "medium-expert")

# Table 3 of the paper: the best confidence level p per (environment, dataset kind).
CONFIDENCE_LEVEL: dict[tuple[str, str], float] = {
    ("halfcheetah", "expert"): 0.5,
    ("hopper", "expert"): 1.0,
    ("walker2d", "expert"): 0.5,
    ("halfcheetah", "medium-expert"): 1.0,
    ("hopper", "medium-expert"): 0.5,
    ("walker2d", "medium-expert"): 0.25,
    ("halfcheetah", "medium"): 0.0,
    ("hopper", "medium"): 0.25,
    ("walker2d", "medium"): 0.25,
    ("halfcheetah", "medium-replay"): 0.0,
    ("hopper", "medium-replay"): 0.0,
    ("walker2d", "medium-replay"): 0.0,
    ("halfcheetah", "random"): 0.0,
    ("hopper", "random"): 0.0,
    ("walker2d", "random"): 0.95,
}

# SPEC section 5: q of the authors' earlier quantile BC rule per (environment, dataset kind).
QUANTILE_LEVEL: dict[tuple[str, str], float] = {
    ("halfcheetah", "expert"): 1.0,
    ("hopper", "expert"): 0.9,
    ("walker2d", "expert"): 1.0,
    ("halfcheetah", "medium-expert"): 1.0,
    ("hopper", "medium-expert"): 0.9,
    ("walker2d", "medium-expert"): 1.0,
    ("halfcheetah", "medium"): 0.05,
    ("hopper", "medium"): 0.9,
    ("walker2d", "medium"): 1.0,
    ("halfcheetah", "medium-replay"): 0.05,
    ("hopper", "medium-replay"): 0.45,
    ("walker2d", "medium-replay"): 0.0,
    ("halfcheetah", "random"): 0.05,
    ("hopper", "random"): 0.05,
    ("walker2d", "random"): 0.0,
}

_NAME = re.compile(
    r"(?P<env>hopper|halfcheetah|walker2d|ant)[-_/]"
    r"(?P<kind>medium[-_]replay|medium[-_]expert|random|medium|expert)(?![a-z])"
)


def parse_task(text: str) -> tuple[str, str] | None:
    """Find ``(env, kind)`` in a dataset name, file name or Minari id, e.g.
    ``hopper_medium_replay-v2.hdf5``, ``mujoco/hopper/medium-v0``, ``eabc/hopper/medium-v0``."""
    match = _NAME.search(text.lower())
    if match is None:
        return None
    return match["env"], match["kind"].replace("_", "-")


def default_confidence_level(task: tuple[str, str] | None) -> float | None:
    return None if task is None else CONFIDENCE_LEVEL.get(task)


def default_quantile_level(task: tuple[str, str] | None) -> float | None:
    return None if task is None else QUANTILE_LEVEL.get(task)


def normalized_score(episode_return: float, ref_min_score: float, ref_max_score: float) -> float:
    """D4RL's normalised score: 0 is a random policy, 100 an expert."""
    return 100.0 * (episode_return - ref_min_score) / (ref_max_score - ref_min_score)
