"""What every agent shares: the mini-batch type and the optimiser step."""

from __future__ import annotations

from typing import ClassVar

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


@pytree.dataclass
class BatchWithNextActions(Batch):
    """A :class:`Batch` with the data's next actions, for the algorithms whose contract asks
    (``next_actions``); a separate type, so that states holding a plain ``Batch`` (MOPO's model
    buffer) keep their checkpoint layout."""

    next_actions: jax.Array
    """The action the data took at s': the next row's where it continues the episode; where the
    data has none (a terminal, a time-limit end, the last row) the row's own action."""


def apply_gradients(tx: optax.GradientTransformation, grads, opt_state, params):
    """One optimiser step: ``(new params, new optimiser state)``."""
    updates, opt_state = tx.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state


class BuiltOn:
    """For a state that holds its base algorithm's state in one field (wPC on TD3+BC's, CQL and
    MOPO on SAC's, UWAC on BEAR's): the contract's ``actor`` and ``step`` are the base's. Set
    ``BASE`` (a ``ClassVar``) to that field's name."""

    BASE: ClassVar[str]

    @property
    def actor(self):
        return getattr(self, self.BASE).actor

    @property
    def step(self) -> jax.Array:
        return getattr(self, self.BASE).step
