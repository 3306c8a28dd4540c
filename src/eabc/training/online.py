"""Online SAC in Gymnasium: the trainer of the behaviour policies behind the built-in datasets.

The environment runs on the host with a NumPy copy of the actor; every ``update_every`` environment
steps the same number of gradient steps run in one compiled ``lax.scan`` (Spinning Up's schedule,
one update per environment step on average). Uniform random actions come first
(``start_steps``), as in Haarnoja et al. (2018).

A run directory holds ``config.json``, ``checkpoint.msgpack`` (networks, optimisers, temperature,
step, random states, episode history), ``replay.npz`` (the replay buffer), ``log.csv`` (training
and evaluation returns), and ``snapshots/`` with the actor every ``snapshot_interval`` steps: the
sequence the medium-replay datasets are rebuilt from. Resuming restores everything except the
episode that was in progress, which restarts.

Why one file of about 350 lines: the environment loop, the replay buffer, snapshots and the resume
path share one run state; each piece is small and only this trainer uses it.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from eabc import networks, pytree, ranges
from eabc.agents import sac
from eabc.agents.common import Batch
from eabc.data import tasks
from eabc.evaluation import Evaluator, make_env
from eabc.progress import bar as progress_bar
from eabc.training import checkpoint, provenance
from eabc.training.checkpoint import CONFIG, read_config
from eabc.training.logger import RunLogger

REPLAY = "replay.npz"
SNAPSHOTS = "snapshots"


@dataclasses.dataclass(frozen=True)
class SACTrainConfig(ranges.Settings):
    """Online SAC's schedule (Haarnoja et al. 2018 for MuJoCo; Spinning Up's update cadence)."""

    env: str = "hopper"
    """hopper, halfcheetah, walker2d, or any Gymnasium id with a Box action space."""
    seed: ranges.Seed = 0
    """Seeds the networks, the environment, exploration and batch sampling."""
    steps: ranges.Steps = 1_000_000
    """Environment steps (one gradient step per environment step after update_after)."""
    start_steps: ranges.NonNegativeSteps = 10_000
    """Uniform random actions for this many first steps."""
    update_after: ranges.NonNegativeSteps = 1_000
    """No gradient steps before the buffer holds this many transitions."""
    update_every: ranges.Steps = 50
    """Environment steps between bursts of as many gradient steps, compiled as one scan."""
    batch_size: ranges.BatchSize = 256
    """Mini-batch size."""
    eval_interval: ranges.Steps = 10_000
    """Deterministic evaluation every this many steps."""
    eval_episodes: ranges.Positive = 10
    """Episodes per evaluation."""
    snapshot_interval: ranges.Steps = 10_000
    """Keep the actor every this many steps (the checkpoint sequence for medium-replay data)."""
    checkpoint_interval: ranges.Steps = 50_000
    """Save networks, optimisers and the replay buffer every this many steps."""
    refill_steps: ranges.NonNegativeSteps = 100_000
    """A run resumed without its replay buffer (a pack) first collects this many transitions with
    its current policy, without gradient steps and without counting them as training steps:
    gradient steps on the first ``update_after`` new transitions alone undo a trained policy."""

    def __post_init__(self):
        super().__post_init__()  # each setting of its declared type and range
        for name in ("eval_interval", "snapshot_interval", "checkpoint_interval"):
            if getattr(self, name) % self.update_every:
                raise ValueError(f"{name} must be a multiple of update_every={self.update_every}")

    @property
    def env_id(self) -> str:
        return tasks.ENVS[self.env].env_id if self.env in tasks.ENVS else self.env


class ReplayBuffer:
    """Transitions in preallocated NumPy arrays (``terminals`` only where the episode ended for real)."""

    FIELDS = ("observations", "actions", "rewards", "next_observations", "terminals")

    @staticmethod
    def bytes(capacity: int, obs_dim: int, act_dim: int) -> int:
        """What a buffer of ``capacity`` transitions allocates (float32 fields)."""
        return 4 * capacity * (2 * obs_dim + act_dim + 2)

    def __init__(self, capacity: int, obs_dim: int, act_dim: int):
        self.size = 0
        self.data = {
            "observations": np.zeros((capacity, obs_dim), np.float32),
            "actions": np.zeros((capacity, act_dim), np.float32),
            "rewards": np.zeros(capacity, np.float32),
            "next_observations": np.zeros((capacity, obs_dim), np.float32),
            "terminals": np.zeros(capacity, np.float32),
        }

    def add(self, obs, action, reward, next_obs, terminal) -> None:
        i = self.size
        d = self.data
        d["observations"][i], d["actions"][i], d["rewards"][i] = obs, action, reward
        d["next_observations"][i], d["terminals"][i] = next_obs, terminal
        self.size += 1

    def sample(self, rng: np.random.Generator, shape: tuple[int, ...]) -> Batch:
        index = rng.integers(0, self.size, shape)
        d = self.data
        return Batch(
            observations=d["observations"][index],
            actions=d["actions"][index],
            rewards=d["rewards"][index],
            next_observations=d["next_observations"][index],
            dones=d["terminals"][index],
        )

    def save(self, path: Path) -> None:
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, **{k: v[: self.size] for k, v in self.data.items()})
        os.replace(tmp, path)

    def load(self, path: Path) -> None:
        with np.load(path, allow_pickle=False) as saved:
            self.size = len(saved["rewards"])
            for key in self.FIELDS:
                self.data[key][: self.size] = saved[key]


@functools.partial(jax.jit, static_argnames=("config", "max_action"))
def update_chunk(state, key, batches: Batch, config: sac.SACConfig, max_action: float):
    """One gradient step per leading entry of ``batches``, in one scan; returns mean metrics."""

    def step(carry, batch):
        state, key = carry
        key, update_key = jax.random.split(key)
        state, metrics = sac.update(state, batch, update_key, config, max_action)
        return (state, key), metrics

    (state, key), metrics = jax.lax.scan(step, (state, key), batches)
    return state, key, jax.tree.map(jnp.mean, metrics)


@dataclasses.dataclass
class OnlineRun:
    run_dir: Path
    config: SACTrainConfig
    agent_config: sac.SACConfig
    env: Any
    max_action: float
    state: dict[str, Any]
    """``agent``, ``key``, ``step``, ``rng`` (NumPy generator state as JSON), ``episodes``
    (list of [end step, return, length]), ``evaluations``, ``elapsed``."""
    buffer: ReplayBuffer


def start_sac(
    config: SACTrainConfig, run_dir: str | Path, agent_config: sac.SACConfig | None = None
) -> OnlineRun:
    run_dir = Path(run_dir)
    if (run_dir / CONFIG).exists():
        raise FileExistsError(
            f"{run_dir} already holds a run; continue it with `eabc sac --resume {run_dir}`"
        )
    agent_config = agent_config or sac.online_preset(config.env)
    run = _build(run_dir, config, agent_config, from_checkpoint=False)
    run_dir.mkdir(parents=True, exist_ok=True)
    checkpoint.save_json(
        run_dir / CONFIG,
        {
            "sac": dataclasses.asdict(config),
            "agent": dataclasses.asdict(agent_config),
            "env_id": config.env_id,
            "max_action": run.max_action,
        },
    )
    return run


def resume_sac(run_dir: str | Path) -> OnlineRun:
    saved = read_config(run_dir)
    config = SACTrainConfig(**saved["sac"])
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in saved["agent"].items()}
    return _build(Path(run_dir), config, sac.SACConfig(**fields), from_checkpoint=True)


def _build(run_dir, config, agent_config, from_checkpoint) -> OnlineRun:
    env = make_env(config.env_id)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    max_action = float(env.action_space.high[0])
    need = ReplayBuffer.bytes(config.steps, obs_dim, act_dim)  # every step's transition
    ranges.check_memory([("--steps", str(config.steps), "the replay buffer", need)])
    init_key, loop_key = jax.random.split(jax.random.PRNGKey(config.seed))
    state = {
        "agent": sac.init(init_key, obs_dim, act_dim, agent_config),
        "key": loop_key,
        "step": 0,
        "rng": json.dumps(np.random.default_rng(config.seed).bit_generator.state),
        "episodes": [],
        "evaluations": {},
        "elapsed": 0.0,
    }
    buffer = ReplayBuffer(config.steps, obs_dim, act_dim)
    if from_checkpoint:
        raw = checkpoint.load_raw(run_dir)
        state = {
            **raw,
            "agent": pytree.from_state_dict(state["agent"], raw["agent"]),
            "episodes": np.asarray(raw["episodes"]).reshape(-1, 3).tolist(),
            "evaluations": raw["evaluations"] or {},
        }
        if (run_dir / REPLAY).exists():
            buffer.load(run_dir / REPLAY)
    return OnlineRun(run_dir, config, agent_config, env, max_action, state, buffer)


def train_sac(run: OnlineRun, progress: bool = True) -> dict[str, Any]:
    """Run online SAC to ``config.steps`` environment steps from wherever the run is."""
    config, run_dir, env = run.config, run.run_dir, run.env
    rng = np.random.default_rng()
    rng.bit_generator.state = json.loads(run.state["rng"])
    step = int(run.state["step"])
    provenance.record(run_dir, step)
    low, high = env.action_space.low, env.action_space.high
    sampler = networks.numpy_gaussian_sampler(
        jax.device_get(run.state["agent"].actor), run.max_action
    )
    if step > 0 and run.buffer.size == 0:
        refill_buffer(run, sampler, rng, min(config.refill_steps, step), progress)
    # A resumed run restarts its episode; the seed makes that restart deterministic too.
    obs, _ = env.reset(seed=config.seed + step)
    evaluator = Evaluator(config.env_id, config.seed + 100, config.eval_episodes)
    env_name = next((k for k, v in tasks.ENVS.items() if v.env_id == config.env_id), None)
    logger = RunLogger(run_dir, resume_step=step)
    (run_dir / SNAPSHOTS).mkdir(exist_ok=True)
    bar = progress_bar(
        config.steps, f"sac {config.env}", initial=step, enabled=progress,
        dynamic_ncols=True, mininterval=1.0,
    )  # fmt: skip
    episode_return, episode_length, window_started = 0.0, 0, time.perf_counter()
    metrics: dict[str, float] = {}
    try:
        while step < config.steps:
            action = _explore(config, step, obs, sampler, rng, low, high)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            run.buffer.add(obs, action, reward, next_obs, float(terminated))
            episode_return += float(reward)
            episode_length += 1
            step += 1
            obs = next_obs
            if terminated or truncated:
                run.state["episodes"].append([step, episode_return, episode_length])
                obs, _ = env.reset()
                episode_return, episode_length = 0.0, 0
            if step % config.update_every:
                continue
            if run.buffer.size >= config.update_after:
                batches = run.buffer.sample(rng, (config.update_every, config.batch_size))
                agent, key, chunk_metrics = update_chunk(
                    run.state["agent"], run.state["key"], batches, run.agent_config, run.max_action
                )
                run.state |= {"agent": agent, "key": key}
                metrics = {k: float(v) for k, v in jax.device_get(chunk_metrics).items()}
                sampler = networks.numpy_gaussian_sampler(
                    jax.device_get(agent.actor), run.max_action
                )
            bar.update(config.update_every)
            if step % config.eval_interval == 0 or step % config.snapshot_interval == 0:
                now = time.perf_counter()
                run.state["elapsed"] += now - window_started
                window_started = now
                row = _log_row(run, step, metrics, evaluator, env_name)
                logger.log(row)
                bar.set_postfix(
                    {"eval": f"{row.get('eval_return', float('nan')):.0f}",
                     "train": f"{row['train_return']:.0f}"}, refresh=False,
                )  # fmt: skip
            if step % config.snapshot_interval == 0:
                save_snapshot(run, step)
            if step % config.checkpoint_interval == 0 or step == config.steps:
                run.state["step"] = step
                run.state["rng"] = json.dumps(rng.bit_generator.state)
                run.buffer.save(run_dir / REPLAY)
                episodes = np.asarray(run.state["episodes"], np.float64).reshape(-1, 3)
                checkpoint.save(run_dir, {**run.state, "episodes": episodes})
    finally:
        bar.close()
        logger.close()
    return summarize_sac(run)


def refill_buffer(run: OnlineRun, sampler, rng: np.random.Generator, n: int, progress: bool):
    """Fill an empty replay buffer with ``n`` transitions of the current stochastic policy
    (uniform random actions if the run is still in its ``start_steps`` warm-up).

    Used when a run resumes without ``replay.npz``: the step count, the episode history and the
    networks stay as they were; only the buffer (and the exploration random state) changes.
    """
    env, step = run.env, int(run.state["step"])
    low, high = env.action_space.low, env.action_space.high
    obs, _ = env.reset(seed=run.config.seed + step + 1)
    for _ in progress_bar(
        n, "refilling the replay buffer", iterable=range(n), enabled=progress,
        dynamic_ncols=True, mininterval=1.0,
    ):  # fmt: skip
        action = _explore(run.config, step, obs, sampler, rng, low, high)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        run.buffer.add(obs, action, reward, next_obs, float(terminated))
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset()


def _explore(config: SACTrainConfig, step: int, obs, sampler, rng, low, high) -> np.ndarray:
    """The acting action at ``step``: uniform during the ``start_steps`` warm-up, then sampled."""
    if step < config.start_steps:
        return rng.uniform(low, high).astype(np.float32)
    return sampler(obs, rng)


def _log_row(run, step, metrics, evaluator, env_name) -> dict[str, float]:
    episodes = [e for e in run.state["episodes"] if e[0] > step - run.config.eval_interval]
    row = {
        "step": step,
        "wall_time": run.state["elapsed"],
        "train_return": float(np.mean([e[1] for e in episodes])) if episodes else float("nan"),
        "train_episodes": len(episodes),
        **metrics,
    }
    if step % run.config.eval_interval == 0:
        policy = networks.numpy_actor(
            jax.device_get(run.state["agent"].actor), run.max_action, gaussian=True
        )
        result = evaluator(policy)
        run.state["evaluations"][str(step)] = result
        row |= {"eval_return": result["return_mean"], "eval_return_std": result["return_std"]}
        if env_name is not None:
            env = tasks.ENVS[env_name]
            row["eval_score"] = tasks.normalized_score(
                result["return_mean"], env.ref_min_score, env.ref_max_score
            )
    return row


def save_snapshot(run: OnlineRun, step: int) -> Path:
    """The actor at ``step`` as ``snapshots/actor_STEP.npz`` (float32 arrays, no pickle)."""
    path = run.run_dir / SNAPSHOTS / f"actor_{step:08d}.npz"
    actor = jax.device_get(run.state["agent"].actor)
    np.savez(path, **{k: np.asarray(v, np.float32) for k, v in actor.items()})
    return path


def summarize_sac(run: OnlineRun) -> dict[str, Any]:
    evaluations = run.state["evaluations"]
    last = evaluations[max(evaluations, key=int)] if evaluations else None
    return {
        "env_id": run.config.env_id,
        "steps": int(run.state["step"]),
        "episodes": len(run.state["episodes"]),
        "wall_time_s": run.state["elapsed"],
        "final_eval_return": last["return_mean"] if last else None,
    }
