"""BEAR (Kumar, Fu, Tucker & Levine, 2019): the actor stays on the support of the behaviour policy,
measured by an MMD to samples of a VAE fitted to the data, with a dual-tuned multiplier.

One call of :func:`update` is one gradient step on ``(s, a, r, s', d)``, in the order of the
authors' code (aviralkumar2907/BEAR, ``algos.py``, class ``BEAR``):

1. VAE (the behaviour model): ``mean_batch |dec(s, z) - a|^2 + 0.5 KL(q(z|s,a) || N(0, 1))``,
   ``z ~ q(z|s, a)``;
2. critics: ``y = r + gamma (1 - d) max_j [lambda min_i Q_targ_i(s', a'_j) + (1 - lambda) max_i
   Q_targ_i(s', a'_j)]`` over ``a'_1..m`` from the target actor, loss
   ``sum_i mean_batch w (Q_i(s, a) - y)^2`` (w = 1 for BEAR; UWAC's uncertainty weight);
3. actor: ``n`` samples ``a~_j`` of pi(s) and ``n`` decoded VAE samples; the support constraint
   ``MMD(s)`` between their pre-tanh values; after ``warmup_steps`` the loss is
   ``mean(-w' Q(s, a~) + alpha MMD(s))``, before it only ``mean(alpha MMD(s))``;
4. multiplier: ``log alpha`` ascends ``alpha mean(MMD(s) - epsilon)``, clipped to
   ``[-5, max_log_lagrange]``;
5. Polyak averaging of critic and actor targets.

UWAC (:mod:`eabc.agents.uwac`) is this rule with MC-dropout critics: it passes its own critic
evaluation (:class:`Critics`) to :func:`step`.

Why one file of about 400 lines: the VAE, the MMD kernels and the five losses are the steps of one
update in the authors' order, each checked against the official code; UWAC reuses them through
:func:`step`, so they stay together rather than spread over modules that only this rule uses.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

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
    NonNegativeCount,
    PositiveNumber,
    Probability,
    Settings,
    Weight,
    Widths,
)

"""The actor outputs a tanh-Gaussian; its deterministic action is ``tanh(mean)``."""

MIN_LOG_LAGRANGE = -5.0
"""Lower clip of log(alpha) (the authors' ``clamp_(min=-5.0)``)."""
VAE_LOG_STD_RANGE = (-4.0, 15.0)
"""Clip of the VAE encoder's log-std (the authors' VAE, taken from BCQ)."""
VAE_LATENT_CLIP = 0.5
"""Decoded latents are N(0, 1) draws clipped to +-0.5 (the authors' ``decode_multiple``)."""


Kernel = Literal["laplacian", "gaussian"]


@dataclasses.dataclass(frozen=True)
class BEARConfig(Settings):
    """BEAR's settings; the defaults are the authors' MuJoCo settings (aviralkumar2907/BEAR: the
    README's hopper command and "hyper-parameters that generally work well", and ``algos.py``)."""

    kernel: Kernel = "laplacian"
    """MMD kernel: exp(-|x - y|_1 / (2 sigma)) or exp(-|x - y|_2^2 / (2 sigma)) (README)."""
    mmd_sigma: PositiveNumber = 10.0
    """sigma of the kernel (README: 10 with the laplacian kernel, 20 with the gaussian)."""
    num_samples_match: Count = 5
    """n, samples of the actor and of the VAE per state for the MMD (README's
    num_samples_match=5)."""
    mmd_threshold: Weight = 0.05
    """epsilon, the MMD the multiplier aims for (``algos.py``: thresh = 0.05)."""
    max_log_lagrange: Weight = 10.0
    """Upper clip of log(alpha) (README's lagrange_thresh=10)."""
    init_log_lagrange: Finite | None = None
    """Initial log(alpha); None: a N(0, 1) draw from the seed (the authors' ``torch.randn``)."""
    lagrange_lr: LearningRate = 1e-3
    """Adam learning rate of log(alpha) (``algos.py``)."""
    num_target_actions: Count = 10
    """m, actions sampled at s' for the target's max (``algos.py``, from BCQ)."""
    target_mix: Probability = 0.75
    """lambda of the soft clipped double-Q target ``lambda min + (1 - lambda) max`` (``algos.py``)."""
    warmup_steps: NonNegativeCount = 20_000
    """Steps that train the actor on the MMD alone (``algos.py``: epoch >= 20, with the README's
    eval_freq=1000 iterations per epoch)."""
    target_actor: bool = True
    """Draw a' from the Polyak-averaged actor (``algos.py``); False: the current actor (rlkit)."""
    actor_q_all_samples: bool = True
    """The actor's Q is averaged over all n samples (``algos.py``); False: the first sample only
    (rlkit's BEAR, which UWAC builds on)."""
    actor_noise_clip: Weight | None = 0.5
    """Clip of the standard-normal noise of the n actor samples (``sample_multiple``: +-0.5);
    None: unclipped (rlkit's TanhGaussianPolicy)."""
    num_critics: Count = 2
    """Q-networks in the ensemble (``main.py``: ``algos.BEAR(2, ...)``)."""
    discount: Discount = 0.99
    """gamma (``algos.py``)."""
    tau: Fraction = 0.005
    """Polyak rate of critic and actor targets (``algos.py``)."""
    actor_lr: LearningRate = 1e-3
    """Adam learning rate of the actor (``algos.py``: PyTorch's default Adam)."""
    critic_lr: LearningRate = 1e-3
    """Adam learning rate of the critics (PyTorch's default Adam)."""
    vae_lr: LearningRate = 1e-3
    """Adam learning rate of the VAE (PyTorch's default Adam)."""
    hidden_dims: Widths = (400, 300)
    """Hidden widths of actor and critics (``RegularActor``, ``EnsembleCritic``)."""
    vae_hidden_dims: Widths = (750, 750)
    """Hidden widths of the VAE's encoder and decoder (``VAE``)."""
    latent_dim: Count | None = None
    """VAE latent size; None: 2 x act_dim (``algos.py``)."""


PRESETS: dict[str, BEARConfig] = {"bear": BEARConfig()}


@pytree.dataclass
class BEARState:
    actor: networks.Params
    actor_target: networks.Params
    critic: networks.Params
    critic_target: networks.Params
    vae: dict[str, networks.Params]
    """``encoder`` ([s, a] -> mean, log-std of z) and ``decoder`` ([s, z] -> pre-tanh action)."""
    log_lagrange: jax.Array
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    vae_opt: optax.OptState
    lagrange_opt: optax.OptState
    step: jax.Array


def _optimizers(config: BEARConfig) -> tuple[optax.GradientTransformation, ...]:
    return (
        optax.adam(config.actor_lr),
        optax.adam(config.critic_lr),
        optax.adam(config.vae_lr),
        optax.adam(config.lagrange_lr),
    )


def latent_size(config: BEARConfig, act_dim: int) -> int:
    return 2 * act_dim if config.latent_dim is None else config.latent_dim


def init_networks(key: jax.Array, obs_dim: int, act_dim: int, config: BEARConfig) -> dict:
    """Actor, critic ensemble, VAE and log(alpha): the parameters every BEAR-family state has."""
    actor_key, critic_key, encoder_key, decoder_key, lagrange_key = jax.random.split(key, 5)
    latent = latent_size(config, act_dim)
    actor = networks.init_mlp(actor_key, (obs_dim, *config.hidden_dims, 2 * act_dim))
    critic = networks.init_mlp(
        critic_key, (obs_dim + act_dim, *config.hidden_dims, 1), num_members=config.num_critics
    )
    vae = {
        "encoder": networks.init_mlp(
            encoder_key, (obs_dim + act_dim, *config.vae_hidden_dims, 2 * latent)
        ),
        "decoder": networks.init_mlp(
            decoder_key, (obs_dim + latent, *config.vae_hidden_dims, act_dim)
        ),
    }
    if config.init_log_lagrange is None:
        log_lagrange = jax.random.normal(lagrange_key, ())
    else:
        log_lagrange = jnp.asarray(config.init_log_lagrange, jnp.float32)
    return {"actor": actor, "critic": critic, "vae": vae, "log_lagrange": log_lagrange}


def init(key: jax.Array, obs_dim: int, act_dim: int, config: BEARConfig) -> BEARState:
    params = init_networks(key, obs_dim, act_dim, config)
    actor_tx, critic_tx, vae_tx, lagrange_tx = _optimizers(config)
    return BEARState(
        actor=params["actor"],
        actor_target=params["actor"],
        critic=params["critic"],
        critic_target=params["critic"],
        vae=params["vae"],
        log_lagrange=params["log_lagrange"],
        actor_opt=actor_tx.init(params["actor"]),
        critic_opt=critic_tx.init(params["critic"]),
        vae_opt=vae_tx.init(params["vae"]),
        lagrange_opt=lagrange_tx.init(params["log_lagrange"]),
        step=jnp.zeros((), jnp.int32),
    )


# ------------------------------------------------------------------------ the behaviour model


def vae_loss(vae, batch: Batch, key, max_action: float):
    """``mean |max_a tanh(dec(s, z)) - a|^2 + 0.5 * mean KL``, ``z = mu + std * eps``."""
    obs, actions = batch.observations, batch.actions
    mean, log_std = jnp.split(
        networks.mlp(vae["encoder"], jnp.concatenate([obs, actions], -1)), 2, -1
    )
    log_std = jnp.clip(log_std, *VAE_LOG_STD_RANGE)
    std = jnp.exp(log_std)
    z = mean + std * jax.random.normal(key, mean.shape)
    recon = max_action * jnp.tanh(networks.mlp(vae["decoder"], jnp.concatenate([obs, z], -1)))
    recon_loss = ((recon - actions) ** 2).mean()
    kl = -0.5 * (1.0 + 2.0 * log_std - mean**2 - std**2).mean()
    loss = recon_loss + 0.5 * kl
    return loss, {"vae_loss": loss, "vae_recon_loss": recon_loss, "vae_kl": kl}


def vae_samples(vae, obs: jax.Array, key, num: int) -> jax.Array:
    """``num`` pre-tanh decoded actions per state, ``[B, num, act_dim]`` (latents clipped)."""
    latent = vae["decoder"]["w0"].shape[0] - obs.shape[-1]
    z = jax.random.normal(key, (obs.shape[0], num, latent))
    z = jnp.clip(z, -VAE_LATENT_CLIP, VAE_LATENT_CLIP)
    obs = jnp.broadcast_to(obs[:, None, :], (obs.shape[0], num, obs.shape[-1]))
    return networks.mlp(vae["decoder"], jnp.concatenate([obs, z], -1))


# --------------------------------------------------------------------------------- the actor


def actor_samples(actor, obs, key, num: int, noise_clip: float | None):
    """``num`` reparameterised samples of pi(s): ``(pre-tanh u, max_a tanh(u))``, ``[B, num, A]``."""
    mean, log_std = networks.gaussian_actor_apply(actor, obs)
    eps = jax.random.normal(key, (obs.shape[0], num, mean.shape[-1]))
    if noise_clip is not None:
        eps = jnp.clip(eps, -noise_clip, noise_clip)
    return mean[:, None, :] + jnp.exp(log_std)[:, None, :] * eps


def mmd(x: jax.Array, y: jax.Array, kernel: str, sigma: float) -> jax.Array:
    """The authors' sampled MMD per state, ``sqrt(k(x,x) + k(y,y) - 2 k(x,y) + 1e-6)``: ``[B]``.

    ``x, y: [B, n, d]``; ``k(x, y)`` is the mean of the kernel over all n x n pairs.
    """

    def mean_kernel(a, b):
        diff = a[:, :, None, :] - b[:, None, :, :]
        dist = jnp.abs(diff).sum(-1) if kernel == "laplacian" else (diff**2).sum(-1)
        return jnp.exp(-dist / (2.0 * sigma)).mean(axis=(1, 2))

    return jnp.sqrt(mean_kernel(x, x) + mean_kernel(y, y) - 2.0 * mean_kernel(x, y) + 1e-6)


# ------------------------------------------------------------------------------- the critics


@dataclasses.dataclass(frozen=True)
class Critics:
    """How the critic ensemble is evaluated: BEAR's plain networks (UWAC overrides all three)."""

    def regress(self, critic, obs, actions, key) -> jax.Array:
        """The values the Bellman loss regresses, ``[K, B]``."""
        del key
        return networks.critic_apply(critic, obs, actions)

    def estimate(self, critic, obs, actions, key) -> tuple[jax.Array, jax.Array]:
        """``(values [K, B], variance [B])`` for the target and the actor (variance 0 here)."""
        del key
        q = networks.critic_apply(critic, obs, actions)
        return q, jnp.zeros(q.shape[1:])

    def target(self, critic_target, obs, actions, key) -> tuple[jax.Array, jax.Array]:
        """:meth:`estimate` for the target networks."""
        return self.estimate(critic_target, obs, actions, key)

    def weight(self, variance: jax.Array) -> jax.Array:
        """Down-weighting of uncertain transitions in the Bellman loss: 1 for BEAR."""
        return jnp.ones_like(variance)

    def actor_weight(self, variance: jax.Array) -> jax.Array:
        """Down-weighting of uncertain states in the actor's objective."""
        return self.weight(variance)


def soft_clipped_target(target_q: jax.Array, mix: float) -> jax.Array:
    """``mix * min_i Q_i + (1 - mix) * max_i Q_i`` over the ensemble axis 0."""
    return mix * target_q.min(axis=0) + (1.0 - mix) * target_q.max(axis=0)


def critic_loss(critic, state, batch: Batch, key, config: BEARConfig, max_action, critics):
    size = batch.rewards.shape[0]
    m = config.num_target_actions
    action_key, target_key, regress_key = jax.random.split(key, 3)
    next_obs = jnp.repeat(batch.next_observations, m, axis=0)  # row b * m + j
    policy = state.actor_target if config.target_actor else state.actor
    mean, log_std = networks.gaussian_actor_apply(policy, next_obs)
    next_actions, _ = networks.sample_tanh_gaussian(action_key, mean, log_std, max_action)
    target_q, target_var = critics.target(state.critic_target, next_obs, next_actions, target_key)
    next_value = soft_clipped_target(target_q, config.target_mix).reshape(size, m).max(axis=1)
    variance = target_var.reshape(size, m).max(axis=1)
    y = batch.rewards + config.discount * (1.0 - batch.dones) * next_value
    y, weight = jax.lax.stop_gradient((y, critics.weight(variance)))
    q = critics.regress(critic, batch.observations, batch.actions, regress_key)
    # UWAC's code weights the error before squaring it: (w (Q - y))^2; w = 1 for BEAR.
    loss = (((q - y[None]) * weight[None]) ** 2).mean(axis=1).sum()
    metrics = {
        "critic_loss": loss,
        "q_mean": q.mean(),
        "target_mean": y.mean(),
        "q_ensemble_std": q.std(axis=0).mean(),
    }
    return loss, (weight, variance, metrics)


def actor_loss(
    actor, critic, vae, log_lagrange, step, batch: Batch, key, config, max_action, critics
):
    n = config.num_samples_match
    actor_key, vae_key, q_key = jax.random.split(key, 3)
    obs = batch.observations
    raw = actor_samples(actor, obs, actor_key, n, config.actor_noise_clip)  # [B, n, A]
    raw_behaviour = vae_samples(vae, obs, vae_key, n)
    divergence = mmd(raw_behaviour, raw, config.kernel, config.mmd_sigma)  # [B]
    actions = max_action * jnp.tanh(raw)
    if config.actor_q_all_samples:
        flat = actions.transpose(1, 0, 2).reshape(n * obs.shape[0], -1)  # row j * B + b
        q, variance = critics.estimate(critic, jnp.tile(obs, (n, 1)), flat, q_key)
        q = q.reshape(q.shape[0], n, obs.shape[0]).mean(axis=1)
        variance = variance.reshape(n, obs.shape[0]).mean(axis=0)
    else:
        q, variance = critics.estimate(critic, obs, actions[:, 0], q_key)
    value = q.min(axis=0)  # the authors' version 0
    weight = jax.lax.stop_gradient(critics.actor_weight(variance))
    alpha = jnp.exp(log_lagrange)
    improvement = jnp.where(step >= config.warmup_steps, 1.0, 0.0)
    loss = (-improvement * weight * value + jax.lax.stop_gradient(alpha) * divergence).mean()
    return loss, (
        divergence,
        {
            "actor_loss": loss,
            "actor_value": value.mean(),
            "mmd": divergence.mean(),
            "actor_weight": weight.mean(),
        },
    )


def lagrange_loss(log_lagrange, divergence, config: BEARConfig):
    """Descending this raises alpha while the MMD exceeds epsilon (dual ascent on the constraint)."""
    return -jnp.exp(log_lagrange) * (divergence - config.mmd_threshold).mean()


def update(
    state: BEARState, batch: Batch, key: jax.Array, config: BEARConfig, max_action: float
) -> tuple[BEARState, dict[str, jax.Array]]:
    """One gradient step of VAE, critics, actor and multiplier (in the authors' order). Pure."""
    return step(state, batch, key, config, max_action, Critics())


def step(state, batch: Batch, key, config: BEARConfig, max_action: float, critics: Critics):
    """:func:`update` with the critics evaluated by ``critics`` (BEAR's, or UWAC's MC dropout)."""
    actor_tx, critic_tx, vae_tx, lagrange_tx = _optimizers(config)
    vae_key, critic_key, actor_key = jax.random.split(key, 3)

    grads, vae_metrics = jax.grad(vae_loss, has_aux=True)(state.vae, batch, vae_key, max_action)
    vae, vae_opt = apply_gradients(vae_tx, grads, state.vae_opt, state.vae)

    grads, (_, _, critic_metrics) = jax.grad(critic_loss, has_aux=True)(
        state.critic, state, batch, critic_key, config, max_action, critics
    )
    critic, critic_opt = apply_gradients(critic_tx, grads, state.critic_opt, state.critic)

    # The actor uses the critics just updated and the VAE just updated, as in the authors' code.
    grads, (divergence, actor_metrics) = jax.grad(actor_loss, has_aux=True)(
        state.actor, critic, vae, state.log_lagrange, state.step, batch, actor_key, config,
        max_action, critics,
    )  # fmt: skip
    actor, actor_opt = apply_gradients(actor_tx, grads, state.actor_opt, state.actor)

    grad = jax.grad(lagrange_loss)(state.log_lagrange, jax.lax.stop_gradient(divergence), config)
    log_lagrange, lagrange_opt = apply_gradients(
        lagrange_tx, grad, state.lagrange_opt, state.log_lagrange
    )
    log_lagrange = jnp.clip(log_lagrange, MIN_LOG_LAGRANGE, config.max_log_lagrange)

    new_state = state.replace(
        actor=actor,
        actor_target=networks.polyak(state.actor_target, actor, config.tau),
        critic=critic,
        critic_target=networks.polyak(state.critic_target, critic, config.tau),
        vae=vae,
        log_lagrange=log_lagrange,
        actor_opt=actor_opt,
        critic_opt=critic_opt,
        vae_opt=vae_opt,
        lagrange_opt=lagrange_opt,
        step=state.step + 1,
    )
    metrics = {**vae_metrics, **critic_metrics, **actor_metrics}
    return new_state, {**metrics, "lagrange": jnp.exp(state.log_lagrange)}


ALGORITHMS = (
    # steps/s: the reference host's (eabc.timing), by benchmarks/algorithms.py.
    Algorithm("bear", "BEAR", PRESETS["bear"], init, update, column=7, actor="tanh-gaussian",
              steps_per_s=42.8),
)  # fmt: skip
