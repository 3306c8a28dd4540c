"""The behaviour-policy zoo: SAC actors shipped with the package, the policies behind the datasets.

Per environment, ``zoo/ENV/`` holds

- ``card.json``: where the policies come from (environment, SAC settings, training steps) and, for
  the ``medium`` and ``expert`` policy, the step it was taken at and its return with sampled
  actions over ``episodes`` episodes (mean, std, D4RL-normalised);
- ``medium.npz`` and ``expert.npz``: actor weights (float16, no pickle);
- ``replay/actor_STEP.npz``: the actor every ``interval`` training steps up to the medium point,
  from which the medium-replay dataset is rebuilt.

:func:`build` makes a zoo entry from an ``eabc sac`` run directory: the expert is the best of the
last snapshots, the medium policy the snapshot whose return is closest to D4RL's medium level
the first time training reaches it (D4RL stopped SAC early at about a third of the expert).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from eabc import networks
from eabc.data import tasks
from eabc.data.dataset import DatasetError

CARD = "card.json"
WEIGHT_DTYPE = np.float16
"""Stored precision of the shipped actors (halves the package size; the card's returns are
measured with exactly these weights)."""

D4RL_LEVEL = {
    # Mean normalised return of D4RL's datasets (../shared/SPEC.md section 3).
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
            f"them with `eabc sac --env {env}` and `python -m eabc.data.zoo build RUN_DIR {env}`"
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
    return networks.numpy_gaussian_sampler(actor, max_action)


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
    import hashlib  # noqa: PLC0415

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


def stochastic_return(
    env_id: str, actor: dict[str, np.ndarray], episodes: int, seed: int
) -> tuple[float, float]:
    """Mean and std of the return of ``actor`` with sampled actions (as the datasets are made)."""
    from eabc.evaluation import make_env  # noqa: PLC0415

    env = make_env(env_id)
    act = sampler(actor, float(env.action_space.high[0]))
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


def _rounded(actor: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v.astype(WEIGHT_DTYPE).astype(np.float32) for k, v in actor.items()}


def _save(path: Path, actor: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{k: v.astype(WEIGHT_DTYPE) for k, v in actor.items()})


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
    from eabc.training.checkpoint import read_config  # noqa: PLC0415
    from eabc.training.online import SNAPSHOTS  # noqa: PLC0415

    run_dir = Path(run_dir)
    config = read_config(run_dir)
    env_id = config["env_id"]
    info = tasks.ENVS.get(env)
    snapshots = sorted(int(p.stem.split("_")[1]) for p in (run_dir / SNAPSHOTS).glob("actor_*.npz"))
    if not snapshots:
        raise DatasetError(f"{run_dir} has no actor snapshots")
    actors = {
        s: _rounded(load_actor(run_dir / SNAPSHOTS / f"actor_{s:08d}.npz")) for s in snapshots
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
    level = D4RL_LEVEL["medium"].get(env)
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

    out = zoo_dir(root) / env
    if out.exists():
        shutil.rmtree(out)
    _save(out / "expert.npz", actors[expert["step"]])
    _save(out / "medium.npz", actors[medium["step"]])
    replay = [s for s in snapshots if s < medium["step"]]
    for s in replay:
        _save(out / "replay" / f"actor_{s:08d}.npz", actors[s])
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
    (out / CARD).write_text(json.dumps(result, indent=2))
    return result


def _training_returns(run_dir: Path) -> dict[int, float]:
    """Mean training-episode return (sampled actions) of each logged window, by step."""
    import csv  # noqa: PLC0415

    with open(run_dir / "log.csv", newline="") as f:
        return {
            int(row["step"]): float(row["train_return"])
            for row in csv.DictReader(f)
            if row.get("train_return") not in (None, "", "nan")
        }


def pack(run_dir: str | os.PathLike, dest: str | os.PathLike) -> Path:
    """Copy what continuing an ``eabc sac`` run needs into ``dest``, small enough to commit.

    Keeps the config, the log, the checkpoint (networks, optimisers, temperature, step, random
    states) and the actor snapshots (float16, which is all :func:`build` uses of them), and drops the
    replay buffer: ``eabc sac --resume`` on a copy of ``dest`` refills it as training goes on.
    """
    from eabc.training import checkpoint  # noqa: PLC0415
    from eabc.training.online import SNAPSHOTS  # noqa: PLC0415

    run_dir, dest = Path(run_dir), Path(dest)
    if not (run_dir / checkpoint.CHECKPOINT).exists():
        raise DatasetError(f"{run_dir} has no checkpoint yet; nothing to pack")
    (dest / SNAPSHOTS).mkdir(parents=True, exist_ok=True)
    for name in (checkpoint.CONFIG, "log.csv", checkpoint.CHECKPOINT):
        shutil.copy2(run_dir / name, dest / name)
    for path in sorted((run_dir / SNAPSHOTS).glob("actor_*.npz")):
        _save(dest / SNAPSHOTS / path.name, load_actor(path))
    return dest


def main(argv: list[str] | None = None) -> None:
    import argparse  # noqa: PLC0415

    parser = argparse.ArgumentParser(
        prog="python -m eabc.data.zoo", description="Build a zoo entry from an `eabc sac` run."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="choose the medium and expert policies of a SAC run")
    b.add_argument("run_dir")
    b.add_argument("env", help="hopper, halfcheetah or walker2d")
    b.add_argument("--root", default=None, help="zoo directory (default: the package's)")
    b.add_argument("--episodes", type=int, default=10)
    b.add_argument("--expert-candidates", type=int, default=5,
                   help="the expert is the best of this many last snapshots")  # fmt: skip
    b.add_argument("--medium-return", type=float, default=None,
                   help="return the medium policy aims at (default: D4RL's medium level)")  # fmt: skip
    b.add_argument("--rechoose-medium", action="store_true",
                   help="search for the medium policy again even if the zoo already has one")  # fmt: skip
    p = sub.add_parser(
        "pack", help="copy a SAC run's checkpoint, log and float16 snapshots (no replay buffer)"
    )
    p.add_argument("run_dir")
    p.add_argument("dest")
    args = parser.parse_args(argv)
    if args.command == "pack":
        print(pack(args.run_dir, args.dest))
        return
    medium_step = None
    if (zoo_dir(args.root) / args.env / CARD).exists() and not args.rechoose_medium:
        medium_step = card(args.env, args.root)["medium"]["step"]
        print(f"keeping the zoo's medium policy (step {medium_step}); --rechoose-medium to search")
    card_ = build(
        args.run_dir,
        args.env,
        args.root,
        args.episodes,
        expert_candidates=args.expert_candidates,
        medium_return=args.medium_return,
        medium_step=medium_step,
    )
    print(json.dumps({k: card_[k] for k in ("expert", "medium")}, indent=2))


if __name__ == "__main__":
    main()
