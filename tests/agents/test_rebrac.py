"""ReBRAC: its losses against hand computations (the critic's next-action penalty, the actor's
beta_1), Table 11's betas per dataset, the data's next actions and ReBRAC's batch size, and
learning on Pendulum."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from handcalc import ACT, OBS, B, np_mlp, quick_jit
from learning import MARGIN, late_gain

from eabc.agents import get_algorithm, rebrac
from eabc.agents.common import Batch, BatchWithNextActions
from eabc.data.dataset import Dataset, DatasetError, Normalizer
from eabc.training.chunks import data_next_actions, device_data, next_action_known
from eabc.training.config import TrainConfig, resolve_agent_config

K = 3  # more critics than ReBRAC's 2, so that the tests see the minimum over all of them
MAX_ACTION = 2.0
rebrac_update = quick_jit(rebrac.update)


def tiny(**kw):
    config = rebrac.ReBRACConfig(
        hidden_dims=(8, 8), num_critics=K, actor_bc_weight=0.3, critic_bc_weight=0.7
    )
    return dataclasses.replace(config, **kw)


def with_next_actions(batch: Batch, seed: int = 1) -> BatchWithNextActions:
    """The tiny batch with next actions in [-MAX_ACTION, MAX_ACTION]."""
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-MAX_ACTION, MAX_ACTION, size=(B, ACT))
    return BatchWithNextActions(**vars(batch), next_actions=jnp.asarray(actions, jnp.float32))


def np_ln_q(critic, obs, act):
    """Every member's Q in float64, each hidden layer Dense, ReLU, LayerNorm (eps 1e-6, Flax's),
    as the authors' critics: ``[K, B]``."""
    out = []
    for i in range(K):
        params = {name: np.asarray(v[i], np.float64) for name, v in critic.items()}
        x = np.concatenate([obs, act], -1)
        n = sum(name.startswith("w") for name in params)
        for layer in range(n):
            x = x @ params[f"w{layer}"] + params[f"b{layer}"]
            if layer < n - 1:
                x = np.maximum(x, 0.0)
                x = (x - x.mean(-1, keepdims=True)) / np.sqrt(x.var(-1, keepdims=True) + 1e-6)
                x = x * params[f"g{layer}"] + params[f"h{layer}"]
        out.append(x[:, 0])
    return np.stack(out)


def perturbed_state(config, seed=0):
    """A fresh state whose targets differ from the online networks and whose LayerNorm scales
    and offsets are not 1 and 0, so that the tests see which network each term uses."""
    state = rebrac.init(jax.random.PRNGKey(seed), OBS, ACT, config)
    rng = np.random.default_rng(seed)

    def scrambled(critic):
        norms = {n: jnp.asarray(1 + 0.3 * rng.normal(size=v.shape), jnp.float32)
                 for n, v in critic.items() if n[0] in "gh"}  # fmt: skip
        return {**critic, **norms}

    return state.replace(
        critic=scrambled(state.critic),
        critic_target=scrambled(jax.tree.map(lambda x: 0.9 * x + 0.01, state.critic)),
        actor_target=jax.tree.map(lambda x: 1.1 * x, state.actor),
    )


def as64(*arrays):
    return tuple(np.asarray(x, np.float64) for x in arrays)


def test_critic_loss_matches_hand_computation(batch):
    config = tiny()
    state = perturbed_state(config)
    data = with_next_actions(batch)
    key = jax.random.PRNGKey(3)
    loss, metrics = rebrac.critic_loss(
        state.critic, state.critic_target, state.actor_target, data, key, config, MAX_ACTION
    )

    s, a, r, s2, d, a2_data = as64(*dataclasses.astuple(data))
    noise = np.clip(np.asarray(jax.random.normal(key, (B, ACT))) * 0.2 * 2, -0.5 * 2, 0.5 * 2)
    a2 = np.clip(MAX_ACTION * np.tanh(np_mlp(state.actor_target, s2)) + noise, -2, 2)
    penalty = ((a2 - a2_data) ** 2).sum(-1)  # summed over action dimensions, as CORL
    y = r + 0.99 * (1 - d) * (np_ln_q(state.critic_target, s2, a2).min(0) - 0.7 * penalty)
    q = np_ln_q(state.critic, s, a)
    expected = sum(((q[i] - y) ** 2).mean() for i in range(K))
    np.testing.assert_allclose(loss, expected, rtol=1e-4)
    np.testing.assert_allclose(metrics["target_mean"], y.mean(), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(metrics["critic_bc_penalty"], penalty.mean(), rtol=1e-5)
    assert penalty.mean() > 0.5, "the penalty should weigh in the test's target"

    # The target is a constant: the gradient is that of sum_i mean (Q_i(s, a) - y)^2 alone.
    y32 = jnp.asarray(y, jnp.float32)
    sa = jnp.concatenate([data.observations, data.actions], -1)

    def with_constant_target(critic):
        q = jax.vmap(lambda m: _ln_mlp(m, sa)[:, 0])(critic)
        return ((q - y32) ** 2).mean(axis=1).sum()

    got = jax.grad(lambda c: rebrac.critic_loss(
        c, state.critic_target, state.actor_target, data, key, config, MAX_ACTION)[0]
    )(state.critic)  # fmt: skip
    want = jax.grad(with_constant_target)(state.critic)
    for name in got:
        np.testing.assert_allclose(got[name], want[name], rtol=2e-3, atol=1e-5)


def _ln_mlp(params, x):
    """One member's network in JAX, written out (LayerNorm after each hidden ReLU)."""
    n = sum(name.startswith("w") for name in params)
    for layer in range(n):
        x = x @ params[f"w{layer}"] + params[f"b{layer}"]
        if layer < n - 1:
            x = jax.nn.relu(x)
            mean, var = x.mean(-1, keepdims=True), x.var(-1, keepdims=True)
            x = (x - mean) / jnp.sqrt(var + 1e-6) * params[f"g{layer}"] + params[f"h{layer}"]
    return x


@pytest.mark.parametrize("normalize_q", [True, False])
def test_actor_loss_matches_hand_computation(batch, normalize_q):
    config = tiny(normalize_q=normalize_q)
    state = perturbed_state(config, seed=1)
    data = with_next_actions(batch)
    loss, metrics = rebrac.actor_loss(state.actor, state.critic, data, config, MAX_ACTION)

    s, a = as64(data.observations, data.actions)
    pi = MAX_ACTION * np.tanh(np_mlp(state.actor, s))
    value = np_ln_q(state.critic, s, pi).min(0)  # the minimum of every critic, as CORL
    lam = 1 / np.abs(value).mean() if normalize_q else 1.0
    bc = ((pi - a) ** 2).sum(-1)
    np.testing.assert_allclose(loss, (0.3 * bc - lam * value).mean(), rtol=1e-4)
    np.testing.assert_allclose(metrics["bc_loss"], bc.mean(), rtol=1e-5)
    np.testing.assert_allclose(metrics["lambda"], lam, rtol=1e-5)

    # lambda is a constant (no gradient); the gradient flows through pi into the BC term and Q.
    def with_constant_lambda(actor):
        pi = MAX_ACTION * jnp.tanh(_mlp(actor, data.observations))
        sa = jnp.concatenate([data.observations, pi], -1)
        q = jax.vmap(lambda m: _ln_mlp(m, sa)[:, 0])(state.critic).min(0)
        return (0.3 * ((pi - data.actions) ** 2).sum(-1) - lam * q).mean()

    got = jax.grad(
        lambda actor: rebrac.actor_loss(actor, state.critic, data, config, MAX_ACTION)[0]
    )(state.actor)
    want = jax.grad(with_constant_lambda)(state.actor)
    for name in got:
        np.testing.assert_allclose(got[name], want[name], rtol=2e-3, atol=1e-6)


def _mlp(params, x):
    """The actor's MLP in JAX, written out (no LayerNorm)."""
    n = len(params) // 2
    for i in range(n):
        x = x @ params[f"w{i}"] + params[f"b{i}"]
        if i < n - 1:
            x = jax.nn.relu(x)
    return x


def test_actor_steps_on_the_new_critics_every_policy_freq_steps(batch):
    config = tiny()
    state = perturbed_state(config)
    data = with_next_actions(batch)
    s1, m1 = rebrac_update(state, data, jax.random.PRNGKey(1), config, MAX_ACTION)
    critic, _ = rebrac.critic_loss(
        state.critic, state.critic_target, state.actor_target, data, jax.random.PRNGKey(1),
        config, MAX_ACTION,
    )  # fmt: skip
    np.testing.assert_allclose(m1["critic_loss"], critic, rtol=1e-6)
    assert not bool(m1["actor_updated"]) and int(s1.step) == 1
    assert all(np.array_equal(s1.actor[k], state.actor[k]) for k in state.actor)
    assert all(np.array_equal(s1.critic_target[k], state.critic_target[k]) for k in state.critic)

    s2, m2 = rebrac_update(s1, data, jax.random.PRNGKey(2), config, MAX_ACTION)
    assert bool(m2["actor_updated"]) and int(s2.step) == 2
    actor, _ = rebrac.actor_loss(s1.actor, s2.critic, data, config, MAX_ACTION)
    np.testing.assert_allclose(m2["actor_loss"], actor, rtol=1e-6)
    assert not np.array_equal(s2.actor["w0"], s1.actor["w0"])
    expected = 0.005 * np.asarray(s2.critic["w1"]) + 0.995 * np.asarray(s1.critic_target["w1"])
    np.testing.assert_allclose(s2.critic_target["w1"], expected, rtol=1e-6)
    expected = 0.005 * np.asarray(s2.actor["w0"]) + 0.995 * np.asarray(s1.actor_target["w0"])
    np.testing.assert_allclose(s2.actor_target["w0"], expected, rtol=1e-6)


def test_networks_are_the_papers():
    state = rebrac.init(jax.random.PRNGKey(0), OBS, ACT, rebrac.ReBRACConfig())
    assert [state.critic[f"w{i}"].shape for i in range(4)] == [
        (2, OBS + ACT, 256), (2, 256, 256), (2, 256, 256), (2, 256, 1)
    ]  # fmt: skip
    assert {"g0", "g1", "g2"} <= set(state.critic) and "g3" not in state.critic
    assert sorted(state.actor) == sorted(f"{p}{i}" for p in "wb" for i in range(4)), "no LN"
    algorithm = get_algorithm("rebrac")
    assert algorithm.display_name == "ReBRAC" and algorithm.next_actions
    assert algorithm.batch_size == 1024
    preset = algorithm.preset
    assert (preset.actor_lr, preset.critic_lr, preset.tau, preset.discount) == (
        1e-3, 1e-3, 0.005, 0.99
    )  # fmt: skip


@pytest.mark.parametrize(
    ("name", "betas"),
    [
        ("hopper-medium", (0.01, 0.001)),  # the paper's; CORL's config has beta_2 0.01
        ("hopper-expert", (0.1, 0.001)),  # the paper's; CORL's config has beta_2 0.1
        ("halfcheetah_medium_replay-v2.hdf5", (0.01, 0.001)),
        ("mujoco/walker2d/random-v0", (0.01, 0.0)),
        ("walker2d-medium-expert", (0.01, 0.01)),
    ],
)
def test_table_11_betas_resolve_from_the_dataset_name(name, betas):
    config = resolve_agent_config("rebrac", name, {})
    assert (config.actor_bc_weight, config.critic_bc_weight) == betas


def test_a_beta_the_user_sets_is_kept():
    config = resolve_agent_config("rebrac", "hopper-medium", {"actor_bc_weight": 0.5})
    assert (config.actor_bc_weight, config.critic_bc_weight) == (0.5, 0.001)
    both = {"actor_bc_weight": 0.2, "critic_bc_weight": 0.0}
    config = resolve_agent_config("rebrac", "pendulum-swingup", both)
    assert (config.actor_bc_weight, config.critic_bc_weight) == (0.2, 0.0)
    assert len(rebrac.BC_WEIGHTS) == 15


def test_a_dataset_outside_table_11_needs_both_betas():
    for given in ({}, {"actor_bc_weight": 0.1}):
        with pytest.raises(ValueError) as error:
            resolve_agent_config("rebrac", "pendulum-swingup", given)
        message = str(error.value)
        assert "\n" not in message and "pendulum-swingup" in message
        assert "--set actor_bc_weight=B1 critic_bc_weight=B2" in message


def test_rebrac_trains_with_batch_1024_unless_the_user_sets_one():
    assert TrainConfig(algo="rebrac").batch_size == 1024
    assert TrainConfig(algo="td3bc").batch_size == 256
    assert TrainConfig(algo="rebrac", batch_size=64).batch_size == 64


def test_next_actions_follow_the_episode_and_rows_without_one_are_dropped():
    """Rows 0-2 one episode ending at a time limit, rows 3-4 one ending at a terminal, row 5 an
    episode that the data cuts off."""
    obs = np.arange(9, dtype=np.float32)[:, None]
    observations = obs[[0, 1, 2, 4, 5, 7]]
    next_observations = obs[[1, 2, 3, 5, 6, 8]]
    actions = np.arange(6, dtype=np.float32)[:, None] / 10
    dataset = Dataset(
        observations, actions, np.zeros(6), next_observations,
        terminals=[0, 0, 0, 0, 1, 0], timeouts=[0, 0, 1, 0, 0, 0],
    )  # fmt: skip
    got = data_next_actions(dataset)[:, 0]
    # The next row's action where it continues the episode, else the row's own.
    np.testing.assert_allclose(got, [0.1, 0.2, 0.2, 0.4, 0.4, 0.5])
    plain = device_data(dataset, Normalizer.identity(1))
    assert type(plain) is Batch, "other algorithms' batches are unchanged"
    np.testing.assert_array_equal(plain.actions, actions)
    # ReBRAC's batches: the time-limit end (row 2) and the cut-off row (5) have no next action
    # in the data and are left out, as the authors' code (D4RL's qlearning_dataset) leaves them;
    # row 1 keeps row 2's action as its next one; the terminal (4) needs none and stays.
    np.testing.assert_array_equal(next_action_known(dataset), [1, 1, 0, 1, 1, 0])
    data = device_data(dataset, Normalizer.identity(1), next_actions=True)
    np.testing.assert_allclose(data.actions[:, 0], [0.0, 0.1, 0.3, 0.4])
    np.testing.assert_allclose(data.next_actions[:, 0], [0.1, 0.2, 0.4, 0.4])
    np.testing.assert_allclose(data.observations[:, 0], [0, 1, 4, 5])
    np.testing.assert_allclose(data.next_observations[:, 0], [1, 2, 5, 6])
    np.testing.assert_array_equal(data.dones, [0, 0, 0, 1])


def test_data_without_any_next_action_is_refused():
    dataset = Dataset(
        np.zeros((2, 1)), np.zeros((2, 1)), np.zeros(2), np.ones((2, 1)),
        terminals=[0, 0], timeouts=[1, 1], name="all-cut",
    )  # fmt: skip
    with pytest.raises(DatasetError, match="all-cut: no transition has the data's next action"):
        device_data(dataset, Normalizer.identity(1), next_actions=True)


def test_rebrac_learns_on_pendulum(tmp_path, pendulum_dataset):
    data = pendulum_dataset
    continues = np.all(data.observations[1:] == data.next_observations[:-1], axis=1)
    assert continues.mean() > 0.99, "each row's s' is the next row's s: next actions are known"
    betas = {"actor_bc_weight": 0.1, "critic_bc_weight": 0.01}
    untrained, late, evaluations = late_gain(tmp_path, pendulum_dataset, "rebrac", betas)
    config = json.loads((tmp_path / "rebrac" / "config.json").read_text())
    assert config["train"]["batch_size"] == 1024
    assert late > untrained + MARGIN, evaluations
