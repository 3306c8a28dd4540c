"""``eabc train``, ``eabc evaluate``, ``eabc sac`` and ``eabc export-policy``."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Annotated

import tyro

from eabc.cli.options import AgentOverrides, SACTrainOptions, TrainOptions, parse_settings


@dataclasses.dataclass(frozen=True)
class Train:
    """Train an offline RL agent with the paper's protocol: progress bar, logs, checkpoints, curve."""

    config: Annotated[TrainOptions, tyro.conf.OmitArgPrefixes]
    agent: Annotated[AgentOverrides, tyro.conf.OmitArgPrefixes]
    set: tuple[str, ...] = ()
    """Any other setting of the algorithm as KEY=VALUE, e.g. eta=0.5, expectile=0.8,
    hidden_dims=512,512 (the settings are listed in the README and in config.json of a run)."""
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

    run_dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    episodes: int = 10
    """Episodes to run."""
    seed: int | None = None
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
    """Continue the run in this directory from its last checkpoint (other options are ignored)."""
    alpha: float | None = None
    """Fixed entropy temperature instead of automatic tuning (default: tuning toward -dim(A);
    walker2d: fixed 0.2, see README)."""
    lr: float | None = None
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


def _start_or_resume_then_train(cmd, resume, start, train) -> dict:
    """``--resume DIR`` or a new run, trained to its end; the summary printed as JSON."""
    run = resume(cmd.resume) if cmd.resume else start()
    print(f"run directory: {run.run_dir}", file=sys.stderr)
    summary = train(run, progress=cmd.progress)
    print(json.dumps(summary, indent=2))
    return summary


def run_sac(cmd: Sac) -> dict:
    from eabc.training import online  # noqa: PLC0415

    def start():
        config = cmd.config
        run_dir = cmd.run_dir or f"runs/sac_{config.env}_seed{config.seed}"
        return online.start_sac(config, run_dir, sac_agent_config(cmd))

    return _start_or_resume_then_train(cmd, online.resume_sac, start, online.train_sac)


@dataclasses.dataclass(frozen=True)
class ExportPolicy:
    """Write a run's policy (the latest checkpoint's actor, observation normaliser inside) as ONNX,
    to run without Python or JAX (onnxruntime, ONNX Runtime Web, TensorRT, ...)."""

    run_dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    onnx: str
    """The ONNX file to write (input observation [batch, obs_dim], output action)."""


def run_train(cmd: Train) -> dict:
    from eabc.training import trainer  # noqa: PLC0415

    def start():
        config = cmd.config
        run_dir = cmd.run_dir or f"runs/{Path(config.dataset).stem}_{config.algo}_seed{config.seed}"
        overrides = dataclasses.asdict(cmd.agent) | parse_settings(cmd.set)
        return trainer.start(config, run_dir, overrides)

    summary = _start_or_resume_then_train(cmd, trainer.resume, start, trainer.train)
    if summary.get("diverged_step") is not None:
        raise RuntimeError(f"training stopped at step {summary['diverged_step']} on NaN/inf")
    return summary


def run_evaluate(cmd: Evaluate) -> dict:
    from eabc.training import trainer  # noqa: PLC0415

    run = trainer.resume(cmd.run_dir, lock=False)  # reads only: a running run can be scored
    run.evaluator.episodes = cmd.episodes
    if cmd.seed is not None:
        run.evaluator.seed = cmd.seed
    result = {"run_dir": cmd.run_dir, "step": run.step, **trainer.evaluate(run)}
    print(json.dumps(result, indent=2))
    return result
