"""Making zoo entries from ``eabc sac`` runs (``eabc zoo build``, ``eabc zoo pack``).

:func:`build` makes ``zoo/ENV`` from an ``eabc sac`` run directory: the expert is the best of the
last snapshots, the medium policy the snapshot whose return is closest to D4RL's medium level
the first time training reaches it (D4RL stopped SAC early at about a third of the expert).
:func:`pack` copies what continuing a run needs, small enough to commit. The zoo's read side is
:mod:`eabc.data.zoo`; this module sits in the training layer because it reads SAC runs.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from eabc.data import antmaze, antmaze_collect, mazes, tasks, zoo
from eabc.data.dataset import DatasetError
from eabc.evaluation import make_env
from eabc.training import checkpoint
from eabc.training.checkpoint import read_config
from eabc.training.online import SNAPSHOTS

OPEN_PLANE_EPISODES = 100
"""Episodes of the AntMaze policy's open-plane measurement (a goal 5-10 m away; about 0.1 s each)."""


def stochastic_return(
    env_id: str, actor: dict[str, np.ndarray], episodes: int, seed: int
) -> tuple[float, float]:
    """Mean and std of the return of ``actor`` with sampled actions (as the datasets are made)."""
    env = make_env(env_id)
    act = zoo.sampler(actor, float(env.action_space.high[0]))
    rng = np.random.default_rng(seed)
    returns = []
    obs, _ = env.reset(seed=seed)
    for _ in range(episodes):
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(act(obs, rng))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
        obs, _ = env.reset()
    return float(np.mean(returns)), float(np.std(returns))


def build(
    run_dir: str | os.PathLike,
    env: str,
    root: str | os.PathLike | None = None,
    episodes: int = 10,
    seed: int = 12345,
    expert_candidates: int = 5,
    medium_return: float | None = None,
    medium_step: int | None = None,
    log: Callable[[str], None] = print,
) -> dict:
    """Make ``zoo/ENV`` from the ``eabc sac`` run in ``run_dir`` (see the module docstring).

    ``medium_step`` fixes the medium policy instead of searching for it: a rebuild after the run
    has trained on keeps the medium policy (and so the medium and medium-replay datasets) that
    was already shipped, and only the expert moves.
    """
    run_dir = Path(run_dir)
    config = _sac_config(run_dir)
    env_id = config["env_id"]
    info = tasks.ENVS.get(env)
    snapshots = sorted(int(p.stem.split("_")[1]) for p in (run_dir / SNAPSHOTS).glob("actor_*.npz"))
    if not snapshots:
        raise DatasetError(f"{run_dir} has no actor snapshots")
    actors = {
        s: zoo.rounded(zoo.load_actor(run_dir / SNAPSHOTS / f"actor_{s:08d}.npz"))
        for s in snapshots
    }

    def score(ret: float) -> float | None:
        return (
            None
            if info is None
            else tasks.normalized_score(ret, info.ref_min_score, info.ref_max_score)
        )

    measured: dict[int, dict] = {}

    def measure(step: int) -> dict:
        if step in measured:  # a snapshot can be both an expert and a medium candidate
            return measured[step]
        mean, std = stochastic_return(env_id, actors[step], episodes, seed)
        entry = {"step": step, "return_mean": mean, "return_std": std, "episodes": episodes}
        entry["normalized_return"] = score(mean)
        log(
            f"{env} snapshot {step}: return {mean:.0f} +- {std:.0f} (normalised {entry['normalized_return']})"
        )
        measured[step] = entry
        return entry

    expert = max(
        (measure(s) for s in snapshots[-expert_candidates:]), key=lambda e: e["return_mean"]
    )
    level = zoo.D4RL_LEVEL["medium"].get(env)
    if medium_return is not None:
        target = medium_return
    elif level is not None:
        target = level / 100.0 * (info.ref_max_score - info.ref_min_score) + info.ref_min_score
    else:
        raise DatasetError(f"no D4RL medium level known for {env!r}; pass medium_return")
    train = _training_returns(run_dir)
    # The first snapshots where training episodes reach 85% of the medium return are candidates.
    reached = [s for s in snapshots if train.get(s, -np.inf) >= 0.85 * target]
    candidates = [s for s in snapshots if reached and reached[0] <= s][:3] or snapshots[-1:]
    if medium_step is not None:
        if medium_step not in actors:
            raise DatasetError(f"{run_dir} has no snapshot at step {medium_step}")
        candidates = [medium_step]
    medium = min((measure(s) for s in candidates), key=lambda e: abs(e["return_mean"] - target))

    out = zoo.zoo_dir(root) / env
    if out.exists():
        shutil.rmtree(out)
    zoo.save_actor(out / "expert.npz", actors[expert["step"]])
    zoo.save_actor(out / "medium.npz", actors[medium["step"]])
    replay = [s for s in snapshots if s < medium["step"]]
    for s in replay:
        zoo.save_actor(out / "replay" / f"actor_{s:08d}.npz", actors[s])
    sac = config["sac"]
    result = {
        "env": env,
        "env_id": env_id,
        "algorithm": "SAC (eabc sac), actions sampled from the tanh-Gaussian policy",
        "sac": sac,
        "agent": config["agent"],
        "training_steps": snapshots[-1],
        "weights": "float16 npz; returns below were measured with these rounded weights",
        "evaluation_seed": seed,
        "expert": {**expert, "file": "expert.npz"},
        "medium": {**medium, "file": "medium.npz", "target_return": target, "d4rl_level": level},
        "replay": {
            "start_steps": sac["start_steps"],
            "interval": sac["snapshot_interval"],
            "snapshots": replay,
            "end_step": medium["step"],
        },
    }
    (out / zoo.CARD).write_text(json.dumps(result, indent=2))
    return result


def _training_returns(run_dir: Path) -> dict[int, float]:
    """Mean training-episode return (sampled actions) of each logged window, by step."""
    with open(run_dir / "log.csv", newline="") as f:
        return {
            int(row["step"]): float(row["train_return"])
            for row in csv.DictReader(f)
            if row.get("train_return") not in (None, "", "nan")
        }


def _sac_config(run_dir: Path) -> dict:
    """The config.json of the ``eabc sac`` run in ``run_dir``; ``DatasetError`` for another
    run's (an offline training run's has ``train`` where SAC's has ``sac`` and ``env_id``)."""
    config = read_config(run_dir)
    if not isinstance(config.get("sac"), dict) or not isinstance(config.get("env_id"), str):
        raise DatasetError(
            f"{run_dir / checkpoint.CONFIG} is not an `eabc sac` run's (no sac settings and "
            "env_id): the zoo is built from the run directory of `eabc sac`"
        )
    return config


def pack(run_dir: str | os.PathLike, dest: str | os.PathLike) -> Path:
    """Copy what continuing an ``eabc sac`` run needs into ``dest``, small enough to commit.

    Keeps the config, the log, the checkpoint (networks, optimisers, temperature, step, random
    states) and the actor snapshots (float16, which is all :func:`build` uses of them), and drops the
    replay buffer: ``eabc sac --resume`` on a copy of ``dest`` refills it as training goes on.
    """
    run_dir, dest = Path(run_dir), Path(dest)
    _sac_config(run_dir)
    if not (run_dir / checkpoint.CHECKPOINT).exists():
        raise DatasetError(f"{run_dir} has no checkpoint yet; nothing to pack")
    (dest / SNAPSHOTS).mkdir(parents=True, exist_ok=True)
    for name in (checkpoint.CONFIG, "log.csv", checkpoint.CHECKPOINT):
        shutil.copy2(run_dir / name, dest / name)
    for path in sorted((run_dir / SNAPSHOTS).glob("actor_*.npz")):
        zoo.save_actor(dest / SNAPSHOTS / path.name, zoo.load_actor(path))
    return dest


def build_antmaze(
    run_dir: str | os.PathLike,
    root: str | os.PathLike | None = None,
    step: int | None = None,
    episodes: int = 30,
    seed: int = 12345,
    log: Callable[[str], None] = print,
    plane_episodes: int = OPEN_PLANE_EPISODES,
) -> dict:
    """Make ``zoo/antmaze`` from an ``eabc sac`` run on ``eabc/AntDirection-v0``: its snapshot at
    ``step`` (default the latest) as ``direction.npz`` (float16), and a card with the training
    steps, the direction task's evaluation return and, per maze, how often the waypoint
    controller with these rounded weights (and the data's action noise) takes the ant from the
    start to the evaluation goal within the time limit, and how often the ant flips; the same for
    the policy alone on the open plane, toward goals 5-10 m away."""
    run_dir = Path(run_dir)
    config = _sac_config(run_dir)
    if config["env_id"] != antmaze.DIRECTION_ENV_ID:
        raise DatasetError(
            f"{run_dir} trained on {config['env_id']}; the AntMaze low-level policy is trained on "
            f"{antmaze.DIRECTION_ENV_ID}"
        )
    snapshots = sorted(int(p.stem.split("_")[1]) for p in (run_dir / SNAPSHOTS).glob("actor_*.npz"))
    if not snapshots or (step is not None and step not in snapshots):
        raise DatasetError(f"{run_dir} has no actor snapshot {'' if step is None else step}")
    step = snapshots[-1] if step is None else step
    actor = zoo.rounded(zoo.load_actor(run_dir / SNAPSHOTS / f"actor_{step:08d}.npz"))
    controller = {}
    for maze in mazes.MAZES:
        collected = antmaze_collect.collect(maze, "fixed", episodes, seed, actor, desc=maze)
        controller[maze] = collected.summary()
        log(
            f"{maze}: success {controller[maze]['success_rate']:.0%}, flips {controller[maze]['flip_rate']:.0%}"
        )
    plane = antmaze_collect.open_plane(actor, plane_episodes, seed)
    log(f"open plane: success {plane['success_rate']:.0%}, flips {plane['flip_rate']:.0%}")
    evaluations = _evaluation_returns(run_dir)
    at = max((s for s in evaluations if s <= step), default=None)
    out = zoo.zoo_dir(root) / antmaze_collect.ZOO_ENTRY
    out.mkdir(parents=True, exist_ok=True)
    zoo.save_actor(out / antmaze_collect.POLICY_FILE, actor)
    card = {
        "env_id": antmaze.DIRECTION_ENV_ID,
        "algorithm": "SAC (eabc sac) on the direction-following task; the controller acts with the "
        "actor's mean action plus Gaussian noise 0.2",
        "sac": config["sac"],
        "agent": config["agent"],
        "training_steps": step,
        "direction_return": None if at is None else {"step": at, "return_mean": evaluations[at]},
        "weights": "float16 npz; the rates below were measured with these rounded weights",
        "evaluation_seed": seed,
        "controller": {
            "what": "episodes from the maze's start to its evaluation goal (family 'fixed'), the "
            "maze's time limit, action noise 0.2; success: within 0.5 of the goal at some step; "
            "flip: the torso upside down at some step",
            **controller,
        },
        "open_plane": {
            "what": "the policy alone on the open plane, fed the unit vector toward a goal 5-10 m "
            "away in a uniform direction, action noise 0.2; success: within 0.5 of the goal within "
            "the time limit; flip: the torso upside down before the goal or the limit",
            **plane,
        },
        "file": antmaze_collect.POLICY_FILE,
    }
    (out / zoo.CARD).write_text(json.dumps(card, indent=2) + "\n")
    return card


def _evaluation_returns(run_dir: Path) -> dict[int, float]:
    """The evaluation return (deterministic actions) logged at each evaluation step."""
    with open(run_dir / "log.csv", newline="") as f:
        return {
            int(row["step"]): float(row["eval_return"])
            for row in csv.DictReader(f)
            if row.get("eval_return") not in (None, "", "nan")
        }
