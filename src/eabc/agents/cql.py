"""Conservative Q-learning (CQL(H); Kumar et al., 2020) on the SAC backbone of :mod:`eabc.agents.sac`.

One call of :func:`update` is one gradient step on a mini-batch ``(s, a, r, s', d)``. As in the
authors' code and young-geng/JaxCQL, every loss is evaluated at the parameters before the step:

1. SAC's actor loss ``mean(alpha log pi(a~|s) - min_i Q_i(s, a~))``, ``a~ ~ pi(s)``, and temperature
   loss ``-mean(log_alpha (log pi(a~|s) + target_entropy))``;
2. ``y = r + gamma (1 - d) min_i Q_targ_i(s', a')``, ``a' ~ pi(s')`` (no entropy term in the backup);
3. critic loss ``sum_i [mean_batch (Q_i(s, a) - y)^2 + min_q_weight * gap_i]`` with the conservative
   gap ``gap_i = mean_batch(logsumexp_j (Q_i(s, a_j) - log mu(a_j)) - Q_i(s, a))`` over ``3 n``
   sampled actions per state: ``n`` uniform in the action box, ``n`` from ``pi(s')`` and ``n`` from
   ``pi(s)``, each less the log-density of its proposal ``mu`` (the importance-sampled log-sum-exp
   of the paper's appendix F, without its constant ``-log 3n``, as in the authors' code);
4. with ``lagrange``, the penalty is ``alpha' * min_q_weight * (gap_i - target_action_gap)`` and
   ``log alpha'`` descends ``-alpha' * min_q_weight * mean_i (gap_i - target_action_gap)``;
5. Polyak averaging of the critic targets.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import optax

from eabc import networks, pytree
from eabc.agents import sac
from eabc.agents.common import Batch, BuiltOn, apply_gradients
from eabc.agents.contract import Algorithm
from eabc.ranges import Count, Discount, Finite, Fraction, LearningRate, Settings, Weight, Widths

"""The actor outputs a tanh-Gaussian; its deterministic action is ``tanh(mean)``."""

NUM_CRITICS = 2
INIT_LOG_ALPHA_PRIME = 1.0
"""JaxCQL's initial log(alpha') (``Scalar(1.0)``)."""
MAX_ALPHA_PRIME = 1e6
"""JaxCQL's clip of alpha'."""


@dataclasses.dataclass(frozen=True)
class CQLConfig(Settings):
    """CQL's settings; the defaults are young-geng/JaxCQL's for D4RL MuJoCo
    (``ConservativeSAC.get_default_config`` and ``conservative_sac_main.py``)."""

    min_q_weight: Weight = 5.0
    """alpha of the paper: weight of the conservative gap (JaxCQL cql_min_q_weight; the CQL paper's
    5.0 for Gym MuJoCo)."""
    num_sampled_actions: Count = 10
    """n, actions drawn per state from each proposal (JaxCQL cql_n_actions)."""
    lagrange: bool = False
    """Tune the weight alpha' by dual descent towards target_action_gap (JaxCQL cql_lagrange)."""
    target_action_gap: Finite = 1.0
    """The gap the Lagrange variant aims for (JaxCQL cql_target_action_gap)."""
    alpha_prime_lr: LearningRate = 3e-4
    """Adam learning rate of log(alpha') (JaxCQL: qf_lr)."""
    backup_entropy: bool = False
    """Subtract alpha log pi(a'|s') in the target (JaxCQL backup_entropy)."""
    discount: Discount = 0.99
    """gamma (JaxCQL discount)."""
    tau: Fraction = 0.005
    """Polyak rate of the critic targets (JaxCQL soft_target_update_rate)."""
    actor_lr: LearningRate = 3e-4
    """Adam learning rate of the actor (JaxCQL policy_lr)."""
    critic_lr: LearningRate = 3e-4
    """Adam learning rate of the critics (JaxCQL qf_lr)."""
    alpha_lr: LearningRate = 3e-4
    """Adam learning rate of log(alpha) (JaxCQL: policy_lr)."""
    target_entropy: Finite | None = None
    """Entropy the temperature aims for (JaxCQL: -act_dim when unset)."""
    hidden_dims: Widths = (256, 256)
    """Hidden layer widths of actor and critics (JaxCQL policy_arch / qf_arch 256-256)."""


PRESETS: dict[str, CQLConfig] = {
    "cql": CQLConfig(),
    # The Lagrange variant (CQL paper section 3, eq. 5) with JaxCQL's target gap.
    "cql-lagrange": CQLConfig(lagrange=True),
}


@pytree.dataclass
class CQLState(BuiltOn):
    BASE: ClassVar[str] = "sac"

    sac: sac.SACState
    """SAC's actor, twin critics, target critics, temperature and optimisers."""
    log_alpha_prime: jax.Array
    """log(alpha'), only trained with ``lagrange``."""
    alpha_prime_opt: optax.OptState


def _optimizers(config: CQLConfig) -> tuple[optax.GradientTransformation, ...]:
    return (
        optax.adam(config.actor_lr),
        optax.adam(config.critic_lr),
        optax.adam(config.alpha_lr),
        optax.adam(config.alpha_prime_lr),
    )


def init(key: jax.Array, obs_dim: int, act_dim: int, config: CQLConfig) -> CQLState:
    """SAC's initial state (twin critics, alpha = 1) plus log(alpha') and its optimiser."""
    backbone = sac.SACConfig(
        num_critics=NUM_CRITICS,
        actor_lr=config.actor_lr,
        critic_lr=config.critic_lr,
        alpha_lr=config.alpha_lr,
        target_entropy=config.target_entropy,
        hidden_dims=config.hidden_dims,
    )
    log_alpha_prime = jnp.asarray(INIT_LOG_ALPHA_PRIME, jnp.float32)
    return CQLState(
        sac=sac.init(key, obs_dim, act_dim, backbone),
        log_alpha_prime=log_alpha_prime,
        alpha_prime_opt=optax.adam(config.alpha_prime_lr).init(log_alpha_prime),
    )


def conservative_gap(critic, actor, batch: Batch, q_data, key, config: CQLConfig, max_action):
    """Per critic, ``mean_batch(logsumexp_j (Q(s, a_j) - log mu(a_j)) - Q(s, a))``: ``[K]``.

    ``q_data: [K, B]`` are the critics' values of the dataset actions.
    """
    size, act_dim = batch.actions.shape
    n = config.num_sampled_actions
    random_key, current_key, next_key = jax.random.split(key, 3)
    obs = jnp.repeat(batch.observations, n, axis=0)  # row b * n + j: state b, sample j
    next_obs = jnp.repeat(batch.next_observations, n, axis=0)
    random_actions = jax.random.uniform(
        random_key, (size * n, act_dim), minval=-max_action, maxval=max_action
    )
    current_actions, current_log_prob = sac.sample_action(actor, obs, current_key, max_action)
    next_actions, next_log_prob = sac.sample_action(actor, next_obs, next_key, max_action)
    # Every proposal is scored at the current state s, pi(s')'s actions included.
    actions = jnp.concatenate([random_actions, next_actions, current_actions])
    uniform_log_density = jnp.full((size * n,), -act_dim * np.log(2.0 * max_action))
    log_density = jnp.concatenate([uniform_log_density, next_log_prob, current_log_prob])
    q = networks.critic_apply(critic, jnp.tile(obs, (3, 1)), actions)  # [K, 3 B n]
    scores = (q - jax.lax.stop_gradient(log_density)).reshape(q.shape[0], 3, size, n)
    soft_max = jax.scipy.special.logsumexp(scores, axis=(1, 3))  # [K, B]
    return (soft_max - q_data).mean(axis=1)


def critic_loss(critic, state: CQLState, batch: Batch, key, config: CQLConfig, max_action):
    base = state.sac
    target_key, gap_key = jax.random.split(key)
    next_action, next_log_prob = sac.sample_action(
        base.actor, batch.next_observations, target_key, max_action
    )
    target_q = networks.critic_apply(base.critic_target, batch.next_observations, next_action)
    next_value = target_q.min(axis=0)
    if config.backup_entropy:
        next_value = next_value - jnp.exp(base.log_alpha) * next_log_prob
    y = jax.lax.stop_gradient(batch.rewards + config.discount * (1.0 - batch.dones) * next_value)
    q = networks.critic_apply(critic, batch.observations, batch.actions)
    td = ((q - y[None]) ** 2).mean(axis=1).sum()
    gap = conservative_gap(critic, base.actor, batch, q, gap_key, config, max_action)
    if config.lagrange:
        weight = alpha_prime(state.log_alpha_prime) * config.min_q_weight
        penalty = weight * (gap - config.target_action_gap).sum()
    else:
        penalty = config.min_q_weight * gap.sum()
    loss = td + penalty
    return loss, (
        gap,
        {
            "critic_loss": loss,
            "td_loss": td,
            "cql_gap": gap.mean(),
            "q_mean": q.mean(),
            "target_mean": y.mean(),
        },
    )


def alpha_prime(log_alpha_prime: jax.Array) -> jax.Array:
    return jnp.clip(jnp.exp(log_alpha_prime), 0.0, MAX_ALPHA_PRIME)


def alpha_prime_loss(log_alpha_prime, gap, config: CQLConfig):
    """The Lagrange multiplier rises while the gap exceeds target_action_gap (dual descent)."""
    return (
        -alpha_prime(log_alpha_prime)
        * config.min_q_weight
        * (gap - config.target_action_gap).mean()
    )


def update(
    state: CQLState, batch: Batch, key: jax.Array, config: CQLConfig, max_action: float
) -> tuple[CQLState, dict[str, jax.Array]]:
    """One gradient step of critics, actor, temperature (and alpha'), all from the current state."""
    actor_tx, critic_tx, alpha_tx, alpha_prime_tx = _optimizers(config)
    critic_key, actor_key = jax.random.split(key)
    base = state.sac

    grads, (gap, critic_metrics) = jax.grad(critic_loss, has_aux=True)(
        base.critic, state, batch, critic_key, config, max_action
    )
    critic, critic_opt = apply_gradients(critic_tx, grads, base.critic_opt, base.critic)

    grads, (log_prob, actor_metrics) = jax.grad(sac.actor_loss, has_aux=True)(
        base.actor, base.critic, base.log_alpha, batch, actor_key, max_action
    )
    actor, actor_opt = apply_gradients(actor_tx, grads, base.actor_opt, base.actor)

    entropy_gap = jax.lax.stop_gradient(log_prob + base.target_entropy).mean()
    alpha_grad = -entropy_gap  # d/d(log_alpha) of -log_alpha * mean(log_pi + target_entropy)
    log_alpha, alpha_opt = apply_gradients(alpha_tx, alpha_grad, base.alpha_opt, base.log_alpha)

    metrics = {**critic_metrics, **actor_metrics, "alpha": jnp.exp(base.log_alpha)}
    log_alpha_prime, alpha_prime_opt = state.log_alpha_prime, state.alpha_prime_opt
    if config.lagrange:
        grad = jax.grad(alpha_prime_loss)(state.log_alpha_prime, gap, config)
        log_alpha_prime, alpha_prime_opt = apply_gradients(
            alpha_prime_tx, grad, alpha_prime_opt, log_alpha_prime
        )
        metrics["alpha_prime"] = alpha_prime(state.log_alpha_prime)

    backbone = base.replace(
        actor=actor,
        critic=critic,
        critic_target=networks.polyak(base.critic_target, critic, config.tau),
        log_alpha=log_alpha,
        actor_opt=actor_opt,
        critic_opt=critic_opt,
        alpha_opt=alpha_opt,
        step=base.step + 1,
    )
    new_state = CQLState(
        sac=backbone, log_alpha_prime=log_alpha_prime, alpha_prime_opt=alpha_prime_opt
    )
    return new_state, metrics


ALGORITHMS = (
    # state_layout 2: the SAC state as one field
    Algorithm("cql", "CQL", PRESETS["cql"], init, update, column=3, actor="tanh-gaussian",
              steps_per_s=34.5, state_layout=2),
    Algorithm("cql-lagrange", "CQL-Lagrange", PRESETS["cql-lagrange"], init, update, column=3.5,
              actor="tanh-gaussian", steps_per_s=37.0, state_layout=2),
)  # fmt: skip
