"""Datasets made by several processes, bit for bit as one process makes them.

**AntMaze.** Episodes run in batches of ``NUM_ENVS``, each episode drawing only from its own
generator (:func:`eabc.data.antmaze_collect.collect`): batches are independent, and a worker makes
whole batches.

**MuJoCo.** One environment and one generator run through all the episodes of a rollout, so where
an episode starts depends on every step before it. What a rollout's state at an episode start
consists of is small: the row, how many episodes came before, the action generator's state (which
follows from the row: every step draws the same number of numbers) and the environment's (which
follows from the episode: every reset draws the same). The rows where episodes start are the only
part that needs the simulation. :data:`TABLE` lists a start every ~:data:`SPACING` rows for the
rollouts of the built-in datasets at seed 0 with the shipped zoo, read from datasets made by one
process (:func:`eabc.data.generate.episode_starts`); from it, workers start mid-rollout.

Nothing is taken on trust: every chunk but the last must end an episode exactly where the next
starts, with both generators in the states the next one started from. By induction the pieces are
then the one-process rollout; a table that does not fit (another zoo, another environment version)
is noticed and the rollout is made by one process instead, never written wrong. Rollouts with no
table entry (other seeds, another zoo) are made by one process.

Workers are spawned processes, each single-threaded (BLAS pools of one thread), that import
neither JAX nor the command line: they start in a second or two.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import hashlib
import json
import multiprocessing
import os
import sys
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from eabc import progress
from eabc.data import antmaze_collect, tasks, zoo

TABLE = Path(__file__).with_name("episode_starts.json")
"""Episode starts of the built-in MuJoCo rollouts (seed 0, the shipped zoo)."""
SPACING = 10_000
"""About how many rows apart the table's starts are: the size of a worker's piece of work."""
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@dataclasses.dataclass(frozen=True)
class Rollout:
    """One rollout of the MuJoCo recipe (:func:`step_rows`): ``size`` transitions in ``env_id``
    from ``seed``, actions sampled from the actor file ``policy`` (uniform random when None)."""

    env_id: str
    policy: str | None
    size: int
    seed: int
    desc: str
    max_episode_steps: int = 1000

    def key(self) -> str:
        """The rollout's name in :data:`TABLE`: environment, the policy file's digest, seed."""
        digest = (
            "uniform"
            if self.policy is None
            else hashlib.sha256(Path(self.policy).read_bytes()).hexdigest()[:16]
        )
        return f"{self.env_id} {digest} seed {self.seed}"


def make_env(env_id: str, max_episode_steps: int = 1000):
    return tasks.make_env(env_id, max_episode_steps=max_episode_steps)


def action_fn(policy: str | os.PathLike | None):
    """``act(obs, rng)`` sampling the zoo actor in file ``policy``; None for uniform actions."""
    return None if policy is None else zoo.sampler(zoo.load_actor(policy))


def empty_rows(env, count: int) -> dict[str, np.ndarray]:
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    return {
        "observations": np.empty((count, obs_dim), np.float32),
        "actions": np.empty((count, act_dim), np.float32),
        "rewards": np.empty(count, np.float32),
        "next_observations": np.empty((count, obs_dim), np.float32),
        "terminals": np.zeros(count, bool),
        "timeouts": np.zeros(count, bool),
    }


def step_rows(env, act, rng: np.random.Generator, obs, out: dict, rows: Iterable[int], stop: int):
    """The MuJoCo recipe's loop: act (uniform random actions when ``act`` is None), step, write row
    ``i`` of ``out``, reset after an episode's end (a terminal or the time limit) unless ``i`` is
    the last row, ``stop - 1``. Returns how many episodes ended."""
    low, high = env.action_space.low, env.action_space.high
    ended = 0
    for i in rows:
        action = rng.uniform(low, high) if act is None else act(obs, rng)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        out["observations"][i], out["actions"][i], out["rewards"][i] = obs, action, reward
        out["next_observations"][i] = next_obs
        out["terminals"][i], out["timeouts"][i] = terminated, truncated and not terminated
        if terminated or truncated:
            ended += 1
            if i + 1 < stop:
                next_obs = env.reset()[0]
        obs = next_obs
    return ended


def table_starts(spec: Rollout, table: Path | None = None) -> list[tuple[int, int]]:
    """``(row, episode)`` of the table's episode starts inside ``spec``'s rows (row 0 implied)."""
    table = TABLE if table is None else table
    if not table.exists():
        return []
    entry = json.loads(table.read_text())["rollouts"].get(spec.key())
    return [(row, episode) for row, episode in entry["starts"] if row < spec.size] if entry else []


def make_rollouts(specs: list[Rollout], workers: int, desc: str) -> list[dict | None]:
    """The rows of each of ``specs`` made by ``workers`` processes from :data:`TABLE`'s episode
    starts; None for a rollout whose starts the table does not know or that they do not fit (one
    process makes it). A rollout's last row is as it came out of the simulation (the caller
    marks the budget's cut)."""
    plans = [_plan(spec) for spec in specs]
    rows = sum(spec.size for spec, plan in zip(specs, plans) if plan)
    if not rows:
        return [None] * len(specs)
    with Pool(workers, desc, rows, sum(len(plan) for plan in plans if plan)) as pool:
        handed = [
            plan and [(pool.submit(_rollout_piece, *args), end) for args, end in plan]
            for plan in plans
        ]
        return [pieces and _joined(spec, pieces) for spec, pieces in zip(specs, handed)]


def _plan(spec: Rollout) -> list[tuple[tuple, dict | None]] | None:
    """``spec``'s pieces between the table's episode starts: each piece's arguments for
    :func:`_rollout_piece` and where it must end (the next piece's start; None for the last)."""
    starts = table_starts(spec)
    if not starts:
        progress.say(f"{spec.desc}: no episode starts of {spec.key()} known; one process makes it")
        return None
    states = list(_start_states(spec, starts))
    plan = []
    for i, (lo, episode, *generators) in enumerate(states):
        last = i + 1 == len(states)
        hi = spec.size if last else states[i + 1][0]
        plan.append(((spec, lo, hi, episode, *generators), None if last else _end(*states[i + 1])))
    return plan


def _joined(spec: Rollout, pieces: list) -> dict[str, np.ndarray] | None:
    """The rows of the pieces, each checked against the next one's start; None if one fails."""
    done = [(piece.result(), expected) for piece, expected in pieces]
    for result, expected in done:
        if expected is not None and result["end"] != expected:
            row = expected["row"]
            progress.say(
                f"{spec.desc}: its episode starts do not fit at row {row:,}; one process makes it"
            )
            return None
    return {k: np.concatenate([r["rows"][k] for r, _ in done]) for k in done[0][0]["rows"]}


def _end(row: int, episode: int, rng_state: dict, env_state: dict, done: bool = True) -> dict:
    """Where a piece ended: the next row, the episodes before it, the two generators' states,
    and whether its last row ended an episode."""
    return {"row": row, "episode": episode, "rng": rng_state, "env": env_state, "done": done}


def _start_states(spec: Rollout, starts: list[tuple[int, int]]) -> Iterator[tuple]:
    """``(row, episode, action generator state, environment generator state)`` at row 0 and at
    each of ``starts``, found by replaying the generators' draws without stepping: the actions
    draw ``act_dim`` numbers a step (uniform, or the policy's float32 normal noise), the
    environment's generator is drawn from only by its resets."""
    env = make_env(spec.env_id, spec.max_episode_steps)
    rng = np.random.default_rng(spec.seed)
    env.reset(seed=spec.seed)
    row, resets = 0, 1
    yield 0, 0, rng.bit_generator.state, env.unwrapped.np_random.bit_generator.state
    act_dim = env.action_space.shape[0]
    for start, episode in starts:
        while resets < episode:
            env.reset()
            resets += 1
        while row < start:  # in blocks: a million steps' draws at once would be 24 MB
            block = min(start - row, 100_000)
            if spec.policy is None:
                rng.random(block * act_dim)
            else:
                rng.standard_normal(block * act_dim, dtype=np.float32)
            row += block
        yield start, episode, rng.bit_generator.state, env.unwrapped.np_random.bit_generator.state
    env.close()


_WORKER_CACHE: dict = {}
"""A worker process's environments and policies, made once per process."""


def _rollout_piece(spec: Rollout, lo: int, hi: int, episode: int, rng_state, env_state) -> dict:
    """Rows ``lo`` to ``hi`` of ``spec``, starting at an episode start in the given states."""
    if spec not in _WORKER_CACHE:
        _WORKER_CACHE[spec] = make_env(spec.env_id, spec.max_episode_steps), action_fn(spec.policy)
    env, act = _WORKER_CACHE[spec]
    obs = env.reset(seed=spec.seed)[0]
    rng = np.random.default_rng(spec.seed)
    if episode:
        rng.bit_generator.state = rng_state
        env.unwrapped.np_random.bit_generator.state = env_state
        obs = env.reset()[0]
    out = empty_rows(env, hi - lo)
    ended = step_rows(env, act, rng, obs, out, range(hi - lo), hi - lo)
    done = bool(out["terminals"][-1] or out["timeouts"][-1])
    state = env.unwrapped.np_random.bit_generator.state
    return {"rows": out, "end": _end(hi, episode + ended, rng.bit_generator.state, state, done)}


def collect_antmaze(
    maze_name: str,
    family: str,
    episodes: int,
    seed: int,
    policy: str | os.PathLike,
    num_envs: int,
    workers: int,
    desc: str,
    recipe_name: str = antmaze_collect.DEFAULT_RECIPE,
) -> antmaze_collect.Collected:
    """:func:`eabc.data.antmaze_collect.collect` with its batches of ``num_envs`` episodes shared
    out to ``workers`` processes; the actor is read from the file ``policy``."""
    steps = antmaze_collect.recipe(recipe_name).steps(antmaze_collect.mazes.get(maze_name))
    rows = episodes * steps
    args = (maze_name, family, episodes, seed, str(policy), num_envs, recipe_name)
    firsts = range(0, episodes, num_envs)
    with Pool(workers, desc, rows, len(firsts)) as pool:
        parts = [
            pool.submit(_antmaze_piece, *args, first, min(first + num_envs, episodes))
            for first in firsts
        ]
        parts = [part.result() for part in parts]
    return antmaze_collect.Collected(
        *(np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(parts[0]))
    )


def _antmaze_piece(maze_name, family, episodes, seed, policy, num_envs, recipe_name, first, stop):
    if policy not in _WORKER_CACHE:
        _WORKER_CACHE[policy] = zoo.load_actor(policy)
    return antmaze_collect.collect(
        maze_name, family, episodes, seed, _WORKER_CACHE[policy], num_envs=num_envs,
        first=first, stop=stop, progress=False, recipe_name=recipe_name,
    )  # fmt: skip


class Pool:
    """``workers`` spawned single-threaded processes making ``rows`` rows in ``pieces`` pieces,
    with progress: a bar on a terminal, else lines (:func:`eabc.progress.bar`). A context
    manager; leaving it on an error, Ctrl-C or a kill stops the workers."""

    def __init__(self, workers: int, desc: str, rows: int, pieces: int):
        context = multiprocessing.get_context("spawn")
        self.executor = concurrent.futures.ProcessPoolExecutor(workers, mp_context=context)
        shared = f"in {pieces} pieces on {workers} processes"
        self.bar = progress.bar(rows, desc, estimate=shared, mininterval=1.0, leave=False)

    def submit(self, work: Callable, *args) -> concurrent.futures.Future:
        """``work(*args)`` in a worker: the future of its result (a dict of rows, or Collected)."""
        with bare_children():  # the executor starts its processes as work arrives
            future = self.executor.submit(work, *args)
        future.add_done_callback(self._progress)
        return future

    def _progress(self, future: concurrent.futures.Future) -> None:
        if not future.cancelled() and future.exception() is None:
            result = future.result()
            actions = result["rows"]["actions"] if isinstance(result, dict) else result.actions
            self.bar.update(len(actions))

    def __enter__(self) -> Pool:
        return self

    def __exit__(self, kind, error, trace) -> None:
        if kind is not None:  # an error, Ctrl-C or a kill: no piece is worth finishing
            for process in list(getattr(self.executor, "_processes", {}).values()):
                process.terminate()  # the executor has no public way to stop running work
        self.executor.shutdown(wait=kind is None, cancel_futures=kind is not None)
        self.bar.close()


@contextlib.contextmanager
def bare_children():
    """Processes spawned meanwhile are single-threaded (BLAS pools of one thread) and start from
    the work's module alone: a script run as the main module (the ``eabc`` command, which imports
    JAX) is not run again in each of them, as spawning otherwise does."""
    saved = {name: os.environ.get(name) for name in _THREAD_VARIABLES}
    os.environ.update(dict.fromkeys(_THREAD_VARIABLES, "1"))
    main = sys.modules.get("__main__")
    script = getattr(main, "__file__", None) if getattr(main, "__spec__", None) is None else None
    if script is not None:
        del main.__file__
    try:
        yield
    finally:
        if script is not None:
            main.__file__ = script
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
