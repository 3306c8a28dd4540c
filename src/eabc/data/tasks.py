"""What we know about D4RL's tasks: environments, reference returns and training conventions.
What an algorithm's paper sets per task (EABC's p, MOPO's h) lives in the algorithm's own file."""

from __future__ import annotations

import dataclasses
import re
import warnings

import gymnasium as gym


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

ANTMAZE_ENVS: dict[str, EnvInfo] = {
    # D4RL's reference scores for AntMaze are 0 and 1: the normalised score is 100 x success rate.
    "umaze": EnvInfo("eabc/AntMaze-UMaze-v0", 0.0, 1.0),
    "medium": EnvInfo("eabc/AntMaze-Medium-v0", 0.0, 1.0),
    "large": EnvInfo("eabc/AntMaze-Large-v0", 0.0, 1.0),
}
"""The evaluation environment of each AntMaze maze (:mod:`eabc.data.antmaze`)."""
ANTMAZE_KINDS = ("umaze", "umaze-diverse", "medium-play", "medium-diverse", "large-play",
                 "large-diverse")  # fmt: skip
"""D4RL's six AntMaze datasets, ``antmaze-KIND``: the maze, then how starts and goals were chosen."""
REWARD_OFFSET: dict[str, float] = {"antmaze": -1.0}
"""Added to the stored rewards for training, per environment: AntMaze's sparse 0/1 rewards become
-1/0 as IQL and CORL train on them (``eabc.data.mazes.training_rewards``)."""

_NAME = re.compile(
    r"(?P<env>hopper|halfcheetah|walker2d|ant)[-_/]"
    r"(?P<kind>medium[-_]replay|medium[-_]expert|random|medium|expert)(?![a-z])"
)
_ANTMAZE = re.compile(
    r"antmaze[-_/](?P<maze>umaze|medium|large)(?:[-_](?P<family>diverse|play))?(?![a-z])"
)


def parse_task(text: str) -> tuple[str, str] | None:
    """Find ``(env, kind)`` in a dataset name, file name or Minari id, e.g.
    ``hopper_medium_replay-v2.hdf5``, ``mujoco/hopper/medium-v0``, ``eabc/hopper/medium-v0``;
    AntMaze's are ``("antmaze", "medium-play")`` (``antmaze-medium-play-v2``,
    ``D4RL/antmaze/medium-play-v1``)."""
    text = text.lower()
    antmaze = _ANTMAZE.search(text)
    if antmaze is not None:
        return "antmaze", "-".join(p for p in (antmaze["maze"], antmaze["family"]) if p)
    match = _NAME.search(text)
    if match is None:
        return None
    return match["env"], match["kind"].replace("_", "-")


def env_info(task: tuple[str, str] | None) -> EnvInfo | None:
    """The evaluation environment and reference scores of a task (None if unknown)."""
    if task is None:
        return None
    if task[0] == "antmaze":
        return ANTMAZE_ENVS.get(task[1].split("-")[0])
    return ENVS.get(task[0])


def antmaze_env_ids() -> set[str]:
    return {info.env_id for info in ANTMAZE_ENVS.values()}


def reward_offset(task: tuple[str, str] | None) -> float | None:
    """What training adds to the task's rewards (None: train on them as they are)."""
    return None if task is None else REWARD_OFFSET.get(task[0])


def normalized_score(episode_return: float, ref_min_score: float, ref_max_score: float) -> float:
    """D4RL's normalised score: 0 is a random policy, 100 an expert."""
    return 100.0 * (episode_return - ref_min_score) / (ref_max_score - ref_min_score)


V4_OUT_OF_DATE = r"(\x1b\[\d+m)?WARN: The environment \w+-v4 is out of date\. You should consider upgrading to version `v5`\."
"""Gymnasium's DeprecationWarning on making a MuJoCo ``-v4`` environment (in yellow ANSI codes)."""


def make_env(env_id: str, **kwargs):
    """``gym.make(env_id, **kwargs)``, the one place eabc makes a Gymnasium environment.

    Gymnasium's warning that ``Hopper-v4`` and the other ``-v4`` tasks are out of date is filtered
    by its exact message, for good: ``-v4`` is kept on purpose. It is the closest to D4RL's
    ``-v2`` tasks, whose reference returns normalise every score; ``-v5`` changes what a return
    is (Hopper's and Walker2d's healthy reward only while healthy), so no score would compare.
    The filter is added to Python's list rather than set in a ``catch_warnings`` block, which is
    not safe while another thread makes an environment (``eabc study`` makes datasets in one)."""
    warnings.filterwarnings(
        "ignore", V4_OUT_OF_DATE, DeprecationWarning, r"gymnasium\.envs\.registration"
    )
    return gym.make(env_id, **kwargs)
