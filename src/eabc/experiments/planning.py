"""A sweep's plan: which jobs run (a seed group per job, or a run per job), what each costs, and
which of them end by a deadline.

Estimates rest on the speeds measured in the sweep root where there are any (:func:`measured_speeds`,
from the runs' logs), else on each algorithm contract's reference-host rate scaled by its settings'
relative cost and by this host's speed (:mod:`eabc.timing`).

Seeds of one setting form a *group*. A group runs either as one process that trains its seeds
together, vectorised with ``vmap`` (fastest on a GPU), or as one single-threaded process per seed
(fastest on a few CPU cores); ``layout="auto"`` picks by the JAX backend (:func:`default_layout`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import jax

from eabc import paths, timing
from eabc.agents import get_algorithm
from eabc.experiments import results
from eabc.experiments.run_status import RUNS, SPEC, status
from eabc.experiments.spec import RunSpec, groups
from eabc.training import trainer


def estimate_seconds(
    run: RunSpec,
    steps_done: int = 0,
    steps_per_s: float | None = None,
    speed: timing.HostSpeed = timing.REFERENCE,
) -> float:
    """A rough cost of the remaining steps: at ``steps_per_s`` where it is known (measured in the
    sweep root, :func:`measured_speeds`), else at the algorithm contract's reference-host rate
    scaled by its settings' relative cost and by this host's ``speed``; plus the one-off
    pretraining (a model fit) of a run not begun, and the evaluations
    (:func:`eabc.training.trainer.estimate_seconds`)."""
    algorithm = get_algorithm(run.algo)
    config = dataclasses.replace(algorithm.preset, **dict(run.overrides))
    train = run.train_config()
    left = max(train.steps - steps_done, 0)
    evaluations = len(train.evaluation_steps(after=steps_done)) * train.eval_episodes
    return trainer.estimate_seconds(
        algorithm, config, left, evaluations, steps_done == 0, steps_per_s, speed
    )


def measured_speeds(runs: list[RunSpec], root: Path) -> dict[str, float]:
    """Steps/s measured in ``root`` for each of ``runs`` that has a measurement to go by: its own
    log's median chunk speed, else the median over every run in the root (begun, running or done)
    of the same algorithm and settings, any dataset or seed. Runs with neither are left out (the
    contract's hint applies)."""
    own: dict[str, float] = {}
    by_setting: dict[tuple, list[float]] = {}
    for spec_file in sorted((root / RUNS).glob(f"*/{SPEC}")):
        run_dir = spec_file.parent
        if not (run_dir / "log.csv").exists():
            continue
        try:
            run = RunSpec.from_json(json.loads(paths.read_file(spec_file).decode()))
        except (OSError, ValueError, KeyError, TypeError):
            continue  # a broken run is reported elsewhere
        speed = results.read_run(run_dir)[0].get("steps_per_s")
        if isinstance(speed, float) and speed > 0:
            own[run.run_id] = speed
            by_setting.setdefault((run.algo, run.overrides), []).append(speed)
    out = {}
    for run in runs:
        speeds = sorted(by_setting.get((run.algo, run.overrides), []))
        if run.run_id in own:
            out[run.run_id] = own[run.run_id]
        elif speeds:
            out[run.run_id] = speeds[len(speeds) // 2]
    return out


def plan(
    runs: list[RunSpec], root: Path, speed: timing.HostSpeed = timing.REFERENCE
) -> list[dict[str, Any]]:
    """Each run's status, steps done and estimated seconds left; ``measured`` says whether the
    estimate rests on speeds measured in ``root`` (else on the contract's reference-host rate
    times this host's ``speed``)."""
    speeds = measured_speeds(runs, root)
    rows = []
    for run in runs:
        state, steps = status(run, root)
        rows.append(
            {
                "run": run,
                "status": state,
                "steps_done": steps,
                "seconds": estimate_seconds(run, steps, speeds.get(run.run_id), speed),
                "measured": run.run_id in speeds,
            }
        )
    return rows


def default_layout() -> str:
    return "vmap" if jax.default_backend() in ("gpu", "cuda", "rocm", "tpu") else "processes"


def jobs(runs: list[RunSpec], root: Path, layout: str) -> list[list[RunSpec]]:
    """The unfinished runs as jobs: a seed group per job (vmap) or one run per job."""
    todo = [r for r in runs if status(r, root)[0] in ("partial", "pending")]
    if layout == "vmap":
        return groups(todo)
    return [[r] for r in todo]


def parse_duration(text: str, flag: str | None = None) -> float:
    """Seconds in ``90s``, ``45m``, ``2.5h`` (a bare number is minutes); a refusal names
    ``flag``, the option it came from, where given."""
    units = {"s": 1.0, "m": 60.0, "h": 3600.0}
    value, unit = (text[:-1], text[-1]) if text and text[-1] in units else (text, "m")
    try:
        seconds = float(value) * units[unit]
    except ValueError:
        seconds = math.nan
    if not seconds > 0 or not math.isfinite(seconds):
        where = f"{flag}: " if flag else ""
        raise ValueError(
            f"{where}a duration is a positive number with s, m or h (90s, 45m, 2.5h), got {text!r}"
        )
    return seconds


def job_estimates(
    job_list: list[list[RunSpec]], root: Path, speed: timing.HostSpeed = timing.REFERENCE
) -> list[float]:
    """Each job's seconds left (its slowest run's), at the speeds measured in ``root`` so far
    (else at the reference rates times this host's ``speed``)."""
    runs = [run for job in job_list for run in job]
    speeds = measured_speeds(runs, root)
    return [
        max(estimate_seconds(r, status(r, root)[1], speeds.get(r.run_id), speed) for r in job)
        for job in job_list
    ]


def next_job(pending: list, seconds: list[float], now: float, deadline: float | None) -> int | None:
    """The index of the first pending job whose estimate ends by ``deadline`` (the first one
    when there is no deadline); None when none does. Time only moves on, so a job that does not
    fit now never will: the caller drops the ones before the index."""
    for i, cost in enumerate(seconds[: len(pending)]):
        if deadline is None or now + cost <= deadline:
            return i
    return None
