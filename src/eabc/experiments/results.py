"""The results store: every run of a sweep root in one SQLite file, rebuilt from the run directories.

``ROOT/results.sqlite`` has two tables:

- ``runs``: one row per run directory: ``run_id, run_dir, dataset, env, kind, algo, seed,
  variant`` and the algorithm settings (``num_critics, confidence_level, pessimism``),
  ``reward_convention`` (what it trained on where the data's rewards are sparse goal rewards:
  :mod:`eabc.training.rewards`; empty for other data), then ``status`` (done, partial,
  diverged: stopped on NaN/inf, broken: its config.json cannot be read or fails its schema
  (:mod:`eabc.training.run_config`), or its log.csv cannot be read, or damaged: its files
  contradict each other, e.g. a log.csv cut short or deleted, a summary.json it disagrees with,
  another run's checkpoint; with why in ``config``;
  ``eabc train --resume`` rebuilds a damaged log from the checkpoint), ``steps``,
  ``steps_target``, ``wall_time_s`` (time in training chunks), ``steps_per_s`` (the median of
  log.csv's per-chunk steps/s: update steps only, no evaluation, no compilation outliers),
  ``final_score`` and ``final_return`` (means over the last 10 evaluations),
  ``q_out_of_range_step`` (the first logged step where the critics' mean Q left the range the
  rewards allow, a sign of divergence; empty if it never did or the log predates the check),
  ``diverged_step`` (where losses or Q became NaN/inf and training stopped), ``q_mean_max`` (the
  largest logged mean Q), the last log row's ``q_mean, q_ensemble_std, policy_q_std, bc_fraction,
  auto_p`` (as ``*_last``), the last in-range row's ``q_mean, q_ensemble_std, policy_q_std``
  before the first out-of-range one (as ``*_onset``; empty for a run that stayed in range),
  ``machine`` and ``code`` (the CPUs and code versions that trained it, from its
  ``provenance.json``; empty for runs from before that record) and ``config`` (JSON);
- ``evaluations``: ``run_id, step, score, score_std, return_mean, return_std``.

The run directories are the source of truth (``config.json``, ``log.csv``, ``summary.json``); the
file is a cache that :func:`collect` rewrites whenever asked, so deleting it loses nothing.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import sqlite3
import sys
import tempfile
from pathlib import Path

import pandas as pd

from eabc import paths, pytree
from eabc.agents import ALGORITHMS
from eabc.data import tasks
from eabc.training import identity, provenance, rewards, run_config
from eabc.training.checkpoint import CHECKPOINT, CONFIG, CheckpointError, file_mode, load_raw
from eabc.training.config import FINAL_EVALUATIONS
from eabc.training.directory import SUMMARY
from eabc.training.logger import LOG, log_problem

DATABASE = "results.sqlite"
UNUSABLE = ("broken", "damaged")
"""Statuses whose numbers are not to be trusted (why is in ``config``); reports leave them out."""
SETTINGS = tuple(dict.fromkeys(k for a in ALGORITHMS.values() for k in a.report_settings))
"""Algorithm settings kept as columns: what the contracts' ``report_settings`` name."""
DIAGNOSTICS = ("q_mean", "q_ensemble_std", "policy_q_std", "bc_fraction", "auto_p")
"""Log columns kept from a run's last row (``*_last``): how its critics and BC term ended."""
ONSET = ("q_mean", "q_ensemble_std", "policy_q_std")
"""Log columns kept (``*_onset``) from the last row before the critics first left the value
range: the ensemble's state as the runaway began (a runaway run's last row is long past it)."""


def run_dirs(root: Path) -> list[Path]:
    """Every run directory under ``root`` (a sweep root, or a single run directory)."""
    root = Path(root)
    if (root / CONFIG).exists():
        return [root]
    # Every config.json but an online SAC run's (``eabc sac``: "sac", no "train") is a training
    # run's; one that cannot be read or fails its schema is listed as broken rather than dropped,
    # and so is a directory whose checkpoint, log or summary is left but whose config.json is gone.
    found = {p.parent for p in root.rglob(CONFIG) if not _online(p)}
    for name in (CHECKPOINT, LOG, SUMMARY):
        found |= {p.parent for p in root.rglob(name) if not (p.parent / CONFIG).exists()}
    return sorted(found)


def _online(path: Path) -> bool:
    """Whether ``path`` is the config.json of an online SAC run (not a training run's)."""
    config = _read_json(path, {"unreadable": True})
    return "sac" in config and "train" not in config


def _read_json(path: Path, unreadable: dict | None = None) -> dict:
    """The JSON object in ``path``; {} if it is missing, ``unreadable`` (default {}) if it is not
    a regular file, not JSON or not an object."""
    try:
        data = json.loads(paths.read_file(path).decode())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {} if unreadable is None or not path.exists() else unreadable
    return data if isinstance(data, dict) else {} if unreadable is None else unreadable


def _broken_row(run_dir: Path, run_id: str, why: str) -> dict:
    return {**dict.fromkeys(RUN_COLUMNS), "run_id": run_id, "run_dir": str(run_dir),
            "status": "broken", "config": why}  # fmt: skip


def read_run(run_dir: Path, root: Path | None = None) -> tuple[dict, list[dict]]:
    """One run's row and its evaluations, from its directory; status ``broken`` (and why, in
    ``config``) when its config.json or log.csv cannot be read or config.json fails its schema, ``damaged`` (and why) when its
    files contradict each other (:func:`_damage`)."""
    run_id = run_dir.name if root is None else str(run_dir.relative_to(root))
    if not (run_dir / CONFIG).exists():
        why = f"{run_dir / CONFIG} is missing (the run's other files are here); restore it"
        return _broken_row(run_dir, run_id, why), []
    try:
        config = run_config.read(run_dir)  # its schema, or why not in one line
    except (OSError, ValueError) as error:
        return _broken_row(run_dir, run_id, str(error)), []
    try:
        return _read_run(run_dir, run_id, config)
    except (OSError, ValueError, KeyError, TypeError, csv.Error) as error:
        return _broken_row(run_dir, run_id, f"{run_dir}: {type(error).__name__}: {error}"), []


def _reward_convention(train: dict, task: tuple[str, str] | None) -> str:
    """What the run trained on where its data's rewards are sparse goal rewards (AntMaze's): its
    recorded ``reward_convention``, or the one every run used before the setting existed; "" for
    data the setting does not apply to."""
    if tasks.reward_offset(task) is None:
        return ""
    return train.get("reward_convention") or rewards.LEGACY


def _read_run(run_dir: Path, run_id: str, config: dict) -> tuple[dict, list[dict]]:
    train, agent = config["train"], config.get("agent", {})
    dataset = config.get("dataset", {}).get("name") or train["dataset"]
    task = tasks.parse_task(dataset)
    # The checkpoint and summary.json before log.csv, which the trainer writes before them: a
    # run training meanwhile can only have moved its log ahead of them, never behind.
    stored, problem = _checkpoint_history(run_dir, config)
    summary = _read_json(run_dir / SUMMARY, {"unreadable": True})
    evaluations, last_row, out_of_range = [], {}, math.nan
    onset = {}  # the last row in range before the first row out of range
    q_max = math.nan  # the largest mean Q any logged chunk reached
    rates = []  # each training chunk's steps/s (no evaluation, no checkpoint)
    log = run_dir / LOG
    if log.exists():
        text = paths.read_file(log).decode()  # a FIFO would block: refused, as OSError
        for row in csv.DictReader(io.StringIO(text, newline="")):
            q_max = _max(q_max, _num(row.get("q_mean")))
            rates.append(_num(row.get("steps_per_s")))
            if _num(row.get("q_out_of_range")) == 1.0 and math.isnan(out_of_range):
                out_of_range = int(float(row["step"]))
                onset = last_row or row  # out of range from the first row: that row
            last_row = row
            # An evaluation row has a return; "nan" cells (which resumes of older versions
            # wrote into empty cells) are no evaluation.
            if not math.isnan(_num(row.get("return_mean"))):
                evaluations.append(
                    {
                        "step": int(float(row["step"])),
                        "score": _num(row.get("score")),
                        "score_std": _num(row.get("score_std")),
                        "return_mean": _num(row.get("return_mean")),
                        "return_std": _num(row.get("return_std")),
                    }
                )
    steps = int(float(last_row["step"])) if last_row else 0
    run = {"algo": train["algo"], "seed": train["seed"], "dataset": dataset}
    problem = problem or _damage(run_dir, summary, evaluations, steps, stored, int(train["steps"]))
    problem = problem or _foreign_summary(run_dir, summary, run)
    wall = _num(last_row.get("wall_time")) if last_row else math.nan
    last = evaluations[-FINAL_EVALUATIONS:]
    spec = _read_json(run_dir / "sweep.json")  # written by eabc.experiments.job_process
    segments = provenance.read(run_dir)
    row = {
        "run_id": run_id,
        "run_dir": str(run_dir),
        "dataset": dataset,
        "env": task[0] if task else None,
        "kind": task[1] if task else None,
        "algo": train["algo"],
        "seed": int(train["seed"]),
        "variant": spec.get("variant", ""),
        **{k: agent.get(k) for k in SETTINGS},
        "reward_convention": _reward_convention(train, task),
        "status": "damaged" if problem else _status(summary, train),
        "steps": steps,
        "steps_target": int(train["steps"]),
        "wall_time_s": wall,
        "steps_per_s": _median(rates),
        "final_score": _mean([e["score"] for e in last]),
        "final_return": _mean([e["return_mean"] for e in last]),
        "q_out_of_range_step": out_of_range,
        "diverged_step": summary.get("diverged_step", math.nan),
        "q_mean_max": q_max,
        **{f"{k}_last": _num(last_row.get(k)) for k in DIAGNOSTICS},
        **{f"{k}_onset": _num(onset.get(k)) for k in ONSET},
        "machine": provenance.machine_text(segments),  # "" for runs trained before the record
        "code": provenance.code_text(segments),
        "config": problem or json.dumps(config),
    }
    return row, [{"run_id": run_id, **e} for e in evaluations]


def _checkpoint_history(run_dir: Path, config: dict) -> tuple[tuple | None, str | None]:
    """``(step, evaluations)`` of the run's checkpoint (None without one) and why it cannot be
    this run's (unreadable, or another run's by its recorded identity), else None."""
    if not (run_dir / CHECKPOINT).exists():
        return None, None
    try:
        algorithm = ALGORITHMS.get(config.get("train", {}).get("algo"))
        infinite = algorithm.infinite_state if algorithm else frozenset()
        raw = identity.checked(load_raw(run_dir, infinite=infinite), run_dir, config, warn=False)
        step = int(pytree.find(raw["agent"], "step"))
    except (CheckpointError, OSError, KeyError, TypeError, ValueError) as error:
        return None, str(error)
    return (step, raw.get("evaluations") or {}), None


def _damage(
    run_dir: Path, summary: dict, evaluations: list[dict], logged: int, stored, target: int
) -> str:
    """Why the run's files contradict each other, or "" when they agree: log.csv against the
    checkpoint's evaluation history (:func:`~eabc.training.logger.log_problem`), against the
    run's ``target`` steps and against summary.json (its steps, its number of evaluations and its
    final return)."""
    problem = ""
    if stored is not None:
        step, history = stored
        problem = log_problem(run_dir / LOG, history, step, target) or ""
    if not problem and logged > target:
        problem = f"{run_dir / LOG} goes on to step {logged}, past the run's {target} steps"
    steps = summary.get("steps")
    if problem or not (run_dir / SUMMARY).exists():
        pass  # a checkpoint's history is the stronger evidence; no summary, nothing to compare
    elif summary.get("unreadable") or not isinstance(steps, int) or isinstance(steps, bool):
        problem = (
            f"{run_dir / SUMMARY} cannot be read as a run's summary (a JSON object with steps)"
        )
    elif not (run_dir / LOG).exists():
        problem = f"{run_dir / LOG} is missing but {SUMMARY} says the run trained"
    else:
        done = steps
        scored = [e for e in evaluations if e["step"] <= done]
        final = _mean([e["return_mean"] for e in scored[-FINAL_EVALUATIONS:]])
        recorded = summary.get("final_return")
        if logged < done:
            problem = f"{run_dir / LOG} ends at step {logged} but {SUMMARY} says {done}"
        elif len(scored) != summary.get("evaluations", len(scored)):
            problem = (
                f"{run_dir / LOG} holds {len(scored)} evaluations up to step {done} but "
                f"{SUMMARY} says {summary['evaluations']}"
            )
        elif recorded is not None and not math.isclose(final, recorded, rel_tol=1e-9):
            problem = f"{run_dir / LOG}'s final return {final!r} is not {SUMMARY}'s {recorded!r}"
    if problem and stored is not None:
        problem += f"; `eabc train --resume {run_dir}` rebuilds it from the checkpoint"
    return problem


def _foreign_summary(run_dir: Path, summary: dict, run: dict) -> str:
    """Why summary.json is another run's (its algorithm, seed or dataset), or ""."""
    for key, value in run.items():
        if key in summary and summary[key] != value:
            return (
                f"{run_dir / SUMMARY} is of {key} {summary[key]!r} but {run_dir / CONFIG}'s run "
                f"has {value!r}: another run's summary"
            )
    return ""


def _status(summary: dict, train: dict) -> str:
    if summary.get("diverged_step") is not None:
        return "diverged"  # stopped on NaN/inf losses or Q values
    return "done" if summary and summary.get("steps", 0) >= train["steps"] else "partial"


def _max(a: float, b: float) -> float:
    return b if math.isnan(a) else a if math.isnan(b) else max(a, b)


def _num(text) -> float:
    return float(text) if text not in (None, "") else math.nan


def _median(values: list[float]) -> float:
    """The median of the finite values (NaN if none): a run's speed from its chunks' speeds, not
    thrown off by the chunks that compiled the program (after every start or resume)."""
    values = sorted(v for v in values if math.isfinite(v))
    if not values:
        return math.nan
    middle = len(values) // 2
    return values[middle] if len(values) % 2 else (values[middle - 1] + values[middle]) / 2


def _mean(values: list[float]) -> float:
    values = [v for v in values if not math.isnan(v)]
    return sum(values) / len(values) if values else math.nan


def collect(root: str | Path, write: bool = True) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``(runs, evaluations)`` of every run under ``root``; also rewrites ``root/results.sqlite``."""
    root = Path(root)
    rows, evaluations = [], []
    for run_dir in run_dirs(root):
        row, evals = read_run(run_dir, root if run_dir != root else None)
        rows.append(row)
        evaluations.extend(evals)
    runs = pd.DataFrame(rows, columns=RUN_COLUMNS)
    evals = pd.DataFrame(evaluations, columns=EVAL_COLUMNS)
    if write:
        store(root, runs, evals)
    return runs, evals


def store(root: str | Path, runs: pd.DataFrame, evals: pd.DataFrame) -> None:
    """Write ``root/results.sqlite`` (atomically) from :func:`collect`'s tables; a command that
    refuses its other inputs calls this only after checking them, so that it changes nothing."""
    root = Path(root)
    if not root.is_dir():
        return
    if not os.access(root, os.W_OK):  # a read-only root is read, never written
        print(f"note: {root} is read-only: {DATABASE} not updated", file=sys.stderr)
        return
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=root, prefix=f".{DATABASE}.", suffix=".tmp")
        os.fchmod(fd, file_mode())  # as open() would, not mkstemp's 0600
        os.close(fd)
        with sqlite3.connect(tmp) as db:
            runs.to_sql("runs", db, index=False, if_exists="replace")
            evals.to_sql("evaluations", db, index=False, if_exists="replace")
        db.close()
        os.replace(tmp, root / DATABASE)
    except (OSError, sqlite3.Error) as error:  # the store is a cache of the run directories
        why = getattr(error, "strerror", None) or str(error)
        print(f"warning: {root / DATABASE} not updated: {why}", file=sys.stderr)
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)


RUN_COLUMNS = [
    "run_id", "run_dir", "dataset", "env", "kind", "algo", "seed", "variant", *SETTINGS,
    "reward_convention", "status", "steps", "steps_target", "wall_time_s", "steps_per_s",
    "final_score", "final_return", "q_out_of_range_step", "diverged_step", "q_mean_max",
    *(f"{k}_last" for k in DIAGNOSTICS), *(f"{k}_onset" for k in ONSET), "machine", "code",
    "config",
]  # fmt: skip
EVAL_COLUMNS = ["run_id", "step", "score", "score_std", "return_mean", "return_std"]


def load(root: str | Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The stored tables, rebuilt from the run directories if the file is missing."""
    path = Path(root) / DATABASE
    if not path.exists():
        return collect(root)
    with sqlite3.connect(path) as db:
        runs = pd.read_sql("SELECT * FROM runs", db)
        evals = pd.read_sql("SELECT * FROM evaluations", db)
    db.close()
    return runs, evals


def query(runs: pd.DataFrame, filters: list[str]) -> pd.DataFrame:
    """Rows matching every ``KEY=VALUE`` filter (values compared as text; ``*`` wildcards)."""
    out = runs
    for item in filters:
        key, sep, value = item.partition("=")
        if not sep or key not in runs.columns:
            raise ValueError(
                f"bad filter {item!r}: use KEY=VALUE with KEY one of {', '.join(runs.columns)}"
            )
        out = out[out[key].astype(str).str.fullmatch(value.replace("*", ".*"))]
    return out
