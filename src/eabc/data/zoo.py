"""The behaviour-policy zoo: SAC actors shipped with the package, the policies behind the datasets.

Per environment, ``zoo/ENV/`` holds

- ``card.json``: where the policies come from (environment, SAC settings, training steps) and, for
  the ``medium`` and ``expert`` policy, the step it was taken at and its return with sampled
  actions over ``episodes`` episodes (mean, std, D4RL-normalised);
- ``medium.npz`` and ``expert.npz``: actor weights (float16, no pickle);
- ``replay/actor_STEP.npz``: the actor every ``interval`` training steps up to the medium point,
  from which the medium-replay dataset is rebuilt.

This module only reads the zoo (it is part of the data layer); ``eabc zoo build`` and ``eabc zoo
pack`` (:mod:`eabc.training.zoo_build`) make entries from ``eabc sac`` runs.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from eabc import numpy_networks
from eabc.data import tasks
from eabc.data.dataset import DatasetError

CARD = "card.json"
WEIGHT_DTYPE = np.float16
"""Stored precision of the shipped actors (halves the package size; the card's returns are
measured with exactly these weights)."""

D4RL_LEVEL = {
    # Mean normalised return of D4RL's datasets (docs/algorithm.md#datasets).
    "medium": {"hopper": 44.0, "halfcheetah": 41.0, "walker2d": 62.0},
    "expert": {"hopper": 108.0, "halfcheetah": 88.0, "walker2d": 107.0},
    "random": {"hopper": 1.0, "halfcheetah": 0.0, "walker2d": 0.0},
    "medium-replay": {"hopper": 15.0, "halfcheetah": 27.0, "walker2d": 15.0},
}
D4RL_LEVEL["medium-expert"] = {
    env: (D4RL_LEVEL["medium"][env] + D4RL_LEVEL["expert"][env]) / 2
    for env in tasks.ENVS
    if env in D4RL_LEVEL["medium"]
}


def zoo_dir(override: str | os.PathLike | None = None) -> Path:
    """The zoo: the argument, else ``$EABC_ZOO_DIR``, else the one shipped in the package."""
    root = override or os.environ.get("EABC_ZOO_DIR") or Path(__file__).parent.parent / "zoo"
    return Path(root)


def card(env: str, root: str | os.PathLike | None = None) -> dict:
    path = zoo_dir(root) / env / CARD
    if not path.exists():
        raise DatasetError(
            f"the behaviour-policy zoo has no policies for {env!r} yet ({path} is missing); train "
            f"them with `eabc sac --env {env}` and `eabc zoo build RUN_DIR {env}`"
        )
    return json.loads(path.read_text())


def load_actor(path: str | os.PathLike) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as saved:
        return {k: saved[k].astype(np.float32) for k in saved.files}


def policy_path(env: str, which: str, root=None) -> Path:
    """``which`` is ``medium``, ``expert`` or ``replay/actor_STEP``."""
    return zoo_dir(root) / env / f"{which}.npz"


def sampler(actor: dict[str, np.ndarray], max_action: float = 1.0) -> Callable:
    """``act(obs, rng)``: actions sampled from the tanh-Gaussian policy, as the datasets use."""
    return numpy_networks.numpy_gaussian_sampler(actor, max_action)


def replay_schedule(env: str, root=None) -> list[tuple[int, int, str | None]]:
    """``(start step, end step, policy)`` of every phase of training up to the medium point.

    ``policy`` is None for the uniform-random warm-up, else the zoo name of the snapshot that acted
    from ``start`` to ``end``.
    """
    info = card(env, root)["replay"]
    steps, end = info["snapshots"], info["end_step"]
    # Before the first kept snapshot the agent acted uniformly at random (the warm-up).
    phases: list[tuple[int, int, str | None]] = [(0, steps[0] if steps else end, None)]
    for start, stop in zip(steps, [*steps[1:], end]):
        phases.append((start, stop, f"replay/actor_{start:08d}"))
    return phases


def fingerprint(env: str, kind: str, root=None) -> str | None:
    """A digest of the zoo files the ``kind`` dataset of ``env`` is made from (None for random).

    Stored in each made dataset's metadata, so a cached dataset made from an older zoo is noticed
    and remade rather than silently reused.
    """
    if kind == "random":
        return None
    info = card(env, root)  # a missing zoo stops here, with the message that says what to do
    digest = hashlib.sha256()
    if kind == "medium-replay":
        digest.update(json.dumps(info["replay"], sort_keys=True).encode())
        names = [p for _, _, p in replay_schedule(env, root) if p is not None]
    else:
        names = ["medium", "expert"] if kind == "medium-expert" else [kind]
    for name in names:
        digest.update(policy_path(env, name, root).read_bytes())
    return digest.hexdigest()[:16]


def rounded(actor: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v.astype(WEIGHT_DTYPE).astype(np.float32) for k, v in actor.items()}


def save_actor(path: Path, actor: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{k: v.astype(WEIGHT_DTYPE) for k, v in actor.items()})
