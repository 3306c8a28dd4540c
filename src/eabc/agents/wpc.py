"""wPC, weighted policy constraints (Peng et al., AAAI 2023): TD3+BC whose behaviour-cloning term
is kept only for the samples whose action looks better than the behaviour policy's average.

On top of TD3+BC (the ``td3bc`` setting of the EABC rule) a state-value network ``V(s)`` is
regressed on the target critics' value of the dataset action, ``min_i Q_targ_i(s, a)``; the
advantage ``A(s, a) = min_i Q_targ_i(s, a) - V(s)`` then decides the BC mask,
``w = 1[A(s, a) > 0]``, where EABC draws ``w ~ Bernoulli(p)``. Everything else (critic, target
smoothing, delayed actor, lambda normalisation) is TD3+BC's, shared with :mod:`eabc.agents.eabc`
and :mod:`eabc.agents.td3_core`.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import optax

from eabc import networks, pytree
from eabc.agents import eabc, td3_core
from eabc.agents.common import Batch, BuiltOn, apply_gradients
from eabc.agents.contract import Algorithm
from eabc.ranges import Ensemble, LearningRate, Probability


@dataclasses.dataclass(frozen=True)
class WPCConfig(eabc.EABCConfig):
    """TD3+BC's settings (Fujimoto & Gu 2021) plus the value network's learning rate."""

    num_critics: Ensemble = 2
    confidence_level: Probability = 1.0
    pessimism: eabc.Pessimism = "min"
    actor_uses_ensemble: bool = False
    value_lr: LearningRate = 3e-4
    """Adam learning rate of V(s) (the critics' rate, as TD3+BC uses for every network)."""


PRESETS = {"wpc": WPCConfig()}


@pytree.dataclass
class WPCState(BuiltOn):
    BASE: ClassVar[str] = "td3bc"

    td3bc: eabc.EABCState
    """TD3+BC's actor, critics, targets and optimisers, trained by :mod:`eabc.agents.eabc`."""
    value: networks.Params
    """V(s)."""
    value_opt: optax.OptState


def init(key: jax.Array, obs_dim: int, act_dim: int, config: WPCConfig) -> WPCState:
    agent_key, value_key = jax.random.split(key)
    value = networks.init_mlp(value_key, (obs_dim, *config.hidden_dims, 1))
    return WPCState(
        td3bc=eabc.init(agent_key, obs_dim, act_dim, config),
        value=value,
        value_opt=optax.adam(config.value_lr).init(value),
    )


def value_loss(value, critic_target, batch: Batch):
    """``mean (V(s) - min_i Q_targ_i(s, a))^2`` and the advantage of every dataset action."""
    target = jax.lax.stop_gradient(
        networks.critic_apply(critic_target, batch.observations, batch.actions).min(axis=0)
    )
    v = networks.mlp(value, batch.observations)[:, 0]
    loss = ((v - target) ** 2).mean()
    return loss, (jax.lax.stop_gradient(target - v), {"value_loss": loss, "v_mean": v.mean()})


def update(
    state: WPCState,
    batch: Batch,
    key: jax.Array,
    config: WPCConfig,
    max_action: float,
    delayed: bool | None = None,
) -> tuple[WPCState, dict[str, jax.Array]]:
    """One gradient step ``t``; ``delayed``: whether ``t % policy_freq == 0`` (the actor's step),
    None: from the step count (see :func:`eabc.agents.td3_core.scheduled`)."""
    return td3_core.scheduled(_step, state, batch, key, config, max_action, delayed)


def _step(state: WPCState, batch: Batch, key, config: WPCConfig, max_action, delayed: bool):
    """TD3+BC's critic step, the value step, then on delayed steps the advantage-masked actor
    step and Polyak averaging."""
    critic_key, actor_key = jax.random.split(key)
    td3bc, metrics = td3_core.critic_step(
        state.td3bc, eabc.critic_loss, batch, critic_key, config, max_action
    )
    grads, (advantage, value_metrics) = jax.grad(value_loss, has_aux=True)(
        state.value, state.td3bc.critic_target, batch
    )
    value, value_opt = apply_gradients(
        optax.adam(config.value_lr), grads, state.value_opt, state.value
    )
    metrics = {**metrics, **value_metrics}
    if delayed:  # TD3+BC's actor loss with w = 1[A(s, a) > 0] in place of w ~ Bernoulli(p)
        td3bc, actor_metrics = td3_core.actor_step(
            td3bc, config, eabc.actor_loss, batch, actor_key, config, max_action, advantage > 0
        )
        metrics = {**metrics, **actor_metrics}
    return WPCState(td3bc=td3bc, value=value, value_opt=value_opt), metrics


ALGORITHMS = (
    Algorithm(
        "wpc", "wPC", PRESETS["wpc"], init, update, column=5, steps_per_s=452.0,
        delayed_period=td3_core.delayed_period,
        cost=lambda config: config.num_critics / 2, report_settings=("num_critics",), cli_flags=("num_critics", "alpha"),
        state_layout=2,  # 2: the TD3+BC state as one field
    ),
)  # fmt: skip
