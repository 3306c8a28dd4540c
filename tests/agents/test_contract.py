"""The algorithm contract over every registered algorithm (the first half here, the rest in
test_contract_more.py, so that the two halves run side by side): see tests/contract.py."""

from __future__ import annotations

import pytest
from contract import FIRST_HALF, check_contract

from eabc.agents import ALGORITHMS, MODULES, get_algorithm
from eabc.agents.contract import field_docs


def test_every_algorithm_is_described_in_its_own_file():
    names = [a.name for module in MODULES for a in module.ALGORITHMS]
    assert len(names) == len(set(names)) == len(ALGORITHMS)
    for algorithm in ALGORITHMS.values():
        assert algorithm.display_name and algorithm.steps_per_s > 0
        assert algorithm.actor in ("deterministic", "tanh-gaussian")
        docs = field_docs(type(algorithm.preset))
        undocumented = sorted(algorithm.settings() - set(docs))
        assert not undocumented, f"{algorithm.name}: settings without a docstring {undocumented}"
        assert set(algorithm.report_settings) <= algorithm.settings()
        assert set(algorithm.cli_flags) <= algorithm.settings()
    with pytest.raises(ValueError, match="unknown algorithm"):
        get_algorithm("nope")


@pytest.mark.parametrize("algo", FIRST_HALF)
def test_contract(tmp_path, pendulum_dataset, algo):
    check_contract(tmp_path, pendulum_dataset, algo)
