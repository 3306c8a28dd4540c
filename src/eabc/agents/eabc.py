"""EABC (Algorithm 1 of the paper), with TD3+BC and TD3 as settings of the same update rule.

One call of :func:`update` is one gradient step ``t`` on a mini-batch ``(s, a, r, s', d)``:

1. target action ``a' = clip(pi_targ(s') + clip(eps, -c, c), -max_a, max_a)``;
2. ``y = r + gamma * (1 - d) * pess(Q_targ_1..K(s', a'))``, one target shared by every member;
3. critic loss ``sum_i mean_batch (Q_i(s, a) - y)^2``;
4. every ``policy_freq`` steps the actor minimises
   ``-lambda * mean(P) + mean(w * mean_dims (pi(s) - a)^2)`` with ``P = pess(Q_1..K(s, pi(s)))``,
   ``lambda = alpha / mean|P|`` (no gradient) and ``w ~ Bernoulli(p)`` per sample;
5. then the actor and critic targets move by Polyak averaging.

``../shared/SPEC.md`` section 1 is the specification this file follows line by line.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import flax.struct
import jax
import jax.numpy as jnp
import optax

from eabc import networks
from eabc.agents.common import Batch

Pessimism = Literal["mean-std", "min", "min2"]


@dataclasses.dataclass(frozen=True)
class EABCConfig:
    """Settings of the EABC family; the defaults are the paper's (Tables 2 and 4)."""

    num_critics: int = 10
    """K, the number of Q-networks in the critic ensemble."""
    confidence_level: float = 1.0
    """p, the probability that a sample's behaviour-cloning term is kept (Table 3 per dataset)."""
    pessimism: Pessimism = "mean-std"
    """How the ensemble becomes one value: mean - std (ddof 1), min of all, or min of 2 random members."""
    actor_uses_ensemble: bool = True
    """Actor maximises pess(Q_1..K); False: it maximises critic 1 only (TD3, TD3+BC)."""
    behavior_cloning: bool = True
    """Keep the BC term and the lambda normalisation; False gives TD3's actor loss -mean Q."""
    alpha: float = 2.5
    """TD3+BC's alpha: lambda = alpha / mean|Q|."""
    discount: float = 0.99
    """gamma."""
    tau: float = 0.005
    """Polyak rate of the target networks."""
    policy_noise: float = 0.2
    """Std of the target-policy smoothing noise, as a fraction of max_action."""
    noise_clip: float = 0.5
    """Clip of the smoothing noise, as a fraction of max_action."""
    policy_freq: int = 2
    """The actor and the targets are updated every policy_freq critic steps."""
    actor_lr: float = 3e-4
    """Adam learning rate of the actor."""
    critic_lr: float = 3e-4
    """Adam learning rate of the critics."""
    hidden_dims: tuple[int, ...] = (256, 256)
    """Hidden layer widths of actor and critics."""

    def __post_init__(self):
        if self.num_critics < 2:
            raise ValueError(f"num_critics must be at least 2, got {self.num_critics}")
        if not 0.0 <= self.confidence_level <= 1.0:
            raise ValueError(f"confidence_level p must lie in [0, 1], got {self.confidence_level}")
        if self.pessimism not in ("mean-std", "min", "min2"):
            raise ValueError(f"pessimism must be mean-std, min or min2, got {self.pessimism!r}")
        if self.policy_freq < 1:
            raise ValueError(f"policy_freq must be at least 1, got {self.policy_freq}")


PRESETS: dict[str, EABCConfig] = {
    "eabc": EABCConfig(),
    # TD3+BC (Fujimoto & Gu, 2021): twin critics, min target, actor on critic 1, full BC.
    "td3bc": EABCConfig(
        num_critics=2, confidence_level=1.0, pessimism="min", actor_uses_ensemble=False
    ),
    # TD3 (Fujimoto et al., 2018) run offline: TD3+BC without the BC term.
    "td3": EABCConfig(
        num_critics=2, pessimism="min", actor_uses_ensemble=False, behavior_cloning=False
    ),
}


@flax.struct.dataclass
class EABCState:
    actor: networks.Params
    critic: networks.Params
    actor_target: networks.Params
    critic_target: networks.Params
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    step: jax.Array
    """Gradient steps taken so far."""


def _optimizers(config: EABCConfig) -> tuple[optax.GradientTransformation, ...]:
    return optax.adam(config.actor_lr), optax.adam(config.critic_lr)


def init(key: jax.Array, obs_dim: int, act_dim: int, config: EABCConfig) -> EABCState:
    actor_key, critic_key = jax.random.split(key)
    actor = networks.init_mlp(actor_key, (obs_dim, *config.hidden_dims, act_dim))
    critic = networks.init_mlp(
        critic_key, (obs_dim + act_dim, *config.hidden_dims, 1), num_members=config.num_critics
    )
    actor_tx, critic_tx = _optimizers(config)
    return EABCState(
        actor=actor,
        critic=critic,
        actor_target=actor,
        critic_target=critic,
        actor_opt=actor_tx.init(actor),
        critic_opt=critic_tx.init(critic),
        step=jnp.zeros((), jnp.int32),
    )


def pessimistic_value(q: jax.Array, pessimism: Pessimism, key: jax.Array) -> jax.Array:
    """Collapse ensemble values ``q: [K, B]`` into one pessimistic value per sample, eq. (4)."""
    if pessimism == "mean-std":
        return q.mean(axis=0) - q.std(axis=0, ddof=1)
    if pessimism == "min":
        return q.min(axis=0)
    pair = jax.random.choice(key, q.shape[0], (2,), replace=False)
    return q[pair].min(axis=0)


def critic_loss(critic, critic_target, actor_target, batch: Batch, key, config, max_action):
    noise_key, pess_key = jax.random.split(key)
    noise = jax.random.normal(noise_key, batch.actions.shape) * config.policy_noise * max_action
    noise = jnp.clip(noise, -config.noise_clip * max_action, config.noise_clip * max_action)
    next_action = networks.actor_apply(actor_target, batch.next_observations, max_action)
    next_action = jnp.clip(next_action + noise, -max_action, max_action)
    target_q = networks.critic_apply(critic_target, batch.next_observations, next_action)
    y = batch.rewards + config.discount * (1.0 - batch.dones) * pessimistic_value(
        target_q, config.pessimism, pess_key
    )
    y = jax.lax.stop_gradient(y)
    q = networks.critic_apply(critic, batch.observations, batch.actions)
    loss = ((q - y[None]) ** 2).mean(axis=1).sum()
    return loss, {
        "critic_loss": loss,
        "q_mean": q.mean(),
        "q_ensemble_std": q.std(axis=0, ddof=1).mean(),
        "target_mean": y.mean(),
    }


def actor_loss(actor, critic, batch: Batch, key, config, max_action, keep=None):
    """The actor loss; ``keep`` (per sample, in [0, 1]) replaces the Bernoulli(p) BC mask if given."""
    pess_key, mask_key = jax.random.split(key)
    pi = networks.actor_apply(actor, batch.observations, max_action)
    q = networks.critic_apply(critic, batch.observations, pi)
    value = pessimistic_value(q, config.pessimism, pess_key) if config.actor_uses_ensemble else q[0]
    if not config.behavior_cloning:
        loss = -value.mean()
        return loss, {"actor_loss": loss, "actor_value": value.mean()}
    lam = jax.lax.stop_gradient(config.alpha / jnp.abs(value).mean())
    if keep is None:
        keep = jax.random.bernoulli(mask_key, config.confidence_level, value.shape)
    keep = keep.astype(pi.dtype)
    bc = (keep * ((pi - batch.actions) ** 2).mean(axis=-1)).mean()
    loss = -lam * value.mean() + bc
    return loss, {
        "actor_loss": loss,
        "actor_value": value.mean(),
        # The ensemble's spread at the policy's own actions: the penalty mean - std actually pays.
        "policy_q_std": q.std(axis=0, ddof=1).mean(),
        "lambda": lam,
        "bc_loss": bc,
        "bc_fraction": keep.mean(),
    }


def critic_step(state, batch: Batch, key, config: EABCConfig, max_action: float):
    """One Adam step of the critic ensemble: ``(critic, critic_opt, metrics)``."""
    _, critic_tx = _optimizers(config)
    grads, metrics = jax.grad(critic_loss, has_aux=True)(
        state.critic, state.critic_target, state.actor_target, batch, key, config, max_action
    )
    updates, critic_opt = critic_tx.update(grads, state.critic_opt, state.critic)
    return optax.apply_updates(state.critic, updates), critic_opt, metrics


def delayed_actor_step(state, critic, step, batch: Batch, key, config, max_action, keep=None):
    """Every ``policy_freq`` steps: an actor step, then Polyak averaging of both targets.

    Returns ``(actor, actor_opt, actor_target, critic_target), metrics`` (zeros when skipped).
    """
    actor_tx, _ = _optimizers(config)

    def actor_step(_):
        grads, metrics = jax.grad(actor_loss, has_aux=True)(
            state.actor, critic, batch, key, config, max_action, keep
        )
        updates, actor_opt = actor_tx.update(grads, state.actor_opt, state.actor)
        actor = optax.apply_updates(state.actor, updates)
        targets = (
            networks.polyak(state.actor_target, actor, config.tau),
            networks.polyak(state.critic_target, critic, config.tau),
        )
        return (actor, actor_opt, *targets), metrics

    def skip(_):
        shapes = jax.eval_shape(actor_step, None)[1]
        zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        return (state.actor, state.actor_opt, state.actor_target, state.critic_target), zeros

    return jax.lax.cond(step % config.policy_freq == 0, actor_step, skip, None)


def update(
    state: EABCState, batch: Batch, key: jax.Array, config: EABCConfig, max_action: float
) -> tuple[EABCState, dict[str, jax.Array]]:
    """One gradient step of Algorithm 1. Pure: the same inputs always give the same outputs."""
    critic_key, actor_key = jax.random.split(key)
    critic, critic_opt, critic_metrics = critic_step(state, batch, critic_key, config, max_action)
    step = state.step + 1
    (actor, actor_opt, actor_target, critic_target), actor_metrics = delayed_actor_step(
        state, critic, step, batch, actor_key, config, max_action
    )
    new_state = EABCState(
        actor=actor,
        critic=critic,
        actor_target=actor_target,
        critic_target=critic_target,
        actor_opt=actor_opt,
        critic_opt=critic_opt,
        step=step,
    )
    metrics = {**critic_metrics, **actor_metrics, "actor_updated": step % config.policy_freq == 0}
    return new_state, metrics
