"""BC and wPC: losses against hand computations, and learning on a small Pendulum dataset."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from handcalc import ACT, OBS, np_mlp, np_q, quick_jit
from learning import MARGIN, late_gain

from eabc.agents import bc, eabc, wpc

wpc_update = quick_jit(wpc.update)


def test_bc_loss_and_step_match_hand_computation(batch):
    config = bc.BCConfig(hidden_dims=(8, 8))
    state = bc.init(jax.random.PRNGKey(0), OBS, ACT, config)
    loss, _ = bc.bc_loss(state.actor, batch, 2.0)
    pi = 2.0 * np.tanh(np_mlp(state.actor, np.asarray(batch.observations)))
    np.testing.assert_allclose(loss, ((pi - np.asarray(batch.actions)) ** 2).mean(), rtol=1e-5)
    new_state, _ = bc.update(state, batch, jax.random.PRNGKey(1), config, 2.0)
    assert float(bc.bc_loss(new_state.actor, batch, 2.0)[0]) < float(loss)
    assert int(new_state.step) == 1


def test_wpc_value_loss_and_advantage_mask_match_hand_computation(batch):
    config = wpc.WPCConfig(hidden_dims=(8, 8))
    state = wpc.init(jax.random.PRNGKey(0), OBS, ACT, config)
    td3bc = state.td3bc  # TD3+BC's networks, which wPC's state holds
    obs, act = np.asarray(batch.observations), np.asarray(batch.actions)
    loss, (advantage, _) = wpc.value_loss(state.value, td3bc.critic_target, batch)
    target = np_q(td3bc.critic_target, 2, obs, act).min(0)
    v = np_mlp(state.value, obs)[:, 0]
    np.testing.assert_allclose(loss, ((v - target) ** 2).mean(), rtol=1e-5)
    np.testing.assert_allclose(advantage, target - v, rtol=1e-5, atol=1e-6)
    keep = target - v > 0
    assert 0 < keep.sum() < len(keep), "the tiny batch should have both signs"

    # The actor's BC term is kept exactly where the advantage is positive.
    actor_loss, metrics = eabc.actor_loss(
        state.actor, td3bc.critic, batch, jax.random.PRNGKey(3), config, 1.0, keep=advantage > 0
    )
    pi = np.tanh(np_mlp(state.actor, obs))
    q1 = np_q(td3bc.critic, 1, obs, pi)[0]
    lam = 2.5 / np.abs(q1).mean()
    expected = -lam * q1.mean() + (keep * ((pi - act) ** 2).mean(-1)).mean()
    np.testing.assert_allclose(actor_loss, expected, rtol=1e-4)
    np.testing.assert_allclose(metrics["bc_fraction"], keep.mean())


def test_wpc_update_steps_value_every_step_and_actor_every_second(batch):
    config = wpc.WPCConfig(hidden_dims=(8, 8))
    state = wpc.init(jax.random.PRNGKey(0), OBS, ACT, config)
    s1, m1 = wpc_update(state, batch, jax.random.PRNGKey(1), config, 1.0)
    assert not bool(m1["actor_updated"])
    assert not np.allclose(s1.value["w0"], state.value["w0"])
    np.testing.assert_array_equal(s1.actor["w0"], state.actor["w0"])
    s2, m2 = wpc_update(s1, batch, jax.random.PRNGKey(2), config, 1.0)
    assert bool(m2["actor_updated"]) and not np.allclose(s2.actor["w0"], s1.actor["w0"])


@pytest.mark.parametrize("algo", ["bc", "wpc"])
def test_learning_improves_on_the_untrained_policy(tmp_path, pendulum_dataset, algo):
    untrained, late, evaluations = late_gain(tmp_path, pendulum_dataset, algo, {})
    assert late > untrained + MARGIN, (untrained, evaluations)
