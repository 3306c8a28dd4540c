"""``eabc train``, ``eabc evaluate``, ``eabc sac`` and ``eabc export-policy``."""

from __future__ import annotations

import dataclasses
import functools
import json
import sys
from pathlib import Path
from typing import Annotated

import tyro

from eabc import ranges
from eabc.cli.options import (
    AgentOverrides,
    Interrupted,
    SACTrainOptions,
    TrainOptions,
    parse_settings,
)
from eabc.ranges import NonNegative, Positive, PositiveNumber, Seed


@dataclasses.dataclass(frozen=True)
class Train:
    """Train an offline RL agent with the paper's protocol: progress bar, logs, checkpoints, curve."""

    config: Annotated[TrainOptions, tyro.conf.OmitArgPrefixes]
    agent: Annotated[AgentOverrides, tyro.conf.OmitArgPrefixes]
    set: tuple[str, ...] = ()
    """Any other setting of the algorithm as KEY=VALUE, e.g. eta=0.5, expectile=0.8,
    hidden_dims=512,512 (`eabc train --algo ALGO --dry-run` lists an algorithm's settings with
    their values, as config.json of a run does)."""
    run_dir: str | None = None
    """Where the run's config, checkpoint, log.csv, TensorBoard events and curve.png go
    (default runs/DATASET_ALGO_seedS)."""
    resume: str | None = None
    """Continue the run in this directory from its last checkpoint, with the settings it was
    started with (other options than --restart, --no-progress and --dry-run are refused: they
    would be ignored). A finished run is left as it is; a run whose checkpoint is missing although
    its log.csv or summary.json shows it got past its first checkpoint is refused (see
    --restart)."""
    restart: bool = False
    """With --resume, for a run whose checkpoint is missing: train it again from step 0, deleting
    its log.csv and summary.json (without this flag such a run is refused, never retrained)."""
    progress: bool = True
    """Show a progress bar."""
    dry_run: bool = False
    """Check every option, the dataset and the algorithm's settings, print the plan (dataset,
    settings, schedule, estimated time) and stop: nothing is made, trained or written."""
    eval_workers: NonNegative = 0
    """Evaluate in this many processes while training goes on (0: in the training process,
    between chunks). The same scores and files either way; worth it where evaluation is a large
    part of the time (on a GPU), not on a CPU whose cores train."""


@dataclasses.dataclass(frozen=True)
class Evaluate:
    """Re-score a run's latest checkpoint in its evaluation environment."""

    run_dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    episodes: Positive = 10
    """Episodes to run."""
    seed: Seed | None = None
    """Environment seed (default: the run's seed + 100, as in training)."""


@dataclasses.dataclass(frozen=True)
class Sac:
    """Train online SAC in a Gymnasium environment (the behaviour policies of the built-in datasets).

    Logs training and evaluation returns to log.csv, keeps the actor every --snapshot-interval
    steps under snapshots/, and checkpoints networks, optimisers and the replay buffer so that
    --resume continues a killed run.
    """

    config: Annotated[SACTrainOptions, tyro.conf.OmitArgPrefixes]
    run_dir: str | None = None
    """Where the run goes (default runs/sac_ENV_seedS)."""
    resume: str | None = None
    """Continue the run in this directory from its last checkpoint, with its own settings (with
    other options than --no-progress it is refused: they would be ignored)."""
    alpha: PositiveNumber | None = None
    """Fixed entropy temperature instead of automatic tuning (default: tuning toward -dim(A);
    walker2d: fixed 0.2, see README)."""
    lr: PositiveNumber | None = None
    """Adam learning rate of actor and critics (default 3e-4; walker2d 1e-3)."""
    progress: bool = True
    """Show a progress bar."""


def sac_agent_config(cmd: Sac):
    """The environment's online SAC preset with the command's overrides."""
    from eabc.agents import sac  # noqa: PLC0415

    agent = sac.online_preset(cmd.config.env)
    if cmd.alpha is not None:
        if cmd.alpha <= 0:
            raise ValueError(f"--alpha must be positive, got {cmd.alpha}")
        agent = dataclasses.replace(agent, init_alpha=cmd.alpha, autotune=False)
    if cmd.lr is not None:
        agent = dataclasses.replace(agent, actor_lr=cmd.lr, critic_lr=cmd.lr)
    return agent


def _start_or_resume_then_train(cmd, resume, start, train, command: str) -> dict:
    """``--resume DIR`` or a new run, trained to its end; the summary printed as JSON. Ctrl-C
    while it trains ends in one line that says how to continue (the checkpoints are written
    atomically, so the resumed run ends as an uninterrupted one would)."""
    run = resume(cmd.resume) if cmd.resume else start()
    print(f"run directory: {run.run_dir}", file=sys.stderr)
    try:
        summary = train(run, progress=cmd.progress)
    except KeyboardInterrupt:
        step = run.step if hasattr(run, "step") else int(run.state["step"])
        raise Interrupted(
            f"interrupted at step {step}; resume with: eabc {command} --resume {run.run_dir} "
            "(it continues from its last checkpoint)"
        ) from None
    print(json.dumps(summary, indent=2))
    return summary


def run_sac(cmd: Sac) -> dict:
    from eabc.training import online  # noqa: PLC0415

    def start():
        config = cmd.config
        run_dir = cmd.run_dir or f"runs/sac_{config.env}_seed{config.seed}"
        return online.start_sac(config, run_dir, sac_agent_config(cmd))

    return _start_or_resume_then_train(cmd, online.resume_sac, start, online.train_sac, "sac")


@dataclasses.dataclass(frozen=True)
class ExportPolicy:
    """Write a run's policy (the latest checkpoint's actor, observation normaliser inside) as ONNX,
    to run without Python or JAX (onnxruntime, ONNX Runtime Web, TensorRT, ...)."""

    run_dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    onnx: str
    """The ONNX file to write (input observation [batch, obs_dim], output action)."""


def run_train(cmd: Train) -> dict:
    from eabc.training import lifecycle, trainer  # noqa: PLC0415

    if cmd.dry_run:
        plan = train_plan(cmd)
        print("\n".join(f"{key:<12} {value}" for key, value in plan.items()))
        return plan

    if cmd.restart and not cmd.resume:
        raise ValueError("--restart goes with --resume RUN_DIR (a new run starts from step 0)")

    def start():
        overrides = dataclasses.asdict(cmd.agent) | parse_settings(cmd.set)
        return lifecycle.start(cmd.config, default_run_dir(cmd), overrides)

    def resume(run_dir):
        run = lifecycle.resume(run_dir, restart=cmd.restart)
        if run.step >= run.config.steps:
            print(f"{run_dir} is finished ({run.step} steps): nothing to train", file=sys.stderr)
        return run

    train = functools.partial(trainer.train, eval_workers=cmd.eval_workers)
    summary = _start_or_resume_then_train(cmd, resume, start, train, "train")
    if summary.get("diverged_step") is not None:
        raise RuntimeError(f"training stopped at step {summary['diverged_step']} on NaN/inf")
    return summary


def default_run_dir(cmd: Train) -> str:
    config = cmd.config
    return cmd.run_dir or f"runs/{Path(config.dataset).stem}_{config.algo}_seed{config.seed}"


def train_plan(cmd: Train) -> dict[str, str]:
    """What ``cmd`` would do, every input checked as training checks it, nothing made or written:
    the dataset (loaded and validated if it is a file or already made), the algorithm's resolved
    settings, the schedule and an estimate of the time."""
    from eabc import timing  # noqa: PLC0415
    from eabc.agents import get_algorithm  # noqa: PLC0415
    from eabc.data import generate, sources  # noqa: PLC0415
    from eabc.evaluation import space_sizes  # noqa: PLC0415
    from eabc.experiments.planning import estimate_seconds  # noqa: PLC0415
    from eabc.experiments.spec import TRAIN_FIELDS, RunSpec  # noqa: PLC0415
    from eabc.training import lifecycle, trainer  # noqa: PLC0415
    from eabc.training.checkpoint import CONFIG  # noqa: PLC0415
    from eabc.training.config import (  # noqa: PLC0415
        check_evaluation_env,
        check_memory,
        resolve_agent_config,
    )

    if cmd.resume:
        run = lifecycle.resume(cmd.resume, lock=False)  # reads only
        config, dataset_name, agent_config = run.config, run.dataset.name, run.agent_config
        what = f"resume {cmd.resume} at step {run.step} of {config.steps}"
        data = f"{dataset_name} ({run.dataset.size:,} transitions), as the run recorded it"
        env_id, steps_done = run.evaluator.env_id, run.step
        overrides = {}
    else:
        config, run_dir = cmd.config, Path(default_run_dir(cmd))
        if (run_dir / CONFIG).exists():
            raise FileExistsError(
                f"{run_dir} already holds a run; continue it with `eabc train --resume {run_dir}`"
                " or choose another --run-dir"
            )
        what = f"a new run in {run_dir}"
        path = generate.dataset_path(config.dataset, config.cache_dir)
        if sources.kind(config.dataset) == "builtin" and not generate.is_current(
            path, config.dataset
        ):
            check_evaluation_env(config)  # --env against the task's shapes, as training will
            size = generate.default_size(config.dataset)
            dataset_name, env_id = config.dataset, None
            shape = size, *space_sizes(_task_env(config.dataset))[:2]
            took = generate.making_time(config.dataset)
            data = f"{config.dataset}: made first into {path} ({size:,} transitions, {took})"
        else:
            dataset = sources.load_dataset(config.dataset, config.cache_dir)
            check_evaluation_env(config, dataset)  # its spaces against the data's
            dataset_name, env_id = dataset.name, dataset.env_id
            data = f"{dataset.name} ({dataset.size:,} transitions) from {config.dataset}"
            shape = dataset.size, dataset.obs_dim, dataset.act_dim
        overrides = {
            k: v for k, v in dataclasses.asdict(cmd.agent).items() if v is not None
        } | parse_settings(cmd.set)
        agent_config = resolve_agent_config(config.algo, dataset_name, overrides, config.steps)
        size, obs_dim, act_dim = shape
        check_memory(config, agent_config, obs_dim, act_dim, size)  # as start() checks it
        env_id = config.env or env_id or _task_env(dataset_name)
        steps_done = 0
    spec = RunSpec(  # every train setting, so that the estimate checks the run's own config
        config.dataset, config.algo, config.seed, tuple(sorted(overrides.items())),
        tuple((f, getattr(config, f)) for f in sorted(TRAIN_FIELDS) if f != "cache_dir"),
    )  # fmt: skip
    seconds, speed = estimate_seconds(spec, steps_done), timing.REFERENCE
    if seconds > 10:  # long enough for this host's speed to matter: probe it
        speed = timing.host_speed(config.cache_dir)
        seconds = estimate_seconds(spec, steps_done, speed=speed)
    algorithm = get_algorithm(config.algo)  # its update alone, as eabc report measures it
    per_million = trainer.estimate_seconds(algorithm, agent_config, 1_000_000, 0, speed=speed)
    settings = ranges.flat(agent_config)
    return {
        "run": what,
        "dataset": data,
        "algorithm": f"{config.algo}: "
        + ", ".join(f"{k}={_short(v)}" for k, v in settings.items()),
        "evaluation": f"{env_id or 'the environment the data name (--env to set one)'}: "
        f"{config.eval_episodes} episodes every {config.eval_interval:,} steps "
        f"({_evaluations(config)}), seed {config.seed} + 100",
        "schedule": f"{config.steps:,} steps of batch {config.batch_size}, a log row every "
        f"{config.log_interval:,}, a checkpoint every {config.checkpoint_interval:,}",
        "estimate": f"about {timing.duration(seconds)} of training, "
        f"{timing.duration(per_million)} per 1M gradient steps, {speed.basis()}",
    }


def _evaluations(config) -> str:
    """``200 evaluations``, or with the thin schedule ``29 evaluations: every 50,000 steps, every
    5,000 in the last 50,000``."""
    count = f"{len(config.evaluation_steps())} evaluations"
    if config.eval_schedule == "every":
        return count
    window = 10 * config.eval_interval
    return f"{count}: every {window:,} steps, every {config.eval_interval:,} in the last {window:,}"


def _task_env(dataset_name: str) -> str | None:
    from eabc.data import tasks  # noqa: PLC0415

    info = tasks.env_info(tasks.parse_task(dataset_name))
    return info.env_id if info else None


def _short(value) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list | tuple):
        return ",".join(_short(v) for v in value)
    return str(value)


def run_evaluate(cmd: Evaluate) -> dict:
    from eabc.training import lifecycle, trainer  # noqa: PLC0415

    run = lifecycle.resume(cmd.run_dir, lock=False)  # reads only: a running run can be scored
    run.evaluator.episodes = cmd.episodes
    if cmd.seed is not None:
        run.evaluator.seed = cmd.seed
    result = {"run_dir": cmd.run_dir, "step": run.step, **trainer.evaluate(run)}
    print(json.dumps(result, indent=2))
    return result
