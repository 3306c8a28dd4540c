"""D4RL-style datasets made here, by D4RL's recipe, into a cache directory.

Random datasets need no behaviour policy (uniform random actions) and are available now; the policy
datasets (medium, expert, medium-replay, medium-expert) need the behaviour-policy zoo.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from eabc.data import tasks
from eabc.data.dataset import Dataset, DatasetError
from eabc.data.loaders import load_file

FORMAT_VERSION = 1
DATASET_SIZE = 1_000_000
"""D4RL's size of the random, medium and expert datasets."""

ActionFn = Callable[[np.ndarray, np.random.Generator], np.ndarray]


def cache_dir(override: str | os.PathLike | None = None) -> Path:
    """Where made datasets live: the argument, else ``$EABC_CACHE_DIR``, else ``~/.cache/eabc``."""
    root = override or os.environ.get("EABC_CACHE_DIR") or Path.home() / ".cache" / "eabc"
    return Path(root).expanduser()


def builtin_names() -> list[str]:
    return [
        f"{env}-{kind}" for env in ("hopper", "halfcheetah", "walker2d") for kind in tasks.KINDS
    ]


def dataset_path(name: str, cache: str | os.PathLike | None = None) -> Path:
    return cache_dir(cache) / "datasets" / f"{name}.hdf5"


def load_or_make(name: str, cache_dir: str | os.PathLike | None = None, seed: int = 0) -> Dataset:
    """The cached dataset ``name``, made first if it is not in the cache yet."""
    path = dataset_path(name, cache_dir)
    if not path.exists():
        make(name, path, seed=seed)
    return load_file(path)


def make(name: str, path: str | os.PathLike, seed: int = 0, size: int | None = None) -> Path:
    """Make the built-in dataset ``name`` and write it to ``path`` in D4RL's HDF5 layout."""
    task = tasks.parse_task(name)
    if name not in builtin_names() or task is None:
        raise DatasetError(f"no recipe for {name!r}; built-in names: {', '.join(builtin_names())}")
    env_name, kind = task
    if kind != "random":
        raise DatasetError(
            f"{name} needs a trained behaviour policy, and the behaviour-policy zoo does not ship "
            "one yet; use a -random dataset, or load your own file (D4RL HDF5, .npz, Minari)"
        )
    env = tasks.ENVS[env_name]
    dataset = rollout(env.env_id, None, size or DATASET_SIZE, seed, desc=name)
    dataset = Dataset(
        **{k: getattr(dataset, k) for k in _ARRAYS},
        name=name,
        env_id=env.env_id,
        ref_min_score=env.ref_min_score,
        ref_max_score=env.ref_max_score,
        metadata={"recipe": "uniform random actions", "seed": seed, "version": FORMAT_VERSION},
    )
    return save_hdf5(dataset, path)


_ARRAYS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")


def rollout(
    env_id: str,
    act: ActionFn | None,
    num_transitions: int,
    seed: int,
    max_episode_steps: int = 1000,
    desc: str = "rollout",
) -> Dataset:
    """Collect ``num_transitions`` transitions with ``act`` (uniform random actions when None).

    Episodes end at a terminal or after ``max_episode_steps`` (a timeout); the last transition is
    flagged as a timeout when the budget cuts an episode short. Deterministic for a given seed.
    """
    import gymnasium as gym  # noqa: PLC0415

    warnings.filterwarnings("ignore", message=r".*is out of date", category=DeprecationWarning)

    env = gym.make(env_id, max_episode_steps=max_episode_steps)
    rng = np.random.default_rng(seed)
    low, high = env.action_space.low, env.action_space.high
    obs_dim = env.observation_space.shape[0]
    out = {
        "observations": np.empty((num_transitions, obs_dim), np.float32),
        "actions": np.empty((num_transitions, len(low)), np.float32),
        "rewards": np.empty(num_transitions, np.float32),
        "next_observations": np.empty((num_transitions, obs_dim), np.float32),
        "terminals": np.zeros(num_transitions, bool),
        "timeouts": np.zeros(num_transitions, bool),
    }
    obs, _ = env.reset(seed=seed)
    for i in tqdm(range(num_transitions), desc=desc, unit="step", mininterval=1.0, leave=False):
        action = rng.uniform(low, high) if act is None else act(obs, rng)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        out["observations"][i], out["actions"][i], out["rewards"][i] = obs, action, reward
        out["next_observations"][i] = next_obs
        out["terminals"][i], out["timeouts"][i] = terminated, truncated and not terminated
        obs = env.reset()[0] if terminated or truncated else next_obs
    if not (out["terminals"][-1] or out["timeouts"][-1]):
        out["timeouts"][-1] = True
    env.close()
    return Dataset(**out, name=desc, env_id=env_id)


def save_hdf5(dataset: Dataset, path: str | os.PathLike) -> Path:
    """Write D4RL's HDF5 layout plus our metadata; atomic (temporary file, then rename)."""
    import h5py  # noqa: PLC0415

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with h5py.File(tmp, "w") as f:
        for key in _ARRAYS:
            f.create_dataset(
                key, data=getattr(dataset, key), compression="gzip", compression_opts=1
            )
        f.attrs["name"] = dataset.name
        f.attrs["env_id"] = dataset.env_id or ""
        if dataset.ref_min_score is not None:
            f.attrs["ref_min_score"] = dataset.ref_min_score
            f.attrs["ref_max_score"] = dataset.ref_max_score
        f.attrs["metadata"] = json.dumps(dataset.metadata)
    os.replace(tmp, path)
    return path
