"""A training run's directory: the files it holds, what they show of its progress, and its
checkpoint as a reader outside training sees it.

A run directory holds ``config.json`` (:mod:`eabc.training.run_config`), the latest checkpoint
(:mod:`eabc.training.checkpoint`, recording which run wrote it: :mod:`eabc.training.identity`),
``log.csv``, ``curve.png`` and, once finished, ``summary.json``. Its results are never thrown away
unasked: a run whose checkpoint is gone but whose ``summary.json`` or ``log.csv`` shows it got past
its first checkpoint has lost progress (:func:`lost_progress`), and starting it again from step 0
is refused (:class:`ProgressLostError`) unless asked for. :func:`read_checkpoint` gives a finished
or running run's settings and checkpoint to readers outside training (``load_policy``, the ONNX
export), each checked to be this run's own.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import jax
import numpy as np

from eabc import paths, pytree, ranges
from eabc.agents import Algorithm, get_algorithm
from eabc.evaluation import make_env
from eabc.training import checkpoint, identity, logger, run_config
from eabc.training.checkpoint import CONFIG
from eabc.training.logger import LOG

SUMMARY = "summary.json"


PRETRAIN_PROGRESS = "pretrain.msgpack"
"""A run's pretraining progress (a model fit, epoch by epoch) until its first checkpoint."""


def refuse_existing(run_dir: Path) -> None:
    """``FileExistsError`` when ``run_dir`` holds a run already (its config.json)."""
    if (run_dir / CONFIG).exists():
        raise FileExistsError(
            f"{run_dir} already holds a run; continue it with `eabc train --resume {run_dir}` or "
            "choose another --run-dir"
        )


def remove_temporaries(run_dir: Path) -> None:
    """Temporary files of writes a kill interrupted (``.NAME.XXXX.tmp``, never renamed); only the
    writer holding the run's lock calls this, so none of them is being written."""
    for path in Path(run_dir).glob(".*.tmp"):
        if path.is_file():
            path.unlink(missing_ok=True)


class ProgressLostError(RuntimeError):
    """A run's checkpoint is gone but its results show progress: resuming would start it again."""


def lost_progress(run_dir: Path, steps: int, checkpoint_interval: int) -> str | None:
    """What ``run_dir``, which has no checkpoint, has done that training it from step 0 would
    throw away: finished (``summary.json``, or a log reaching ``steps``) or logged past its first
    checkpoint (so one was written and is gone); None for a run killed before its first
    checkpoint, which loses nothing by starting again."""
    summary_path = run_dir / SUMMARY
    if summary_path.exists():
        try:
            summary = json.loads(paths.read_file(summary_path).decode())
            done = f"{int(summary['steps'])} of {steps} steps"
            if summary.get("diverged_step") is not None:
                done += f", stopped on NaN/inf at step {summary['diverged_step']}"
        except (OSError, ValueError, KeyError, TypeError):
            done = f"{SUMMARY} unreadable"
        return (
            f"{run_dir} is finished ({done}; {SUMMARY}) but its {checkpoint.CHECKPOINT} is missing"
        )
    if not (run_dir / LOG).exists():
        return None
    rows, _ = logger.readable_rows(run_dir / LOG)
    if rows is None:
        return f"{run_dir}'s {LOG} cannot be read and its {checkpoint.CHECKPOINT} is missing"
    last = max((int(float(row["step"])) for row in rows), default=0)
    if last >= steps:
        return (
            f"{run_dir} is finished ({LOG} reaches step {last} of {steps}) but its "
            f"{checkpoint.CHECKPOINT} is missing"
        )
    if last > min(checkpoint_interval, steps):
        return (
            f"{run_dir} has trained to step {last} ({LOG}), past its first checkpoint, but its "
            f"{checkpoint.CHECKPOINT} is missing"
        )
    return None


def agent_config_from_json(algorithm: Algorithm, fields: dict) -> Any:
    """The agent settings a config.json records, as the algorithm's config."""
    names = algorithm.settings() | set(ranges.groups(type(algorithm.preset)))
    fields = {k: v for k, v in fields.items() if k in names}  # settings since dropped: ignored
    return ranges.validated(algorithm.preset, fields, f"{algorithm.name} setting ")


def settings_text(algorithm: Algorithm, agent_config) -> str:
    """The settings that differ from the algorithm's preset, e.g. ``num_critics=5``."""
    changed = [
        f"{f.name}={getattr(agent_config, f.name)}"
        for f in dataclasses.fields(agent_config)
        if getattr(agent_config, f.name) != getattr(algorithm.preset, f.name)
    ]
    return ", ".join(changed) or "its preset settings"


def read_checkpoint(run_dir: str | Path) -> tuple[dict, Algorithm, dict]:
    """A run's config.json, algorithm and latest checkpoint payload, for a reader outside
    training (``load_policy``, the ONNX export): the checkpoint's identity checked against
    config.json, its state layout against the algorithm's, and its actor's and normaliser's
    structure, shapes and dtypes against what the run's settings make."""
    run_dir = Path(run_dir)
    config = run_config.read(run_dir)
    if config.get("max_action") is None:  # the policy's output scale: no guess
        raise run_config.ConfigError(
            f"{run_dir / CONFIG}: max_action is missing (every eabc writes it); put back the "
            "evaluation environment's action bound (its action_space.high), e.g. 1.0"
        )
    env_id = config["train"].get("env") or config["dataset"].get("env_id")
    if env_id:  # a run that names its environment: max_action must be that environment's
        env = make_env(env_id)
        try:
            run_config.check_max_action(config, run_dir / CONFIG, env)
        finally:
            env.close()
    algorithm = get_algorithm(config["train"]["algo"])
    raw = checkpoint.load_raw(run_dir, infinite=algorithm.infinite_state)
    raw = identity.checked(raw, run_dir, config)
    raw = checkpoint.check_layout(raw, run_dir, algorithm.name, algorithm.state_layout)
    agent_config = agent_config_from_json(algorithm, config.get("agent", {}))
    path = run_dir / checkpoint.CHECKPOINT
    what = f"this {algorithm.name} run ({settings_text(algorithm, agent_config)})"
    try:
        actor = pytree.find(raw["agent"], "actor")
        obs_dim = int(np.shape(raw["normalizer"]["mean"])[0])
        outputs = int(np.shape(actor[f"b{sum(k.startswith('w') for k in actor) - 1}"])[0])
    except (KeyError, IndexError, TypeError) as error:
        raise checkpoint.CheckpointError(
            f"{path} has no actor or normaliser where {what} keeps them ({error}); it is not a "
            "checkpoint of this run"
        ) from None
    act_dim = outputs // 2 if algorithm.gaussian_actor else outputs
    shapes = jax.eval_shape(
        lambda key: algorithm.init(key, obs_dim, act_dim, agent_config), jax.random.PRNGKey(0)
    )
    zeros = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), pytree.to_state_dict(shapes))
    template = {
        "actor": pytree.find(zeros, "actor"),
        "normalizer": {"mean": np.zeros(obs_dim, np.float32), "std": np.zeros(obs_dim, np.float32)},
    }
    found = {"actor": actor, "normalizer": raw["normalizer"]}
    checkpoint.check_structure(found, template, path, what)
    return config, algorithm, raw
