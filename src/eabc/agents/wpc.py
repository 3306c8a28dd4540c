"""wPC, weighted policy constraints (Peng et al., AAAI 2023): TD3+BC whose behaviour-cloning term
is kept only for the samples whose action looks better than the behaviour policy's average.

On top of TD3+BC (the ``td3bc`` setting of the EABC rule) a state-value network ``V(s)`` is
regressed on the target critics' value of the dataset action, ``min_i Q_targ_i(s, a)``; the
advantage ``A(s, a) = min_i Q_targ_i(s, a) - V(s)`` then decides the BC mask,
``w = 1[A(s, a) > 0]``, where EABC draws ``w ~ Bernoulli(p)``. Everything else (critic, target
smoothing, delayed actor, lambda normalisation) is TD3+BC's, shared with :mod:`eabc.agents.eabc`.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import optax

from eabc import networks, pytree
from eabc.agents import eabc
from eabc.agents.common import Batch, BuiltOn, apply_gradients
from eabc.agents.contract import Algorithm


@dataclasses.dataclass(frozen=True)
class WPCConfig(eabc.EABCConfig):
    """TD3+BC's settings (Fujimoto & Gu 2021) plus the value network's learning rate."""

    num_critics: int = 2
    confidence_level: float = 1.0
    pessimism: eabc.Pessimism = "min"
    actor_uses_ensemble: bool = False
    value_lr: float = 3e-4
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
    state: WPCState, batch: Batch, key: jax.Array, config: WPCConfig, max_action: float
) -> tuple[WPCState, dict[str, jax.Array]]:
    """Critic step, value step, then (every policy_freq steps) the advantage-masked actor step."""
    base = state.td3bc
    critic_key, actor_key = jax.random.split(key)
    critic, critic_opt, critic_metrics = eabc.critic_step(
        base, batch, critic_key, config, max_action
    )
    grads, (advantage, value_metrics) = jax.grad(value_loss, has_aux=True)(
        state.value, base.critic_target, batch
    )
    value, value_opt = apply_gradients(
        optax.adam(config.value_lr), grads, state.value_opt, state.value
    )
    step = base.step + 1
    keep = advantage > 0
    (actor, actor_opt, actor_target, critic_target), actor_metrics = eabc.delayed_actor_step(
        base, critic, step, batch, actor_key, config, max_action, keep
    )
    td3bc = base.replace(
        actor=actor,
        critic=critic,
        actor_target=actor_target,
        critic_target=critic_target,
        actor_opt=actor_opt,
        critic_opt=critic_opt,
        step=step,
    )
    new_state = WPCState(td3bc=td3bc, value=value, value_opt=value_opt)
    metrics = {
        **critic_metrics,
        **value_metrics,
        **actor_metrics,
        "actor_updated": step % config.policy_freq == 0,
    }
    return new_state, metrics


ALGORITHMS = (
    Algorithm(
        "wpc", "wPC", PRESETS["wpc"], init, update, column=5, steps_per_s=452.0,
        cost=lambda config: config.num_critics / 2, report_settings=("num_critics",), cli_flags=("num_critics", "alpha"),
        state_layout=2,  # 2: the TD3+BC state as one field
    ),
)  # fmt: skip
