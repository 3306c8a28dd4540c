"""What every agent shares: the mini-batch type and the optimiser step."""

from __future__ import annotations

import jax
import optax

from eabc import pytree


@pytree.dataclass
class Batch:
    """A mini-batch of transitions (observations already normalised)."""

    observations: jax.Array
    actions: jax.Array
    rewards: jax.Array
    next_observations: jax.Array
    dones: jax.Array
    """1.0 where the episode terminated (not where it was truncated by a time limit)."""


def apply_gradients(tx: optax.GradientTransformation, grads, opt_state, params):
    """One optimiser step: ``(new params, new optimiser state)``."""
    updates, opt_state = tx.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state
