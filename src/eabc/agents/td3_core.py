"""The TD3 update (Fujimoto et al., 2018) once, for every algorithm built on it: TD3, TD3+BC and
EABC (settings of :mod:`eabc.agents.eabc`), ReBRAC and wPC.

One gradient step ``t`` on a mini-batch ``(s, a, r, s', d)``:

1. the critics take one Adam step on their loss (:func:`critic_step`), whose target is taken at
   the smoothed target action ``a' = clip(pi_targ(s') + clip(eps, -c, c), -max_a, max_a)``,
   ``eps ~ N(0, sigma^2)`` (:func:`target_action`; ``sigma`` and ``c`` scale with ``max_a``);
2. on the delayed steps, ``t % policy_freq == 0``, the actor takes one Adam step on its loss
   against the critics just updated, and both target networks then move by Polyak averaging
   (:func:`actor_step`).

An algorithm adds its two losses and whatever state its paper adds, in a step function
``step(state, batch, key, config, max_action, delayed)`` whose ``delayed`` is a Python bool: the
step reads as the paper's lines, ``if delayed:`` around the actor's. Its ``update`` is
:func:`scheduled` of that step. The training chunks know which steps are delayed (every
``policy_freq``-th: :func:`delayed_period`) and say so, so that the program they compile holds no
branch: under ``vmap`` (seeds trained together) a ``lax.cond`` becomes a ``select`` that computes
both of its branches, the actor's on every step. A caller that steps one at a time may leave
``delayed`` unset; the step then decides from the state's step count (one ``lax.cond``).

Every step returns the same metrics: on the other steps the actor's are zeros and
``actor_updated`` is false, and a log row averages the actor's over the delayed steps only
(:data:`eabc.agents.contract.CRITIC_METRICS`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax

from eabc import networks, pytree
from eabc.agents.common import Batch, apply_gradients

StepFn = Callable[..., tuple[Any, dict[str, jax.Array]]]
"""``step(state, batch, key, config, max_action, delayed: bool) -> (state, metrics)``."""


@pytree.dataclass
class TD3State:
    actor: networks.Params
    critic: networks.Params
    """The critic ensemble (its members stacked on a leading axis)."""
    actor_target: networks.Params
    critic_target: networks.Params
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    step: jax.Array
    """Gradient steps taken so far."""


def optimizers(config: Any) -> tuple[optax.GradientTransformation, optax.GradientTransformation]:
    """Adam for the actor and for the critics, at ``config.actor_lr`` and ``config.critic_lr``."""
    return optax.adam(config.actor_lr), optax.adam(config.critic_lr)


def init(
    key: jax.Array,
    obs_dim: int,
    act_dim: int,
    config: Any,
    hidden_bias: float | None = None,
    actor_output_bound: float | None = None,
    critic_output_bound: float | None = None,
) -> TD3State:
    """An actor ``obs -> hidden_dims -> act`` and ``num_critics`` critics ``(obs, act) ->
    hidden_dims -> 1`` (LayerNorm with ``critic_layer_norm``), each target a copy of its network;
    PyTorch's initialisation, but for the hidden biases and output layers the arguments set
    (:func:`eabc.networks.init_mlp`)."""
    actor_key, critic_key = jax.random.split(key)
    actor = networks.init_mlp(
        actor_key,
        (obs_dim, *config.hidden_dims, act_dim),
        hidden_bias=hidden_bias,
        output_bound=actor_output_bound,
    )
    critic = networks.init_mlp(
        critic_key,
        (obs_dim + act_dim, *config.hidden_dims, 1),
        num_members=config.num_critics,
        layer_norm=config.critic_layer_norm,
        hidden_bias=hidden_bias,
        output_bound=critic_output_bound,
    )
    actor_tx, critic_tx = optimizers(config)
    return TD3State(
        actor=actor,
        critic=critic,
        actor_target=actor,
        critic_target=critic,
        actor_opt=actor_tx.init(actor),
        critic_opt=critic_tx.init(critic),
        step=jnp.zeros((), jnp.int32),
    )


def delayed_period(config: Any) -> int:
    """How often the actor and the targets move: every ``policy_freq`` gradient steps."""
    return config.policy_freq


def target_action(actor_target, batch: Batch, key: jax.Array, config: Any, max_action: float):
    """Target policy smoothing: ``clip(pi_targ(s') + clip(eps, -c, c), -max_a, max_a)`` with
    ``eps ~ N(0, (policy_noise max_a)^2)`` and ``c = noise_clip max_a``."""
    noise = jax.random.normal(key, batch.actions.shape) * config.policy_noise * max_action
    noise = jnp.clip(noise, -config.noise_clip * max_action, config.noise_clip * max_action)
    next_action = networks.actor_apply(actor_target, batch.next_observations, max_action)
    return jnp.clip(next_action + noise, -max_action, max_action)


def critic_step(state, loss: Callable, batch: Batch, key, config: Any, max_action: float):
    """Step ``t = state.step + 1`` begins: one Adam step of the critics on
    ``loss(critic, critic_target, actor_target, batch, key, config, max_action) -> (loss,
    metrics)``. Returns ``(state with the new critics and step t, metrics)``."""
    _, critic_tx = optimizers(config)
    grads, metrics = jax.grad(loss, has_aux=True)(
        state.critic, state.critic_target, state.actor_target, batch, key, config, max_action
    )
    critic, critic_opt = apply_gradients(critic_tx, grads, state.critic_opt, state.critic)
    return state.replace(critic=critic, critic_opt=critic_opt, step=state.step + 1), metrics


def actor_step(state, config: Any, loss: Callable, *args):
    """The delayed part of a step: one Adam step of the actor on ``loss(actor, critic, *args) ->
    (loss, metrics)`` against the state's (just updated) critics, then Polyak averaging of both
    targets towards their networks. Returns ``(state, metrics)``."""
    actor_tx, _ = optimizers(config)
    grads, metrics = jax.grad(loss, has_aux=True)(state.actor, state.critic, *args)
    actor, actor_opt = apply_gradients(actor_tx, grads, state.actor_opt, state.actor)
    return state.replace(
        actor=actor,
        actor_opt=actor_opt,
        actor_target=networks.polyak(state.actor_target, actor, config.tau),
        critic_target=networks.polyak(state.critic_target, state.critic, config.tau),
    ), metrics


def scheduled(
    step: StepFn, state, batch: Batch, key, config: Any, max_action: float, delayed: bool | None
):
    """One gradient step of ``step`` with the same metrics on every step (see the module's
    docstring). ``delayed``: whether this step (``t = state.step + 1``) moves the actor and the
    targets, i.e. ``t % policy_freq == 0``; None decides it from ``state.step`` in a ``lax.cond``."""
    if delayed is None:
        due = (state.step + 1) % delayed_period(config) == 0
        return jax.lax.cond(
            due,
            lambda: scheduled(step, state, batch, key, config, max_action, True),
            lambda: scheduled(step, state, batch, key, config, max_action, False),
        )
    new_state, metrics = step(state, batch, key, config, max_action, delayed)
    if not delayed:  # the actor's metrics as zeros, in the shapes of a delayed step's
        full = jax.eval_shape(lambda: step(state, batch, key, config, max_action, True))[1]
        metrics = {**{k: jnp.zeros(s.shape, s.dtype) for k, s in full.items()}, **metrics}
    return new_state, {**metrics, "actor_updated": jnp.asarray(delayed)}
