"""EABC (Algorithm 1 of the paper), with TD3+BC and TD3 as settings of the same update rule.

One call of :func:`update` is one gradient step ``t`` on a mini-batch ``(s, a, r, s', d)``:

1. target action ``a' = clip(pi_targ(s') + clip(eps, -c, c), -max_a, max_a)``;
2. ``y = r + gamma * (1 - d) * pess(Q_targ_1..K(s', a'))``, one target shared by every member;
3. critic loss ``sum_i mean_batch (Q_i(s, a) - y)^2``;
4. every ``policy_freq`` steps the actor minimises
   ``-lambda * mean(P) + mean(w * mean_dims (pi(s) - a)^2)`` with ``P = pess(Q_1..K(s, pi(s)))``,
   ``lambda = alpha / mean|P|`` (no gradient) and ``w ~ Bernoulli(p)`` per sample;
5. then the actor and critic targets move by Polyak averaging.

Steps 1, 3 and 5 and the schedule of step 4 are TD3's (:mod:`eabc.agents.td3_core`); this file
holds the target, the losses and the BC weight.

docs/algorithm.md#the-update is the specification this file follows line by line; with every
setting at its default the rule is exactly that (published EABC). The settings below it are the
variants the study screened (docs/results/screen/README.md), each a switch of this one rule:

- ``critic_layer_norm``: LayerNorm before every hidden ReLU of the critics (SEEM, Yue et al. 2023;
  ReBRAC, Tarasov et al. 2023, puts it after the ReLU), which bounds how fast a critic can
  extrapolate;
- ``pessimism_beta``: ``mean - beta * std`` instead of ``mean - std``;
- ``independent_targets``: member ``i`` regresses on its own target ``r + gamma (1 - d) Q_targ_i``
  (MSG, Ghasemipour et al. 2022), so the members stay diverse off the data and the actor's
  ``mean - beta * std`` sees a real spread there;
- ``bc_rule``: how the per-sample BC weight ``w`` is chosen, a config of its own
  (:class:`eabc.agents.bc_weights.BCWeightConfig`, set by its settings' names: ``bc_weight``,
  ``quantile_level``, ``auto_*``). ``bernoulli`` is the paper's ``w ~ Bernoulli(p)``;
  ``advantage`` keeps BC where the ensemble rates the data's action at least as high as the
  policy's (:func:`advantage_keep`); the authors' earlier ``quantile`` rule and the automatic p
  (``auto``) live in :mod:`eabc.agents.bc_weights`. None of them beat full cloning in the screen
  (docs/results/screen/README.md).

Every variant is a setting of the one rule, so that comparing two variants compares that setting
alone; the rule and its settings (with the docstrings the CLI and the contract tests read) live
here, the longer BC-weight rules it can switch to in :mod:`eabc.agents.bc_weights`.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp

from eabc import networks, pytree
from eabc.agents import bc_weights, td3_core
from eabc.agents.common import Batch
from eabc.agents.contract import Algorithm
from eabc.data import tasks
from eabc.ranges import (
    Count,
    Discount,
    Ensemble,
    Fraction,
    LearningRate,
    Probability,
    Settings,
    Weight,
    Widths,
)

Pessimism = Literal["mean-std", "min", "min2"]


@dataclasses.dataclass(frozen=True)
class EABCConfig(Settings):
    """Settings of the EABC family; the defaults are the paper's (Tables 2 and 4)."""

    num_critics: Ensemble = 10
    """K, the number of Q-networks in the critic ensemble."""
    confidence_level: Probability | None = None
    """p, the probability that a sample's behaviour-cloning term is kept; None: Table 3's p for
    the dataset (bc_weight bernoulli)."""
    pessimism: Pessimism = "mean-std"
    """How the ensemble becomes one value: mean - std (ddof 1), min of all, or min of 2 random members."""
    actor_uses_ensemble: bool = True
    """Actor maximises pess(Q_1..K); False: it maximises critic 1 only (TD3, TD3+BC)."""
    behavior_cloning: bool = True
    """Keep the BC term and the lambda normalisation; False gives TD3's actor loss -mean Q."""
    alpha: Weight = 2.5
    """TD3+BC's alpha: lambda = alpha / mean|Q|."""
    discount: Discount = 0.99
    """gamma."""
    tau: Fraction = 0.005
    """Polyak rate of the target networks."""
    policy_noise: Weight = 0.2
    """Std of the target-policy smoothing noise, as a fraction of max_action."""
    noise_clip: Weight = 0.5
    """Clip of the smoothing noise, as a fraction of max_action."""
    policy_freq: Count = 2
    """The actor and the targets are updated every policy_freq critic steps."""
    actor_lr: LearningRate = 3e-4
    """Adam learning rate of the actor."""
    critic_lr: LearningRate = 3e-4
    """Adam learning rate of the critics."""
    hidden_dims: Widths = (256, 256)
    """Hidden layer widths of actor and critics."""
    critic_layer_norm: bool = False
    """LayerNorm before each hidden ReLU of the critics (SEEM's order; ReBRAC's authors put it
    after). Not in the paper."""
    pessimism_beta: Weight = 1.0
    """beta of ``mean - beta * std`` (pessimism mean-std); the paper's is 1."""
    independent_targets: bool = False
    """Each member regresses on its own target network's value (MSG) instead of one shared
    pess(...) target; pessimism then acts through the actor's value only."""
    bc_rule: bc_weights.BCWeightConfig = bc_weights.BCWeightConfig()
    """How the per-sample BC weight is chosen: the paper's w ~ Bernoulli(p) by default; the
    screened rules (bc_weight quantile, auto, advantage) and their settings, each set by its own
    name, in eabc.agents.bc_weights.BCWeightConfig."""


PRESETS: dict[str, EABCConfig] = {
    "eabc": EABCConfig(),
    # TD3+BC (Fujimoto & Gu, 2021): twin critics, min target, actor on critic 1, full BC.
    "td3bc": EABCConfig(
        num_critics=2, confidence_level=1.0, pessimism="min", actor_uses_ensemble=False
    ),
    # TD3 (Fujimoto et al., 2018) run offline: TD3+BC without the BC term.
    "td3": EABCConfig(
        num_critics=2,
        confidence_level=1.0,
        pessimism="min",
        actor_uses_ensemble=False,
        behavior_cloning=False,
    ),
    # The authors' earlier rule: BC switched per sample by the ensemble, q per dataset
    # (docs/algorithm.md#the-authors-earlier-bc-rule).
    "eabc-quantile": EABCConfig(bc_rule=bc_weights.BCWeightConfig(bc_weight="quantile")),
    # EABC with p adapted during training from offline signals (no per-dataset p).
    "eabc-auto": EABCConfig(bc_rule=bc_weights.BCWeightConfig(bc_weight="auto")),
    # A candidate for the recommended variant: automatic p on LayerNorm critics, its
    # spread-ratio target calibrated over the first 5,000 steps at p = 1 (a target of 1 let p
    # fall to 0.1 on hopper-medium and the score with it; see bc_weights.adapt_confidence_level).
    "eabc-robust": EABCConfig(
        critic_layer_norm=True,
        bc_rule=bc_weights.BCWeightConfig(
            bc_weight="auto", auto_calibration_steps=5000, auto_rate=1e-2
        ),
    ),
    # The recommended variant: full cloning (p = 1, no per-dataset p) on LayerNorm critics. In the
    # screen (seed 0, 50K steps; docs/results/screen/README.md) it was within a point of TD3+BC or
    # above it on every dataset, with its critics in range, while every p < 1 we tried lost
    # hopper-medium's score; the study sets it against TD3+BC at 3 seeds x 100K steps
    # (docs/results/study/README.md).
    "eabc-ln": EABCConfig(confidence_level=1.0, critic_layer_norm=True),
    # Automatic p as a trust region: p follows the policy's distance from the data's actions,
    # kept within twice what full cloning leaves over the first 5,000 steps, on LayerNorm critics
    # (every spread-ratio controller on hopper-medium kept the critics sound and still let the
    # policy drift; the distance sees the drift itself). In the screen (docs/results/screen/) it
    # holds the distance but lost hopper-medium (22; 35 at 1x) and walker2d-medium (14 at 1x):
    # not recommended.
    "eabc-trust": EABCConfig(
        critic_layer_norm=True,
        bc_rule=bc_weights.BCWeightConfig(
            bc_weight="auto", auto_signal="distance", auto_calibration_steps=5000, auto_rate=1e-2
        ),
    ),
}
PUBLISHED = "eabc"
"""The published rule (Table 3's p): the side of the study's failure tables that fails."""
RECOMMENDED = "eabc-ln"
"""The recommended variant (docs/results/study/README.md), the README's first command: what
reports set beside it."""


@pytree.dataclass
class EABCState(td3_core.TD3State):
    """TD3's networks, optimisers and step count (:class:`~eabc.agents.td3_core.TD3State`)."""

    controller: dict[str, jax.Array] = pytree.field(default_factory=dict)
    """bc_weight auto's state: ``p`` and the reward range seen so far (empty otherwise)."""


def init(key: jax.Array, obs_dim: int, act_dim: int, config: EABCConfig) -> EABCState:
    base = td3_core.init(key, obs_dim, act_dim, config)
    auto = config.bc_rule.bc_weight == "auto"
    controller = bc_weights.initial_controller(config) if auto else {}
    return EABCState(**vars(base), controller=controller)


def pessimistic_value(
    q: jax.Array, pessimism: Pessimism, key: jax.Array, beta: float = 1.0
) -> jax.Array:
    """Collapse ensemble values ``q: [K, B]`` into one pessimistic value per sample, eq. (4)
    (``mean - beta * std``; the paper's beta is 1)."""
    if pessimism == "mean-std":
        return q.mean(axis=0) - beta * q.std(axis=0, ddof=1)
    if pessimism == "min":
        return q.min(axis=0)
    pair = jax.random.choice(key, q.shape[0], (2,), replace=False)
    return q[pair].min(axis=0)


def critic_loss(critic, critic_target, actor_target, batch: Batch, key, config, max_action):
    noise_key, pess_key = jax.random.split(key)
    next_action = td3_core.target_action(actor_target, batch, noise_key, config, max_action)
    target_q = networks.critic_apply(critic_target, batch.next_observations, next_action)
    if config.independent_targets:  # [K, B]: member i bootstraps from its own target network
        next_value = target_q
    else:  # [1, B]: one shared pessimistic target
        next_value = pessimistic_value(target_q, config.pessimism, pess_key, config.pessimism_beta)[
            None
        ]
    y = batch.rewards + config.discount * (1.0 - batch.dones) * next_value
    y = jax.lax.stop_gradient(y)
    q = networks.critic_apply(critic, batch.observations, batch.actions)
    loss = ((q - y) ** 2).mean(axis=1).sum()
    return loss, {
        "critic_loss": loss,
        "q_mean": q.mean(),
        "q_ensemble_std": q.std(axis=0, ddof=1).mean(),
        "target_mean": y.mean(),
    }


def actor_loss(actor, critic, batch: Batch, key, config, max_action, keep=None, p=None):
    """The actor loss; ``keep`` (per sample, in [0, 1]) replaces the Bernoulli BC mask if given,
    and ``p`` (a traced scalar: bc_weight auto's current p) replaces ``config.confidence_level``.
    With bc_weight advantage the mask is ``pess Q(s, a) >= pess Q(s, pi(s))``, no gradient."""
    pess_key, mask_key = jax.random.split(key)
    pi = networks.actor_apply(actor, batch.observations, max_action)
    q = networks.critic_apply(critic, batch.observations, pi)
    if config.actor_uses_ensemble:
        value = pessimistic_value(q, config.pessimism, pess_key, config.pessimism_beta)
    else:
        value = q[0]
    if not config.behavior_cloning:
        loss = -value.mean()
        return loss, {"actor_loss": loss, "actor_value": value.mean()}
    lam = jax.lax.stop_gradient(config.alpha / jnp.abs(value).mean())
    if keep is None and config.bc_rule.bc_weight == "advantage":
        keep = advantage_keep(critic, batch, value, pess_key, config)
    if keep is None:
        p = config.confidence_level if p is None else p
        if p is None:
            raise ValueError(
                "confidence_level p is unset: resolve it from the dataset (Table 3, done by the "
                "trainer) or set it"
            )
        keep = jax.random.bernoulli(mask_key, p, value.shape)
    keep = keep.astype(pi.dtype)
    squared = ((pi - batch.actions) ** 2).mean(axis=-1)
    bc = (keep * squared).mean()
    loss = -lam * value.mean() + bc
    metrics = {
        "actor_loss": loss,
        "actor_value": value.mean(),
        "actor_q_mean": q.mean(),
        # The ensemble's spread at the policy's own actions: the penalty mean - std actually pays.
        "policy_q_std": q.std(axis=0, ddof=1).mean(),
        "lambda": lam,
        "bc_loss": bc,
        "bc_fraction": keep.mean(),
    }
    if config.bc_rule.bc_weight == "auto" and config.bc_rule.auto_signal == "distance":
        metrics["action_distance"] = jax.lax.stop_gradient(squared.mean()) / max_action**2
    return loss, metrics


def advantage_keep(critic, batch: Batch, policy_value, key, config: EABCConfig) -> jax.Array:
    """bc_weight advantage's mask: 1 where the data's action is valued at least as high as the
    policy's, both by the actor's own value (``pess`` of the ensemble, or critic 1 for
    actor_uses_ensemble False; min2 draws the same pair for both)."""
    q = networks.critic_apply(critic, batch.observations, batch.actions)
    if config.actor_uses_ensemble:
        data_value = pessimistic_value(q, config.pessimism, key, config.pessimism_beta)
    else:
        data_value = q[0]
    better = data_value >= policy_value
    return jax.lax.stop_gradient(better.astype(policy_value.dtype))


def update(
    state: EABCState,
    batch: Batch,
    key: jax.Array,
    config: EABCConfig,
    max_action: float,
    delayed: bool | None = None,
) -> tuple[EABCState, dict[str, jax.Array]]:
    """One gradient step ``t`` of Algorithm 1; ``delayed``: whether ``t % policy_freq == 0`` (the
    actor's step), None: from ``state.step`` (see :func:`eabc.agents.td3_core.scheduled`). Pure:
    the same inputs always give the same outputs."""
    return td3_core.scheduled(_step, state, batch, key, config, max_action, delayed)


def _step(state: EABCState, batch: Batch, key, config: EABCConfig, max_action, delayed: bool):
    critic_key, actor_key = jax.random.split(key)
    # Lines 1-3: the smoothed target action, the pessimistic target, the critics' step.
    new, metrics = td3_core.critic_step(state, critic_loss, batch, critic_key, config, max_action)
    if not delayed:
        return new, metrics
    # Lines 4-5: the actor's step on the critics just updated, then Polyak averaging. The
    # quantile rule reads the critics from before this step's update (the authors' order).
    rule = config.bc_rule.bc_weight
    keep = bc_weights.quantile_keep(state.critic, batch, config) if rule == "quantile" else None
    p = state.controller["p"] if rule == "auto" else None
    new, actor_metrics = td3_core.actor_step(
        new, config, actor_loss, batch, actor_key, config, max_action, keep, p
    )
    metrics = {**metrics, **actor_metrics}
    if rule == "auto":  # p moves after each actor step
        controller, controller_metrics = bc_weights.adapt_confidence_level(
            state.controller, batch, metrics, config, new.step
        )
        new = new.replace(controller=controller)
        metrics = {**metrics, **controller_metrics}
    return new, metrics


# Table 3 of the paper: the best confidence level p per (environment, dataset kind); Table 5's
# for AntMaze.
CONFIDENCE_LEVEL: dict[tuple[str, str], float] = {
    ("halfcheetah", "expert"): 0.5, ("hopper", "expert"): 1.0, ("walker2d", "expert"): 0.5,
    ("halfcheetah", "medium-expert"): 1.0, ("hopper", "medium-expert"): 0.5,
    ("walker2d", "medium-expert"): 0.25,
    ("halfcheetah", "medium"): 0.0, ("hopper", "medium"): 0.25, ("walker2d", "medium"): 0.25,
    ("halfcheetah", "medium-replay"): 0.0, ("hopper", "medium-replay"): 0.0,
    ("walker2d", "medium-replay"): 0.0,
    ("halfcheetah", "random"): 0.0, ("hopper", "random"): 0.0, ("walker2d", "random"): 0.95,
    ("antmaze", "umaze"): 1.0, ("antmaze", "umaze-diverse"): 0.5,
    ("antmaze", "medium-play"): 1.0, ("antmaze", "medium-diverse"): 0.75,
    ("antmaze", "large-play"): 1.0, ("antmaze", "large-diverse"): 1.0,
}  # fmt: skip
# q of the authors' earlier quantile BC rule per (environment, dataset kind)
# (docs/algorithm.md#the-authors-earlier-bc-rule).
QUANTILE_LEVEL: dict[tuple[str, str], float] = {
    ("halfcheetah", "expert"): 1.0, ("hopper", "expert"): 0.9, ("walker2d", "expert"): 1.0,
    ("halfcheetah", "medium-expert"): 1.0, ("hopper", "medium-expert"): 0.9,
    ("walker2d", "medium-expert"): 1.0,
    ("halfcheetah", "medium"): 0.05, ("hopper", "medium"): 0.9, ("walker2d", "medium"): 1.0,
    ("halfcheetah", "medium-replay"): 0.05, ("hopper", "medium-replay"): 0.45,
    ("walker2d", "medium-replay"): 0.0,
    ("halfcheetah", "random"): 0.05, ("hopper", "random"): 0.05, ("walker2d", "random"): 0.0,
}  # fmt: skip


def resolve(config: EABCConfig, dataset_name: str, steps: int, given: frozenset[str]):
    """Table 3's p (bc_weight bernoulli) and the authors' earlier q (bc_weight quantile) for the
    dataset, where they are unset."""
    task = tasks.parse_task(dataset_name)
    rule = config.bc_rule
    if rule.bc_weight == "quantile" and rule.quantile_level is None:
        q = QUANTILE_LEVEL.get(task)
        if q is None:
            raise ValueError(
                f"no default quantile level q for dataset {dataset_name!r} (the authors' "
                "table covers hopper/halfcheetah/walker2d x the five kinds); pass --set "
                "quantile_level=Q"
            )
        config = dataclasses.replace(config, bc_rule=dataclasses.replace(rule, quantile_level=q))
    if rule.bc_weight == "bernoulli" and config.confidence_level is None:
        p = CONFIDENCE_LEVEL.get(task)
        if p is None:
            raise ValueError(
                f"no default confidence level p for dataset {dataset_name!r} (Table 3 covers "
                "hopper/halfcheetah/walker2d x random/medium/medium-replay/medium-expert/expert); "
                "pass --confidence-level P (the paper suggests p <= 0.25 for data from weak "
                "policies and p >= 0.5 for good ones)"
            )
        config = dataclasses.replace(config, confidence_level=p)
    return config


def _ensemble_cost(reference: int):
    return lambda config: config.num_critics / reference  # the critic ensemble dominates a step


_FAMILY = {
    "resolve": resolve,
    "delayed_period": td3_core.delayed_period,
    "report_settings": ("num_critics", "confidence_level", "pessimism"),
    "cli_flags": ("confidence_level", "num_critics", "pessimism", "alpha"),
    # Used only as numbers in the losses (a Bernoulli probability, lambda's numerator, mean -
    # beta * std): the datasets of one environment, with Table 3's p each, train as one program.
    "traced_settings": ("confidence_level", "alpha", "pessimism_beta"),
    # The authors' TD3_BC code trains on the stored rewards (TD3_BC/main.py changes none).
    "reward_convention": "raw",
    "infinite_state": bc_weights.UNBOUNDED,
}
DIVERGENCE_ADVICE = (
    "For EABC, more behaviour cloning (a higher --confidence-level) is what stopped it on our "
    "hopper-medium; --pessimism min only slowed it."
)
"""What the trainer's warning suggests when an EABC run's critics run away."""
# steps/s: the reference host's (eabc.timing), by benchmarks/algorithms.py, hopper shapes.
ALGORITHMS = (
    Algorithm("eabc", "EABC", PRESETS["eabc"], init, update, column=13, steps_per_s=151.0,
              cost=_ensemble_cost(10), recommended_variant=RECOMMENDED,
              divergence_advice=DIVERGENCE_ADVICE, **_FAMILY),
    Algorithm("td3bc", "TD3+BC", PRESETS["td3bc"], init, update, column=2, steps_per_s=620.0,
              cost=_ensemble_cost(2), comparison_baseline=True, **_FAMILY),  # the study's reference
    Algorithm("td3", "TD3", PRESETS["td3"], init, update, column=1, steps_per_s=653.0,
              cost=_ensemble_cost(2), **_FAMILY),
    *(
        Algorithm(name, display, PRESETS[name], init, update, column=column, steps_per_s=speed,
                  cost=_ensemble_cost(10), divergence_advice=DIVERGENCE_ADVICE, **_FAMILY)
        for name, display, column, speed in (
            # EABC's rate over LayerNorm's measured cost per step, 1.13-1.24 (docs/speed.md)
            ("eabc-ln", "EABC-LN", 13.5, 122.0),
            ("eabc-quantile", "EABC-quantile", 14, 106.0),
            ("eabc-auto", "EABC-auto", 15, 110.0),
            ("eabc-robust", "EABC-robust", 16, 103.0),
            ("eabc-trust", "EABC-trust", 17, 107.0),
        )
    ),
)  # fmt: skip
