"""The algorithm contract over the second half of the registered algorithms (tests/contract.py)."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from contract import FIRST_HALF, check_contract

from eabc import pytree
from eabc.agents import ALGORITHMS


@pytest.mark.parametrize("algo", [name for name in ALGORITHMS if name not in FIRST_HALF])
def test_contract(tmp_path, pendulum_dataset, algo):
    check_contract(tmp_path, pendulum_dataset, algo)


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_every_infinite_entry_of_an_initial_state_is_declared(name):
    """A fresh state holds +-inf only in the entries its algorithm declares
    (``infinite_state``); checkpoints refuse +-inf anywhere else, so an undeclared one would make
    the algorithm's own first checkpoint unreadable."""
    algorithm = ALGORITHMS[name]
    state = algorithm.init(jax.random.PRNGKey(0), 3, 1, algorithm.preset)
    leaves = jax.tree_util.tree_flatten_with_path(pytree.to_state_dict(state))[0]
    infinite = {
        str(getattr(path[-1], "key", path[-1]))
        for path, leaf in leaves
        if np.asarray(leaf).dtype.kind == "f" and not np.isfinite(np.asarray(leaf)).all()
    }
    assert infinite <= algorithm.infinite_state, (name, infinite)
