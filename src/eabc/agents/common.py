"""What every agent shares: the mini-batch type."""

from __future__ import annotations

import flax.struct
import jax


@flax.struct.dataclass
class Batch:
    """A mini-batch of transitions (observations already normalised)."""

    observations: jax.Array
    actions: jax.Array
    rewards: jax.Array
    next_observations: jax.Array
    dones: jax.Array
    """1.0 where the episode terminated (not where it was truncated by a time limit)."""
