"""SAC, SAC-N and EDAC: the tanh-Gaussian, the losses against hand computations, online learning."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from handcalc import ACT, OBS, B, member, np_mlp, np_q, quick_jit
from learning import MARGIN, late_gain

from eabc import cli, networks
from eabc.agents import sac
from eabc.training import checkpoint, online

sac_update = quick_jit(sac.update)


def tiny(**kw):
    return dataclasses.replace(sac.SACConfig(hidden_dims=(8, 8)), **kw)


def test_tanh_gaussian_log_density_is_the_change_of_variables():
    rng = np.random.default_rng(0)
    mean = jnp.asarray(rng.normal(size=(5, 3)), jnp.float32)
    log_std = jnp.asarray(rng.uniform(-1, 0.5, size=(5, 3)), jnp.float32)
    key = jax.random.PRNGKey(3)
    action, log_prob = networks.sample_tanh_gaussian(key, mean, log_std, max_action=2.0)
    # Recover u from the action and evaluate the density of a = 2 tanh(u) by hand.
    m, s = np.asarray(mean, np.float64), np.exp(np.asarray(log_std, np.float64))
    u = np.arctanh(np.asarray(action, np.float64) / 2.0)
    gauss = -0.5 * ((u - m) / s) ** 2 - np.log(s) - 0.5 * np.log(2 * np.pi)
    jacobian = np.log(2.0 * (1.0 - np.tanh(u) ** 2))
    np.testing.assert_allclose(log_prob, (gauss - jacobian).sum(-1), rtol=1e-3, atol=1e-3)
    assert np.all(np.abs(np.asarray(action)) <= 2.0)


def test_critic_loss_matches_hand_computation(batch):
    config = tiny(num_critics=3)
    state = sac.init(jax.random.PRNGKey(0), OBS, ACT, config)
    state = state.replace(log_alpha=jnp.asarray(np.log(0.3), jnp.float32))
    key = jax.random.PRNGKey(1)
    loss, _ = sac.critic_loss(state.critic, state, batch, key, config, 1.0)

    next_action, next_log_prob = sac.sample_action(state.actor, batch.next_observations, key, 1.0)
    obs, act = np.asarray(batch.observations), np.asarray(batch.actions)
    target_q = np_q(state.critic_target, 3, np.asarray(batch.next_observations), next_action)
    next_value = target_q.min(0) - 0.3 * np.asarray(next_log_prob)
    y = np.asarray(batch.rewards) + 0.99 * (1 - np.asarray(batch.dones)) * next_value
    expected = ((np_q(state.critic, 3, obs, act) - y) ** 2).mean(1).sum()
    np.testing.assert_allclose(loss, expected, rtol=1e-5)


def test_edac_diversity_penalty_matches_hand_computation(batch):
    config = tiny(num_critics=4, eta=1.0)
    critic = sac.init(jax.random.PRNGKey(2), OBS, ACT, config).critic
    penalty = sac.diversity_loss(critic, batch.observations, batch.actions)

    grads = []
    for i in range(4):  # one member at a time: d Q_i(s, a) / d a, then unit length
        q_i = lambda a, i=i: networks.mlp(
            member(critic, i), jnp.concatenate([batch.observations, a], -1)
        ).sum()
        g = np.asarray(jax.grad(q_i)(batch.actions), np.float64)
        grads.append(g / np.linalg.norm(g, axis=-1, keepdims=True))
    expected = np.mean(
        [
            sum(grads[i][b] @ grads[j][b] for i in range(4) for j in range(4) if i != j)
            for b in range(B)
        ]
    ) / (4 - 1)
    np.testing.assert_allclose(penalty, expected, rtol=1e-4)

    state = sac.init(jax.random.PRNGKey(2), OBS, ACT, config)
    key = jax.random.PRNGKey(5)
    with_penalty, metrics = sac.critic_loss(state.critic, state, batch, key, config, 1.0)
    without, _ = sac.critic_loss(state.critic, state, batch, key, tiny(num_critics=4), 1.0)
    np.testing.assert_allclose(with_penalty - without, penalty, rtol=1e-4)


def test_actor_and_temperature_updates_match_hand_computation(batch):
    config = tiny(num_critics=2)
    state = sac.init(jax.random.PRNGKey(0), OBS, ACT, config)
    key = jax.random.PRNGKey(4)
    loss, (log_prob, _) = sac.actor_loss(
        state.actor, state.critic, state.log_alpha, batch, key, 1.0
    )
    action, expected_log_prob = sac.sample_action(state.actor, batch.observations, key, 1.0)
    q = np_q(state.critic, 2, np.asarray(batch.observations), np.asarray(action)).min(0)
    np.testing.assert_allclose(loss, (1.0 * np.asarray(expected_log_prob) - q).mean(), rtol=1e-5)
    np.testing.assert_allclose(log_prob, expected_log_prob)

    # The temperature descends -log_alpha * (log_pi + target_entropy) from log_alpha = 0, and
    # Adam's first step is lr * sign of the negated gradient.
    key = jax.random.PRNGKey(9)
    new_state, _ = sac_update(state, batch, key, config, 1.0)
    _, actor_key = jax.random.split(key)
    log_prob = sac.sample_action(state.actor, batch.observations, actor_key, 1.0)[1]
    gap = float(np.mean(np.asarray(log_prob)) + state.target_entropy)
    assert state.target_entropy == -ACT
    np.testing.assert_allclose(
        float(new_state.log_alpha), np.sign(gap) * config.alpha_lr, rtol=1e-3
    )
    assert int(new_state.step) == 1


def test_fixed_temperature_stays_while_the_networks_learn(batch):
    config = tiny(init_alpha=0.2, autotune=False)
    state = sac.init(jax.random.PRNGKey(0), OBS, ACT, config)
    new_state, metrics = sac_update(state, batch, jax.random.PRNGKey(1), config, 1.0)
    assert float(new_state.log_alpha) == float(np.log(np.float32(0.2)))
    np.testing.assert_allclose(metrics["alpha"], 0.2, rtol=1e-6)
    assert not np.allclose(new_state.actor["w0"], state.actor["w0"])
    assert not np.allclose(new_state.critic["w0"], state.critic["w0"])
    # The same update with tuning on moves the temperature.
    tuned = dataclasses.replace(config, autotune=True)
    moved, _ = sac_update(state, batch, jax.random.PRNGKey(1), tuned, 1.0)
    assert float(moved.log_alpha) != float(state.log_alpha)


def test_sac_command_uses_the_environment_preset_and_overrides():
    walker = cli.sac_agent_config(cli.Sac(config=online.SACTrainConfig(env="walker2d")))
    assert walker == sac.ONLINE_PRESETS["walker2d"]
    assert (walker.autotune, walker.init_alpha, walker.critic_lr) == (False, 0.2, 1e-3)
    hopper = cli.sac_agent_config(cli.Sac(config=online.SACTrainConfig(env="hopper")))
    assert hopper == sac.PRESETS["sac"] and hopper.autotune
    fixed = cli.sac_agent_config(
        cli.Sac(config=online.SACTrainConfig(env="hopper"), alpha=0.1, lr=5e-4)
    )
    assert (fixed.autotune, fixed.init_alpha, fixed.actor_lr, fixed.critic_lr) == (
        False, 0.1, 5e-4, 5e-4,
    )  # fmt: skip
    with pytest.raises(ValueError, match="--alpha must be positive"):
        cli.sac_agent_config(cli.Sac(config=online.SACTrainConfig(env="hopper"), alpha=0.0))


def test_actor_is_mean_action_when_deterministic():
    config = tiny()
    actor = sac.init(jax.random.PRNGKey(0), OBS, ACT, config).actor
    obs = np.random.default_rng(0).normal(size=(4, OBS)).astype(np.float32)
    mean = np_mlp(actor, obs)[:, :ACT]
    act = networks.numpy_actor(jax.device_get(actor), 1.0, gaussian=True)
    np.testing.assert_allclose(act(obs), np.tanh(mean), rtol=1e-5, atol=1e-6)


PENDULUM = dict(
    env="Pendulum-v1",
    start_steps=1000,
    eval_interval=1000,
    snapshot_interval=1000,
    checkpoint_interval=1000,
    eval_episodes=3,
)


def test_online_sac_learns_pendulum_and_keeps_snapshots(tmp_path):
    # SAC's own 256-256 networks on batches of 64, not 256: a third of the CPU time (20 s against
    # 58 s on two busy cores) and as good a policy (returns -1613, -1793, -1160, -253, -246
    # at steps 1000-5000, against -1482, -1756, -1045, -493, -247); 64-64 networks on batches of
    # 256 stayed at -859 by step 5000.
    config = online.SACTrainConfig(**PENDULUM, steps=5000, batch_size=64)
    run = online.start_sac(config, tmp_path / "sac")
    summary = online.train_sac(run, progress=False)
    returns = {int(k): v["return_mean"] for k, v in run.state["evaluations"].items()}
    assert returns[1000] < -900, returns  # the untrained policy barely moves the pendulum
    assert returns[5000] > -500, returns
    assert summary["steps"] == 5000
    snapshots = sorted(p.name for p in (tmp_path / "sac" / online.SNAPSHOTS).iterdir())
    assert snapshots == [f"actor_{s:08d}.npz" for s in range(1000, 5001, 1000)]
    with np.load(tmp_path / "sac" / online.SNAPSHOTS / snapshots[-1], allow_pickle=False) as f:
        final = dict(f)
    for k, v in jax.device_get(run.state["agent"].actor).items():
        np.testing.assert_array_equal(final[k], v)


def test_online_sac_resumes_from_its_checkpoint(tmp_path):
    config = online.SACTrainConfig(**PENDULUM, steps=2000)
    # Small networks: resuming does not depend on their size, and the run's own settings (not the
    # preset's) must come back from config.json.
    agent = dataclasses.replace(sac.online_preset(config.env), hidden_dims=(16, 16))
    run = online.start_sac(config, tmp_path / "sac", agent)
    online.train_sac(run, progress=False)
    saved = json.loads((tmp_path / "sac" / "config.json").read_text())
    assert saved["sac"]["steps"] == 2000
    # Extend the run: the resumed run starts at step 2000 with its buffer and history.
    saved["sac"]["steps"] = 3000
    checkpoint.save_json(tmp_path / "sac" / "config.json", saved)
    resumed = online.resume_sac(tmp_path / "sac")
    assert resumed.agent_config == agent
    assert resumed.state["step"] == 2000 and resumed.buffer.size == 2000
    before = jax.device_get(resumed.state["agent"].critic)
    for k, v in jax.device_get(run.state["agent"].critic).items():
        np.testing.assert_array_equal(before[k], v)
    assert len(resumed.state["episodes"]) == 10  # 200-step episodes
    summary = online.train_sac(resumed, progress=False)
    assert summary["steps"] == 3000 and resumed.buffer.size == 3000
    assert sorted(resumed.state["evaluations"], key=int) == ["1000", "2000", "3000"]


def test_edac_config_rejects_a_single_critic():
    with pytest.raises(ValueError, match="num_critics"):
        sac.SACConfig(num_critics=1, eta=1.0)


def test_offline_edac_improves_on_the_untrained_policy(tmp_path, pendulum_dataset):
    overrides = dict(num_critics=5)
    untrained, late, evaluations = late_gain(tmp_path, pendulum_dataset, "edac-10", overrides)
    assert late > untrained + MARGIN, (untrained, evaluations)
