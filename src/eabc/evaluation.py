"""Evaluation in Gymnasium: the NumPy policy, deterministic episodes, D4RL-normalised scores, and
space checks."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable

import numpy as np

from eabc import networks
from eabc.data import tasks
from eabc.data.dataset import Dataset, DatasetError, Normalizer


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


def make_env(env_id: str):
    import gymnasium as gym  # noqa: PLC0415

    warnings.filterwarnings("ignore", message=r".*is out of date", category=DeprecationWarning)

    try:
        return gym.make(env_id)
    except gym.error.Error as error:
        raise DatasetError(
            f"cannot make evaluation environment {env_id!r} ({error}); pass --env with a Gymnasium id"
        ) from error


def check_spaces(env, dataset: Dataset) -> None:
    """Raise a clear error if the dataset cannot have come from ``env``."""
    antmaze = tasks.antmaze_env_ids()
    if dataset.env_id in antmaze and env.spec.id not in antmaze:
        raise DatasetError(
            f"{dataset.name} is AntMaze data, evaluated on {dataset.env_id}; {env.spec.id} is "
            "another task: leave --env out (or pass --env one of the AntMaze environments, "
            f"{', '.join(sorted(antmaze))})"
        )
    obs_shape, act_space = env.observation_space.shape, env.action_space
    if obs_shape != (dataset.obs_dim,):
        raise DatasetError(
            f"{dataset.name}: observations have dim {dataset.obs_dim} but {env.spec.id} observes "
            f"shape {obs_shape}; is this the right environment?"
        )
    if act_space.shape != (dataset.act_dim,):
        raise DatasetError(
            f"{dataset.name}: actions have dim {dataset.act_dim} but {env.spec.id} acts with shape "
            f"{act_space.shape}; is this the right environment?"
        )
    tolerance = 1e-3 * (act_space.high - act_space.low)
    if (dataset.actions < act_space.low - tolerance).any() or (
        dataset.actions > act_space.high + tolerance
    ).any():
        raise DatasetError(
            f"{dataset.name}: actions lie outside {env.spec.id}'s bounds "
            f"[{act_space.low.min()}, {act_space.high.max()}]"
        )


@dataclasses.dataclass
class Evaluator:
    """Runs ``episodes`` deterministic episodes on an environment reseeded with ``seed`` each time."""

    env_id: str
    seed: int
    episodes: int = 10
    ref_min_score: float | None = None
    ref_max_score: float | None = None

    def __post_init__(self):
        self.env = make_env(self.env_id)

    def __call__(self, policy: Callable[[np.ndarray], np.ndarray]) -> dict[str, float]:
        returns = []
        obs, _ = self.env.reset(seed=self.seed)
        for _ in range(self.episodes):
            total, done = 0.0, False
            while not done:
                obs, reward, terminated, truncated, _ = self.env.step(policy(obs))
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
            obs, _ = self.env.reset()
        result = {"return_mean": float(np.mean(returns)), "return_std": float(np.std(returns))}
        if self.ref_min_score is not None and self.ref_max_score is not None:
            scores = [
                tasks.normalized_score(r, self.ref_min_score, self.ref_max_score) for r in returns
            ]
            result |= {"score": float(np.mean(scores)), "score_std": float(np.std(scores))}
        return result
