"""Starting and resuming a training run: the :class:`Run` that the loop trains.

:func:`start` makes a run directory (config.json with the dataset's fingerprint, the initial agent,
and the algorithm's pretraining if it has one) and returns a :class:`Run`; :func:`resume` rebuilds
the same :class:`Run` from the directory's checkpoint (from step 0 if it died before its first),
so that the loop (:mod:`eabc.training.trainer`) continues bit for bit, and extends it to more
steps when asked. What the run trains with comes from :mod:`eabc.training.config`; what its
directory holds, and what may not be thrown away, from :mod:`eabc.training.directory`.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
from pathlib import Path
from typing import Any

import jax
import numpy as np

from eabc import networks, paths, programs, ranges
from eabc.agents import Algorithm, get_algorithm
from eabc.data import sources
from eabc.data.dataset import Dataset, DatasetError, Normalizer, reference_scores_problem
from eabc.data.sources import load_dataset
from eabc.evaluation import Evaluator, check_spaces
from eabc.training import checkpoint, directory, identity, logger, rewards, run_config
from eabc.training.checkpoint import CONFIG
from eabc.training.chunks import device_data
from eabc.training.config import (
    TrainConfig,
    check_cache_dir,
    check_evaluation_env,
    check_memory,
    resolve_agent_config,
)
from eabc.training.lock import RunLock
from eabc.training.logger import CURVE, LOG


@dataclasses.dataclass
class Run:
    """Everything one training run needs; made by :func:`start` or :func:`resume`."""

    run_dir: Path
    config: TrainConfig
    algorithm: Algorithm
    agent_config: Any
    dataset: Dataset
    normalizer: Normalizer
    evaluator: Evaluator
    max_action: float
    state: dict[str, Any]
    """``agent`` (the algorithm's state), ``key``, ``evaluations`` (history), ``elapsed`` seconds
    and ``normalizer``: everything a checkpoint holds."""
    lock: RunLock | None = None
    """The run directory's writer lock, held from start/resume until training ends."""
    diverged_step: int | None = None
    """The step whose losses or Q values were NaN/inf; training stopped there."""
    identity: dict[str, Any] | None = None
    """Which run this is (:func:`eabc.training.identity.of_config`), recorded in every checkpoint."""

    @property
    def step(self) -> int:
        return int(self.state["agent"].step)


def start(
    config: TrainConfig,
    run_dir: str | Path,
    agent_overrides: dict[str, Any] | None = None,
    dataset: Dataset | None = None,
) -> Run:
    """Set up a new run in ``run_dir`` (which must not hold a run already); the run holds the
    directory's writer lock until :func:`train` ends."""
    run_dir = Path(run_dir)
    directory.refuse_existing(run_dir)
    config = _absolute_paths(config)
    if config.cache_dir is None and os.environ.get("EABC_CACHE_DIR"):
        check_cache_dir(os.environ["EABC_CACHE_DIR"], "$EABC_CACHE_DIR")
    if dataset is None:
        check_evaluation_env(config)  # before a built-in dataset is made (minutes)
    dataset = dataset if dataset is not None else load_dataset(config.dataset, config.cache_dir)
    agent_config = resolve_agent_config(
        config.algo, dataset.name, agent_overrides or {}, config.steps
    )
    check_memory(config, agent_config, dataset.obs_dim, dataset.act_dim, dataset.size)
    run = _build(run_dir, config, agent_config, dataset, state=None)
    run.lock = RunLock(run_dir).acquire()
    try:
        directory.refuse_existing(run_dir)  # again, now that no other writer can be starting here
    except BaseException:
        run.lock.release()
        raise
    directory.remove_temporaries(run_dir)
    saved = {
        "run_id": identity.new_run_id(),
        "train": dataclasses.asdict(config),
        "agent": ranges.flat(agent_config),  # a group's settings by their own names
        "dataset": {
            "name": dataset.name,
            "size": dataset.size,
            "fingerprint": dataset.fingerprint(),
            "env_id": run.evaluator.env_id,
            "ref_min_score": dataset.ref_min_score,
            "ref_max_score": dataset.ref_max_score,
        },
        "max_action": run.max_action,
    }
    checkpoint.save_json(run_dir / CONFIG, saved)
    run.identity = identity.of_config(run_config.read(run_dir))  # as every reader will see it
    if run.algorithm.pretrain is not None:
        try:
            _pretrain(run)
        except BaseException:
            run.lock.release()
            raise
    return run


@dataclasses.dataclass
class _FileProgress:
    """:class:`~eabc.agents.contract.PretrainProgress` in a file of the run directory."""

    path: Path

    def load(self) -> dict[str, Any] | None:
        if not self.path.exists():
            return None
        try:
            return checkpoint.read_tree(self.path)
        except checkpoint.CheckpointError as error:
            print(f"{error}: pretraining from the start", file=sys.stderr, flush=True)
            return None

    def save(self, tree: Any) -> None:
        checkpoint.write_tree(self.path, tree)


def _keys(seed: int) -> tuple[jax.Array, jax.Array]:
    """A run's initialisation key (the agent's, and folded with 1 its pretraining's) and the
    training loop's key."""
    init_key, loop_key = jax.random.split(jax.random.PRNGKey(seed))
    return init_key, loop_key


def _pretrain(run: Run) -> None:
    """The algorithm's one-off pretraining of a run at step 0 (continuing what a killed run saved
    of it), then the run's first checkpoint: a run killed after it does not pretrain again."""
    progress = _FileProgress(run.run_dir / directory.PRETRAIN_PROGRESS)
    algorithm = run.algorithm
    data = device_data(
        prepared(algorithm, run.dataset, run.config.reward_convention),
        run.normalizer,
        algorithm.next_actions,
    )
    init_key, _ = _keys(run.config.seed)
    run.state["agent"] = run.algorithm.pretrain(
        run.state["agent"], data, jax.random.fold_in(init_key, 1), run.agent_config,
        run.normalizer, progress,
    )  # fmt: skip
    checkpoint.save(run.run_dir, run.state, run.algorithm.state_layout, run.identity)
    progress.path.unlink(missing_ok=True)


def _absolute_paths(config: TrainConfig) -> TrainConfig:
    """Dataset files and the cache directory as absolute paths, so that config.json works from
    any directory (``eabc evaluate``, ``--resume`` and sweeps elsewhere)."""
    if sources.kind(config.dataset) == "file":
        # Absolute, not resolved: a link stays the path the user gave (and errors name it).
        config = dataclasses.replace(config, dataset=os.path.abspath(paths.expand(config.dataset)))
    if config.cache_dir is not None:
        config = dataclasses.replace(config, cache_dir=str(Path(config.cache_dir).resolve()))
    return config


def resume(
    run_dir: str | Path,
    dataset: Dataset | None = None,
    lock: bool = True,
    steps: int | None = None,
    restart: bool = False,
) -> Run:
    """Reopen a run from its directory and latest checkpoint (from step 0 if it died before its
    first one). With ``lock`` (for training) the run holds the directory's writer lock until
    :func:`train` ends; without it (to evaluate) nothing in the directory is written. ``steps``
    extends the run to that many steps (config.json records the new length).

    A run whose checkpoint is missing although it got past its first one (finished, or its log
    goes further) is refused (:class:`~eabc.training.directory.ProgressLostError`) unless ``restart``, which trains it
    again from step 0, replacing its log.csv and summary.json. Resumed for training, a run's
    log.csv that lacks what its checkpoint holds (deleted, cut short) is rebuilt from the
    checkpoint's evaluation history, and temporary files a killed writer left are removed."""
    run_dir = Path(run_dir)
    held = RunLock(run_dir).acquire() if lock else None
    try:
        if lock:
            directory.remove_temporaries(run_dir)
        run = _resume(run_dir, dataset, write=lock, restart=restart)
        if steps is not None and steps != run.config.steps:
            run = _extend(run, steps)
    except BaseException:
        if held is not None:
            held.release()
        raise
    run.lock = held
    return run


def _extend(run: Run, steps: int) -> Run:
    if steps < run.step:
        raise ValueError(
            f"{run.run_dir} has trained {run.step} steps, more than the {steps} asked; use "
            "another run directory for a shorter run"
        )
    saved = run_config.read(run.run_dir)
    saved["train"]["steps"] = steps
    checkpoint.save_json(run.run_dir / CONFIG, saved)
    return dataclasses.replace(run, config=dataclasses.replace(run.config, steps=steps))


def _resume(run_dir: Path, dataset: Dataset | None, write: bool, restart: bool = False) -> Run:
    saved = run_config.read(run_dir)  # checked by its schema before anything uses it
    # a run from before the setting trained on r - 1, whatever its algorithm's default now
    config = TrainConfig(**{"reward_convention": rewards.LEGACY, **saved["train"]})
    has_checkpoint = (run_dir / checkpoint.CHECKPOINT).exists()
    if has_checkpoint and restart:
        raise ValueError(
            f"--restart trains a run again only when its checkpoint is missing; {run_dir} has "
            f"one: resume without --restart to continue it"
        )
    lost = (
        None
        if has_checkpoint
        else directory.lost_progress(run_dir, config.steps, config.checkpoint_interval)
    )
    if lost and not write:
        raise FileNotFoundError(f"{lost}: there is nothing to read")
    if lost and not restart:
        raise directory.ProgressLostError(
            f"{lost}; resuming would train it again from step 0 and replace its {LOG} and "
            f"{directory.SUMMARY}: restore the checkpoint, train in a new --run-dir, or pass --restart to "
            "train this run again from step 0"
        )
    algorithm = get_algorithm(config.algo)
    agent_config = directory.agent_config_from_json(algorithm, saved["agent"])
    dataset = dataset if dataset is not None else load_dataset(config.dataset, config.cache_dir)
    recorded = saved.get("dataset", {})
    if recorded.get("size") is not None and dataset.size != recorded["size"]:
        raise DatasetError(
            f"{config.dataset} now has {dataset.size} transitions, but the run was trained on "
            f"{recorded['size']}; resume needs the same data"
        )
    expected = recorded.get("fingerprint")  # absent in runs from before the check
    if expected is not None and dataset.fingerprint() != expected:
        raise DatasetError(
            f"{config.dataset} is not the data {run_dir} was trained on (its content fingerprint "
            f"changed from {expected[:12]}... to {dataset.fingerprint()[:12]}...); resume needs "
            "the same data: restore that file, or train a new run"
        )
    if not has_checkpoint:
        if not write:
            raise FileNotFoundError(f"no checkpoint in {run_dir}; the run has not saved one yet")
        run = _build(run_dir, config, agent_config, dataset, state=None)
        # Killed before its first checkpoint (or --restart): nothing to continue from.
        for name in (LOG, directory.SUMMARY, CURVE):
            (run_dir / name).unlink(missing_ok=True)
        shutil.rmtree(run_dir / "tb", ignore_errors=True)
        run.identity = identity.of_run(run_dir, saved)
        if algorithm.pretrain is not None:
            _pretrain(run)
        return run
    run = _build(run_dir, config, agent_config, dataset, state="checkpoint", saved=saved)
    if write:
        run.identity = identity.of_run(run_dir, saved)
        problem = logger.log_problem(
            run_dir / LOG, run.state["evaluations"], run.step, config.steps
        )
        if problem:
            logger.rebuild_log(run_dir / LOG, run.state["evaluations"], run.step)
            print(
                f"warning: {problem}: rebuilt its evaluations up to step {run.step} from "
                f"{checkpoint.CHECKPOINT} (the training metrics of lost rows are gone)",
                file=sys.stderr,
                flush=True,
            )
    return run


def _build(run_dir, config, agent_config, dataset, state, saved=None) -> Run:
    env_id = config.env or dataset.env_id
    if not env_id:
        raise DatasetError(
            f"{dataset.name} does not say which environment it came from; pass --env GYM_ID"
        )
    _check_reference_scores(config, dataset)
    evaluator = Evaluator(
        env_id,
        config.seed + 100,
        config.eval_episodes,
        dataset.ref_min_score,
        dataset.ref_max_score,
    )
    check_spaces(evaluator.env, dataset)
    max_action = float(evaluator.env.action_space.high[0])
    if saved is not None:  # what the export and load_policy will scale the actions by
        run_config.check_max_action(saved, run_dir / CONFIG, evaluator.env)
    algorithm = get_algorithm(config.algo)
    normalizer = (
        Normalizer.fit(dataset.observations)
        if algorithm.normalize_observations
        else Normalizer.identity(dataset.obs_dim)
    )
    init_key, loop_key = _keys(config.seed)
    fresh = {
        "agent": init_agent(
            algorithm.init, init_key, dataset.obs_dim, dataset.act_dim, agent_config
        ),
        "key": loop_key,
        "evaluations": {},
        "elapsed": 0.0,
        "normalizer": {"mean": normalizer.mean, "std": normalizer.std},
    }
    if state == "checkpoint":
        what = f"this {config.algo} run ({directory.settings_text(algorithm, agent_config)}, {dataset.name})"
        template = {**fresh, "evaluations": None}
        raw = identity.checked(
            checkpoint.load_raw(run_dir, infinite=algorithm.infinite_state), run_dir, saved
        )
        stored = checkpoint.restore(
            raw, run_dir, template, what, config.algo, algorithm.state_layout
        )
        fresh = {**stored, "evaluations": stored["evaluations"] or {}}
        normalizer = Normalizer(**{k: np.asarray(v) for k, v in stored["normalizer"].items()})
    return Run(
        run_dir, config, algorithm, agent_config, dataset, normalizer, evaluator, max_action, fresh
    )


def _check_reference_scores(config: TrainConfig, dataset: Dataset) -> None:
    """Refuse reference scores that make the normalised score undefined, before any training
    (found at the first evaluation, they cost the whole first interval and left a broken run)."""
    low, high = dataset.ref_min_score, dataset.ref_max_score
    if (low is None) != (high is None):
        given, lacking = ("ref_min_score", "ref_max_score")
        if low is None:
            given, lacking = lacking, given
        raise DatasetError(
            f"{config.dataset}: it has {given} but no {lacking}; the normalised score needs both "
            "(a random and an expert policy's return): add the other, or remove both to report "
            "returns only"
        )
    problem = reference_scores_problem(low, high)  # a Dataset refuses them too: any source
    if problem:
        raise DatasetError(f"{config.dataset}: {problem}")


def prepared(algorithm: Algorithm, dataset: Dataset, convention: str | None = None) -> Dataset:
    """The data as the algorithm trains on it; the run keeps the dataset as loaded.

    A dataset with sparse goal rewards (a ``reward_offset``: AntMaze) is trained on by the run's
    ``reward_convention`` (:mod:`eabc.training.rewards`; None: the algorithm's default) in place
    of the algorithm's reward preprocessing; other data by the algorithm's preprocessing."""
    return rewards.apply(algorithm, dataset, convention)


# One compiled program rather than dozens of eagerly compiled operations (and cacheable on disk),
# built with the options of programs that run once (networks.INIT_COMPILE_OPTIONS).
init_agent = programs.Program(
    lambda init, *args: init(*args), networks.INIT_COMPILE_OPTIONS, static_argnums=(0, 2, 3, 4)
)
