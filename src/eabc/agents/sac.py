"""Soft actor-critic with automatic entropy tuning; with N critics it is SAC-N, and with the
ensemble-gradient diversity penalty it is EDAC (An et al., 2021).

One call of :func:`update` is one gradient step on a mini-batch ``(s, a, r, s', d)``:

1. ``a' ~ pi(s')``; ``y = r + gamma (1 - d) (min_i Q_targ_i(s', a') - alpha log pi(a'|s'))``;
2. critic loss ``sum_i mean_batch (Q_i(s, a) - y)^2``, plus for EDAC
   ``eta * mean_batch sum_{i != j} cos(grad_a Q_i, grad_a Q_j) / (N - 1)``;
3. actor loss ``mean(alpha log pi(a~|s) - min_i Q_i(s, a~))``, ``a~ ~ pi(s)`` (reparameterised);
4. temperature loss ``-mean(log_alpha * (log pi(a~|s) + target_entropy))``;
5. Polyak averaging of the critic targets every step.

The same rule trains the online SAC that makes the behaviour policies (``eabc sac``) and, offline,
the SAC-N and EDAC baselines (``eabc train --algo sac-n|edac|edac-10``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax

from eabc import networks, pytree
from eabc.agents.common import Batch, apply_gradients
from eabc.agents.contract import Algorithm
from eabc.ranges import (
    Count,
    Discount,
    Finite,
    Fraction,
    LearningRate,
    PositiveNumber,
    Settings,
    Weight,
    Widths,
)

"""The actor outputs a tanh-Gaussian; its deterministic action is ``tanh(mean)``."""


@dataclasses.dataclass(frozen=True)
class SACConfig(Settings):
    """SAC's settings; the defaults are Haarnoja et al. (2018)'s for MuJoCo."""

    num_critics: Count = 2
    """N, the number of Q-networks (2 for SAC; SAC-N and EDAC use more)."""
    eta: Weight = 0.0
    """EDAC's weight of the ensemble-gradient diversity penalty (0: plain SAC / SAC-N)."""
    discount: Discount = 0.99
    """gamma."""
    tau: Fraction = 0.005
    """Polyak rate of the critic targets."""
    actor_lr: LearningRate = 3e-4
    """Adam learning rate of the actor."""
    critic_lr: LearningRate = 3e-4
    """Adam learning rate of the critics."""
    alpha_lr: LearningRate = 3e-4
    """Adam learning rate of log(alpha)."""
    init_alpha: PositiveNumber = 1.0
    """Initial entropy temperature."""
    autotune: bool = True
    """Tune the temperature toward ``target_entropy`` (False: keep ``init_alpha`` throughout)."""
    target_entropy: Finite | None = None
    """Entropy the temperature aims for (default -act_dim)."""
    hidden_dims: Widths = (256, 256)
    """Hidden layer widths of actor and critics."""

    def __post_init__(self):
        super().__post_init__()
        if self.eta > 0 and self.num_critics < 2:
            raise ValueError(
                f"eta={self.eta} (EDAC's diversity penalty) needs num_critics >= 2, got "
                f"{self.num_critics}; set num_critics 2 or more, or eta 0"
            )


PRESETS: dict[str, SACConfig] = {
    "sac": SACConfig(),
    # SAC-N (An et al., 2021): SAC with N critics and the min over all of them; eta = 0.
    "sac-n": SACConfig(num_critics=10),
    # EDAC (An et al., 2021): N = 50 and eta = 1 as for hopper in the paper's Table 5.
    "edac": SACConfig(num_critics=50, eta=1.0),
    # EDAC-10, the paper's Table 6 setting with ten critics.
    "edac-10": SACConfig(num_critics=10, eta=1.0),
}

ONLINE_PRESETS: dict[str, SACConfig] = {
    # Spinning Up's SAC: fixed temperature 0.2, Adam 1e-3. With automatic tuning toward -dim(A) the
    # temperature fell to 0.04 within 20K steps and four walker2d runs (2 seeds, interleaved
    # updates, critic lr 1e-3) stayed near 500 return for 90K-250K steps; this setting passed
    # 2,700 by 150K (README, "Behaviour policies: online SAC and the zoo").
    "walker2d": SACConfig(init_alpha=0.2, autotune=False, actor_lr=1e-3, critic_lr=1e-3),
}
"""Online SAC settings per environment, where they differ from :data:`PRESETS` ``["sac"]``."""


def online_preset(env: str) -> SACConfig:
    """The online SAC settings ``eabc sac`` uses for ``env``."""
    return ONLINE_PRESETS.get(env, PRESETS["sac"])


@pytree.dataclass
class SACState:
    actor: networks.Params
    critic: networks.Params
    critic_target: networks.Params
    log_alpha: jax.Array
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    alpha_opt: optax.OptState
    step: jax.Array
    target_entropy: float = pytree.field(static=True, default=0.0)


def _optimizers(config: SACConfig) -> tuple[optax.GradientTransformation, ...]:
    return optax.adam(config.actor_lr), optax.adam(config.critic_lr), optax.adam(config.alpha_lr)


def init(key: jax.Array, obs_dim: int, act_dim: int, config: SACConfig) -> SACState:
    actor_key, critic_key = jax.random.split(key)
    actor = networks.init_mlp(actor_key, (obs_dim, *config.hidden_dims, 2 * act_dim))
    critic = networks.init_mlp(
        critic_key, (obs_dim + act_dim, *config.hidden_dims, 1), num_members=config.num_critics
    )
    log_alpha = jnp.asarray(jnp.log(config.init_alpha), jnp.float32)
    actor_tx, critic_tx, alpha_tx = _optimizers(config)
    target_entropy = (
        -float(act_dim) if config.target_entropy is None else float(config.target_entropy)
    )
    return SACState(
        actor=actor,
        critic=critic,
        critic_target=critic,
        log_alpha=log_alpha,
        actor_opt=actor_tx.init(actor),
        critic_opt=critic_tx.init(critic),
        alpha_opt=alpha_tx.init(log_alpha),
        step=jnp.zeros((), jnp.int32),
        target_entropy=target_entropy,
    )


def sample_action(actor, obs, key, max_action):
    mean, log_std = networks.gaussian_actor_apply(actor, obs)
    return networks.sample_tanh_gaussian(key, mean, log_std, max_action)


def diversity_loss(critic, obs: jax.Array, actions: jax.Array) -> jax.Array:
    """EDAC's penalty: mean over the batch of ``sum_{i != j} cos(grad_a Q_i, grad_a Q_j) / (N-1)``."""
    # Member i sees its own copy of the actions, so the gradient of the sum of all values with
    # respect to the copies is every member's own action gradient.
    num = critic["w0"].shape[0]
    obs = jnp.broadcast_to(obs, (num, *obs.shape))

    def total(a):  # a: [N, B, A]
        return networks.ensemble_mlp(critic, jnp.concatenate([obs, a], axis=-1)).sum()

    grads = jax.grad(total)(jnp.broadcast_to(actions, (num, *actions.shape)))  # [N, B, A]
    grads = grads / (jnp.linalg.norm(grads, axis=-1, keepdims=True) + 1e-10)
    cosines = jnp.einsum("iba,jba->bij", grads, grads)
    off_diagonal = cosines.sum(axis=(1, 2)) - jnp.trace(cosines, axis1=1, axis2=2)
    return off_diagonal.mean() / (num - 1)


def critic_loss(critic, state: SACState, batch: Batch, key, config: SACConfig, max_action):
    next_action, next_log_prob = sample_action(
        state.actor, batch.next_observations, key, max_action
    )
    target_q = networks.critic_apply(state.critic_target, batch.next_observations, next_action)
    alpha = jnp.exp(state.log_alpha)
    next_value = target_q.min(axis=0) - alpha * next_log_prob
    y = jax.lax.stop_gradient(batch.rewards + config.discount * (1.0 - batch.dones) * next_value)
    q = networks.critic_apply(critic, batch.observations, batch.actions)
    td = ((q - y[None]) ** 2).mean(axis=1).sum()
    metrics = {"critic_loss": td, "q_mean": q.mean(), "target_mean": y.mean()}
    if config.num_critics > 1:
        metrics["q_ensemble_std"] = q.std(axis=0, ddof=1).mean()
    if config.eta > 0:
        diversity = diversity_loss(critic, batch.observations, batch.actions)
        metrics["diversity_loss"] = diversity
        return td + config.eta * diversity, metrics
    return td, metrics


def actor_loss(actor, critic, log_alpha, batch: Batch, key, max_action):
    action, log_prob = sample_action(actor, batch.observations, key, max_action)
    q = networks.critic_apply(critic, batch.observations, action).min(axis=0)
    loss = (jnp.exp(log_alpha) * log_prob - q).mean()
    return loss, (
        log_prob,
        {"actor_loss": loss, "actor_value": q.mean(), "entropy": -log_prob.mean()},
    )


def update(
    state: SACState, batch: Batch, key: jax.Array, config: SACConfig, max_action: float
) -> tuple[SACState, dict[str, jax.Array]]:
    """One gradient step of critics, actor and temperature. Pure."""
    actor_tx, critic_tx, alpha_tx = _optimizers(config)
    critic_key, actor_key = jax.random.split(key)

    grads, critic_metrics = jax.grad(critic_loss, has_aux=True)(
        state.critic, state, batch, critic_key, config, max_action
    )
    critic, critic_opt = apply_gradients(critic_tx, grads, state.critic_opt, state.critic)

    grads, (log_prob, actor_metrics) = jax.grad(actor_loss, has_aux=True)(
        state.actor, critic, state.log_alpha, batch, actor_key, max_action
    )
    actor, actor_opt = apply_gradients(actor_tx, grads, state.actor_opt, state.actor)

    log_alpha, alpha_opt = state.log_alpha, state.alpha_opt
    if config.autotune:
        entropy_gap = jax.lax.stop_gradient(log_prob + state.target_entropy).mean()
        alpha_grad = -entropy_gap  # d/d(log_alpha) of -log_alpha * mean(log_pi + target_entropy)
        log_alpha, alpha_opt = apply_gradients(alpha_tx, alpha_grad, alpha_opt, log_alpha)

    new_state = state.replace(
        actor=actor,
        critic=critic,
        critic_target=networks.polyak(state.critic_target, critic, config.tau),
        log_alpha=log_alpha,
        actor_opt=actor_opt,
        critic_opt=critic_opt,
        alpha_opt=alpha_opt,
        step=state.step + 1,
    )
    return new_state, {**critic_metrics, **actor_metrics, "alpha": jnp.exp(state.log_alpha)}


def _critic_cost(reference: int):
    return lambda config: config.num_critics / reference


ALGORITHMS = (
    Algorithm("sac-n", "SAC-N", PRESETS["sac-n"], init, update, column=6, actor="tanh-gaussian",
              steps_per_s=129.0, cost=_critic_cost(10),
              report_settings=("num_critics",), cli_flags=("num_critics",)),
    Algorithm("edac", "EDAC", PRESETS["edac"], init, update, column=11, actor="tanh-gaussian",
              steps_per_s=8.8, cost=_critic_cost(50),
              report_settings=("num_critics",), cli_flags=("num_critics",)),
    Algorithm("edac-10", "EDAC-10", PRESETS["edac-10"], init, update, column=12, actor="tanh-gaussian",
              steps_per_s=68.0, cost=_critic_cost(10),
              report_settings=("num_critics",), cli_flags=("num_critics",)),
)  # fmt: skip
