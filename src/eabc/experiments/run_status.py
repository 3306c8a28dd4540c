"""The state of a sweep's runs on disk: each run in its own directory under ``ROOT/runs``, named by
its spec (:meth:`~eabc.experiments.spec.RunSpec.run_id`).

A run is ``done``, ``partial``, ``pending``, ``changed`` (its directory holds a run of another
spec) or ``broken`` (a file of it cannot be read): :func:`status`, with why in words
(:func:`status_with_reason`). Names too long for the file system are refused before any job
starts (:func:`check_names`); a run done in an earlier report or in another sweep root on this
machine is not trained again (:func:`archived_done`, :func:`taken_elsewhere`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from eabc import paths, pytree
from eabc.agents import get_algorithm
from eabc.data import sources
from eabc.experiments.spec import RunSpec, differences
from eabc.training import checkpoint
from eabc.training.directory import SUMMARY, lost_progress
from eabc.training.lock import in_use

RUNS = "runs"
SPEC = "sweep.json"
"""What a sweep knows about one of its runs (its spec and variant label)."""


def status(run: RunSpec, root: Path) -> tuple[str, int]:
    """The state of a run and the steps done so far: ``done`` (also when it stopped on NaN/inf),
    ``partial`` (has a checkpoint), ``pending``, ``changed`` (its directory holds a run of another
    spec, or of more steps than asked) or ``broken`` (a file of it cannot be read)."""
    return status_with_reason(run, root)[:2]


def status_with_reason(run: RunSpec, root: Path) -> tuple[str, int, str]:
    """:func:`status` and why, in words (for ``changed`` and ``broken``)."""
    run_dir = root / RUNS / run.run_id
    target = run.train_config().steps
    if (run_dir / SPEC).exists():
        try:
            stored = RunSpec.from_json(json.loads(paths.read_file(run_dir / SPEC).decode()))
        except (OSError, ValueError, KeyError, TypeError) as error:
            return "broken", 0, f"{run_dir / SPEC} cannot be read ({type(error).__name__})"
        changed = differences(stored, run)
        if changed:
            return "changed", 0, f"{run_dir} was trained with {'; '.join(changed)}"
    summary = _read_json(run_dir / SUMMARY)  # an unreadable summary is rewritten by the run
    steps = summary.get("steps", 0)
    if summary.get("diverged_step") is not None:
        return "done", steps, ""
    if steps > target:
        return "changed", steps, f"{run_dir} has trained {steps} steps, the spec asks {target}"
    if summary and steps == target:
        return "done", steps, ""
    if (run_dir / checkpoint.CHECKPOINT).exists():
        try:
            raw = checkpoint.load_raw(run_dir, infinite=get_algorithm(run.algo).infinite_state)
            return "partial", int(pytree.find(raw["agent"], "step")), ""
        except (ValueError, KeyError, TypeError) as error:
            return "broken", 0, str(error)
    train = run.train_config()  # a run past its first checkpoint is not started again unasked
    lost = lost_progress(run_dir, train.steps, train.checkpoint_interval)
    if lost:
        return "broken", 0, f"{lost}; restore it, or delete the run directory to train it again"
    return "pending", 0, ""


def check_startable(runs: list[RunSpec], root: Path) -> None:
    """What a sweep or a study checks before its first run starts, and in a dry run: every
    dataset loadable by its name or path alone (nothing made or read), then every run's name
    (:func:`check_names`)."""
    for dataset in dict.fromkeys(run.dataset for run in runs):
        sources.check_source(dataset)
    check_names(runs, root)


def check_names(runs: list[RunSpec], root: Path) -> None:
    """Refuse, before any job starts (and in a dry run), a run whose directory or log file
    would be named longer than the file system under ``root`` allows (255 bytes on most), or
    whose files' paths would be longer than its path limit: a dataset file may have a
    240-character name, and its run's name adds the algorithm, the settings and the seed. Found
    when its job started, it stopped the sweep and the healthy jobs running beside it."""
    existing = paths.expand(root).absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    name_max, path_max = (_limit(existing, key, default) for key, default in
                          (("PC_NAME_MAX", 255), ("PC_PATH_MAX", 4096)))  # fmt: skip
    for run in runs:
        log_name = f"{run.run_id}.log"  # the longest name: the run's log, beside its directory
        if len(log_name.encode()) > name_max:
            raise ValueError(
                f"{run.dataset}: the sweep would name this run's directory and log "
                f"{log_name[:48]}... ({len(log_name.encode())} bytes), longer than the "
                f"{name_max} bytes the file system of {existing} allows in a name; give the "
                "dataset (file) a shorter name, or the grid fewer settings"
            )
        deepest = paths.expand(root).absolute() / RUNS / run.run_id / ".checkpoint.msgpack.x.tmp"
        if len(str(deepest).encode()) + 16 > path_max:
            raise ValueError(
                f"{run.dataset}: this run's files would lie {len(str(deepest).encode())} bytes "
                f"deep under --root, longer than the {path_max} bytes the file system allows in "
                "a path; use a shorter --root or give the dataset a shorter name"
            )


def _limit(path: Path, key: str, default: int) -> int:
    try:
        return os.pathconf(path, key)
    except (OSError, ValueError):
        return default


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(paths.read_file(path).decode())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def problems(runs: list[RunSpec], root: Path) -> dict[str, list[str]]:
    """``changed`` and ``broken`` runs of a sweep, each with why."""
    out: dict[str, list[str]] = {"changed": [], "broken": []}
    for run in runs:
        state, _, why = status_with_reason(run, root)
        if state in out:
            out[state].append(why)
    return out


def archived_done(runs: list[RunSpec], archives: list[tuple[Any, Any]]) -> set[str]:
    """The ids of ``runs`` that an earlier report (``archive_merge.read_archive``) holds as done with
    at least the steps the spec asks."""
    done = set()
    for table, _ in archives:
        finished = table[(table["status"] == "done") & (table["steps"] >= table["steps_target"])]
        done |= {(rid, int(steps)) for rid, steps in zip(finished["run_id"], finished["steps"])}
    return {
        run.run_id
        for run in runs
        for rid, steps in done
        if rid == f"{RUNS}/{run.run_id}" and steps >= run.train_config().steps
    }


def taken_elsewhere(run: RunSpec, roots: list[Path]) -> str | None:
    """Why another sweep root (``--include ROOT`` on the same machine) has ``run`` in hand: done
    there at the spec's steps, or being trained there now; None if neither. Asked again just
    before each job starts, so two sweeps that share runs (one per core, each in its own root)
    never train the same run twice, even when one reaches it after the other began."""
    for other in roots:
        if status(run, other)[0] == "done":
            return f"done in {other}"
        if in_use(other / RUNS / run.run_id):
            return f"being trained in {other}"
    return None
