"""A training run's configuration: how to train (:class:`TrainConfig`), the agent's settings as
the run trains with them (:func:`resolve_agent_config`), and the checks that refuse a
configuration before a run directory is written or data is made (a cache directory that cannot be
one, an evaluation environment that cannot have made the data, a run that does not fit in memory).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Literal

import jax

from eabc import agents, paths, ranges
from eabc.agents import ALGORITHMS, get_algorithm
from eabc.data import sources, tasks
from eabc.data.dataset import Dataset, DatasetError
from eabc.evaluation import check_spaces, make_env
from eabc.training import rewards

FINAL_EVALUATIONS = 10
"""The score of a run is the mean of its last 10 evaluations."""


@dataclasses.dataclass(frozen=True)
class TrainConfig(ranges.Settings):
    """How to train: data, length, evaluation and bookkeeping (the paper's protocol by default).
    Each field's type says its range (:mod:`eabc.ranges`), checked when the config is made."""

    dataset: str = "hopper-random"
    """A built-in name (hopper-random, ...), a .hdf5/.npz path, or minari:ID."""
    algo: str = agents.DEFAULT
    """Algorithm: a name registered in ``eabc.agents`` (docs/algorithms.md describes each; an
    unknown name is refused with the list)."""
    seed: ranges.Seed = 0
    """Seeds network initialisation and batch sampling; evaluation uses seed + 100."""
    steps: ranges.Steps = 1_000_000
    """Gradient steps."""
    batch_size: ranges.BatchSize | None = None
    """Mini-batch size N; unset: the algorithm's (256 unless its paper says otherwise)."""
    eval_interval: ranges.Steps = 5000
    """Evaluate every this many gradient steps."""
    eval_episodes: ranges.Positive = 10
    """Episodes per evaluation."""
    eval_schedule: Literal["every", "thin"] = "every"
    """every: evaluate every eval_interval steps; thin: every 10 x eval_interval steps, and every
    eval_interval in the last 10 x eval_interval (the final score's 10 evaluations as with every;
    at 1M steps, 5K apart: 29 evaluations rather than 200)."""
    log_interval: ranges.Steps = 1000
    """Steps per compiled chunk: log rows and progress updates come this often."""
    checkpoint_interval: ranges.Steps = 5000
    """Save a checkpoint every this many steps (a multiple of log_interval)."""
    env: str | None = None
    """Gymnasium id for evaluation; by default the one the dataset names."""
    reward_convention: Literal["minus-one", "raw", "iql-scale"] | None = None
    """What sparse goal rewards (AntMaze's 0/1) are trained as: minus-one (r - 1), raw (0/1) or
    iql-scale (x 1000 / return range); unset: the algorithm's published default (see
    docs/algorithms.md). MuJoCo data ignore it."""
    cache_dir: str | None = None
    """Where built-in datasets are made (default $EABC_CACHE_DIR or ~/.cache/eabc)."""

    def __post_init__(self):
        super().__post_init__()  # each setting of its declared type and range
        if self.algo not in ALGORITHMS:
            raise ValueError(
                f"algo: unknown algorithm {self.algo!r}; choose one of {', '.join(ALGORITHMS)}"
            )
        if self.batch_size is None:  # set here, so config.json records the size trained with
            object.__setattr__(self, "batch_size", get_algorithm(self.algo).batch_size)
        for name in ("eval_interval", "checkpoint_interval"):
            value = getattr(self, name)
            if value % self.log_interval:
                fits = -(-value // self.log_interval) * self.log_interval
                raise ValueError(
                    f"{name} must be a multiple of log_interval={self.log_interval}: "
                    f"e.g. {name} {fits}, or a log_interval that divides {value}"
                )
        if self.cache_dir is not None:  # checked now, not after minutes of making a dataset
            check_cache_dir(self.cache_dir, "cache_dir")
        if self.reward_convention is None:  # set here, so config.json records what was used
            object.__setattr__(self, "reward_convention", rewards.default(self.algo))
        rewards.check(self.reward_convention)

    def evaluates(self, step: int) -> bool:
        """Whether the run evaluates after ``step`` steps (always after its last): see
        ``eval_schedule``."""
        if step == self.steps:
            return True
        if step % self.eval_interval:
            return False
        window = FINAL_EVALUATIONS * self.eval_interval  # the final score's evaluations
        return self.eval_schedule == "every" or step % window == 0 or step > self.steps - window

    def evaluation_steps(self, after: int = 0) -> list[int]:
        """The steps after ``after`` at which the run evaluates."""
        first = after - after % self.eval_interval + self.eval_interval
        steps = range(first, self.steps + 1, self.eval_interval)
        return [s for s in steps if self.evaluates(s)] + (
            [self.steps] if self.steps % self.eval_interval and self.steps > after else []
        )


def check_cache_dir(path: str | Path, what: str) -> None:
    """``ValueError`` naming ``what`` when ``path`` cannot become a directory: it, or the nearest
    of its parents that exists, is a file."""
    where = paths.expand(path)
    while not where.exists() and where != where.parent:
        where = where.parent
    if where.exists() and not where.is_dir():
        inside = "" if where == paths.expand(path) else f" ({where} is a file)"
        raise ValueError(
            f"{what} {path} is not a directory{inside}: give a directory for the datasets and "
            "compiled programs (it is made if missing), or leave it unset for ~/.cache/eabc"
        )


def memory_needed(
    config: TrainConfig, agent_config: Any, obs_dim: int, act_dim: int, size: int
) -> list[tuple[str, str, str, float]]:
    """What a run keeps in memory while it trains, by the flag that sizes it (at least this
    much; XLA's temporaries come on top): the dataset on the device, one batch with the
    activations of its networks' layers, and the agent's state (networks and optimisers)."""
    algorithm = get_algorithm(config.algo)
    row = 4 * (2 * obs_dim + act_dim * (2 if algorithm.next_actions else 1) + 2)
    networks = 1 + getattr(agent_config, "num_critics", 1)  # the actor and each critic
    hidden = sum(getattr(agent_config, "hidden_dims", ()) or ())
    shapes = jax.eval_shape(
        lambda key: algorithm.init(key, obs_dim, act_dim, agent_config), jax.random.PRNGKey(0)
    )
    state = sum(leaf.size * leaf.dtype.itemsize for leaf in jax.tree.leaves(shapes))
    return [
        ("--batch-size", str(config.batch_size), "a batch with its activations",
         config.batch_size * (row + 4 * hidden * networks)),
        ("--dataset", config.dataset, f"the data ({size:,} transitions)", size * row),
        ("--set hidden_dims/num_critics", "", f"{config.algo}'s networks and optimisers", state),
    ]  # fmt: skip


def device_memory() -> int | None:
    """Bytes free on the accelerator JAX trains on; None on the CPU (the machine's memory)."""
    device = jax.local_devices()[0]
    if device.platform == "cpu":
        return None
    stats = device.memory_stats() or {}
    if "bytes_limit" not in stats:
        return None
    return stats["bytes_limit"] - stats.get("bytes_in_use", 0)


def check_memory(
    config: TrainConfig, agent_config: Any, obs_dim: int, act_dim: int, size: int
) -> None:
    """Refuse, before a run directory is written, a run whose batch, data and networks
    (:func:`memory_needed`) would not fit in the memory free where it trains, naming the flag of
    the largest part (``--batch-size``, ``--dataset``) in one line."""
    ranges.check_memory(
        memory_needed(config, agent_config, obs_dim, act_dim, size), device_memory()
    )


def check_evaluation_env(config: TrainConfig, dataset: Dataset | None = None) -> None:
    """Refuse, before any data is made or any training, an evaluation environment (``--env``)
    that cannot be made or cannot have produced the data: the data's own spaces when ``dataset``
    is loaded, else (a built-in dataset, perhaps still to be made) its task's environment's."""
    if dataset is not None:
        env_id = config.env or dataset.env_id
        if env_id:
            check_spaces(make_env(env_id), dataset)
        return
    info = tasks.env_info(tasks.parse_task(config.dataset))
    if not config.env or info is None or sources.kind(config.dataset) != "builtin":
        return
    env, own = make_env(config.env), make_env(info.env_id)
    for space in ("observation", "action"):
        theirs, ours = (getattr(e, f"{space}_space").shape for e in (env, own))
        if theirs != ours:
            raise DatasetError(
                f"--env {config.env}: its {space}s have shape {theirs}, but {config.dataset}'s "
                f"({info.env_id}) have {ours}; leave --env out to evaluate in {info.env_id}"
            )


def resolve_agent_config(
    algo: str, dataset_name: str, overrides: dict[str, Any], steps: int | None = None
) -> Any:
    """The algorithm's preset with the user's overrides, then the settings that depend on the data
    and the run's length resolved by the algorithm itself (its contract's ``resolve``: its paper's
    defaults per dataset, schedules over ``steps``)."""
    algorithm = get_algorithm(algo)
    overrides = {k: v for k, v in overrides.items() if v is not None}
    fields = algorithm.settings()
    unknown = set(overrides) - fields
    if unknown:
        raise ValueError(f"{algo} has no setting(s) {sorted(unknown)}; it has {sorted(fields)}")
    config = ranges.validated(algorithm.preset, overrides, f"{algo} setting ")
    return algorithm.resolved(config, dataset_name, steps, set(overrides))
