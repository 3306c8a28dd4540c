"""The BC-weight rules EABC can switch to besides the paper's ``w ~ Bernoulli(p)``, screened and
not recommended (docs/results/screen/README.md, docs/notes/eabc-divergence.md); kept so that
their results can be reproduced:

- ``bc_weight = quantile``, the authors' earlier rule
  (docs/algorithm.md#the-authors-earlier-bc-rule): ``w = 1`` where the q-quantile of the K
  values ``Q_k(s, a)`` exceeds ``m + s / sqrt(K)``;
- ``bc_weight = auto``: ``w ~ Bernoulli(p_t)`` with ``p_t`` adapted during training by offline
  signals only, never by evaluation returns (:func:`adapt_confidence_level`);
- ``bc_weight = advantage``: ``w = 1`` where the ensemble rates the data's action at least as
  high as the policy's (:func:`eabc.agents.eabc.advantage_keep`).

Their settings live in a config of their own, :class:`BCWeightConfig`, which EABC's config holds
as one field (``bc_rule``); a user sets them by their own names as before (``--set
bc_weight=auto auto_rate=0.01``, ``{algo: eabc, bc_weight: advantage}`` in a sweep spec), and a
run's ``config.json`` records them beside EABC's own settings, so that each variant stays a
setting of the one update rule.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import jax
import jax.numpy as jnp

from eabc import networks
from eabc.agents.common import Batch
from eabc.ranges import NonNegativeCount, PositiveNumber, Probability, Settings, Weight

Rule = Literal["bernoulli", "quantile", "auto", "advantage"]
Signal = Literal["spread", "distance"]


@dataclasses.dataclass(frozen=True)
class BCWeightConfig(Settings):
    """How EABC's per-sample BC weight ``w`` is chosen; the default is the paper's."""

    bc_weight: Rule = "bernoulli"
    """Per-sample BC weight: bernoulli (w ~ Bernoulli(p), the paper), quantile (the authors'
    earlier ensemble rule, docs/algorithm.md#the-authors-earlier-bc-rule), auto (Bernoulli(p_t),
    p_t adapted; see below) or advantage (w = 1 where pess Q(s, a) >= pess Q(s, pi(s)); no p)."""
    quantile_level: Probability | None = None
    """q of the quantile rule; None: the authors' q for the dataset (docs/algorithm.md)."""
    auto_initial_p: Probability = 1.0
    """auto: p at step 0 (start as TD3+BC, relax where the evidence allows)."""
    auto_min_p: Probability = 0.0
    """auto: the lowest p the controller may reach (at most auto_initial_p)."""
    auto_rate: Weight = 1e-3
    """auto: how far p moves per actor step at a full-scale signal (|error| = 1)."""
    auto_spread_ratio: PositiveNumber = 1.0
    """auto: target of std_K Q(s, pi(s)) / std_K Q(s, a): p rises while the policy's actions are
    more uncertain than the data's by more than this, and falls while they are less."""
    auto_value_margin: PositiveNumber = 0.9
    """auto: p jumps to 1 when the ensemble's mean value at the data's or the policy's actions
    passes this fraction of max(0, max r) / (1 - gamma), the rewards seen so far allowing."""
    auto_calibration_steps: NonNegativeCount = 0
    """auto: when > 0, p is held at auto_initial_p for this many gradient steps while the spread
    ratio under that much behaviour cloning is averaged; the target is then auto_spread_ratio
    times that average (the ratio as a relative signal: p falls only while the policy's actions
    stay as sure, relative to the data's, as cloning keeps them). 0: the target is
    auto_spread_ratio itself."""
    auto_signal: Signal = "spread"
    """auto: what p follows. spread: the spread ratio above. distance: the policy's squared
    distance from the data's actions, mean (pi(s) - a)^2 / max_action^2, against
    auto_distance_ratio times its mean over the second half of the calibration (a trust region
    relative to what cloning alone reaches on this data; needs auto_calibration_steps > 0)."""
    auto_distance_ratio: PositiveNumber = 2.0
    """auto, signal distance: how far, relative to full cloning's fit, the policy may move from
    the data's actions before p rises."""

    def __post_init__(self):
        super().__post_init__()
        if self.auto_min_p > self.auto_initial_p:
            raise ValueError(
                f"auto_min_p must be at most auto_initial_p={self.auto_initial_p}, got "
                f"{self.auto_min_p}: p starts at auto_initial_p and never falls below auto_min_p"
            )
        if (
            self.bc_weight == "auto"
            and self.auto_signal == "distance"
            and self.auto_calibration_steps < 2
        ):
            raise ValueError(
                "auto_signal distance measures full cloning's fit first: set "
                "auto_calibration_steps (e.g. 5000)"
            )


UNBOUNDED = frozenset({"reward_min", "reward_max"})
"""The controller's entries that hold +-inf until the first batch is seen: the reward range."""


def initial_controller(config: Any) -> dict[str, jax.Array]:
    """bc_weight auto's state at step 0: ``p``, the reward range seen so far and, while
    calibrating, the calibration's running sum and count."""
    rule = config.bc_rule
    controller = {
        "p": jnp.asarray(rule.auto_initial_p, jnp.float32),
        "reward_min": jnp.asarray(jnp.inf, jnp.float32),
        "reward_max": jnp.asarray(-jnp.inf, jnp.float32),
    }
    if rule.auto_calibration_steps:
        name = "ratio" if rule.auto_signal == "spread" else "distance"
        controller[f"{name}_sum"] = jnp.zeros((), jnp.float32)
        controller[f"{name}_count"] = jnp.zeros((), jnp.float32)
    return controller


def quantile_keep(critic, batch: Batch, config: Any) -> jax.Array:
    """The authors' earlier BC weight (docs/algorithm.md#the-authors-earlier-bc-rule):
    ``w = 1`` where the q-quantile of the K online values at the batch's own actions exceeds
    ``mean + std / sqrt(K)`` (ddof 1)."""
    level = config.bc_rule.quantile_level
    if level is None:
        raise ValueError("bc_weight quantile needs quantile_level q (its table: docs/algorithm.md)")
    q = jax.lax.stop_gradient(networks.critic_apply(critic, batch.observations, batch.actions))
    upper = jnp.quantile(q, level, axis=0)  # linear, as torch.quantile
    k = q.shape[0]
    return (upper > q.mean(axis=0) + q.std(axis=0, ddof=1) / jnp.sqrt(k)).astype(q.dtype)


def adapt_confidence_level(controller, batch: Batch, metrics, config: Any, step=None):
    """One step of bc_weight auto's controller for p, after an actor step.

    Signals, all offline (from the batch and the networks, never from evaluation returns):

    - ``auto_signal = spread``: the spread ratio ``x = rho = std_K Q(s, pi(s)) / std_K Q(s, a)``
      (batch means, online critics): above 1 the policy acts where the ensemble is less sure than
      at the data's own actions;
    - ``auto_signal = distance``: the policy's squared distance from the data's actions,
      ``x = delta = mean (pi(s) - a)^2 / max_action^2`` (before this step's actor update): how far
      the policy has moved from the behaviour it would clone;
    - the value bounds ``V_hi = max(0, max r) / (1 - gamma)`` and ``V_lo = min(0, min r) /
      (1 - gamma)`` over the rewards seen so far: no policy's value can lie outside them.

    Rule: ``p <- clip(p + rate * clip(log(x / target), -1, 1), auto_min_p, 1)``;
    and ``p <- 1`` at once when the mean value at the data's or the policy's actions passes
    ``auto_value_margin * V_hi`` or falls below ``V_lo - 0.1 (V_hi - V_lo)``, or is not finite
    (the critics are extrapolating: clone fully until they come back). So p falls while the
    signal stays under its target and rises as soon as it passes it.

    Targets. spread: ``auto_spread_ratio``; with ``auto_calibration_steps = N > 0`` it is
    ``auto_spread_ratio * mean(rho over the actor steps before gradient step N)``, p held at
    ``auto_initial_p`` meanwhile (the guard still acts). Why: on our hopper-medium rho sits at
    0.93-0.95 under full cloning, with or without LayerNorm critics, so a target of 1 lowered p
    steadily to about 0.1, where the critics stayed in range but the score fell from 94 to 18-27.
    distance (N required): ``auto_distance_ratio * mean(delta over the actor steps in (N/2, N])``,
    i.e. a trust region around the data's actions whose radius is measured, not chosen: twice (by
    default) the error that cloning alone leaves on this data, so a dataset of noisy or mixed
    behaviour (random, replay) gives the policy more room than one of a single steady policy.
    Why: every spread-ratio run on hopper-medium kept its critics in range and still lost its
    score as p fell (the ensemble cannot see the policy drifting where its members agree); the
    distance sees the drift itself. ``step`` is the gradient step just taken (for calibrating).
    """
    rule = config.bc_rule
    low = jnp.minimum(controller["reward_min"], batch.rewards.min())
    high = jnp.maximum(controller["reward_max"], batch.rewards.max())
    scale = 1.0 / (1.0 - config.discount)
    top, bottom = jnp.maximum(high, 0.0) * scale, jnp.minimum(low, 0.0) * scale
    ceiling = rule.auto_value_margin * top
    floor = bottom - 0.1 * (top - bottom)  # the divergence flag's own lower edge
    tiny = 1e-6
    ratio = (metrics["policy_q_std"] + tiny) / (metrics["q_ensemble_std"] + tiny)
    if rule.auto_signal == "distance":
        name, signal, first = "distance", metrics["action_distance"] + tiny, 0.5
        target = jnp.asarray(rule.auto_distance_ratio, jnp.float32)
    else:
        name, signal, first = "ratio", ratio, 0.0
        target = jnp.asarray(rule.auto_spread_ratio, jnp.float32)
    calibration = {}
    if rule.auto_calibration_steps:
        calibrating = step <= rule.auto_calibration_steps
        counted = calibrating & (step > first * rule.auto_calibration_steps)
        total = controller[f"{name}_sum"] + jnp.where(counted, signal, 0.0)
        count = controller[f"{name}_count"] + jnp.where(counted, 1.0, 0.0)
        calibration = {f"{name}_sum": total, f"{name}_count": count}
        target = target * total / jnp.maximum(count, 1.0)
    error = jnp.clip(jnp.log(signal / jnp.maximum(target, tiny)), -1.0, 1.0)
    p = jnp.clip(controller["p"] + rule.auto_rate * error, rule.auto_min_p, 1.0)
    if rule.auto_calibration_steps:
        p = jnp.where(calibrating, controller["p"], p)
    values = jnp.stack([metrics["q_mean"], metrics["actor_q_mean"]])
    out_of_range = jnp.any((values > ceiling) | (values < floor)) | ~jnp.all(jnp.isfinite(values))
    p = jnp.where(out_of_range, 1.0, p)
    metrics = {"auto_p": p, "spread_ratio": ratio, "value_ceiling": ceiling}
    if rule.auto_calibration_steps:
        metrics["spread_target" if name == "ratio" else "distance_target"] = target
    return {"p": p, "reward_min": low, "reward_max": high, **calibration}, metrics
