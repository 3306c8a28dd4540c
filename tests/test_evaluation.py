"""Evaluation: episodes side by side equal the episodes one by one, batched actions equal single
ones, AntMaze's goals are fresh at every evaluation, the thinned evaluation schedule, and an
environment's sizes read without keeping it open."""

from __future__ import annotations

import numpy as np
import pytest

from eabc import evaluation
from eabc.data.dataset import Normalizer
from eabc.evaluation import Evaluator, Policy, _near_rounding_boundary, make_env
from eabc.training.config import FINAL_EVALUATIONS, TrainConfig


def random_policy(obs_dim, act_dim, seed=0, gaussian=False, hidden=64, scale=1.0):
    rng = np.random.default_rng(seed)
    sizes = [obs_dim, hidden, hidden, act_dim * (2 if gaussian else 1)]
    actor = {}
    for i in range(3):
        bound = 1 / np.sqrt(sizes[i])
        actor[f"w{i}"] = rng.uniform(-bound, bound, sizes[i : i + 2]).astype(np.float32) * scale
        actor[f"b{i}"] = rng.uniform(-bound, bound, sizes[i + 1]).astype(np.float32)
    normalizer = Normalizer(
        rng.normal(0, 0.5, obs_dim).astype(np.float32),
        rng.uniform(0.5, 2.0, obs_dim).astype(np.float32),
    )
    return Policy(actor, normalizer, 1.0, gaussian)


def todays_returns(env_id, seed, episodes, policy):
    """The evaluation as the training process runs it: one environment, reseeded once, the
    episodes one after another."""
    env = make_env(env_id)
    returns = []
    obs, _ = env.reset(seed=seed)
    for _ in range(episodes):
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(policy(obs))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
        obs, _ = env.reset()
    return returns


@pytest.mark.parametrize(
    ("env_id", "obs_dim", "act_dim", "scale"),
    [("Hopper-v4", 11, 3, 1.0), ("Hopper-v4", 11, 3, 8.0), ("Pendulum-v1", 3, 1, 4.0)],
)
def test_episodes_side_by_side_return_exactly_what_they_return_one_by_one(
    env_id, obs_dim, act_dim, scale
):
    """Hopper's episodes end at different steps (the batch shrinks); Pendulum's run 200 steps."""
    policy = random_policy(obs_dim, act_dim, seed=3, scale=scale)
    evaluator = Evaluator(env_id, seed=105, episodes=5)
    expected = todays_returns(env_id, 105, 5, policy)
    assert len(set(expected)) == 5  # five different episodes, not one counted five times
    assert evaluator.returns(policy, step=5000, vectorised=True) == expected
    assert evaluator.returns(policy, step=5000) == expected
    assert evaluator.returns(policy, step=10000, vectorised=True) == expected  # MuJoCo: same seed
    again = evaluator(policy, step=5000, vectorised=True)
    assert again["return_mean"] == np.mean(expected)


def test_a_step_that_draws_from_the_generator_falls_back_to_episodes_one_by_one(monkeypatch):
    """Side by side is the same only while steps draw nothing from the environment's generator;
    an environment whose steps do is noticed and evaluated one episode after another."""
    from gymnasium.envs.classic_control.pendulum import PendulumEnv

    step = PendulumEnv.step

    def noisy_step(self, action):
        return step(self, action + self.np_random.normal(0.0, 0.1, np.shape(action)))

    monkeypatch.setattr(PendulumEnv, "step", noisy_step)
    policy = random_policy(3, 1, seed=4)
    evaluator = Evaluator("Pendulum-v1", seed=101, episodes=3)
    assert evaluator._side_by_side(policy, 101) is None
    expected = todays_returns("Pendulum-v1", 101, 3, policy)
    assert evaluator.returns(policy, vectorised=True) == expected


@pytest.mark.parametrize("gaussian", [False, True])
def test_batched_actions_are_the_single_observation_actions_bit_for_bit(gaussian):
    policy = random_policy(17, 6, seed=1, gaussian=gaussian, hidden=256, scale=3.0)
    observations = np.random.default_rng(2).normal(0, 3, (4000, 17))
    batched = np.concatenate([policy.batch(part) for part in np.split(observations, 400)])
    single = np.stack([policy(obs) for obs in observations])
    assert batched.dtype == single.dtype == np.float32
    np.testing.assert_array_equal(batched, single)


def test_values_next_to_a_float32_rounding_boundary_are_found():
    rounded = np.array([1.0, 0.5, -3.0], np.float32)
    half_ulp = (np.nextafter(rounded, np.float32(np.inf)).astype(np.float64) - rounded) / 2
    exact = rounded.astype(np.float64) + half_ulp * np.array([1 - 1e-13, 0.5, -(1 - 1e-13)])
    assert _near_rounding_boundary(exact, rounded).tolist() == [True, False, True]


def antmaze_goals(evaluator, step):
    """The goals of the episodes of the evaluation at ``step``, each environment's last."""
    policy = random_policy(29, 8, seed=0)
    evaluator.returns(policy, step=step, vectorised=True)
    return [tuple(env.unwrapped.goal) for env in evaluator._batch]


def test_antmaze_evaluations_draw_fresh_goals_and_a_rerun_draws_the_same(monkeypatch):
    """Each of a run's evaluations draws its own noisy goals (not the same ten at every step),
    from the run's seed: the run trained again evaluates on the same goals."""
    import gymnasium as gym

    monkeypatch.setattr(gym.registry["eabc/AntMaze-UMaze-v0"], "max_episode_steps", 20)  # quick
    evaluator = Evaluator("eabc/AntMaze-UMaze-v0", seed=100, episodes=3)
    first, second = antmaze_goals(evaluator, 5000), antmaze_goals(evaluator, 10000)
    assert len(set(first)) == 3
    assert not set(first) & set(second)
    rerun = Evaluator("eabc/AntMaze-UMaze-v0", seed=100, episodes=3)
    assert antmaze_goals(rerun, 5000) == first
    assert antmaze_goals(rerun, 10000) == second
    other_seed = Evaluator("eabc/AntMaze-UMaze-v0", seed=101, episodes=3)
    assert antmaze_goals(other_seed, 5000) != first
    # MuJoCo tasks keep one seed for every evaluation, as they always did.
    assert Evaluator("Hopper-v4", seed=100).seed_at(5000) == 100
    assert evaluator.seed_at(None) == 100


def test_the_thin_schedule_keeps_the_final_window_and_thins_the_rest():
    every = TrainConfig(steps=1_000_000)
    thin = TrainConfig(steps=1_000_000, eval_schedule="thin")
    assert every.evaluation_steps() == list(range(5000, 1_000_001, 5000))
    expected = list(range(50_000, 950_001, 50_000)) + list(range(955_000, 1_000_001, 5000))
    assert thin.evaluation_steps() == expected
    assert len(expected) == 29
    final = every.evaluation_steps()[-FINAL_EVALUATIONS:]
    assert thin.evaluation_steps()[-FINAL_EVALUATIONS:] == final
    assert final == list(range(955_000, 1_000_001, 5000))
    # A run whose length is not a multiple of the interval still evaluates at its end.
    odd = TrainConfig(steps=123_000, eval_interval=5000, eval_schedule="thin")
    assert odd.evaluation_steps()[-FINAL_EVALUATIONS - 1 :] == [
        *range(75_000, 120_001, 5000),
        123_000,
    ]
    assert odd.evaluation_steps()[:2] == [50_000, 75_000]
    assert thin.evaluation_steps(after=950_000) == list(range(955_000, 1_000_001, 5000))
    with pytest.raises(ValueError, match="eval_schedule"):
        TrainConfig(eval_schedule="sparse")


def test_a_sweep_estimates_the_evaluations_its_schedule_makes():
    from eabc import timing
    from eabc.experiments import planning
    from eabc.experiments.spec import RunSpec

    def seconds(schedule, done=0):
        train = (("eval_schedule", schedule), ("steps", 1_000_000))
        return planning.estimate_seconds(RunSpec("hopper-medium", "td3bc", 0, (), train), done)

    episode = timing.EPISODE_SECONDS / timing.REFERENCE.factor
    assert seconds("every") - seconds("thin") == pytest.approx((200 - 29) * 10 * episode)
    # Half-way, 9 sparse evaluations and the final window's 10 are left.
    assert seconds("every", 500_000) - seconds("thin", 500_000) == pytest.approx(
        (100 - 19) * 10 * episode
    )


@pytest.mark.parametrize(
    "env_id, sizes", [("Hopper-v4", (11, 3, 1.0)), ("HalfCheetah-v4", (17, 6, 1.0))]
)
def test_space_sizes_reads_an_environments_sizes_and_closes_it(monkeypatch, env_id, sizes):
    closed = []

    def make_watched(env_id):
        env = make_env(env_id)
        close = env.close
        env.close = lambda: closed.append(env_id) or close()
        return env

    monkeypatch.setattr(evaluation, "make_env", make_watched)
    assert evaluation.space_sizes(env_id) == sizes
    assert closed == [env_id]
