"""The variants of the EABC rule (the study's) against hand computations, and the auto-p controller's
response to synthetic signals."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from handcalc import ACT, OBS, B, member, np_mlp, quick_jit
from learning import MARGIN, late_gain

from eabc import networks, ranges
from eabc.agents import bc_weights, eabc
from eabc.training.config import resolve_agent_config

eabc_update = quick_jit(eabc.update)


def tiny(**kw):
    """A small EABC config with ``kw`` set by name (a BC-weight rule's settings too)."""
    return ranges.validated(eabc.EABCConfig(hidden_dims=(8, 8), num_critics=4), kw)


def np_layer_norm_q(critic, k, obs, act):
    """Every member's Q with LayerNorm before each hidden ReLU, in float64."""
    out = []
    for i in range(k):
        params = {name: np.asarray(v[i], np.float64) for name, v in critic.items()}
        x = np.concatenate([obs, act], -1)
        n = sum(name.startswith("w") for name in params)
        for layer in range(n):
            x = x @ params[f"w{layer}"] + params[f"b{layer}"]
            if layer < n - 1:
                mean, var = x.mean(-1, keepdims=True), x.var(-1, keepdims=True)
                x = (x - mean) / np.sqrt(var + 1e-5) * params[f"g{layer}"] + params[f"h{layer}"]
                x = np.maximum(x, 0.0)
        out.append(x[:, 0])
    return np.stack(out)


def test_layer_norm_critic_matches_hand_computation(batch):
    config = tiny(critic_layer_norm=True)
    state = eabc.init(jax.random.PRNGKey(0), OBS, ACT, config)
    assert state.critic["g0"].shape == (4, 8) and "g2" not in state.critic
    # Non-trivial scale and offset, so the test sees them used per member.
    rng = np.random.default_rng(0)
    critic = {
        **state.critic,
        **{n: jnp.asarray(rng.normal(size=(4, 8)), jnp.float32) for n in ("g0", "h0", "g1", "h1")},
    }
    got = networks.critic_apply(critic, batch.observations, batch.actions)
    s, a = (np.asarray(x, np.float64) for x in (batch.observations, batch.actions))
    np.testing.assert_allclose(got, np_layer_norm_q(critic, 4, s, a), rtol=1e-4, atol=1e-5)
    assert networks.num_layers(critic) == 3


def _target_inputs(state, batch, key, config):
    noise_key, _ = jax.random.split(key)
    noise = np.clip(np.asarray(jax.random.normal(noise_key, (B, ACT))) * 0.2, -0.5, 0.5)
    s2 = np.asarray(batch.next_observations, np.float64)
    a2 = np.clip(np.tanh(np_mlp(state.actor_target, s2)) + noise, -1, 1)
    k = config.num_critics
    sa2 = np.concatenate([s2, a2], -1)
    q_next = np.stack([np_mlp(member(state.critic_target, i), sa2)[:, 0] for i in range(k)])
    s, a = (np.asarray(x, np.float64) for x in (batch.observations, batch.actions))
    q = np.stack(
        [np_mlp(member(state.critic, i), np.concatenate([s, a], -1))[:, 0] for i in range(k)]
    )
    r, d = np.asarray(batch.rewards, np.float64), np.asarray(batch.dones, np.float64)
    return q, q_next, r, d


@pytest.mark.parametrize("beta", [0.0, 2.5])
def test_pessimism_beta_scales_the_std_in_the_shared_target(batch, beta):
    config = tiny(pessimism_beta=beta)
    state = eabc.init(jax.random.PRNGKey(1), OBS, ACT, config)
    state = state.replace(critic_target=jax.tree.map(lambda x: x * 0.9 + 0.01, state.critic))
    key = jax.random.PRNGKey(4)
    loss, metrics = eabc.critic_loss(
        state.critic, state.critic_target, state.actor_target, batch, key, config, 1.0
    )
    q, q_next, r, d = _target_inputs(state, batch, key, config)
    y = r + 0.99 * (1 - d) * (q_next.mean(0) - beta * q_next.std(0, ddof=1))
    np.testing.assert_allclose(loss, ((q - y) ** 2).mean(1).sum(), rtol=1e-4)
    np.testing.assert_allclose(metrics["target_mean"], y.mean(), rtol=1e-4)


def test_independent_targets_give_each_member_its_own_target(batch):
    config = tiny(independent_targets=True)
    state = eabc.init(jax.random.PRNGKey(1), OBS, ACT, config)
    state = state.replace(critic_target=jax.tree.map(lambda x: x * 0.9 + 0.01, state.critic))
    key = jax.random.PRNGKey(4)
    loss, _ = eabc.critic_loss(
        state.critic, state.critic_target, state.actor_target, batch, key, config, 1.0
    )
    q, q_next, r, d = _target_inputs(state, batch, key, config)
    y = r + 0.99 * (1 - d) * q_next  # [K, B]
    np.testing.assert_allclose(loss, ((q - y) ** 2).mean(1).sum(), rtol=1e-4)
    shared = r + 0.99 * (1 - d) * (q_next.mean(0) - q_next.std(0, ddof=1))
    assert not np.isclose(float(loss), ((q - shared) ** 2).mean(1).sum(), rtol=1e-3)


def test_actor_uses_beta_in_its_pessimistic_value(batch):
    config = tiny(pessimism_beta=3.0, confidence_level=0.0)
    state = eabc.init(jax.random.PRNGKey(2), OBS, ACT, config)
    _, metrics = eabc.actor_loss(
        state.actor, state.critic, batch, jax.random.PRNGKey(0), config, 1.0
    )
    s = np.asarray(batch.observations, np.float64)
    pi = np.tanh(np_mlp(state.actor, s))
    q = np.stack(
        [np_mlp(member(state.critic, i), np.concatenate([s, pi], -1))[:, 0] for i in range(4)]
    )
    expected = (q.mean(0) - 3.0 * q.std(0, ddof=1)).mean()
    np.testing.assert_allclose(metrics["actor_value"], expected, rtol=1e-4)


@pytest.mark.parametrize("level", [0.05, 0.45, 0.9, 1.0])
def test_quantile_rule_matches_hand_computation(batch, level):
    config = tiny(bc_weight="quantile", quantile_level=level, num_critics=5)
    state = eabc.init(jax.random.PRNGKey(3), OBS, ACT, config)
    got = np.asarray(bc_weights.quantile_keep(state.critic, batch, config))
    s, a = (np.asarray(x, np.float64) for x in (batch.observations, batch.actions))
    q = np.stack(
        [np_mlp(member(state.critic, i), np.concatenate([s, a], -1))[:, 0] for i in range(5)]
    )
    upper = np.quantile(q, level, axis=0)  # linear interpolation, as torch.quantile
    expected = upper > q.mean(0) + q.std(0, ddof=1) / np.sqrt(5)
    np.testing.assert_array_equal(got, expected.astype(np.float32))
    if level == 1.0:  # the maximum is above mean + std / sqrt(K) for any non-constant ensemble
        assert got.all()


def test_quantile_rule_masks_the_actor_step_with_the_pre_update_critics(batch):
    config = tiny(bc_weight="quantile", quantile_level=0.45, num_critics=5)
    state = eabc.init(jax.random.PRNGKey(3), OBS, ACT, config)
    state = state.replace(step=jnp.ones((), jnp.int32))  # the next step updates the actor
    _, metrics = eabc_update(state, batch, jax.random.PRNGKey(0), config, 1.0)
    keep = bc_weights.quantile_keep(state.critic, batch, config)
    np.testing.assert_allclose(metrics["bc_fraction"], keep.mean())


def _pessimistic(critic, obs, act, k=4, beta=1.0):
    q = np.stack(
        [np_mlp(member(critic, i), np.concatenate([obs, act], -1))[:, 0] for i in range(k)]
    )
    return q.mean(0) - beta * q.std(0, ddof=1)


@pytest.mark.parametrize("beta", [0.0, 1.0, 2.0])
def test_advantage_rule_matches_hand_computation(batch, beta):
    config = tiny(bc_weight="advantage", pessimism_beta=beta)
    state = eabc.init(jax.random.PRNGKey(4), OBS, ACT, config)
    loss, metrics = eabc.actor_loss(
        state.actor, state.critic, batch, jax.random.PRNGKey(0), config, 1.0
    )
    s, a = (np.asarray(x, np.float64) for x in (batch.observations, batch.actions))
    pi = np.tanh(np_mlp(state.actor, s))
    policy_value = _pessimistic(state.critic, s, pi, beta=beta)
    keep = (_pessimistic(state.critic, s, a, beta=beta) >= policy_value).astype(np.float64)
    assert 0 < keep.sum() < len(keep)  # this batch has both cases, so the mask is tested
    bc = (keep * ((pi - a) ** 2).mean(-1)).mean()
    expected = -2.5 / np.abs(policy_value).mean() * policy_value.mean() + bc
    np.testing.assert_allclose(metrics["bc_fraction"], keep.mean(), rtol=1e-6)
    np.testing.assert_allclose(metrics["bc_loss"], bc, rtol=1e-4)
    np.testing.assert_allclose(loss, expected, rtol=1e-4)


def test_advantage_rule_clones_where_the_policy_takes_the_data_action(batch):
    """At the data's own actions the two values are equal, so every sample is cloned (also for
    min2, whose random pair is the same for both values)."""
    for pessimism in ("mean-std", "min2"):
        config = tiny(bc_weight="advantage", pessimism=pessimism)
        state = eabc.init(jax.random.PRNGKey(4), OBS, ACT, config)
        actions = networks.actor_apply(state.actor, batch.observations, 1.0)
        on_policy = batch.replace(actions=actions)
        keep = eabc.advantage_keep(
            state.critic,
            on_policy,
            eabc.pessimistic_value(
                networks.critic_apply(state.critic, batch.observations, actions),
                pessimism,
                jax.random.PRNGKey(1),
            ),
            jax.random.PRNGKey(1),
            config,
        )
        assert np.asarray(keep).all(), pessimism


def test_advantage_rule_needs_no_confidence_level(batch):
    resolved = resolve_agent_config("eabc", "hopper-medium", {"bc_weight": "advantage"})
    assert resolved.confidence_level is None  # nothing to look up, nothing to tune
    config = tiny(bc_weight="advantage")
    state = eabc.init(jax.random.PRNGKey(0), OBS, ACT, config)
    state = state.replace(step=jnp.ones((), jnp.int32))  # the next step updates the actor
    _, metrics = eabc_update(state, batch, jax.random.PRNGKey(0), config, 1.0)
    assert 0.0 <= float(metrics["bc_fraction"]) <= 1.0


def _controller(p=0.5, rewards=(0.0, 1.0)):
    return {
        "p": jnp.asarray(p),
        "reward_min": jnp.asarray(rewards[0]),
        "reward_max": jnp.asarray(rewards[1]),
    }


def _signals(policy_std, data_std, q_mean=10.0, actor_q_mean=10.0):
    return {
        "policy_q_std": jnp.asarray(policy_std),
        "q_ensemble_std": jnp.asarray(data_std),
        "q_mean": jnp.asarray(q_mean),
        "actor_q_mean": jnp.asarray(actor_q_mean),
    }


def test_auto_p_rises_when_the_policy_is_less_certain_than_the_data(batch):
    config = tiny(bc_weight="auto", auto_rate=0.01)
    rise, m = bc_weights.adapt_confidence_level(_controller(), batch, _signals(2.0, 1.0), config)
    np.testing.assert_allclose(rise["p"], 0.5 + 0.01 * np.log(2.0), rtol=1e-5)
    np.testing.assert_allclose(m["spread_ratio"], 2.0, rtol=1e-5)
    fall, _ = bc_weights.adapt_confidence_level(_controller(), batch, _signals(0.5, 1.0), config)
    np.testing.assert_allclose(fall["p"], 0.5 - 0.01 * np.log(2.0), rtol=1e-5)
    # The error is clipped to [-1, 1]: a huge ratio moves p by at most the rate.
    big, _ = bc_weights.adapt_confidence_level(_controller(), batch, _signals(1e6, 1.0), config)
    np.testing.assert_allclose(big["p"], 0.51, rtol=1e-5)
    # The target ratio shifts the set point.
    shifted = ranges.validated(config, {"auto_spread_ratio": 2.0})
    same, _ = bc_weights.adapt_confidence_level(_controller(), batch, _signals(2.0, 1.0), shifted)
    np.testing.assert_allclose(same["p"], 0.5, rtol=1e-6)


def test_calibrated_auto_p_holds_p_then_targets_the_cloning_spread_ratio(batch):
    config = tiny(bc_weight="auto", auto_rate=0.01, auto_calibration_steps=4)
    controller = {**_controller(p=1.0), "ratio_sum": jnp.zeros(()), "ratio_count": jnp.zeros(())}
    for step, ratio in zip((2, 4), (0.9, 0.7)):  # actor steps inside the calibration: p held
        controller, m = bc_weights.adapt_confidence_level(
            controller, batch, _signals(ratio, 1.0), config, jnp.asarray(step)
        )
        np.testing.assert_allclose(controller["p"], 1.0)
    np.testing.assert_allclose(m["spread_target"], 0.8, rtol=1e-5)  # mean of 0.9 and 0.7
    # After it: a ratio at the calibrated 0.8 holds p; above it p rises, below it p falls.
    held, _ = bc_weights.adapt_confidence_level(
        {**controller, "p": jnp.asarray(0.5)}, batch, _signals(0.8, 1.0), config, jnp.asarray(6)
    )
    np.testing.assert_allclose(held["p"], 0.5, rtol=1e-5)
    np.testing.assert_allclose(held["ratio_count"], 2.0)  # the calibration no longer moves
    fall, m = bc_weights.adapt_confidence_level(controller, batch, _signals(0.4, 1.0), config, 6)
    np.testing.assert_allclose(fall["p"], 1.0 - 0.01 * np.log(2.0), rtol=1e-5)
    np.testing.assert_allclose(m["spread_target"], 0.8, rtol=1e-5)
    # auto_spread_ratio scales the calibrated target.
    scaled = ranges.validated(config, {"auto_spread_ratio": 0.5})
    same, _ = bc_weights.adapt_confidence_level(
        {**controller, "p": jnp.asarray(0.5)}, batch, _signals(0.4, 1.0), scaled, 6
    )
    np.testing.assert_allclose(same["p"], 0.5, rtol=1e-5)


def test_calibrated_auto_p_in_a_training_step_starts_and_stays_at_one_while_calibrating(batch):
    config = tiny(bc_weight="auto", auto_calibration_steps=4)
    state = eabc.init(jax.random.PRNGKey(0), 3, 2, config)
    assert set(state.controller) >= {"ratio_sum", "ratio_count"}
    for i in range(6):
        state, metrics = eabc_update(state, batch, jax.random.PRNGKey(i), config, 1.0)
        if i < 4:
            assert float(state.controller["p"]) == 1.0
    assert float(state.controller["ratio_count"]) == 2.0  # actor steps 2 and 4
    assert float(state.controller["p"]) != 1.0 or float(metrics["spread_ratio"]) >= float(
        metrics["spread_target"]
    )


def _distance_signals(distance, policy_std=1.0):
    return {**_signals(policy_std, 1.0), "action_distance": jnp.asarray(distance)}


def test_distance_auto_p_calibrates_on_the_second_half_then_keeps_a_trust_region(batch):
    """auto_signal distance: p held during the calibration while the policy's distance from the
    data's actions is averaged over its second half; then the target is auto_distance_ratio x
    that mean, p falls inside it and rises outside it, whatever the spread ratio says."""
    config = tiny(
        bc_weight="auto",
        auto_signal="distance",
        auto_rate=0.01,
        auto_calibration_steps=8,
        auto_distance_ratio=2.0,
    )
    controller = {
        **_controller(p=1.0),
        "distance_sum": jnp.zeros(()),
        "distance_count": jnp.zeros(()),
    }
    # Steps 2 and 4 (first half: the fit is still settling) do not count; 6 and 8 do.
    for step, distance in zip((2, 4, 6, 8), (5.0, 3.0, 0.12, 0.08)):
        controller, m = bc_weights.adapt_confidence_level(
            controller, batch, _distance_signals(distance), config, jnp.asarray(step)
        )
        np.testing.assert_allclose(controller["p"], 1.0)
    np.testing.assert_allclose(controller["distance_count"], 2.0)
    np.testing.assert_allclose(m["distance_target"], 2.0 * 0.1, rtol=1e-4)
    at = {**controller, "p": jnp.asarray(0.5)}
    held, _ = bc_weights.adapt_confidence_level(at, batch, _distance_signals(0.2), config, 10)
    np.testing.assert_allclose(held["p"], 0.5, rtol=1e-4)
    # Inside the region p falls even where the spread ratio is high (the signal is the distance).
    fall, _ = bc_weights.adapt_confidence_level(at, batch, _distance_signals(0.1, 5.0), config, 10)
    np.testing.assert_allclose(fall["p"], 0.5 - 0.01 * np.log(2.0), rtol=1e-4)
    rise, _ = bc_weights.adapt_confidence_level(at, batch, _distance_signals(0.4, 0.1), config, 10)
    np.testing.assert_allclose(rise["p"], 0.5 + 0.01 * np.log(2.0), rtol=1e-4)
    far, _ = bc_weights.adapt_confidence_level(at, batch, _distance_signals(1e3), config, 10)
    np.testing.assert_allclose(far["p"], 0.51, rtol=1e-5)  # the error is clipped at 1


def test_distance_auto_p_in_a_training_step_measures_the_policy_against_the_data(batch):
    config = tiny(bc_weight="auto", auto_signal="distance", auto_calibration_steps=4)
    state = eabc.init(jax.random.PRNGKey(0), 3, 2, config)
    assert set(state.controller) >= {"distance_sum", "distance_count"}
    assert "ratio_sum" not in state.controller
    state = state.replace(step=jnp.ones((), jnp.int32))  # the next step updates the actor
    pi = np.tanh(np_mlp(state.actor, np.asarray(batch.observations, np.float64)))
    expected = ((pi - np.asarray(batch.actions, np.float64)) ** 2).mean()
    _, metrics = eabc_update(state, batch, jax.random.PRNGKey(0), config, 1.0)
    np.testing.assert_allclose(metrics["action_distance"], expected, rtol=1e-4)
    with pytest.raises(ValueError, match="auto_calibration_steps"):
        tiny(bc_weight="auto", auto_signal="distance")
    with pytest.raises(ValueError, match="auto_signal"):
        tiny(bc_weight="auto", auto_signal="returns")


def test_auto_p_stays_within_its_bounds(batch):
    config = tiny(bc_weight="auto", auto_rate=0.3, auto_min_p=0.2)
    controller = _controller(p=0.5)
    for _ in range(10):
        controller, _ = bc_weights.adapt_confidence_level(
            controller, batch, _signals(0.01, 1.0), config
        )
    np.testing.assert_allclose(controller["p"], 0.2)
    for _ in range(10):
        controller, _ = bc_weights.adapt_confidence_level(
            controller, batch, _signals(100.0, 1.0), config
        )
    np.testing.assert_allclose(controller["p"], 1.0)


def test_auto_p_jumps_to_full_cloning_when_values_leave_what_rewards_allow(batch):
    config = tiny(bc_weight="auto", auto_rate=0.01, auto_value_margin=0.9)
    # The batch's rewards extend the range seen so far.
    seen, _ = bc_weights.adapt_confidence_level(
        _controller(rewards=(0.0, 0.0)), batch, _signals(1.0, 1.0), config
    )
    np.testing.assert_allclose(seen["reward_max"], float(np.max(batch.rewards)))
    np.testing.assert_allclose(seen["reward_min"], float(np.min(batch.rewards)))
    ceiling = 0.9 * 1.0 / (1 - 0.99)  # reward_max 1 -> V_hi = 100
    batch = dataclasses.replace(batch, rewards=jnp.clip(batch.rewards, -0.5, 0.5))
    below, m = bc_weights.adapt_confidence_level(
        _controller(p=0.1, rewards=(0.0, 5.0)), batch, _signals(0.5, 1.0, q_mean=80.0), config
    )
    assert float(below["p"]) < 0.1
    above, m = bc_weights.adapt_confidence_level(
        _controller(p=0.1, rewards=(-1e-3, 1.0)), batch, _signals(0.5, 1.0, q_mean=100.0), config
    )
    np.testing.assert_allclose(m["value_ceiling"], ceiling, rtol=1e-5)
    np.testing.assert_allclose(above["p"], 1.0)
    # At the policy's actions too, and for values that are not finite.
    policy, _ = bc_weights.adapt_confidence_level(
        _controller(p=0.1), batch, _signals(0.5, 1.0, actor_q_mean=91.0), config
    )
    nan, _ = bc_weights.adapt_confidence_level(
        _controller(p=0.1), batch, _signals(0.5, 1.0, q_mean=np.nan), config
    )
    assert float(policy["p"]) == 1.0 and float(nan["p"]) == 1.0


def test_auto_p_moves_only_on_actor_steps_and_drives_the_mask(batch):
    config = tiny(bc_weight="auto", auto_initial_p=0.5, auto_rate=0.05)
    state = eabc.init(jax.random.PRNGKey(0), OBS, ACT, config)
    np.testing.assert_allclose(state.controller["p"], 0.5)
    s1, _ = eabc_update(state, batch, jax.random.PRNGKey(1), config, 1.0)  # critic only
    np.testing.assert_array_equal(s1.controller["p"], state.controller["p"])
    s2, m2 = eabc_update(s1, batch, jax.random.PRNGKey(2), config, 1.0)  # actor step
    assert float(s2.controller["p"]) != 0.5
    np.testing.assert_allclose(m2["auto_p"], s2.controller["p"])
    # The actor step's Bernoulli mask used p = 0.5 (the controller's value before the step).
    _, mask_key = jax.random.split(jax.random.split(jax.random.PRNGKey(2))[1])
    expected = jax.random.bernoulli(mask_key, 0.5, (B,)).mean()
    np.testing.assert_allclose(m2["bc_fraction"], expected)


def test_variant_presets_resolve_against_the_dataset():
    quantile = resolve_agent_config("eabc-quantile", "hopper-medium-replay", {})
    assert quantile.bc_rule.bc_weight == "quantile" and quantile.bc_rule.quantile_level == 0.45
    with pytest.raises(ValueError, match="quantile_level"):
        resolve_agent_config("eabc-quantile", "my-data", {})
    # auto needs no p, on any data; published EABC still needs Table 3's.
    assert resolve_agent_config("eabc-auto", "my-data", {}).bc_rule.bc_weight == "auto"
    eabc_q = resolve_agent_config(
        "eabc", "my-data", {"bc_weight": "quantile", "quantile_level": 0.5}
    )
    assert eabc_q.bc_rule.quantile_level == 0.5
    with pytest.raises(ValueError, match="confidence level"):
        resolve_agent_config("eabc", "my-data", {})


def test_invalid_variant_settings_are_refused():
    with pytest.raises(ValueError, match="bc_weight"):
        bc_weights.BCWeightConfig(bc_weight="sometimes")
    with pytest.raises(ValueError, match="quantile_level"):
        bc_weights.BCWeightConfig(quantile_level=1.5)
    with pytest.raises(ValueError, match="auto_min_p"):
        bc_weights.BCWeightConfig(auto_min_p=0.8, auto_initial_p=0.5)
    with pytest.raises(ValueError, match="pessimism_beta"):
        eabc.EABCConfig(pessimism_beta=-1.0)
    with pytest.raises(ValueError, match="auto_calibration_steps"):
        bc_weights.BCWeightConfig(auto_calibration_steps=-5)


def test_eabc_auto_learns(tmp_path, pendulum_dataset):
    overrides = {"num_critics": 4, "critic_layer_norm": True}
    untrained, late, evaluations = late_gain(tmp_path, pendulum_dataset, "eabc-auto", overrides)
    assert late > untrained + MARGIN, (untrained, late, evaluations)
