"""BEAR and UWAC: the MMD, the VAE, the soft clipped target, the actor and multiplier, UWAC's MC
dropout, spectral norm and uncertainty weights against float64 NumPy, and learning on Pendulum."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from handcalc import ACT, OBS, B, member, np_mlp, np_q
from learning import MARGIN, late_gain

from eabc.agents import bear, get_algorithm, uwac
from eabc.programs import Program
from eabc.training.chunks import FAST_COMPILE_OPTIONS

SMALL = {"hidden_dims": (8, 8), "vae_hidden_dims": (8, 8)}
UPDATE = bear.BEARConfig(**SMALL, warmup_steps=0)
"""The settings of the tests of BEAR's whole step, so that its update compiles once for them."""
# One step each: compiled quickly (XLA O0), since a test runs them once or twice.
bear_update = Program(bear.update, FAST_COMPILE_OPTIONS, static_argnums=(3, 4))
uwac_update = Program(uwac.update, FAST_COMPILE_OPTIONS, static_argnums=(3, 4))


def as64(*arrays):
    return tuple(np.asarray(x, np.float64) for x in arrays)


def np_mmd(x, y, kernel, sigma):
    """Sampled MMD of one state by explicit loops over the n x n pairs."""

    def k(a, b):
        total = 0.0
        for i in range(len(a)):
            for j in range(len(b)):
                d = (
                    np.abs(a[i] - b[j]).sum()
                    if kernel == "laplacian"
                    else ((a[i] - b[j]) ** 2).sum()
                )
                total += np.exp(-d / (2 * sigma))
        return total / (len(a) * len(b))

    return np.sqrt(k(x, x) + k(y, y) - 2 * k(x, y) + 1e-6)


def bear_state(config, seed=0):
    state = bear.init(jax.random.PRNGKey(seed), OBS, ACT, config)
    # Targets that differ from the online networks, so that the tests tell them apart.
    return state.replace(
        critic_target=jax.tree.map(lambda x: 1.2 * x + 0.03, state.critic),
        actor_target=jax.tree.map(lambda x: 0.8 * x - 0.02, state.actor),
    )


def np_gaussian_head(actor, obs):
    out = np_mlp(actor, obs)
    mean, log_std = np.split(out, 2, axis=-1)
    return mean, np.clip(log_std, -5.0, 2.0)


# ----------------------------------------------------------------------------------------- MMD


@pytest.mark.parametrize("kernel, sigma", [("laplacian", 10.0), ("gaussian", 0.7)])
def test_mmd_is_the_authors_sampled_estimate(kernel, sigma):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3, 5, ACT)).astype(np.float32)
    y = (rng.normal(size=(3, 5, ACT)) + np.array([0.0, 1.0, 3.0])[:, None, None]).astype(np.float32)
    got = bear.mmd(jnp.asarray(x), jnp.asarray(y), kernel, sigma)
    expected = [np_mmd(*as64(x[b], y[b]), kernel, sigma) for b in range(3)]
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    assert np.all(np.diff(expected) > 0), "the further apart, the larger"
    np.testing.assert_allclose(
        bear.mmd(jnp.asarray(x), jnp.asarray(x), kernel, sigma), 1e-3, rtol=1e-3
    )


# ----------------------------------------------------------------------------------------- VAE


def test_vae_loss_is_reconstruction_plus_half_the_kl(batch):
    config = bear.BEARConfig(**SMALL)
    state = bear_state(config)
    key = jax.random.PRNGKey(3)
    loss, metrics = bear.vae_loss(state.vae, batch, key, 2.0)

    s, a = as64(batch.observations, batch.actions)
    mean, log_std = np.split(np_mlp(state.vae["encoder"], np.concatenate([s, a], -1)), 2, -1)
    log_std = np.clip(log_std, -4, 15)
    eps = np.asarray(jax.random.normal(key, mean.shape), np.float64)
    z = mean + np.exp(log_std) * eps
    recon = 2.0 * np.tanh(np_mlp(state.vae["decoder"], np.concatenate([s, z], -1)))
    kl = -0.5 * (1 + 2 * log_std - mean**2 - np.exp(log_std) ** 2).mean()
    np.testing.assert_allclose(metrics["vae_kl"], kl, rtol=1e-4)
    np.testing.assert_allclose(loss, ((recon - a) ** 2).mean() + 0.5 * kl, rtol=1e-5)
    assert latent_of(state) == 2 * ACT  # latent 2 x act_dim, as the authors'


def latent_of(state):
    return state.vae["decoder"]["w0"].shape[0] - OBS


def test_vae_samples_clip_the_latent_to_half():
    config = bear.BEARConfig(**SMALL)
    state = bear_state(config)
    obs = jnp.asarray(np.random.default_rng(1).normal(size=(4, OBS)), jnp.float32)
    key = jax.random.PRNGKey(5)
    got = bear.vae_samples(state.vae, obs, key, 6)
    z = np.clip(np.asarray(jax.random.normal(key, (4, 6, 2 * ACT)), np.float64), -0.5, 0.5)
    s = np.broadcast_to(np.asarray(obs, np.float64)[:, None], (4, 6, OBS))
    expected = np_mlp(state.vae["decoder"], np.concatenate([s, z], -1))
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)


# -------------------------------------------------------------------------------------- critic


def np_sample_actions(actor, obs, key, max_action):
    mean, log_std = np_gaussian_head(actor, obs)
    eps = np.asarray(jax.random.normal(key, mean.shape), np.float64)
    return max_action * np.tanh(mean + np.exp(log_std) * eps)


@pytest.mark.parametrize("target_actor", [True, False])
def test_bear_target_mixes_min_and_max_and_takes_the_max_over_actions(batch, target_actor):
    config = bear.BEARConfig(**SMALL, num_target_actions=4, target_actor=target_actor)
    state = bear_state(config)
    key = jax.random.PRNGKey(7)
    loss, (weight, _, metrics) = bear.critic_loss(
        state.critic, state, batch, key, config, 1.5, bear.Critics()
    )

    s, a, r, s2, d = as64(*dataclasses.astuple(batch))
    action_key = jax.random.split(key, 3)[0]
    s2_rep = np.repeat(s2, 4, axis=0)
    policy = state.actor_target if target_actor else state.actor
    a2 = np_sample_actions(policy, s2_rep, action_key, 1.5)
    q_next = np_q(state.critic_target, 2, s2_rep, a2)  # [2, 4 B]
    mixed = 0.75 * q_next.min(0) + 0.25 * q_next.max(0)
    y = r + 0.99 * (1 - d) * mixed.reshape(B, 4).max(1)
    q = np_q(state.critic, 2, s, a)
    np.testing.assert_allclose(metrics["target_mean"], y.mean(), rtol=1e-5)
    np.testing.assert_allclose(loss, ((q - y) ** 2).mean(1).sum(), rtol=1e-5)
    np.testing.assert_array_equal(weight, np.ones(B))


def test_target_mix_one_is_the_clipped_double_q_min():
    q = jnp.asarray([[1.0, 5.0], [3.0, -2.0]])
    np.testing.assert_allclose(bear.soft_clipped_target(q, 1.0), [1.0, -2.0])
    np.testing.assert_allclose(bear.soft_clipped_target(q, 0.75), [1.5, -0.25])


# --------------------------------------------------------------------------- actor, multiplier


@pytest.mark.parametrize("after_warmup", [False, True])
@pytest.mark.parametrize("all_samples", [True, False])
def test_bear_actor_loss_is_value_plus_alpha_mmd_after_the_warmup(batch, after_warmup, all_samples):
    n = 3
    config = bear.BEARConfig(
        **SMALL, num_samples_match=n, warmup_steps=10, actor_q_all_samples=all_samples
    )
    state = bear_state(config)
    key = jax.random.PRNGKey(9)
    step = jnp.asarray(10 if after_warmup else 9)
    log_lagrange = jnp.asarray(0.3)
    loss, (divergence, metrics) = bear.actor_loss(
        state.actor, state.critic, state.vae, log_lagrange, step, batch, key, config, 2.0,
        bear.Critics(),
    )  # fmt: skip

    s = as64(batch.observations)[0]
    actor_key, vae_key, _ = jax.random.split(key, 3)
    mean, log_std = np_gaussian_head(state.actor, s)
    eps = np.clip(np.asarray(jax.random.normal(actor_key, (B, n, ACT)), np.float64), -0.5, 0.5)
    raw = mean[:, None] + np.exp(log_std)[:, None] * eps
    z = np.clip(np.asarray(jax.random.normal(vae_key, (B, n, 2 * ACT)), np.float64), -0.5, 0.5)
    s_rep = np.broadcast_to(s[:, None], (B, n, OBS))
    raw_behaviour = np_mlp(state.vae["decoder"], np.concatenate([s_rep, z], -1))
    mmd = np.array([np_mmd(raw_behaviour[b], raw[b], "laplacian", 10.0) for b in range(B)])
    np.testing.assert_allclose(divergence, mmd, rtol=1e-4)
    actions = 2.0 * np.tanh(raw)
    if all_samples:
        q = np.mean([np_q(state.critic, 2, s, actions[:, j]) for j in range(n)], axis=0)
    else:
        q = np_q(state.critic, 2, s, actions[:, 0])
    value = q.min(0)
    expected = (np.exp(0.3) * mmd - (value if after_warmup else 0.0)).mean()
    np.testing.assert_allclose(loss, expected, rtol=1e-4)
    np.testing.assert_allclose(metrics["actor_value"], value.mean(), rtol=1e-4)


def test_multiplier_rises_while_the_mmd_exceeds_epsilon_and_stays_clipped(batch):
    config = UPDATE  # log(alpha) starts at 0 here
    state = bear_state(config).replace(log_lagrange=jnp.asarray(0.0))
    new, metrics = bear_update(state, batch, jax.random.PRNGKey(0), config, 1.0)
    # Adam's first step moves log(alpha) by lr * sign(mean(MMD) - epsilon).
    expected = 1e-3 * np.sign(float(metrics["mmd"]) - 0.05)
    np.testing.assert_allclose(new.log_lagrange, expected, rtol=1e-4)
    grad = jax.grad(bear.lagrange_loss)(jnp.asarray(0.0), jnp.asarray([0.01, 0.02]), config)
    assert float(grad) > 0, "below epsilon the multiplier falls"
    assert float(metrics["mmd"]) > config.mmd_threshold  # so alpha would rise at the clip too
    top = state.replace(log_lagrange=jnp.asarray(config.max_log_lagrange))
    assert (
        float(bear_update(top, batch, jax.random.PRNGKey(0), config, 1.0)[0].log_lagrange) == 10.0
    )


def test_bear_update_trains_everything_and_moves_both_targets(batch):
    config = UPDATE
    state = bear_state(config)
    new, metrics = bear_update(state, batch, jax.random.PRNGKey(1), config, 1.0)
    for name in ("actor", "critic", "vae"):
        assert not np.allclose(
            jax.tree.leaves(getattr(new, name))[0], jax.tree.leaves(getattr(state, name))[0]
        ), name
    for online, target in (("actor", "actor_target"), ("critic", "critic_target")):
        expected = 0.005 * np.asarray(getattr(new, online)["w1"]) + 0.995 * np.asarray(
            getattr(state, target)["w1"]
        )
        np.testing.assert_allclose(getattr(new, target)["w1"], expected, rtol=1e-6, atol=1e-8)
    assert int(new.step) == 1
    assert np.isfinite(list(jax.device_get(metrics).values())).all()


def test_bear_defaults_are_the_authors_mujoco_settings():
    config = get_algorithm("bear").preset
    assert (config.kernel, config.mmd_sigma, config.num_samples_match) == ("laplacian", 10.0, 5)
    assert (config.mmd_threshold, config.max_log_lagrange, config.target_mix) == (0.05, 10.0, 0.75)
    assert get_algorithm("bear").gaussian_actor and get_algorithm("uwac").gaussian_actor
    with pytest.raises(ValueError, match="kernel"):
        bear.BEARConfig(kernel="rbf")
    with pytest.raises(ValueError, match="num_dropout_samples"):
        uwac.UWACConfig(num_dropout_samples=1)


# ------------------------------------------------------------------------------------- UWAC


def test_uwac_weight_is_the_clipped_exponential_or_inverse_of_the_variance():
    var = jnp.asarray([0.0, 0.5, 4.0, -1.0])
    config = uwac.UWACConfig(beta=0.5, clip_bottom=0.1, clip_top=1.0)
    np.testing.assert_allclose(
        uwac.uncertainty_weight(var, config), np.clip(np.exp(-0.5 * np.asarray(var)), 0.1, 1.0)
    )
    inverse = dataclasses.replace(config, exponential_weight=False, clip_top=1.5)
    np.testing.assert_allclose(
        uwac.uncertainty_weight(var[1:3], inverse), np.clip(0.5 / np.asarray([0.5, 4.0]), 0.1, 1.5)
    )


def test_dropout_critic_drops_hidden_units_and_rescales(batch):
    config = uwac.UWACConfig(**SMALL, dropout_rate=0.4)
    state = uwac.init(jax.random.PRNGKey(0), OBS, ACT, config)
    key = jax.random.PRNGKey(2)
    got = uwac.dropout_critic_apply(state.bear.critic, batch.observations, batch.actions, key, 0.4)
    s, a = as64(batch.observations, batch.actions)
    x = np.concatenate([s, a], -1)
    keys = jax.random.split(key, 2)
    expected = []
    for k in range(2):
        p = member(state.bear.critic, k)
        h = np.maximum(x @ np.float64(p["w0"]) + np.float64(p["b0"]), 0)
        keep = np.asarray(jax.random.bernoulli(keys[0], 0.6, (2, B, 8)))[k]
        h = np.maximum(np.where(keep, h / 0.6, 0) @ np.float64(p["w1"]) + np.float64(p["b1"]), 0)
        keep = np.asarray(jax.random.bernoulli(keys[1], 0.6, (2, B, 8)))[k]
        expected.append(
            (np.where(keep, h / 0.6, 0) @ np.float64(p["w2"]) + np.float64(p["b2"]))[:, 0]
        )
    np.testing.assert_allclose(got, np.stack(expected), rtol=1e-5, atol=1e-6)
    no_dropout = uwac.dropout_critic_apply(
        state.bear.critic, batch.observations, batch.actions, key, 0.0
    )
    np.testing.assert_allclose(no_dropout, np_q(state.bear.critic, 2, s, a), rtol=1e-5)


def test_per_pass_dropout_is_t_sampled_networks_shared_by_the_rows(batch):
    t, rate = 6, 0.4  # two groups of three passes
    config = uwac.UWACConfig(**SMALL, dropout_rate=rate)
    state = uwac.init(jax.random.PRNGKey(0), OBS, ACT, config)
    key = jax.random.PRNGKey(3)
    got = uwac.dropout_passes(
        state.bear.critic, batch.observations, batch.actions, key, rate, t
    )  # [K, T, B]
    x = np.concatenate(as64(batch.observations, batch.actions), -1)
    keys = jax.random.split(key, 2)
    masks = [np.asarray(jax.random.bernoulli(k, 1 - rate, (2, t, 8))) for k in keys]
    for k in range(2):
        p = {name: np.float64(v) for name, v in member(state.bear.critic, k).items()}
        for i in range(t):
            h = np.maximum(x @ p["w0"] + p["b0"], 0)
            h = np.maximum(np.where(masks[0][k, i], h / (1 - rate), 0) @ p["w1"] + p["b1"], 0)
            q = (np.where(masks[1][k, i], h / (1 - rate), 0) @ p["w2"] + p["b2"])[:, 0]
            np.testing.assert_allclose(got[k, i], q, rtol=1e-5, atol=1e-6)
    assert np.ptp(np.asarray(got), axis=1).min() > 0  # the passes differ


def test_per_pass_and_per_row_masks_estimate_the_same_variance():
    """Each row's T passes are independent either way: over many rows the two estimators'
    variances agree, though each row's estimate differs."""
    config = uwac.UWACConfig(hidden_dims=(32, 32), vae_hidden_dims=(8, 8), spectral_norm=False)
    state = uwac.init(jax.random.PRNGKey(0), OBS, ACT, config)
    rows = jax.random.normal(jax.random.PRNGKey(1), (400, OBS + ACT))
    obs, act = rows[:, :OBS], jnp.tanh(rows[:, OBS:])
    variances = {}
    for masks in ("per-pass", "per-row"):
        critics = uwac.DropoutCritics(dataclasses.replace(config, dropout_masks=masks))
        estimate = jax.jit(critics.estimate)  # one program, not 75 eager operations
        means, var = zip(
            *(estimate(state.bear.critic, obs, act, jax.random.PRNGKey(s)) for s in range(25)),
            strict=True,
        )
        variances[masks] = np.mean(var)
    assert variances["per-pass"] > 0, variances
    np.testing.assert_allclose(variances["per-pass"], variances["per-row"], rtol=0.1)


def test_dropout_masks_must_be_named():
    with pytest.raises(ValueError, match="per-pass"):
        uwac.UWACConfig(dropout_masks="per-batch")


def test_mc_estimate_is_the_mean_and_summed_variance_over_dropout_passes(batch):
    config = uwac.UWACConfig(
        **SMALL,
        dropout_rate=0.3,
        num_dropout_samples=6,
        spectral_norm=False,
        dropout_masks="per-row",
    )
    state = uwac.init(jax.random.PRNGKey(0), OBS, ACT, config)
    critics = uwac.DropoutCritics(config)
    key = jax.random.PRNGKey(4)
    mean, var = critics.estimate(state.bear.critic, batch.observations, batch.actions, key)
    obs, act = jnp.tile(batch.observations, (6, 1)), jnp.tile(batch.actions, (6, 1))
    passes = np.asarray(
        uwac.dropout_critic_apply(state.bear.critic, obs, act, key, 0.3), np.float64
    )
    passes = passes.reshape(2, 6, B)
    np.testing.assert_allclose(mean, passes.mean(1), rtol=1e-5)
    np.testing.assert_allclose(var, passes.var(1, ddof=1).sum(0), rtol=1e-4)
    assert (np.asarray(var) > 0).all()


def test_spectral_norm_divides_by_the_power_iteration_estimate_and_converges():
    config = uwac.UWACConfig(**SMALL)
    state = uwac.init(jax.random.PRNGKey(0), OBS, ACT, config)
    u, normalised = uwac.power_iteration(state.bear.critic, state.spectral_u)
    w = np.asarray(state.bear.critic["w1"][1], np.float64)
    v = w @ np.asarray(state.spectral_u["u1"][1], np.float64)
    v /= np.linalg.norm(v)
    u1 = v @ w
    u1 /= np.linalg.norm(u1)
    np.testing.assert_allclose(u["u1"][1], u1, rtol=1e-5)
    np.testing.assert_allclose(normalised["w1"][1], w / (v @ w @ u1), rtol=1e-5)
    many = jax.jit(
        lambda u: jax.lax.fori_loop(
            0, 500, lambda _, u: uwac.power_iteration(state.bear.critic, u)[0], u
        )
    )
    _, normalised = uwac.power_iteration(state.bear.critic, many(u))
    top = np.linalg.svd(np.asarray(normalised["w1"][1], np.float64), compute_uv=False)[0]
    np.testing.assert_allclose(top, 1.0, rtol=1e-3)


class FixedVariance(bear.Critics):
    """Plain critics whose target reports a given variance: the weight path in isolation."""

    def __init__(self, variance, config):
        object.__setattr__(self, "variance", variance)
        object.__setattr__(self, "config", config)

    def target(self, critic_target, obs, actions, key):
        q, _ = super().target(critic_target, obs, actions, key)
        return q, self.variance

    def weight(self, variance):
        return uwac.uncertainty_weight(variance, self.config)


def test_uwac_weight_multiplies_the_bellman_error_before_squaring(batch):
    config = uwac.UWACConfig(**SMALL, num_target_actions=2)
    state = bear_state(config)
    key = jax.random.PRNGKey(3)
    variance = jnp.linspace(0.0, 6.0, B * 2)
    loss, (weight, var, metrics) = bear.critic_loss(
        state.critic, state, batch, key, config, 1.0, FixedVariance(variance, config)
    )

    expected_var = np.asarray(variance).reshape(B, 2).max(1)  # the max over the m actions
    np.testing.assert_allclose(var, expected_var)
    w = np.exp(-0.5 * expected_var)
    np.testing.assert_allclose(weight, w, rtol=1e-6)
    s, a, r, s2, d = as64(*dataclasses.astuple(batch))
    next_obs = np.repeat(s2, 2, axis=0)
    a2 = np_sample_actions(state.actor, next_obs, jax.random.split(key, 3)[0], 1.0)  # current actor
    q_next = np_q(state.critic_target, 2, next_obs, a2)
    y = r + 0.99 * (1 - d) * (0.75 * q_next.min(0) + 0.25 * q_next.max(0)).reshape(B, 2).max(1)
    np.testing.assert_allclose(metrics["target_mean"], y.mean(), rtol=1e-5)
    q = np_q(state.critic, 2, s, a)
    np.testing.assert_allclose(loss, (((q - y) * w) ** 2).mean(1).sum(), rtol=1e-5)


def test_uwac_without_dropout_or_spectral_norm_is_bear(batch):
    """p = 0 (zero variance, weight 1) and no spectral norm: UWAC's step is BEAR's on the same
    settings."""
    config = uwac.UWACConfig(**SMALL, dropout_rate=0.0, spectral_norm=False, warmup_steps=0)
    fields = {f.name: getattr(config, f.name) for f in dataclasses.fields(bear.BEARConfig)}
    bear_config = bear.BEARConfig(**fields)
    state = uwac.init(jax.random.PRNGKey(0), OBS, ACT, config)
    key = jax.random.PRNGKey(6)
    new, metrics = uwac_update(state, batch, key, config, 1.0)
    expected, expected_metrics = bear_update(state.bear, batch, key, bear_config, 1.0)
    np.testing.assert_allclose(new.actor["w0"], expected.actor["w0"], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(new.bear.critic["w1"], expected.critic["w1"], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(metrics["critic_loss"], expected_metrics["critic_loss"], rtol=1e-5)
    np.testing.assert_allclose(metrics["actor_weight"], 1.0)


def test_uwac_update_moves_the_spectral_vectors_and_is_deterministic(batch):
    # The warm-up test's settings (one compiled update for both); the warm-up does not touch
    # the critics and their spectral vectors.
    config = uwac.UWACConfig(**SMALL, num_dropout_samples=4, warmup_steps=10)
    state = uwac.init(jax.random.PRNGKey(0), OBS, ACT, config)
    new, metrics = uwac_update(state, batch, jax.random.PRNGKey(1), config, 1.0)
    again, _ = uwac_update(state, batch, jax.random.PRNGKey(1), config, 1.0)
    np.testing.assert_array_equal(new.bear.critic["w0"], again.bear.critic["w0"])
    expected, _ = uwac.power_iteration(state.bear.critic_target, state.spectral_u_target)
    np.testing.assert_allclose(new.spectral_u_target["u0"], expected["u0"], rtol=1e-6)
    assert not np.allclose(new.spectral_u["u0"], state.spectral_u["u0"])
    assert 0.0 < float(metrics["actor_weight"]) <= 1.0


# ------------------------------------------------------------------------------------ learning


# Pendulum's 3,000-step check: 64-64 networks and the warm-up (20K/40K steps of MMD-only training
# in the authors' settings) shortened to 500 steps. For UWAC also: 4 dropout passes and 4 target
# actions instead of 100 and 10 (the MC estimate dominates its cost: 630 s with 10 and 10 on two
# busy cores), and the actor's lr 1e-3 (BEAR's) without spectral norm: with the
# authors' 1e-4 and spectral norm the critics grow so slowly (mean Q -4 after 2,800 steps)
# that 3,000 steps score at the untrained level (-21 vs -18). Both train on batches of 128, not
# 256, at about two thirds of the cost: UWAC gains as much over the untrained policy (seeds 0, 1,
# 2: 55, 39, 37 points, against 52, 47, 38 on 256), BEAR less but still well past the threshold
# of 30 (48, 61, 63 against 76, 78, 72).
LEARNING_BATCH = 128
LEARNING_OVERRIDES = {
    "bear": {"vae_hidden_dims": (64, 64), "warmup_steps": 500},
    "uwac": {
        "vae_hidden_dims": (64, 64),
        "warmup_steps": 500,
        "num_dropout_samples": 4,
        "num_target_actions": 4,
        "actor_lr": 1e-3,
        "spectral_norm": False,
    },
}


@pytest.mark.parametrize("algo", ["bear", "uwac"])
def test_bear_and_uwac_improve_on_the_untrained_policy(tmp_path, pendulum_dataset, algo):
    untrained, late, evaluations = late_gain(
        tmp_path, pendulum_dataset, algo, LEARNING_OVERRIDES[algo], LEARNING_BATCH
    )
    assert late > untrained + MARGIN, (untrained, evaluations)


def test_uwac_policy_ignores_the_critics_during_the_warmup(batch):
    """Before ``warmup_steps`` the actor follows the MMD alone, so the number of dropout passes
    cannot change it (why the README's 20K-step UWAC run may use T = 10)."""
    actors, critics = [], []
    for passes in (2, 4):
        config = uwac.UWACConfig(**SMALL, num_dropout_samples=passes, warmup_steps=10)
        state = uwac.init(jax.random.PRNGKey(0), OBS, ACT, config)
        for i in range(3):
            state, _ = uwac_update(state, batch, jax.random.PRNGKey(i), config, 1.0)
        actors.append(state.bear.actor)
        critics.append(state.bear.critic)
    jax.tree.map(np.testing.assert_array_equal, *actors)
    assert not np.allclose(critics[0]["w1"], critics[1]["w1"])  # T does change the critics
