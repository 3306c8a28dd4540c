"""Implicit Q-learning (IQL; Kostrikov, Nair & Levine, 2021), with the authors' D4RL MuJoCo settings.

One call of :func:`update` is one gradient step on a mini-batch ``(s, a, r, s', d)``, in the order
of the authors' code:

1. value loss ``mean(|tau - 1(u < 0)| u^2)``, ``u = min_i Q_targ_i(s, a) - V(s)``
   (expectile regression, eq. 5 of the paper);
2. actor loss ``-mean(w log pi(a|s))`` with ``w = min(exp(beta (min_i Q_targ_i(s, a) - V(s))), 100)``
   and the updated V (advantage-weighted regression, eq. 7);
3. critic loss ``sum_i mean_batch (Q_i(s, a) - y)^2``, ``y = r + gamma (1 - d) V(s')`` with the
   updated V (eq. 6);
4. Polyak averaging of the critic targets.

The actor is the authors' Gaussian with a tanh-squashed mean and a state-independent log standard
deviation: ``pi(a|s) = N(a / max_action; tanh(MLP(s)), exp(log_std))``. The mean MLP is
``state.actor`` (so the deterministic action is ``max_action * tanh(MLP(s))``, as for a deterministic
actor) and ``log_std`` lives beside it in the state. The actor's learning rate decays to zero on a
cosine over the run (``total_steps``), and rewards are scaled by ``1000 / (max - min episode return)``
of the dataset (:func:`preprocess`), as the authors do for the MuJoCo tasks.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Annotated

import annotated_types
import jax
import jax.numpy as jnp
import numpy as np
import optax

from eabc import networks, pytree
from eabc.agents.common import Batch, apply_gradients
from eabc.agents.contract import Algorithm
from eabc.data import tasks
from eabc.ranges import (
    Count,
    Discount,
    Fraction,
    LearningRate,
    PositiveNumber,
    Settings,
    Weight,
    Widths,
)

if TYPE_CHECKING:
    from eabc.data.dataset import Dataset

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
"""Clip of the actor's log standard deviation (the authors' ``log_std_min=-5``, ``LOG_STD_MAX``)."""


@dataclasses.dataclass(frozen=True)
class IQLConfig(Settings):
    """IQL's settings; the defaults are the authors' for D4RL MuJoCo (configs/mujoco_config.py)."""

    expectile: Annotated[float, annotated_types.Interval(gt=0, lt=1)] = 0.7
    """tau, the expectile V regresses to (0.5: the mean; towards 1: the max over dataset actions)."""
    temperature: Weight = 3.0
    """beta, the inverse temperature of the advantage weights exp(beta * (Q - V))."""
    max_weight: PositiveNumber = 100.0
    """Clip of the advantage weights (the authors' code)."""
    discount: Discount = 0.99
    """gamma."""
    tau: Fraction = 0.005
    """Polyak rate of the critic targets."""
    actor_lr: LearningRate = 3e-4
    """Initial Adam learning rate of the actor (cosine decay to zero over total_steps)."""
    critic_lr: LearningRate = 3e-4
    """Adam learning rate of the twin Q-networks."""
    value_lr: LearningRate = 3e-4
    """Adam learning rate of V."""
    total_steps: Count | None = None
    """Length of the actor's cosine decay: the run's steps, which the trainer fills in (None:
    constant learning rate)."""
    hidden_dims: Widths = (256, 256)
    """Hidden layer widths of actor, critics and V."""


PRESETS: dict[str, IQLConfig] = {"iql": IQLConfig()}


@pytree.dataclass
class IQLState:
    actor: networks.Params
    """MLP of the tanh-squashed mean (w/b only, like a deterministic actor)."""
    log_std: jax.Array
    """State-independent log standard deviation of the actor, ``[act_dim]``."""
    value: networks.Params
    critic: networks.Params
    critic_target: networks.Params
    actor_opt: optax.OptState
    """Adam state of ``(actor, log_std)``."""
    value_opt: optax.OptState
    critic_opt: optax.OptState
    step: jax.Array


def _optimizers(config: IQLConfig) -> tuple[optax.GradientTransformation, ...]:
    actor_lr = (
        config.actor_lr
        if config.total_steps is None
        else optax.cosine_decay_schedule(config.actor_lr, config.total_steps)
    )
    return optax.adam(actor_lr), optax.adam(config.value_lr), optax.adam(config.critic_lr)


def init(key: jax.Array, obs_dim: int, act_dim: int, config: IQLConfig) -> IQLState:
    actor_key, value_key, critic_key = jax.random.split(key, 3)
    actor = networks.init_mlp(actor_key, (obs_dim, *config.hidden_dims, act_dim))
    log_std = jnp.zeros((act_dim,), jnp.float32)
    value = networks.init_mlp(value_key, (obs_dim, *config.hidden_dims, 1))
    critic = networks.init_mlp(
        critic_key, (obs_dim + act_dim, *config.hidden_dims, 1), num_members=2
    )
    actor_tx, value_tx, critic_tx = _optimizers(config)
    return IQLState(
        actor=actor,
        log_std=log_std,
        value=value,
        critic=critic,
        critic_target=critic,
        actor_opt=actor_tx.init((actor, log_std)),
        value_opt=value_tx.init(value),
        critic_opt=critic_tx.init(critic),
        step=jnp.zeros((), jnp.int32),
    )


def preprocess(dataset: Dataset) -> Dataset:
    """Rewards times ``1000 / (max - min episode return)``, the authors' MuJoCo normalisation.

    A dataset whose episodes all have the same return is left as it is.
    """
    returns = dataset.episode_returns()
    spread = float(returns.max() - returns.min())
    if spread <= 0.0:
        return dataset
    scale = 1000.0 / spread
    return dataclasses.replace(
        dataset,
        rewards=(dataset.rewards.astype(np.float64) * scale).astype(np.float32),
        metadata={**dataset.metadata, "reward_scale": scale},
    )


def value_fn(value: networks.Params, obs: jax.Array) -> jax.Array:
    return networks.mlp(value, obs)[:, 0]


def expectile_loss(diff: jax.Array, expectile: float) -> jax.Array:
    """``mean(|tau - 1(diff < 0)| diff^2)``: asymmetric least squares."""
    weight = jnp.where(diff > 0, expectile, 1.0 - expectile)
    return (weight * diff**2).mean()


def gaussian_log_prob(actor, log_std, obs, actions, max_action) -> jax.Array:
    """``log N(a / max_action; tanh(MLP(s)), exp(log_std))``, summed over action dimensions."""
    mean = jnp.tanh(networks.mlp(actor, obs))
    log_std = jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)
    z = (actions / max_action - mean) * jnp.exp(-log_std)
    return (-0.5 * z**2 - log_std - 0.5 * np.log(2 * np.pi)).sum(axis=-1)


def value_loss(value, critic_target, batch: Batch, config: IQLConfig):
    q = networks.critic_apply(critic_target, batch.observations, batch.actions).min(axis=0)
    v = value_fn(value, batch.observations)
    loss = expectile_loss(q - v, config.expectile)
    return loss, {"value_loss": loss, "v_mean": v.mean()}


def actor_loss(actor_params, value, critic_target, batch: Batch, config: IQLConfig, max_action):
    actor, log_std = actor_params
    q = networks.critic_apply(critic_target, batch.observations, batch.actions).min(axis=0)
    advantage = q - value_fn(value, batch.observations)
    weight = jnp.minimum(jnp.exp(config.temperature * advantage), config.max_weight)
    log_prob = gaussian_log_prob(actor, log_std, batch.observations, batch.actions, max_action)
    loss = -(weight * log_prob).mean()
    return loss, {
        "actor_loss": loss,
        "advantage_mean": advantage.mean(),
        "weight_mean": weight.mean(),
        "log_std_mean": jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX).mean(),
    }


def critic_loss(critic, value, batch: Batch, config: IQLConfig):
    next_v = value_fn(value, batch.next_observations)
    y = batch.rewards + config.discount * (1.0 - batch.dones) * next_v
    q = networks.critic_apply(critic, batch.observations, batch.actions)
    loss = ((q - y[None]) ** 2).mean(axis=1).sum()
    return loss, {"critic_loss": loss, "q_mean": q.mean(), "target_mean": y.mean()}


def update(
    state: IQLState, batch: Batch, key: jax.Array, config: IQLConfig, max_action: float
) -> tuple[IQLState, dict[str, jax.Array]]:
    """One gradient step of V, actor and critics (in that order). Pure; ``key`` is unused."""
    del key  # IQL's losses are deterministic (the authors' dropout is off for MuJoCo)
    actor_tx, value_tx, critic_tx = _optimizers(config)

    grads, value_metrics = jax.grad(value_loss, has_aux=True)(
        state.value, state.critic_target, batch, config
    )
    value, value_opt = apply_gradients(value_tx, grads, state.value_opt, state.value)

    actor_params = (state.actor, state.log_std)
    grads, actor_metrics = jax.grad(actor_loss, has_aux=True)(
        actor_params, value, state.critic_target, batch, config, max_action
    )
    (actor, log_std), actor_opt = apply_gradients(actor_tx, grads, state.actor_opt, actor_params)

    grads, critic_metrics = jax.grad(critic_loss, has_aux=True)(state.critic, value, batch, config)
    critic, critic_opt = apply_gradients(critic_tx, grads, state.critic_opt, state.critic)

    new_state = state.replace(
        actor=actor,
        log_std=log_std,
        value=value,
        critic=critic,
        critic_target=networks.polyak(state.critic_target, critic, config.tau),
        actor_opt=actor_opt,
        value_opt=value_opt,
        critic_opt=critic_opt,
        step=state.step + 1,
    )
    return new_state, {**value_metrics, **actor_metrics, **critic_metrics}


ANTMAZE = {"expectile": 0.9, "temperature": 10.0}
"""The authors' AntMaze settings (their ``configs/antmaze_config.py``; CORL's AntMaze configs
agree); the preset's 0.7 and 3.0 are their MuJoCo ones."""


def resolve(
    config: IQLConfig, dataset_name: str, steps: int | None, given: frozenset[str]
) -> IQLConfig:
    """On AntMaze data, the authors' AntMaze expectile and temperature where the user set none;
    the actor's cosine schedule runs over the run's steps unless total_steps is set."""
    task = tasks.parse_task(dataset_name)
    if task is not None and task[0] == "antmaze":
        config = dataclasses.replace(config, **{k: v for k, v in ANTMAZE.items() if k not in given})
    if config.total_steps is None and steps:
        return dataclasses.replace(config, total_steps=steps)
    return config


ALGORITHMS = (
    Algorithm(
        "iql", "IQL", PRESETS["iql"], init, update, column=4,
        preprocess=preprocess, resolve=resolve, steps_per_s=523.0,
        # r - 1 on AntMaze (train_offline.py); its MuJoCo scaling offered to every algorithm
        reward_convention="minus-one", reward_conventions={"iql-scale": preprocess},
    ),
)  # fmt: skip
