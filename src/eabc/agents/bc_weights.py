"""The BC-weight rules EABC can switch to besides the paper's ``w ~ Bernoulli(p)``, screened and
not recommended (docs/results/screen/README.md, docs/notes/eabc-divergence.md); kept so that
their results can be reproduced:

- ``bc_weight = quantile``, the authors' earlier rule
  (docs/algorithm.md#the-authors-earlier-bc-rule): ``w = 1`` where the q-quantile of the K
  values ``Q_k(s, a)`` exceeds ``m + s / sqrt(K)``;
- ``bc_weight = auto``: ``w ~ Bernoulli(p_t)`` with ``p_t`` adapted during training by offline
  signals only, never by evaluation returns (:func:`adapt_confidence_level`).

Their settings are fields of :class:`eabc.agents.eabc.EABCConfig` (``quantile_level``,
``auto_*``), so that each variant stays a setting of the one update rule.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from eabc import networks
from eabc.agents.common import Batch


def initial_controller(config: Any) -> dict[str, jax.Array]:
    """bc_weight auto's state at step 0: ``p``, the reward range seen so far and, while
    calibrating, the calibration's running sum and count."""
    controller = {
        "p": jnp.asarray(config.auto_initial_p, jnp.float32),
        "reward_min": jnp.asarray(jnp.inf, jnp.float32),
        "reward_max": jnp.asarray(-jnp.inf, jnp.float32),
    }
    if config.auto_calibration_steps:
        name = "ratio" if config.auto_signal == "spread" else "distance"
        controller[f"{name}_sum"] = jnp.zeros((), jnp.float32)
        controller[f"{name}_count"] = jnp.zeros((), jnp.float32)
    return controller


def quantile_keep(critic, batch: Batch, config: Any) -> jax.Array:
    """The authors' earlier BC weight (docs/algorithm.md#the-authors-earlier-bc-rule):
    ``w = 1`` where the q-quantile of the K online values at the batch's own actions exceeds
    ``mean + std / sqrt(K)`` (ddof 1)."""
    if config.quantile_level is None:
        raise ValueError("bc_weight quantile needs quantile_level q (its table: docs/algorithm.md)")
    q = jax.lax.stop_gradient(networks.critic_apply(critic, batch.observations, batch.actions))
    upper = jnp.quantile(q, config.quantile_level, axis=0)  # linear, as torch.quantile
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
    low = jnp.minimum(controller["reward_min"], batch.rewards.min())
    high = jnp.maximum(controller["reward_max"], batch.rewards.max())
    scale = 1.0 / (1.0 - config.discount)
    top, bottom = jnp.maximum(high, 0.0) * scale, jnp.minimum(low, 0.0) * scale
    ceiling = config.auto_value_margin * top
    floor = bottom - 0.1 * (top - bottom)  # the divergence flag's own lower edge
    tiny = 1e-6
    ratio = (metrics["policy_q_std"] + tiny) / (metrics["q_ensemble_std"] + tiny)
    if config.auto_signal == "distance":
        name, signal, first = "distance", metrics["action_distance"] + tiny, 0.5
        target = jnp.asarray(config.auto_distance_ratio, jnp.float32)
    else:
        name, signal, first = "ratio", ratio, 0.0
        target = jnp.asarray(config.auto_spread_ratio, jnp.float32)
    calibration = {}
    if config.auto_calibration_steps:
        calibrating = step <= config.auto_calibration_steps
        counted = calibrating & (step > first * config.auto_calibration_steps)
        total = controller[f"{name}_sum"] + jnp.where(counted, signal, 0.0)
        count = controller[f"{name}_count"] + jnp.where(counted, 1.0, 0.0)
        calibration = {f"{name}_sum": total, f"{name}_count": count}
        target = target * total / jnp.maximum(count, 1.0)
    error = jnp.clip(jnp.log(signal / jnp.maximum(target, tiny)), -1.0, 1.0)
    p = jnp.clip(controller["p"] + config.auto_rate * error, config.auto_min_p, 1.0)
    if config.auto_calibration_steps:
        p = jnp.where(calibrating, controller["p"], p)
    values = jnp.stack([metrics["q_mean"], metrics["actor_q_mean"]])
    out_of_range = jnp.any((values > ceiling) | (values < floor)) | ~jnp.all(jnp.isfinite(values))
    p = jnp.where(out_of_range, 1.0, p)
    metrics = {"auto_p": p, "spread_ratio": ratio, "value_ceiling": ceiling}
    if config.auto_calibration_steps:
        metrics["spread_target" if name == "ratio" else "distance_target"] = target
    return {"p": p, "reward_min": low, "reward_max": high, **calibration}, metrics
