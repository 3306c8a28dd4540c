"""Offline RL agents. Each algorithm file ends with ``ALGORITHMS``: its typed descriptions
(:class:`eabc.agents.contract.Algorithm`); adding an algorithm is its file and one entry in
``MODULES`` below.

``ALGORITHMS`` maps the names accepted by ``eabc train --algo`` to their description.
"""

from __future__ import annotations

from eabc.agents import bc, bear, cql, eabc, iql, mopo, morel, rebrac, sac, uwac, wpc
from eabc.agents.contract import Algorithm

MODULES = (eabc, bc, wpc, iql, cql, sac, bear, uwac, mopo, morel, rebrac)
"""The registered algorithm files, in the order ``--help`` lists their algorithms."""

ALGORITHMS: dict[str, Algorithm] = {
    algorithm.name: algorithm for module in MODULES for algorithm in module.ALGORITHMS
}
DEFAULT = next(iter(ALGORITHMS))
"""What ``eabc train`` runs without ``--algo``: the first registered algorithm."""

__all__ = ["ALGORITHMS", "DEFAULT", "MODULES", "Algorithm", "get_algorithm"]


def get_algorithm(name: str) -> Algorithm:
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r}; choose one of {', '.join(ALGORITHMS)}")
    return ALGORITHMS[name]
