"""The algorithm contract over the second half of the registered algorithms (tests/contract.py)."""

from __future__ import annotations

import pytest
from contract import check_contract
from test_contract import FIRST_HALF

from eabc.agents import ALGORITHMS


@pytest.mark.parametrize("algo", [name for name in ALGORITHMS if name not in FIRST_HALF])
def test_contract(tmp_path, pendulum_dataset, algo):
    check_contract(tmp_path, pendulum_dataset, algo)
