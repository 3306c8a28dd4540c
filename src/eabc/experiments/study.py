"""The study engine: a queue of runs trained against a time budget on one accelerator.

A lent GPU machine gives minutes, not hours, and returns only a few small files. So the queue is
trained in one process, slice after slice (a slice is one sweep spec): each group of a slice's
runs that share their networks' shapes (seeds, datasets of one environment, values of the
algorithm's traced settings: :func:`eabc.experiments.spec.groups`) is one compiled program
(``vmap``-ped, :func:`eabc.training.trainer.train_runs`), the groups one after another, so one
program holds the accelerator's memory at a time (XLA's pre-allocation is turned off by the
command). The built-in datasets the queue names are made by a pool of processes while the first
groups train, and a thread compiles each new group's program ahead (:class:`Compiler`): the first
while its data are made, each next one while the group before it trains. A group starts only if
its estimate ends before the deadline; the estimates are the contract's reference-host hints
scaled by how long the groups trained so far took against theirs.
Once started, a group's first chunks measure its real speed: if the rest would end after the
deadline it stops there, and its first runs, as many as that speed says fit the time left, start
again as a narrower program (:func:`fitting`); the others wait for their turn behind them.
After every finished group, everything the queue has finished is written to ``OUT`` in
:data:`OUT_FILES` (no checkpoints), each file replaced whole, so a command stopped at its limit
still returns all it finished. ``eabc report --include OUT`` reads ``OUT`` back beside other
results, and a later study given ``--include OUT`` skips what it holds.
"""

from __future__ import annotations

import concurrent.futures
import json
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pandas as pd

from eabc import compile_cache, evaluation, paths, timing
from eabc.data import generate, sources, tasks
from eabc.experiments import job_process, planning, results, run_status
from eabc.experiments.spec import RunSpec, job_name
from eabc.training import chunks, eval_pool, trainer
from eabc.training.checkpoint import atomic_write
from eabc.training.config import resolve_agent_config
from eabc.training.trainer import PastDeadline

OUT_FILES = (
    "runs.csv",  # one row per finished run, as `eabc report` writes it (read back by --include)
    "evaluations.csv",  # every evaluation of those runs (step, score, return)
    "logs.csv",  # their log.csv rows, a run_id column first
    "runs.jsonl",  # per run: summary.json, config.json, provenance.json and the sweep's spec
    "study.log",  # what the study did, a line per stage
)
"""What a study writes to its ``OUT`` folder: five files, whatever the number of runs."""


def _write_atomic(path: Path, text: str) -> None:
    atomic_write(path, text.encode("utf-8"))


class StudyLog:
    """A line per stage, to the terminal (or a log) and to ``OUT/study.log``; from any thread."""

    def __init__(self, out: Path, echo: Callable[[str], None] = print):
        self.path, self.echo, self.lines = out / "study.log", echo, []
        self.started = time.time()
        self.lock = threading.Lock()

    def __call__(self, text: str) -> None:
        with self.lock:  # each write holds every line before it
            line = f"[{time.time() - self.started:7.1f} s] {text}"
            self.lines.append(line)
            self.echo(line)
            _write_atomic(self.path, "\n".join(self.lines) + "\n")


def export(root: Path, out: Path) -> int:
    """Write every finished run under ``root`` into ``out`` (:data:`OUT_FILES` but the log);
    returns how many runs that is."""
    table, evaluations = results.collect(root, write=False)
    done = table[table["status"] == "done"] if not table.empty else table
    _write_atomic(
        out / "runs.csv", done.drop(columns=["config"], errors="ignore").to_csv(index=False)
    )
    ids = set(done["run_id"]) if not done.empty else set()
    finished = (
        evaluations[evaluations["run_id"].isin(ids)] if not evaluations.empty else evaluations
    )
    _write_atomic(out / "evaluations.csv", finished.to_csv(index=False))
    logs, records = [], []
    for run_id in sorted(ids):
        run_dir = root / run_id
        log = run_dir / "log.csv"
        if log.is_file():
            logs.append(pd.read_csv(log).assign(run_id=run_id))
        record = {"run_id": run_id}
        for name in ("summary.json", "config.json", "provenance.json", run_status.SPEC):
            file = run_dir / name
            record[name] = json.loads(file.read_text()) if file.is_file() else None
        records.append(json.dumps(record, sort_keys=True))
    frame = pd.concat(logs, ignore_index=True) if logs else pd.DataFrame(columns=["run_id"])
    frame = frame[["run_id", *[c for c in frame.columns if c != "run_id"]]]
    _write_atomic(out / "logs.csv", frame.to_csv(index=False))
    _write_atomic(out / "runs.jsonl", "".join(f"{r}\n" for r in records))
    return len(ids)


def _make_dataset(name: str, cache_dir: str | None, size: int | None, workers: int) -> str:
    path = generate.dataset_path(name, cache_dir)
    generate.make(name, path, size=size, workers=workers)
    return str(path)


def start_datasets(
    job_list: list[list[RunSpec]], workers: int, size: int | None, log
) -> tuple[dict[str, concurrent.futures.Future], concurrent.futures.Executor | None]:
    """Make the missing built-in datasets of ``job_list`` one after another in queue order, each
    by ``workers`` processes (the same bytes for any number, :func:`eabc.data.generate.make`), in
    a background thread while the groups before them train; returns a future per dataset (done
    at once for those already made) and the thread's executor."""
    futures: dict[str, concurrent.futures.Future] = {}
    pool = None
    for run in (run for job in job_list for run in job):
        config = run.train_config()
        name = config.dataset
        if name in futures or sources.kind(name) != "builtin":
            continue
        path = generate.dataset_path(name, config.cache_dir)
        if generate.is_current(path, name):
            futures[name] = concurrent.futures.Future()
            futures[name].set_result(str(path))
            continue
        if pool is None:
            pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="datasets")
        log(f"making {name} into {path} in the background ({workers} processes)")
        futures[name] = pool.submit(_make_dataset, name, config.cache_dir, size, workers)
    return futures, pool


def compile_group(job: list[RunSpec], size: int | None) -> bool:
    """Compile the first chunk's program of a group of new runs on built-in datasets before its
    data are made (:func:`eabc.training.chunks.compile_first_chunk`, sized by the recipe's
    rows or ``size``); False, compiling nothing, for a group of other data."""
    names = list(dict.fromkeys(run.dataset for run in job))
    if any(sources.kind(name) != "builtin" for name in names):
        return False
    configs = [run.train_config() for run in job]
    agent_configs = [
        resolve_agent_config(c.algo, run.dataset, dict(run.overrides), c.steps)
        for run, c in zip(job, configs)
    ]
    env_id = configs[0].env or tasks.env_info(tasks.parse_task(names[0])).env_id
    obs_dim, act_dim, max_action = evaluation.space_sizes(env_id)
    rows = [size or generate.default_size(name) for name in names]
    chunks.compile_first_chunk(configs[0], agent_configs, obs_dim, act_dim, max_action, rows)
    return True


class Compiler:
    """Compiles groups' programs ahead, one at a time in a thread of their own, into XLA's
    persistent cache: the first group's while its data are made, each next one while the group
    before it trains (on an accelerator the host's cores are otherwise idle then)."""

    def __init__(self, root: Path, size: int | None, log):
        self.root, self.size, self.log = root, size, log
        self.pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="compile")
        self.futures: dict[tuple, concurrent.futures.Future] = {}

    def ahead(self, job: list[RunSpec]) -> None:
        """Start compiling ``job``'s program, if its runs are new and it is not begun yet."""
        ids = tuple(run.run_id for run in job)
        if ids in self.futures or any(
            run_status.status(run, self.root)[0] != "pending" for run in job
        ):
            return
        self.futures[ids] = self.pool.submit(self._compile, job)

    def _compile(self, job: list[RunSpec]) -> None:
        label = f"{job_name(job)} ({len(job)} run{'s' * (len(job) > 1)})"
        started = time.time()
        try:
            if compile_group(job, self.size):
                self.log(f"compiled ahead in {time.time() - started:.0f} s: {label}")
        except Exception as error:  # the group's own first chunk compiles it, or says what fails
            self.log(f"not compiled ahead: {label}: {type(error).__name__}: {error}")

    def wait(self, job: list[RunSpec]) -> None:
        """Let ``job``'s compilation, if begun, end: its first chunk then finds the program."""
        future = self.futures.get(tuple(run.run_id for run in job))
        if future is not None:
            future.result()

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


def algorithm_major(runs: list[RunSpec]) -> list[RunSpec]:
    """``runs`` algorithm by algorithm, in the order of each algorithm's first run, otherwise as
    given (a spec's expansion lists them dataset by dataset): a slice trains its first algorithm
    on all its datasets before the next, so that a call too short for the whole slice brings back
    one method's row on every dataset rather than every method on the first dataset."""
    first: dict[str, int] = {}
    for run in runs:
        first.setdefault(run.algo, len(first))
    return sorted(runs, key=lambda run: first[run.algo])


def _scale(took: dict[str, list[tuple[float, float]]], algo: str) -> float:
    """How long groups took here against their reference-host estimates: this algorithm's
    groups where one has finished, else every finished group's, else 1."""
    pairs = took.get(algo) or [pair for pairs in took.values() for pair in pairs]
    return sum(a for a, _ in pairs) / sum(e for _, e in pairs) if pairs else 1.0


def fitting(stopped: PastDeadline, seconds_left: float) -> int:
    """How many of a stopped group's runs to train again in ``seconds_left``: as many as end in
    time (after compiling again) at the seed-steps per second its first chunks reached, fewer than
    it had; 0 where not even one does. A narrower program makes fewer seed-steps per second on an
    accelerator, so a first guess can be stopped again, and is narrowed again."""
    seed_steps_per_s = stopped.steps_per_s * stopped.width
    time_for_steps = seconds_left - stopped.compile_s
    fit = int(time_for_steps * seed_steps_per_s / (trainer.DEADLINE_MARGIN * stopped.steps))
    return max(0, min(fit, stopped.width - 1))


def run_study(
    slices: list[list[RunSpec]],
    root: Path,
    out: Path,
    deadline: float | None = None,
    data_workers: int = 1,
    dataset_size: int | None = None,
    echo: Callable[[str], None] = print,
    eval_workers: int = 0,
) -> dict[str, Any]:
    """Train ``slices`` (lists of runs: the queue, in order), group by group in this process,
    until the queue or the time is spent;
    ``eval_workers`` processes evaluate every group's runs while training goes on (one pool for
    the whole queue; 0: in this process, between chunks).

    Returns what happened: ``finished`` (run ids), ``skipped`` (groups not started because
    their estimate ended past ``deadline``, or stopped because their first chunks showed that
    not even one of their runs would end before it), ``narrowed`` (groups stopped after their
    first chunks and trained again with fewer runs), ``failed`` (group label -> error) and
    ``exported`` (finished runs in ``out``, this study's and earlier ones' in the same root)."""
    out.mkdir(parents=True, exist_ok=True)
    root.mkdir(parents=True, exist_ok=True)
    log = StudyLog(out, echo)
    job_list = [job for runs in slices for job in planning.jobs(runs, root, "vmap")]
    count = sum(len(job) for job in job_list)
    log(f"{count} runs in {len(job_list)} groups to train in {root}")
    compiler = None  # none without the on-disk cache: a program compiled ahead is kept there
    if job_list and compile_cache.enable(cache_root=job_list[0][0].train_config().cache_dir):
        compiler = Compiler(root, dataset_size, log)
        compiler.ahead(job_list[0])  # while its data are made
    futures, pool = start_datasets(job_list, data_workers, dataset_size, log)
    evaluators = eval_pool.EvaluationPool(eval_workers) if eval_workers else 0
    took: dict[str, list[tuple[float, float]]] = {}  # algo -> (actual, estimated) seconds
    report: dict[str, Any] = {
        "finished": [], "skipped": [], "narrowed": [], "failed": {}, "exported": 0
    }  # fmt: skip
    try:
        while job_list:
            job = job_list.pop(0)
            label = f"{job_name(job)} ({len(job)} run{'s' * (len(job) > 1)})"
            base = max(planning.estimate_seconds(r, run_status.status(r, root)[1]) for r in job)
            guess = base * _scale(took, job[0].algo)
            if deadline is not None and took and time.time() + guess > deadline:
                log(f"not started, ~{guess:.0f} s would end past the deadline: {label}")
                report["skipped"].append(label)
                continue
            for name in dict.fromkeys(run.dataset for run in job):
                if name in futures:
                    futures[name].result()  # its datasets, made meanwhile
            if compiler is not None:
                compiler.wait(job)
                if job_list:
                    compiler.ahead(job_list[0])  # the next group, while this one trains
            log(f"training {label} (~{guess:.0f} s by the estimates so far)")
            started = time.time()
            try:
                job_process.execute(
                    [job_process.absolute_spec(r) for r in job], str(root), evaluators, deadline
                )
            except PastDeadline as stopped:
                fit = fitting(stopped, deadline - time.time())
                if fit:
                    log(f"stopped: {label}: {stopped}; again with its first {fit}")
                    report["narrowed"].append(label)
                    job_list[:0] = [job[:fit], job[fit:]]
                else:
                    log(f"stopped: {label}: {stopped}; not even one run would end in time")
                    report["skipped"].append(label)
                continue
            except Exception as error:  # one failed group does not stop the queue
                log(f"failed: {label}: {error}")
                report["failed"][label] = str(error)
                continue
            seconds = time.time() - started
            took.setdefault(job[0].algo, []).append((seconds, base))
            report["finished"] += [r.run_id for r in job]
            report["exported"] = export(root, out)
            log(f"done in {seconds:.0f} s: {label}; {report['exported']} runs in {out}")
    finally:
        if pool is not None:  # the queue's later datasets are not begun; one being made ends
            pool.shutdown(wait=False, cancel_futures=True)
        if evaluators:
            evaluators.close(finished=False)
        if compiler is not None:
            compiler.close()
    report["exported"] = export(root, out)
    log(
        f"finished {len(report['finished'])} runs, skipped {len(report['skipped'])} groups, "
        f"narrowed {len(report['narrowed'])}, {len(report['failed'])} failed; {report['exported']} runs in {out}"
    )
    return report


def plan(slices: list[list[RunSpec]], root: Path, names: list[str]) -> list[str]:
    """What :func:`run_study` would train, as lines: per slice (``names``, e.g. its spec's file),
    its groups in order, each with its runs, its datasets (made already, or to make) and one
    run's estimate on the reference CPU host (what the deadline's first guess scales; a group is
    one program, timed on the accelerator by its first chunks)."""
    lines = []
    for name, runs in zip(names, slices):
        jobs = planning.jobs(runs, root, "vmap")
        lines.append(
            f"{name}: {sum(len(job) for job in jobs)} runs to train, {len(jobs)} group{'s' * (len(jobs) != 1)}"
        )
        for job in jobs:
            data = []
            for dataset in dict.fromkeys(run.dataset for run in job):
                config = job[0].train_config()
                made = sources.kind(dataset) != "builtin" or generate.is_current(
                    generate.dataset_path(dataset, config.cache_dir), dataset
                )
                data.append(dataset if made else f"{dataset} (to make)")
            seconds = max(planning.estimate_seconds(r, run_status.status(r, root)[1]) for r in job)
            label = f"{job_name(job)} ({len(job)} run{'s' * (len(job) > 1)})"
            lines.append(
                f"  {label}: {', '.join(data)}; {timing.duration(seconds)} a run on the reference CPU host"
            )
    return lines


def check_out(out: str | Path) -> Path:
    """``out`` as a directory a study may write: new, empty, or one a study wrote before."""
    path = paths.expand(out)
    if path.exists() and not path.is_dir():
        raise ValueError(f"--out {out} is a file: give a directory for the study's results")
    if path.is_dir():
        foreign = [
            p.name for p in path.iterdir() if p.name not in OUT_FILES and not p.name.startswith(".")
        ]
        if foreign:
            raise ValueError(
                f"--out {out} holds other files ({', '.join(sorted(foreign)[:3])}): give an empty "
                "directory or one a study wrote"
            )
    return path
