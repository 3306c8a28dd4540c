"""Offline RL agents. Each algorithm module provides ``init``, ``update`` and a config dataclass.

``ALGORITHMS`` maps the names accepted by ``eabc train --algo`` to their module and config preset.
"""

from __future__ import annotations

import dataclasses
from types import ModuleType

from eabc.agents import bc, bear, cql, eabc, iql, mopo, morel, sac, uwac, wpc


@dataclasses.dataclass(frozen=True)
class Algorithm:
    name: str
    module: ModuleType
    """Provides ``init(key, obs_dim, act_dim, config)`` and ``update(state, batch, key, config, max_action)``."""
    preset: object
    """The default config (a frozen dataclass) of this algorithm."""

    @property
    def gaussian_actor(self) -> bool:
        """Whether the actor is tanh-Gaussian (its deterministic action is tanh of the mean)."""
        return getattr(self.module, "GAUSSIAN_ACTOR", False)


ALGORITHMS: dict[str, Algorithm] = {
    **{name: Algorithm(name, eabc, preset) for name, preset in eabc.PRESETS.items()},
    **{name: Algorithm(name, sac, sac.PRESETS[name]) for name in ("sac-n", "edac", "edac-10")},
    "bc": Algorithm("bc", bc, bc.PRESETS["bc"]),
    "wpc": Algorithm("wpc", wpc, wpc.PRESETS["wpc"]),
    "iql": Algorithm("iql", iql, iql.PRESETS["iql"]),
    **{name: Algorithm(name, cql, preset) for name, preset in cql.PRESETS.items()},
    "bear": Algorithm("bear", bear, bear.PRESETS["bear"]),
    "uwac": Algorithm("uwac", uwac, uwac.PRESETS["uwac"]),
    "mopo": Algorithm("mopo", mopo, mopo.PRESETS["mopo"]),
    "morel": Algorithm("morel", morel, morel.PRESETS["morel"]),
}


def get_algorithm(name: str) -> Algorithm:
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r}; choose one of {', '.join(ALGORITHMS)}")
    return ALGORITHMS[name]
