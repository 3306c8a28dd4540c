"""The offline dataset type: float32 transitions, checked on construction, and its normaliser."""

from __future__ import annotations

import dataclasses
import hashlib
import math
from typing import Any

import numpy as np

from eabc.data import tasks

FIELDS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")


class DatasetError(ValueError):
    """A dataset that cannot be used, with a message that says what to do about it."""


@dataclasses.dataclass(frozen=True)
class Normalizer:
    """Observation normalisation of the reference TD3+BC code: ``(s - mean) / (std + 1e-3)``."""

    mean: np.ndarray
    std: np.ndarray
    """Population standard deviation plus 1e-3."""

    @classmethod
    def fit(cls, observations: np.ndarray) -> Normalizer:
        mean = observations.mean(axis=0, dtype=np.float64).astype(np.float32)
        std = (observations.std(axis=0, dtype=np.float64) + 1e-3).astype(np.float32)
        return cls(mean, std)

    @classmethod
    def identity(cls, dim: int) -> Normalizer:
        return cls(np.zeros(dim, np.float32), np.ones(dim, np.float32))

    def __call__(self, observations: np.ndarray) -> np.ndarray:
        return ((observations - self.mean) / self.std).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class Dataset:
    """Transitions ``(s, a, r, s', terminal, timeout)`` as float32/bool arrays of one length.

    ``terminals`` marks a true end of an episode (no bootstrapping); ``timeouts`` marks a time-limit
    truncation, which is not a terminal.
    """

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_observations: np.ndarray
    terminals: np.ndarray
    timeouts: np.ndarray
    name: str = "dataset"
    env_id: str | None = None
    """Gymnasium id of the environment the data came from (for evaluation)."""
    ref_min_score: float | None = None
    """Return of a random policy, for normalised scores."""
    ref_max_score: float | None = None
    """Return of an expert policy, for normalised scores."""
    reward_offset: float | None = None
    """Added to every reward for training, by every algorithm (AntMaze: -1, the ``r - 1`` IQL and
    CORL train on); None: train on the rewards as stored, with the algorithm's own preprocessing."""
    metadata: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        for key in ("observations", "actions", "next_observations"):
            set_(key, _as_2d(np.asarray(getattr(self, key), np.float32), key, self.name))
        set_("rewards", np.asarray(self.rewards, np.float32).reshape(-1))
        for key in ("terminals", "timeouts"):
            set_(key, _flags(np.asarray(getattr(self, key)).reshape(-1), key, self.name))
        n = len(self.observations)
        if n == 0:
            raise DatasetError(f"{self.name}: the dataset is empty")
        lengths = {key: len(getattr(self, key)) for key in FIELDS}
        if len(set(lengths.values())) != 1:
            raise DatasetError(
                f"{self.name}: fields have different lengths {lengths}; every field needs one row "
                "per transition"
            )
        if self.next_observations.shape[1] != self.observations.shape[1]:
            raise DatasetError(
                f"{self.name}: next_observations have dim {self.next_observations.shape[1]} but "
                f"observations have dim {self.observations.shape[1]}"
            )
        problem = reference_scores_problem(self.ref_min_score, self.ref_max_score)
        if problem:
            raise DatasetError(f"{self.name}: {problem}")
        for key in ("observations", "actions", "rewards", "next_observations"):
            values = getattr(self, key)
            bad = ~np.isfinite(values)
            if bad.any():
                rows = np.unique(np.nonzero(bad)[0])
                raise DatasetError(
                    f"{self.name}: {key} holds {bad.sum()} NaN/inf values (first at rows "
                    f"{rows[:5].tolist()}); clean or drop those transitions first"
                )

    def fingerprint(self) -> str:
        """SHA-256 of the transitions (every field's dtype, shape and bytes): the same data gives
        the same fingerprint on any machine, whatever file or name it came from."""
        if "_fingerprint" not in self.__dict__:  # computed once (about 0.3 s per 1M transitions)
            digest = hashlib.sha256()
            for key in FIELDS:
                array = np.ascontiguousarray(getattr(self, key))
                digest.update(f"{key}:{array.dtype.str}:{array.shape};".encode())
                digest.update(array.tobytes())
            self.__dict__["_fingerprint"] = digest.hexdigest()
        return self.__dict__["_fingerprint"]

    @property
    def size(self) -> int:
        return len(self.observations)

    @property
    def obs_dim(self) -> int:
        return self.observations.shape[1]

    @property
    def act_dim(self) -> int:
        return self.actions.shape[1]

    def episode_returns(self) -> np.ndarray:
        """Undiscounted return of every episode (an episode ends at a terminal or a timeout)."""
        ends = self.terminals | self.timeouts
        ends[-1] = True
        episode = np.concatenate([[0], np.cumsum(ends)[:-1]])
        return np.bincount(episode, weights=self.rewards).astype(np.float64)

    def training_view(self) -> Dataset:
        """The transitions with :attr:`reward_offset` added to the rewards (itself if None)."""
        if self.reward_offset is None:
            return self
        rewards = (self.rewards.astype(np.float64) + self.reward_offset).astype(np.float32)
        return dataclasses.replace(self, rewards=rewards, reward_offset=None)

    def normalized_score(self, episode_return: float) -> float | None:
        """D4RL-normalised score of a return, or None without reference returns."""
        if self.ref_min_score is None or self.ref_max_score is None:
            return None
        return tasks.normalized_score(episode_return, self.ref_min_score, self.ref_max_score)


def reference_scores_problem(low: float | None, high: float | None) -> str | None:
    """Why reference scores (a random and an expert policy's returns) cannot normalise a score,
    or None: both must be finite and the random one below the expert one. Reversed, near-random
    data scored near 100; equal, every score divided by zero. One of them alone is a run's
    problem, not the data's (:func:`eabc.training.lifecycle.start` refuses it: returns only need
    neither)."""
    if low is None or high is None:
        return None
    if not (math.isfinite(low) and math.isfinite(high)):
        problem = "are not both finite numbers"
    elif low >= high:
        problem = "equal" if low == high else "in the wrong order (random above expert)"
        problem = f"are {problem}"
    else:
        return None
    return (
        f"its reference scores ref_min_score={low} and ref_max_score={high} {problem}; the "
        "normalised score 100 (return - ref_min_score) / (ref_max_score - ref_min_score) needs "
        "a random policy's return below an expert's: set them so (swap them if they were "
        "exchanged), or remove both to report returns only"
    )


def _flags(values: np.ndarray, key: str, name: str) -> np.ndarray:
    """0/1 (or boolean) flags as booleans; anything else (0.5, -1, NaN) is refused."""
    if values.dtype != bool:
        bad = ~np.isin(values, (0, 1))
        if bad.any():
            rows = np.flatnonzero(bad)
            raise DatasetError(
                f"{name}: {key} must be 0 or 1, but {bad.sum()} values are not (first "
                f"{values[rows[:3]].tolist()} at rows {rows[:3].tolist()}); fix those flags first"
            )
    return values.astype(bool)


def _as_2d(array: np.ndarray, key: str, name: str) -> np.ndarray:
    if array.ndim == 1:
        return array[:, None]
    if array.ndim != 2:
        raise DatasetError(f"{name}: {key} must be [N, dim], got shape {array.shape}")
    return array


def concatenate(datasets: list[Dataset], name: str) -> Dataset:
    """Stack datasets of the same environment (e.g. medium + expert = medium-expert)."""
    first = datasets[0]
    fields = {k: np.concatenate([getattr(d, k) for d in datasets]) for k in FIELDS}
    return dataclasses.replace(first, **fields, name=name)
