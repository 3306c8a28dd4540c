"""Hand computations in float64 NumPy that the agents' losses are checked against."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from eabc.agents.common import Batch
from eabc.programs import Program
from eabc.training.chunks import FAST_COMPILE_OPTIONS

OBS, ACT, B = 3, 2, 7


def np_mlp(params, x):
    """Hand-written forward pass of one network (member ``m`` of an ensemble, or the actor)."""
    n = len(params) // 2
    for i in range(n):
        x = x @ np.asarray(params[f"w{i}"], np.float64) + np.asarray(params[f"b{i}"], np.float64)
        if i < n - 1:
            x = np.maximum(x, 0.0)
    return x


def member(params, i):
    return {k: v[i] for k, v in params.items()}


def np_q(critic, k, obs, act):
    """Every member's Q-value, ``[k, B]``."""
    return np.stack(
        [np_mlp(member(critic, i), np.concatenate([obs, act], -1))[:, 0] for i in range(k)]
    )


def quick_jit(update):
    """An algorithm's ``update(state, batch, key, config, max_action)`` (or another function whose
    last two arguments are the config and the action bound) as one program compiled at XLA O0. Run eagerly, an update compiles each of its hundreds of operations on first use and
    its ``lax.cond`` again on every call: SAC's first eager step took 7.7 s of CPU, EABC's every
    step 1 s; compiled this way, 1.2-2 s once per config, and the tests check the update compiled,
    as training runs it (inside its scan)."""
    return Program(update, FAST_COMPILE_OPTIONS, static_argnums=(3, 4))


def make_batch(seed: int = 0) -> Batch:
    rng = np.random.default_rng(seed)
    return Batch(
        observations=jnp.asarray(rng.normal(size=(B, OBS)), jnp.float32),
        actions=jnp.asarray(rng.uniform(-1, 1, size=(B, ACT)), jnp.float32),
        rewards=jnp.asarray(rng.normal(size=B), jnp.float32),
        next_observations=jnp.asarray(rng.normal(size=(B, OBS)), jnp.float32),
        dones=jnp.asarray([0, 0, 1, 0, 0, 1, 0], jnp.float32),
    )
