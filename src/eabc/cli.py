"""The ``eabc`` command line, generated from typed dataclasses (``eabc --help``, ``eabc train --help``)."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Annotated, Literal

import tyro

from eabc.training.online import SACTrainConfig
from eabc.training.trainer import TrainConfig


@dataclasses.dataclass(frozen=True)
class AgentOverrides:
    """Algorithm settings to change from the preset chosen by --algo (unset: the preset's)."""

    confidence_level: float | None = None
    """EABC's p in [0, 1]; by default the paper's Table 3 value for the dataset."""
    num_critics: int | None = None
    """K, critic ensemble size (eabc: 10, td3bc/td3: 2)."""
    pessimism: Literal["mean-std", "min", "min2"] | None = None
    """How the ensemble is made pessimistic (eabc: mean-std, td3bc/td3: min)."""
    alpha: float | None = None
    """TD3+BC's alpha in lambda = alpha / mean|Q| (2.5)."""


@dataclasses.dataclass(frozen=True)
class Train:
    """Train an offline RL agent with the paper's protocol: progress bar, logs, checkpoints, curve."""

    config: Annotated[TrainConfig, tyro.conf.OmitArgPrefixes]
    agent: Annotated[AgentOverrides, tyro.conf.OmitArgPrefixes]
    run_dir: str | None = None
    """Where the run's config, checkpoint, log.csv, TensorBoard events and curve.png go
    (default runs/DATASET_ALGO_seedS)."""
    resume: str | None = None
    """Continue the run in this directory from its last checkpoint (other options are ignored)."""
    progress: bool = True
    """Show a progress bar."""


@dataclasses.dataclass(frozen=True)
class Evaluate:
    """Re-score a run's latest checkpoint in its evaluation environment."""

    run_dir: tyro.conf.Positional[str]
    episodes: int = 10
    """Episodes to run."""
    seed: int | None = None
    """Environment seed (default: the run's seed + 100, as in training)."""


@dataclasses.dataclass(frozen=True)
class DataMake:
    """Make a built-in D4RL-style dataset (e.g. hopper-random) in the cache directory."""

    name: tyro.conf.Positional[str]
    seed: int = 0
    """Seed of the environment and the actions; the same seed gives the same file."""
    size: int | None = None
    """Transitions (default D4RL's size)."""
    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""
    force: bool = False
    """Remake the dataset even if it is cached."""


@dataclasses.dataclass(frozen=True)
class DataInfo:
    """Describe a dataset: size, episodes, returns and normalised score."""

    name: tyro.conf.Positional[str]
    """A built-in name, a file path or minari:ID."""
    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""


@dataclasses.dataclass(frozen=True)
class DataList:
    """List the built-in datasets and which of them are in the cache."""

    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""


@dataclasses.dataclass(frozen=True)
class Sac:
    """Train online SAC in a Gymnasium environment (the behaviour policies of the built-in datasets).

    Logs training and evaluation returns to log.csv, keeps the actor every --snapshot-interval
    steps under snapshots/, and checkpoints networks, optimisers and the replay buffer so that
    --resume continues a killed run.
    """

    config: Annotated[SACTrainConfig, tyro.conf.OmitArgPrefixes]
    run_dir: str | None = None
    """Where the run goes (default runs/sac_ENV_seedS)."""
    resume: str | None = None
    """Continue the run in this directory from its last checkpoint (other options are ignored)."""
    progress: bool = True
    """Show a progress bar."""


def run_sac(cmd: Sac) -> dict:
    from eabc.training import online  # noqa: PLC0415

    if cmd.resume:
        run = online.resume_sac(cmd.resume)
    else:
        config = cmd.config
        run = online.start_sac(config, cmd.run_dir or f"runs/sac_{config.env}_seed{config.seed}")
    print(f"run directory: {run.run_dir}", file=sys.stderr)
    summary = online.train_sac(run, progress=cmd.progress)
    print(json.dumps(summary, indent=2))
    return summary


def run_train(cmd: Train) -> dict:
    from eabc.training import trainer  # noqa: PLC0415

    if cmd.resume:
        run = trainer.resume(cmd.resume)
    else:
        config = cmd.config
        run_dir = cmd.run_dir or f"runs/{Path(config.dataset).stem}_{config.algo}_seed{config.seed}"
        run = trainer.start(config, run_dir, dataclasses.asdict(cmd.agent))
    print(f"run directory: {run.run_dir}", file=sys.stderr)
    summary = trainer.train(run, progress=cmd.progress)
    print(json.dumps(summary, indent=2))
    return summary


def run_evaluate(cmd: Evaluate) -> dict:
    from eabc.training import trainer  # noqa: PLC0415

    run = trainer.resume(cmd.run_dir)
    run.evaluator.episodes = cmd.episodes
    if cmd.seed is not None:
        run.evaluator.seed = cmd.seed
    result = {"run_dir": cmd.run_dir, "step": run.step, **trainer.evaluate(run)}
    print(json.dumps(result, indent=2))
    return result


@dataclasses.dataclass(frozen=True)
class DataExport:
    """Export a dataset to the local Minari path, for d3rlpy, CORL and other Minari readers."""

    name: tyro.conf.Positional[str]
    """A built-in name (made first if needed), a file path or minari:ID."""
    minari: bool = True
    """Export as a Minari dataset (the only format for now)."""
    dataset_id: str | None = None
    """The Minari id (default eabc/ENV/KIND-v0, e.g. eabc/hopper/medium-v0)."""
    force: bool = False
    """Replace an existing Minari dataset of that id."""
    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""


def run_data(cmd: DataMake | DataInfo | DataList | DataExport) -> None:
    from eabc.data import generate, loaders  # noqa: PLC0415

    if isinstance(cmd, DataMake):
        path = generate.dataset_path(cmd.name, cmd.cache_dir)
        if path.exists() and not cmd.force:
            print(f"{path} (cached; --force to remake)")
            return
        print(generate.make(cmd.name, path, seed=cmd.seed, size=cmd.size))
    elif isinstance(cmd, DataList):
        header = f"{'dataset':26s} {'transitions':>11s} {'episodes':>8s} {'return':>17s} {'score':>6s} {'D4RL':>5s}  file"
        print(header)
        for name in generate.builtin_names():
            path = generate.dataset_path(name, cmd.cache_dir)
            level = generate.d4rl_level(name)
            if not path.exists():
                print(
                    f"{name:26s} {'-':>11s} {'-':>8s} {'-':>17s} {'-':>6s} {level:5.0f}  (not made)"
                )
                continue
            info = generate.describe(path)
            spread = f"{info['return_mean']:.0f} +- {info['return_std']:.0f}"
            print(
                f"{name:26s} {info['transitions']:11d} {info['episodes']:8d} {spread:>17s} "
                f"{info['normalized_return']:6.1f} {level:5.0f}  {path}"
            )
    elif isinstance(cmd, DataExport):
        dataset = loaders.load_dataset(cmd.name, cmd.cache_dir)
        dataset_id = cmd.dataset_id or loaders.minari_id(dataset.name)
        print(loaders.export_minari(dataset, dataset_id, overwrite=cmd.force))
    else:
        dataset = loaders.load_dataset(cmd.name, cmd.cache_dir)
        print(json.dumps(generate.describe_dataset(dataset), indent=2))


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    commands: dict[str, type] = {
        "train": Train,
        "evaluate": Evaluate,
        "sac": Sac,
        "data": DataList,
    }
    description = "EABC: ensemble-based offline RL with adaptive behaviour cloning."
    if argv[:1] == ["data"]:  # a second level: eabc data {make,list,info}
        commands = {"make": DataMake, "list": DataList, "info": DataInfo, "export": DataExport}
        argv = argv[1:]
        description = "Datasets: make the built-in ones, list the cache, describe any dataset, export to Minari."
    try:
        cmd = tyro.extras.subcommand_cli_from_dict(commands, args=argv, description=description)
    except ValueError as error:  # invalid settings caught in a dataclass __post_init__
        sys.exit(f"error: {error}")
    try:
        if isinstance(cmd, Train):
            run_train(cmd)
        elif isinstance(cmd, Evaluate):
            run_evaluate(cmd)
        elif isinstance(cmd, Sac):
            run_sac(cmd)
        else:
            run_data(cmd)
    except (ValueError, FileNotFoundError, FileExistsError) as error:
        sys.exit(f"error: {error}")


if __name__ == "__main__":
    main()
