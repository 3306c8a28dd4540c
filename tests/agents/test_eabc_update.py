"""The EABC update rule against hand computations, and TD3+BC / TD3 as its special cases."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from handcalc import ACT, OBS, B, member, np_mlp, np_q, quick_jit

from eabc.agents import eabc

eabc_update = quick_jit(eabc.update)


def tiny(**kw):
    return dataclasses.replace(eabc.EABCConfig(hidden_dims=(8, 8)), **kw)


def test_pessimistic_value_operators():
    q = jnp.asarray(np.random.default_rng(1).normal(size=(4, 6)), jnp.float32)
    key = jax.random.PRNGKey(0)
    expected = np.asarray(q).mean(0) - np.asarray(q).std(0, ddof=1)
    np.testing.assert_allclose(eabc.pessimistic_value(q, "mean-std", key), expected, rtol=1e-5)
    np.testing.assert_allclose(eabc.pessimistic_value(q, "min", key), np.asarray(q).min(0))
    pairs = set()
    for seed in range(40):
        got = np.asarray(eabc.pessimistic_value(q, "min2", jax.random.PRNGKey(seed)))
        match = [
            (i, j)
            for i in range(4)
            for j in range(i + 1, 4)
            if np.allclose(got, np.minimum(q[i], q[j]))
        ]
        assert match, "min2 must be the minimum of two distinct members"
        pairs.add(match[0])
    assert len(pairs) >= 4, "min2 must draw a fresh pair of members"


def test_critic_loss_matches_hand_computation(batch):
    config = tiny(num_critics=3)
    state = eabc.init(jax.random.PRNGKey(0), OBS, ACT, config)
    # Make targets differ from online networks so the test tells them apart.
    critic_target = jax.tree.map(lambda x: x * 0.9 + 0.01, state.critic)
    actor_target = jax.tree.map(lambda x: x * 1.1, state.actor)
    key, max_action = jax.random.PRNGKey(3), 1.0
    loss, metrics = eabc.critic_loss(
        state.critic, critic_target, actor_target, batch, key, config, max_action
    )

    noise_key, _ = jax.random.split(key)
    noise = np.clip(np.asarray(jax.random.normal(noise_key, (B, ACT))) * 0.2, -0.5, 0.5)
    s, a, r, s2, d = (
        batch.observations,
        batch.actions,
        batch.rewards,
        batch.next_observations,
        batch.dones,
    )
    s, a, r, s2, d = (np.asarray(x, np.float64) for x in (s, a, r, s2, d))
    a2 = np.clip(np.tanh(np_mlp(actor_target, s2)) + noise, -1, 1)
    q_next = np_q(critic_target, 3, s2, a2)
    y = r + 0.99 * (1 - d) * (q_next.mean(0) - q_next.std(0, ddof=1))
    q = np_q(state.critic, 3, s, a)
    expected = sum(((q[i] - y) ** 2).mean() for i in range(3))
    np.testing.assert_allclose(loss, expected, rtol=1e-4)
    np.testing.assert_allclose(metrics["target_mean"], y.mean(), rtol=1e-4)


@pytest.mark.parametrize("p", [0.0, 0.5, 1.0])
def test_actor_loss_matches_hand_computation(batch, p):
    config = tiny(num_critics=4, confidence_level=p)
    state = eabc.init(jax.random.PRNGKey(1), OBS, ACT, config)
    key = jax.random.PRNGKey(5)
    loss, metrics = eabc.actor_loss(state.actor, state.critic, batch, key, config, 1.0)

    _, mask_key = jax.random.split(key)
    w = np.asarray(jax.random.bernoulli(mask_key, p, (B,)), np.float64)
    s, a = np.asarray(batch.observations, np.float64), np.asarray(batch.actions, np.float64)
    pi = np.tanh(np_mlp(state.actor, s))
    q = np_q(state.critic, 4, s, pi)
    value = q.mean(0) - q.std(0, ddof=1)
    lam = 2.5 / np.abs(value).mean()
    expected = -lam * value.mean() + (w * ((pi - a) ** 2).mean(-1)).mean()
    np.testing.assert_allclose(loss, expected, rtol=1e-4)
    np.testing.assert_allclose(metrics["bc_fraction"], w.mean())
    np.testing.assert_allclose(metrics["policy_q_std"], q.std(0, ddof=1).mean(), rtol=1e-4)
    if p == 1.0:  # exactly TD3+BC's mean-squared error
        np.testing.assert_allclose(metrics["bc_loss"], ((pi - a) ** 2).mean(), rtol=1e-5)

    # Gradient: lambda is a constant (stop_gradient), the gradient flows through mean and std.
    def with_constant_lambda(actor):
        pi = jnp.tanh(_mlp(actor, batch.observations))
        qs = jnp.stack(
            [
                _mlp(member(state.critic, i), jnp.concatenate([batch.observations, pi], -1))[:, 0]
                for i in range(4)
            ]
        )
        v = qs.mean(0) - qs.std(0, ddof=1)
        return -lam * v.mean() + (w * ((pi - batch.actions) ** 2).mean(-1)).mean()

    got = jax.grad(lambda actor: eabc.actor_loss(actor, state.critic, batch, key, config, 1.0)[0])(
        state.actor
    )
    want = jax.grad(with_constant_lambda)(state.actor)
    for k in got:
        np.testing.assert_allclose(got[k], want[k], rtol=2e-3, atol=1e-6)


def _mlp(params, x):
    n = len(params) // 2
    for i in range(n):
        x = x @ params[f"w{i}"] + params[f"b{i}"]
        if i < n - 1:
            x = jax.nn.relu(x)
    return x


def reference_td3bc_losses(state, batch, key, max_action=1.0):
    """TD3+BC's losses written out as in the authors' code, with two separate critics."""
    q1, q2 = member(state.critic, 0), member(state.critic, 1)
    q1t, q2t = member(state.critic_target, 0), member(state.critic_target, 1)
    noise_key, _ = jax.random.split(key)
    noise = jnp.clip(jax.random.normal(noise_key, batch.actions.shape) * 0.2, -0.5, 0.5)
    next_action = jnp.clip(
        jnp.tanh(_mlp(state.actor_target, batch.next_observations)) + noise, -1, 1
    )
    sa2 = jnp.concatenate([batch.next_observations, next_action], -1)
    target_q = jnp.minimum(_mlp(q1t, sa2), _mlp(q2t, sa2))[:, 0]
    target_q = batch.rewards + (1 - batch.dones) * 0.99 * target_q
    sa = jnp.concatenate([batch.observations, batch.actions], -1)
    critic_loss = ((_mlp(q1, sa)[:, 0] - target_q) ** 2).mean() + (
        (_mlp(q2, sa)[:, 0] - target_q) ** 2
    ).mean()

    def actor_loss(actor):
        pi = jnp.tanh(_mlp(actor, batch.observations))
        q = _mlp(q1, jnp.concatenate([batch.observations, pi], -1))[:, 0]
        lmbda = jax.lax.stop_gradient(2.5 / jnp.abs(q).mean())
        return -lmbda * q.mean() + ((pi - batch.actions) ** 2).mean()

    return critic_loss, actor_loss


def test_td3bc_preset_equals_reference(batch):
    config = dataclasses.replace(eabc.PRESETS["td3bc"], hidden_dims=(8, 8))
    state = eabc.init(jax.random.PRNGKey(2), OBS, ACT, config)
    state = state.replace(critic_target=jax.tree.map(lambda x: x * 0.95, state.critic))
    key = jax.random.PRNGKey(9)
    ref_critic, ref_actor = reference_td3bc_losses(state, batch, key)
    critic, _ = eabc.critic_loss(
        state.critic, state.critic_target, state.actor_target, batch, key, config, 1.0
    )
    np.testing.assert_allclose(critic, ref_critic, rtol=1e-5)
    actor, _ = eabc.actor_loss(state.actor, state.critic, batch, key, config, 1.0)
    np.testing.assert_allclose(actor, ref_actor(state.actor), rtol=1e-5)
    got = jax.grad(lambda a: eabc.actor_loss(a, state.critic, batch, key, config, 1.0)[0])(
        state.actor
    )
    want = jax.grad(ref_actor)(state.actor)
    for k in got:
        np.testing.assert_allclose(got[k], want[k], rtol=1e-4, atol=1e-7)


def test_td3_preset_has_no_bc_term(batch):
    config = dataclasses.replace(eabc.PRESETS["td3"], hidden_dims=(8, 8))
    state = eabc.init(jax.random.PRNGKey(2), OBS, ACT, config)
    loss, _ = eabc.actor_loss(state.actor, state.critic, batch, jax.random.PRNGKey(0), config, 1.0)
    pi = jnp.tanh(_mlp(state.actor, batch.observations))
    q1 = _mlp(member(state.critic, 0), jnp.concatenate([batch.observations, pi], -1))[:, 0]
    np.testing.assert_allclose(loss, -q1.mean(), rtol=1e-5)


def test_actor_and_targets_move_every_policy_freq_steps(batch):
    config = tiny(num_critics=3, confidence_level=0.5)
    state = eabc.init(jax.random.PRNGKey(0), OBS, ACT, config)
    s1, m1 = eabc_update(state, batch, jax.random.PRNGKey(1), config, 1.0)
    assert not bool(m1["actor_updated"])
    assert all(np.array_equal(s1.actor[k], state.actor[k]) for k in state.actor)
    assert all(np.array_equal(s1.critic_target[k], state.critic_target[k]) for k in state.critic)
    assert not np.array_equal(s1.critic["w1"], state.critic["w1"])
    s2, m2 = eabc_update(s1, batch, jax.random.PRNGKey(2), config, 1.0)
    assert bool(m2["actor_updated"]) and int(s2.step) == 2
    assert not np.array_equal(s2.actor["w0"], s1.actor["w0"])
    expected = 0.005 * np.asarray(s2.critic["w1"]) + 0.995 * np.asarray(s1.critic_target["w1"])
    np.testing.assert_allclose(s2.critic_target["w1"], expected, rtol=1e-6)


def test_ensemble_members_are_initialised_independently():
    state = eabc.init(jax.random.PRNGKey(0), OBS, ACT, tiny(num_critics=5))
    w = np.asarray(state.critic["w0"])
    assert w.shape == (5, OBS + ACT, 8)
    assert all(not np.allclose(w[0], w[i]) for i in range(1, 5))


def test_invalid_settings_are_refused():
    with pytest.raises(ValueError, match="confidence_level"):
        eabc.EABCConfig(confidence_level=1.5)
    with pytest.raises(ValueError, match="num_critics"):
        eabc.EABCConfig(num_critics=1)
