"""Evaluation in Gymnasium: the NumPy policy, deterministic episodes, D4RL-normalised scores, and
space checks.

An evaluation's episodes run one after another in one environment reseeded at its start
(:class:`Evaluator`), or side by side in a batch of environments with one policy call per step
(``vectorised=True``, what the evaluation processes of :mod:`eabc.training.eval_pool` do): each
environment of the batch starts its episode from the random state the one environment would have
reached, so both give the same returns, bit for bit. This module imports neither JAX nor the
training code, so that evaluation processes start quickly.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import gymnasium as gym
import numpy as np

from eabc.data import tasks
from eabc.data.dataset import Dataset, DatasetError, Normalizer
from eabc.numpy_networks import numpy_actor, numpy_mlp

ROUNDING_MARGIN = 1e-11
"""How near (relative) to a float32 rounding boundary a batched action may fall before it is
computed again for its observation alone (:meth:`Policy.batch`)."""


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
        self.max_action = max_action
        self.gaussian = gaussian
        self._act = numpy_actor(actor, max_action, gaussian)
        self._mlp = numpy_mlp(actor)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return self._act(self.normalizer(np.asarray(observation, np.float32)))

    def batch(self, observations: np.ndarray) -> np.ndarray:
        """The actions of a batch of observations ``[n, obs_dim]``, each equal to ``self(row)``.

        The network runs once for the batch, in float64, as for one observation; but a matrix
        product sums in another order than a vector product (other BLAS kernels), which moves the
        float64 result in its last bits. Rounded to float32 that changes nothing unless the value
        lies next to a float32 rounding boundary: such rows (about one in 10^4 values) are
        computed again one by one, so every action is the one-observation action bit for bit."""
        observations = np.asarray(observations, np.float32)
        out = self._mlp(self.normalizer(observations))
        if self.gaussian:
            out = out[:, : out.shape[1] // 2]
        # One row at a time as the one-observation path does it (a contiguous row through the
        # same tanh loop): NumPy's vectorised tanh may round differently on strided data.
        exact = np.stack([self.max_action * np.tanh(np.ascontiguousarray(row)) for row in out])
        actions = exact.astype(np.float32)
        for i in np.flatnonzero(_near_rounding_boundary(exact, actions).any(axis=1)):
            actions[i] = self(observations[i])
        return actions


def _near_rounding_boundary(exact: np.ndarray, rounded: np.ndarray) -> np.ndarray:
    """Where the float64 ``exact`` lies within :data:`ROUNDING_MARGIN` of a value halfway between
    its float32 rounding ``rounded`` and a neighbour of it."""
    up = np.nextafter(rounded, np.float32(np.inf)).astype(np.float64)
    down = np.nextafter(rounded, np.float32(-np.inf)).astype(np.float64)
    here = rounded.astype(np.float64)
    distance = np.minimum(np.abs(exact - (here + up) / 2), np.abs(exact - (here + down) / 2))
    return distance <= ROUNDING_MARGIN * np.maximum(np.abs(exact), 1e-30)


def make_env(env_id: str):
    try:
        return tasks.make_env(env_id)
    except gym.error.Error as error:
        raise DatasetError(
            f"cannot make evaluation environment {env_id!r} ({error}); pass --env with a Gymnasium id"
        ) from error


def space_sizes(env_id: str) -> tuple[int, int, float]:
    """``env_id``'s observation size, action size and largest action, from an environment made
    for the purpose and closed again."""
    env = make_env(env_id)
    try:
        (obs_dim,), (act_dim,) = env.observation_space.shape, env.action_space.shape
        return obs_dim, act_dim, float(env.action_space.high[0])
    finally:
        env.close()


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
    """Runs ``episodes`` deterministic episodes on an environment reseeded at every evaluation.

    MuJoCo tasks are reseeded with ``seed`` itself, so every evaluation starts its episodes from
    the same states. Goal-conditioned tasks (AntMaze: every episode draws its goal's noise at
    reset) are reseeded with a seed drawn from ``seed`` and the evaluation's step
    (:meth:`seed_at`): each evaluation draws fresh goals, and a rerun of the run draws the same.
    """

    env_id: str
    seed: int
    episodes: int = 10
    ref_min_score: float | None = None
    ref_max_score: float | None = None

    def __post_init__(self):
        self.env = make_env(self.env_id)
        self._batch: list = []  # the environments of side-by-side episodes, made on first use

    @property
    def fresh_goals(self) -> bool:
        """Whether each evaluation draws its own goals (:meth:`seed_at`)."""
        return self.env_id in tasks.antmaze_env_ids()

    def seed_at(self, step: int | None) -> int:
        """The seed the environment is reset with at the evaluation of ``step``: ``seed`` (also
        with no step, or for a task without goals), else one drawn from ``seed`` and ``step``."""
        if step is None or not self.fresh_goals:
            return self.seed
        return int(np.random.SeedSequence([self.seed, step]).generate_state(1)[0])

    def __call__(
        self,
        policy: Callable[[np.ndarray], np.ndarray],
        step: int | None = None,
        vectorised: bool = False,
    ) -> dict[str, float]:
        """The returns (and scores) of ``policy`` at the evaluation of ``step``; ``vectorised``
        runs the episodes side by side, one ``policy.batch`` call per step (a :class:`Policy`),
        with the same returns."""
        return self.result(self.returns(policy, step, vectorised))

    def returns(
        self,
        policy: Callable[[np.ndarray], np.ndarray],
        step: int | None = None,
        vectorised: bool = False,
    ) -> list[float]:
        """The episodes' returns, in episode order (see :meth:`__call__`)."""
        seed = self.seed_at(step)
        returns = None
        if vectorised and hasattr(policy, "batch"):
            returns = self._side_by_side(policy, seed)
        if returns is None:
            returns = self._one_by_one(policy, seed)
        return returns

    def _one_by_one(self, policy, seed: int) -> list[float]:
        returns = []
        obs, _ = self.env.reset(seed=seed)
        for _ in range(self.episodes):
            total, done = 0.0, False
            while not done:
                obs, reward, terminated, truncated, _ = self.env.step(policy(obs))
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
            obs, _ = self.env.reset()
        return returns

    def _side_by_side(self, policy: Policy, seed: int) -> list[float] | None:
        """The episodes of :meth:`_one_by_one`, one environment each, stepped together.

        Episode k of :meth:`_one_by_one` starts from the generator state its environment has after
        k resets; the states are found by resetting only, and each environment of the batch is
        put in its episode's state before its reset. That is the same episode as long as steps
        draw nothing from the generator: checked at each episode's end (its generator must be
        where the next reset starts); None if not, and the episodes are then run one by one."""
        self.env.reset(seed=seed)
        states = [None, _generator_state(self.env)]
        for _ in range(self.episodes - 1):
            self.env.reset()
            states.append(_generator_state(self.env))
        while len(self._batch) < self.episodes:
            self._batch.append(make_env(self.env_id))
        envs = self._batch[: self.episodes]
        observations = []
        for k, env in enumerate(envs):
            if k == 0:
                obs, _ = env.reset(seed=seed)
            else:
                env.unwrapped.np_random.bit_generator.state = states[k]
                obs, _ = env.reset()
            observations.append(obs)
        observations = np.stack(observations)
        totals = [0.0] * self.episodes
        running = list(range(self.episodes))
        while running:
            actions = policy.batch(observations[running])
            still = []
            for k, action in zip(running, actions):
                observations[k], reward, terminated, truncated, _ = envs[k].step(action)
                totals[k] += float(reward)
                if not (terminated or truncated):
                    still.append(k)
                elif _generator_state(envs[k]) != states[k + 1]:
                    return None
            running = still
        return totals

    def result(self, returns: list[float]) -> dict[str, float]:
        """Mean and spread of the episodes' returns, and of their normalised scores."""
        result = {"return_mean": float(np.mean(returns)), "return_std": float(np.std(returns))}
        if self.ref_min_score is not None and self.ref_max_score is not None:
            scores = [
                tasks.normalized_score(r, self.ref_min_score, self.ref_max_score) for r in returns
            ]
            result |= {"score": float(np.mean(scores)), "score_std": float(np.std(scores))}
        return result


def _generator_state(env) -> dict:
    """The state of ``env``'s random generator (``np_random``), a plain dict."""
    return env.unwrapped.np_random.bit_generator.state
