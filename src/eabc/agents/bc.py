"""Behaviour cloning: a deterministic actor regressed on the dataset's actions.

``loss = mean_batch mean_dims (pi(s) - a)^2`` with ``pi(s) = max_action * tanh(MLP(s))``, the same
actor, observation normalisation and schedule as TD3+BC (whose paper reports this BC baseline).
"""

from __future__ import annotations

import dataclasses

import jax
import optax

from eabc import networks, pytree
from eabc.agents.common import Batch, apply_gradients
from eabc.agents.contract import Algorithm
from eabc.ranges import LearningRate, Settings, Widths


@dataclasses.dataclass(frozen=True)
class BCConfig(Settings):
    """Fujimoto & Gu (2021)'s BC baseline: TD3+BC's actor and optimiser without critics."""

    actor_lr: LearningRate = 3e-4
    """Adam learning rate."""
    hidden_dims: Widths = (256, 256)
    """Hidden layer widths."""


PRESETS = {"bc": BCConfig()}


@pytree.dataclass
class BCState:
    actor: networks.Params
    actor_opt: optax.OptState
    step: jax.Array


def init(key: jax.Array, obs_dim: int, act_dim: int, config: BCConfig) -> BCState:
    actor = networks.init_mlp(key, (obs_dim, *config.hidden_dims, act_dim))
    return BCState(actor, optax.adam(config.actor_lr).init(actor), jax.numpy.zeros((), "int32"))


def bc_loss(actor, batch: Batch, max_action: float):
    pi = networks.actor_apply(actor, batch.observations, max_action)
    loss = ((pi - batch.actions) ** 2).mean()
    return loss, {"bc_loss": loss}


def update(
    state: BCState, batch: Batch, key: jax.Array, config: BCConfig, max_action: float
) -> tuple[BCState, dict[str, jax.Array]]:
    del key  # deterministic
    grads, metrics = jax.grad(bc_loss, has_aux=True)(state.actor, batch, max_action)
    actor, actor_opt = apply_gradients(
        optax.adam(config.actor_lr), grads, state.actor_opt, state.actor
    )
    return BCState(actor, actor_opt, state.step + 1), metrics


ALGORITHMS = (
    # It reads no reward; "raw" as the TD3+BC code whose BC baseline it is.
    Algorithm("bc", "BC", PRESETS["bc"], init, update, column=0, steps_per_s=2319.0,
              reward_convention="raw"),
)  # fmt: skip
