"""IQL and CQL: losses against hand computations, reward scaling, the schedule, learning on Pendulum."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from handcalc import ACT, OBS, B, np_mlp, np_q, quick_jit
from learning import MARGIN, late_gain

from eabc import networks
from eabc.agents import cql, get_algorithm, iql, sac
from eabc.data.dataset import Dataset
from eabc.training import lifecycle, trainer
from eabc.training.config import TrainConfig, resolve_agent_config

iql_update = quick_jit(iql.update)
cql_update = quick_jit(cql.update)


def as64(*arrays):
    return tuple(np.asarray(x, np.float64) for x in arrays)


def iql_state(config, batch, seed=0):
    state = iql.init(jax.random.PRNGKey(seed), OBS, ACT, config)
    # Targets that differ from the online critics, so that the tests tell them apart, and V
    # shifted to the middle of the target values, so that advantages of both signs occur.
    critic_target = jax.tree.map(lambda x: 1.3 * x + 0.05, state.critic)
    s, a = as64(batch.observations, batch.actions)
    u = np_q(critic_target, 2, s, a).min(0) - np_mlp(state.value, s)[:, 0]
    last = f"b{len(state.value) // 2 - 1}"
    value = {**state.value, last: state.value[last] + float(u.mean())}
    return state.replace(critic_target=critic_target, value=value)


# ----------------------------------------------------------------------------------------- IQL


def test_iql_value_loss_is_the_expectile_regression(batch):
    config = iql.IQLConfig(hidden_dims=(8, 8))
    state = iql_state(config, batch)
    loss, _ = iql.value_loss(state.value, state.critic_target, batch, config)

    s, a = as64(batch.observations, batch.actions)
    u = np_q(state.critic_target, 2, s, a).min(0) - np_mlp(state.value, s)[:, 0]
    assert (u > 0).any() and (u < 0).any(), "the tiny batch should have both signs"
    expected = np.mean([(0.7 if x > 0 else 0.3) * x**2 for x in u])
    np.testing.assert_allclose(loss, expected, rtol=1e-5)


def test_iql_critic_loss_bootstraps_from_v(batch):
    config = iql.IQLConfig(hidden_dims=(8, 8))
    state = iql_state(config, batch)
    loss, metrics = iql.critic_loss(state.critic, state.value, batch, config)

    s, a, r, s2, d = as64(*dataclasses.astuple(batch))
    y = r + 0.99 * (1 - d) * np_mlp(state.value, s2)[:, 0]
    q = np_q(state.critic, 2, s, a)
    np.testing.assert_allclose(loss, ((q[0] - y) ** 2).mean() + ((q[1] - y) ** 2).mean(), rtol=1e-5)
    np.testing.assert_allclose(metrics["target_mean"], y.mean(), rtol=1e-5)


def test_iql_actor_loss_is_advantage_weighted_gaussian_log_likelihood(batch):
    config = iql.IQLConfig(hidden_dims=(8, 8), temperature=40.0)
    state = iql_state(config, batch)
    log_std = jnp.asarray([-6.0, 0.4], jnp.float32)  # the first is clipped to -5
    max_action = 2.0
    loss, _ = iql.actor_loss(
        (state.actor, log_std), state.value, state.critic_target, batch, config, max_action
    )

    s, a = as64(batch.observations, batch.actions)
    advantage = np_q(state.critic_target, 2, s, a).min(0) - np_mlp(state.value, s)[:, 0]
    raw = np.exp(40.0 * advantage)
    assert (raw > 100).any() and (raw < 100).any(), "some weights should hit the clip"
    weight = np.minimum(raw, 100.0)
    mean = np.tanh(np_mlp(state.actor, s))
    std = np.exp([-5.0, 0.4])
    log_prob = (
        -0.5 * ((a / max_action - mean) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi)
    ).sum(-1)
    np.testing.assert_allclose(loss, -(weight * log_prob).mean(), rtol=1e-4)


def test_iql_update_uses_the_new_v_for_actor_and_critics(batch):
    config = iql.IQLConfig(hidden_dims=(8, 8))
    state = iql_state(config, batch)
    state = state.replace(log_std=jnp.asarray([0.2, -0.3], jnp.float32))
    new, metrics = iql_update(state, batch, jax.random.PRNGKey(0), config, 1.0)
    assert not np.allclose(new.value["w0"], state.value["w0"])
    critic, _ = iql.critic_loss(state.critic, new.value, batch, config)
    np.testing.assert_allclose(metrics["critic_loss"], critic, rtol=1e-6)
    actor, _ = iql.actor_loss(
        (state.actor, state.log_std), new.value, state.critic_target, batch, config, 1.0
    )
    np.testing.assert_allclose(metrics["actor_loss"], actor, rtol=1e-6)
    assert not np.allclose(new.log_std, state.log_std), "log_std is trained with the actor"
    expected = 0.005 * np.asarray(new.critic["w1"]) + 0.995 * np.asarray(state.critic_target["w1"])
    np.testing.assert_allclose(new.critic_target["w1"], expected, rtol=1e-6)
    assert int(new.step) == 1


def test_iql_deterministic_action_is_max_action_tanh_of_the_mlp():
    algorithm = get_algorithm("iql")
    state = iql.init(jax.random.PRNGKey(0), OBS, ACT, iql.IQLConfig(hidden_dims=(8, 8)))
    assert sorted(state.actor) == ["b0", "b1", "b2", "w0", "w1", "w2"]
    assert not algorithm.gaussian_actor
    obs = np.random.default_rng(0).normal(size=(4, OBS)).astype(np.float32)
    act = networks.numpy_actor(jax.device_get(state.actor), 2.0, algorithm.gaussian_actor)
    np.testing.assert_allclose(act(obs), 2.0 * np.tanh(np_mlp(state.actor, obs)), rtol=1e-5)


def test_iql_actor_learning_rate_decays_on_a_cosine_to_zero(batch):
    config = iql.IQLConfig(hidden_dims=(8, 8), total_steps=2)
    states = [iql_state(config, batch)]
    for seed in range(3):
        states.append(iql_update(states[-1], batch, jax.random.PRNGKey(seed), config, 1.0)[0])
    # Adam's first step moves every parameter with a gradient by the learning rate itself.
    step = np.abs(np.asarray(states[1].log_std) - np.asarray(states[0].log_std))
    np.testing.assert_allclose(step, 3e-4, rtol=1e-3)
    assert not np.allclose(states[2].actor["w0"], states[1].actor["w0"])  # lr(1) = 1.5e-4
    np.testing.assert_array_equal(states[3].actor["w0"], states[2].actor["w0"])  # lr(2) = 0
    np.testing.assert_array_equal(states[3].log_std, states[2].log_std)
    assert not np.allclose(states[3].value["w0"], states[2].value["w0"])  # V's rate is constant


def test_total_steps_is_filled_from_the_run_length(tmp_path, pendulum_dataset, quick_chunks):
    assert resolve_agent_config("iql", "x", {}, steps=5000).total_steps == 5000
    assert resolve_agent_config("iql", "x", {"total_steps": 7}, steps=5000).total_steps == 7
    assert resolve_agent_config("iql", "x", {}).total_steps is None
    assert resolve_agent_config("td3bc", "x", {}, steps=5000) == get_algorithm("td3bc").preset

    config = TrainConfig(
        algo="iql",
        steps=200,
        log_interval=100,
        eval_interval=200,
        checkpoint_interval=200,
        eval_episodes=1,
        env="Pendulum-v1",
    )
    run = lifecycle.start(config, tmp_path / "iql", {"hidden_dims": (8, 8)}, pendulum_dataset)
    assert run.agent_config.total_steps == 200
    saved = json.loads((tmp_path / "iql" / "config.json").read_text())
    assert saved["agent"]["total_steps"] == 200
    trainer.train(run, progress=False)
    assert lifecycle.resume(tmp_path / "iql", pendulum_dataset).agent_config.total_steps == 200


def episodes_dataset(episode_rewards):
    rewards = np.concatenate(episode_rewards)
    n = len(rewards)
    ends = np.cumsum([len(e) for e in episode_rewards]) - 1
    terminals = np.zeros(n, bool)
    timeouts = np.zeros(n, bool)
    terminals[ends[0]] = True  # one episode ends in a terminal, the others by time limit
    timeouts[ends[1:]] = True
    obs = np.arange(n, dtype=np.float32)[:, None]
    return Dataset(obs, np.zeros((n, 1)), rewards, obs + 1, terminals, timeouts)


def test_iql_scales_rewards_by_the_spread_of_episode_returns():
    episodes = [np.array([1.0, 2.0]), np.array([-3.0, 0.5, 0.5]), np.array([10.0, 0.0])]
    data = episodes_dataset(episodes)  # returns 3, -2 and 10: spread 12
    scaled = iql.preprocess(data)
    np.testing.assert_allclose(scaled.rewards, data.rewards * 1000.0 / 12.0, rtol=1e-6)
    np.testing.assert_allclose(scaled.episode_returns(), [250.0, -2000.0 / 12, 10000.0 / 12])
    np.testing.assert_array_equal(scaled.observations, data.observations)
    np.testing.assert_array_equal(data.rewards, np.concatenate(episodes))  # the input is kept

    same = episodes_dataset([np.array([1.0, 2.0]), np.array([3.0])])
    np.testing.assert_array_equal(iql.preprocess(same).rewards, same.rewards)


class Stop(Exception):
    pass


@pytest.mark.parametrize("algo", ["iql", "cql"])
def test_trainer_trains_on_the_preprocessed_data(tmp_path, pendulum_dataset, monkeypatch, algo):
    seen = {}

    def capture(dataset, normalizer, *args):
        seen["rewards"] = dataset.rewards
        raise Stop

    monkeypatch.setattr(trainer, "device_data", capture)
    config = TrainConfig(algo=algo, steps=100, log_interval=100, eval_interval=100)
    config = dataclasses.replace(config, checkpoint_interval=100, env="Pendulum-v1")
    run = lifecycle.start(config, tmp_path / algo, {"hidden_dims": (8, 8)}, pendulum_dataset)
    with pytest.raises(Stop):
        trainer.train(run, progress=False)
    returns = pendulum_dataset.episode_returns()
    scale = 1000.0 / (returns.max() - returns.min()) if algo == "iql" else 1.0
    assert algo == "cql" or not np.isclose(scale, 1.0)
    np.testing.assert_allclose(seen["rewards"], pendulum_dataset.rewards * scale, rtol=1e-6)


# ----------------------------------------------------------------------------------------- CQL


def hand_gap(critic, actor, batch, key, n, max_action):
    """The conservative gap per critic, one state and one critic at a time in float64."""
    random_key, current_key, next_key = jax.random.split(key, 3)
    s, s2, a = as64(batch.observations, batch.next_observations, batch.actions)
    uniform = jax.random.uniform(random_key, (B * n, ACT), minval=-max_action, maxval=max_action)
    # The same draws as the agent's: sample j of state b sits in row b * n + j.
    current = sac.sample_action(actor, np.repeat(batch.observations, n, 0), current_key, max_action)
    following = sac.sample_action(
        actor, np.repeat(batch.next_observations, n, 0), next_key, max_action
    )
    uniform_log_density = ACT * np.log(1.0 / (2.0 * max_action))
    gaps = []
    for i in range(2):
        critic_i = {k: v[i : i + 1] for k, v in critic.items()}
        per_state = []
        for b in range(B):
            rows = slice(b * n, (b + 1) * n)
            scores = []
            for actions, log_density in [
                (uniform[rows], np.full(n, uniform_log_density)),
                (following[0][rows], following[1][rows]),
                (current[0][rows], current[1][rows]),
            ]:
                obs = np.repeat(s[b : b + 1], n, 0)
                q = np_q(critic_i, 1, obs, np.asarray(actions, np.float64))[0]
                scores.extend(q - np.asarray(log_density, np.float64))
            scores = np.array(scores)
            top = scores.max()
            soft_max = top + np.log(np.exp(scores - top).sum())
            q_data = np_q(critic_i, 1, s[b : b + 1], a[b : b + 1])[0, 0]
            per_state.append(soft_max - q_data)
        gaps.append(np.mean(per_state))
    return np.array(gaps)


def cql_state(config, seed=0):
    state = cql.init(jax.random.PRNGKey(seed), OBS, ACT, config)
    base = state.sac
    return state.replace(
        sac=base.replace(critic_target=jax.tree.map(lambda x: 0.9 * x - 0.02, base.critic))
    )


@pytest.mark.parametrize("max_action", [1.0, 2.0])
def test_cql_conservative_gap_matches_hand_computation(batch, max_action):
    config = cql.CQLConfig(hidden_dims=(8, 8), num_sampled_actions=3)
    state = cql_state(config)
    key = jax.random.PRNGKey(7)
    q_data = networks.critic_apply(state.sac.critic, batch.observations, batch.actions)
    gap = cql.conservative_gap(
        state.sac.critic, state.actor, batch, q_data, key, config, max_action
    )
    expected = hand_gap(state.sac.critic, state.actor, batch, key, 3, max_action)
    np.testing.assert_allclose(gap, expected, rtol=1e-4)


@pytest.mark.parametrize("lagrange", [False, True])
def test_cql_critic_loss_matches_hand_computation(batch, lagrange):
    config = cql.CQLConfig(hidden_dims=(8, 8), num_sampled_actions=4, lagrange=lagrange)
    state = cql_state(config)
    key = jax.random.PRNGKey(3)
    loss, (gap, metrics) = cql.critic_loss(state.sac.critic, state, batch, key, config, 1.0)

    target_key, gap_key = jax.random.split(key)
    next_action, _ = sac.sample_action(state.actor, batch.next_observations, target_key, 1.0)
    s, a, r, s2, d = as64(*dataclasses.astuple(batch))
    # No entropy term in the backup (JaxCQL's backup_entropy=False).
    y = r + 0.99 * (1 - d) * np_q(state.sac.critic_target, 2, s2, np.asarray(next_action)).min(0)
    q = np_q(state.sac.critic, 2, s, a)
    td = ((q[0] - y) ** 2).mean() + ((q[1] - y) ** 2).mean()
    gaps = hand_gap(state.sac.critic, state.actor, batch, gap_key, 4, 1.0)
    if lagrange:  # alpha' = e^1 at the start, the target gap is 1
        penalty = np.e * 5.0 * (gaps - 1.0).sum()
    else:
        penalty = 5.0 * gaps.sum()
    np.testing.assert_allclose(metrics["td_loss"], td, rtol=1e-5)
    np.testing.assert_allclose(gap, gaps, rtol=1e-4)
    np.testing.assert_allclose(loss, td + penalty, rtol=1e-4)


@pytest.mark.parametrize("lagrange", [False, True])
def test_cql_update_steps_every_loss_from_the_current_state(batch, lagrange):
    config = cql.CQLConfig(hidden_dims=(8, 8), num_sampled_actions=4, lagrange=lagrange)
    state = cql_state(config)
    key = jax.random.PRNGKey(11)
    new, metrics = cql_update(state, batch, key, config, 1.0)
    critic_key, actor_key = jax.random.split(key)

    # The actor maximises the critics of before the step (as in JaxCQL).
    actor_loss, _ = sac.actor_loss(
        state.actor, state.sac.critic, state.sac.log_alpha, batch, actor_key, 1.0
    )
    np.testing.assert_allclose(metrics["actor_loss"], actor_loss, rtol=1e-6)
    assert not np.allclose(new.actor["w0"], state.actor["w0"])
    assert not np.allclose(new.sac.critic["w0"], state.sac.critic["w0"])
    assert int(new.step) == 1
    # Adam's first step on log(alpha') is lr * sign(mean gap - target gap): alpha' rises while
    # the critics' gap exceeds the target.
    gap = hand_gap(state.sac.critic, state.actor, batch, jax.random.split(critic_key)[1], 4, 1.0)
    if lagrange:
        expected = 1.0 + 3e-4 * np.sign(gap.mean() - 1.0)
        np.testing.assert_allclose(new.log_alpha_prime, expected, rtol=1e-5)
        np.testing.assert_allclose(metrics["alpha_prime"], np.e, rtol=1e-6)
    else:
        assert float(new.log_alpha_prime) == float(state.log_alpha_prime)
    np.testing.assert_allclose(metrics["cql_gap"], gap.mean(), rtol=1e-4)


def test_cql_presets_and_settings():
    assert not get_algorithm("cql").preset.lagrange
    assert get_algorithm("cql-lagrange").preset.lagrange
    assert get_algorithm("cql").gaussian_actor
    with pytest.raises(ValueError, match="num_sampled_actions"):
        cql.CQLConfig(num_sampled_actions=0)
    with pytest.raises(ValueError, match="expectile"):
        iql.IQLConfig(expectile=1.0)


# ------------------------------------------------------------------------------------ learning


# CQL's penalty is weighed against TD errors in reward units; Pendulum's rewards per step are about
# a tenth of MuJoCo's, so the test scales the weight down from 5 to 1 (with 5 the policy of 3000
# steps is still near the untrained one) and samples 5 actions per proposal instead of 10 for speed.
LEARNING_OVERRIDES = {
    "iql": {},
    "cql": {"min_q_weight": 1.0, "num_sampled_actions": 5},
}


@pytest.mark.parametrize("algo", ["iql", "cql"])
def test_offline_iql_and_cql_improve_on_the_untrained_policy(tmp_path, pendulum_dataset, algo):
    overrides = LEARNING_OVERRIDES[algo]
    untrained, late, evaluations = late_gain(tmp_path, pendulum_dataset, algo, overrides)
    assert late > untrained + MARGIN, (untrained, evaluations)


def test_iql_takes_the_authors_antmaze_settings_on_antmaze_data_unless_set():
    """Before: AntMaze runs trained with the MuJoCo expectile 0.7 and temperature 3, where the
    authors' AntMaze configuration has 0.9 and 10."""
    antmaze = resolve_agent_config("iql", "antmaze-medium-play", {})
    assert (antmaze.expectile, antmaze.temperature) == (0.9, 10.0)
    mine = resolve_agent_config("iql", "antmaze-umaze@planner-v0", {"temperature": 5.0})
    assert (mine.expectile, mine.temperature) == (0.9, 5.0)
    hopper = resolve_agent_config("iql", "hopper-medium", {})
    assert (hopper.expectile, hopper.temperature) == (0.7, 3.0)
