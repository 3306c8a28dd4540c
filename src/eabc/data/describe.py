"""What a dataset holds, in numbers: its size, episodes and returns, its normalised return beside
D4RL's dataset of the same name, and for AntMaze the checks of its recipe (``eabc data info``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from eabc.data import antmaze_collect, tasks, zoo
from eabc.data.dataset import Dataset
from eabc.data.loaders import load_file


def d4rl_level(name: str) -> float | None:
    """The mean normalised return of D4RL's dataset of this name (docs/algorithm.md#datasets)."""
    task = tasks.parse_task(name)
    return None if task is None else zoo.D4RL_LEVEL.get(task[1], {}).get(task[0])


def describe_dataset(dataset: Dataset) -> dict:
    """Size, episodes, returns and normalised return beside D4RL's level."""
    returns = dataset.episode_returns()
    mean = float(returns.mean()) if len(returns) else float("nan")
    info = {
        "name": dataset.name,
        "env_id": dataset.env_id,
        "transitions": dataset.size,
        "episodes": len(returns),
        "terminals": int(dataset.terminals.sum()),
        "timeouts": int(dataset.timeouts.sum()),
        "return_mean": mean,
        "return_std": float(returns.std()) if len(returns) else float("nan"),
        "normalized_return": dataset.normalized_score(mean),
        "d4rl_normalized_return": d4rl_level(dataset.name),
        "metadata": dataset.metadata,
    }
    if dataset.env_id in tasks.antmaze_env_ids():
        info["antmaze"] = antmaze_collect.checks(dataset)
    return info


def describe(path: str | os.PathLike) -> dict:
    """:func:`describe_dataset` of a cached file, remembered in a sidecar ``.info.json``."""
    path = Path(path)
    sidecar = path.with_suffix(".info.json")
    if sidecar.is_file() and sidecar.stat().st_mtime >= path.stat().st_mtime:
        try:  # a damaged sidecar is only a lost shortcut: described again below
            info = json.loads(sidecar.read_text())
            if isinstance(info, dict):
                return info
        except (OSError, ValueError):
            pass
    info = describe_dataset(load_file(path))
    try:
        sidecar.write_text(json.dumps(info, indent=2))
    except OSError:  # a read-only cache: described every time
        pass
    return info
