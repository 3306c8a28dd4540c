"""Experiment sweeps: each run in its own directory, resumable, local or on Ray.

What a sweep runs comes from a specification (:mod:`eabc.experiments.spec`, the YAML format and
its expansion; :mod:`eabc.experiments.presets`, the paper's and the study's grids). This module
runs it: the state of each run on disk, the plan and its cost, and the two backends.

Seeds of one setting form a *group*. A group runs either as one process that trains its seeds
together, vectorised with ``vmap`` (fastest on a GPU), or as one single-threaded process per seed
(fastest on a few CPU cores); ``layout="auto"`` picks by the JAX backend.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from eabc import compile_cache, paths, timing
from eabc.agents import get_algorithm
from eabc.data import generate
from eabc.experiments.spec import RunSpec, differences, groups, is_path, job_name
from eabc.training import trainer
from eabc.training.directory import SUMMARY

RUNS = "runs"
SPEC = "sweep.json"
"""What a sweep knows about one of its runs (its spec and variant label)."""


def status(run: RunSpec, root: Path) -> tuple[str, int]:
    """The state of a run and the steps done so far: ``done`` (also when it stopped on NaN/inf),
    ``partial`` (has a checkpoint), ``pending``, ``changed`` (its directory holds a run of another
    spec, or of more steps than asked) or ``broken`` (a file of it cannot be read)."""
    return _status(run, root)[:2]


def _status(run: RunSpec, root: Path) -> tuple[str, int, str]:
    """:func:`status` and why, in words (for ``changed`` and ``broken``)."""
    from eabc import pytree  # noqa: PLC0415
    from eabc.training import checkpoint  # noqa: PLC0415
    from eabc.training.directory import lost_progress  # noqa: PLC0415

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
            return "partial", int(pytree.find(checkpoint.load_raw(run_dir)["agent"], "step")), ""
        except (ValueError, KeyError, TypeError) as error:
            return "broken", 0, str(error)
    train = run.train_config()  # a run past its first checkpoint is not started again unasked
    lost = lost_progress(run_dir, train.steps, train.checkpoint_interval)
    if lost:
        return "broken", 0, f"{lost}; restore it, or delete the run directory to train it again"
    return "pending", 0, ""


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
        state, _, why = _status(run, root)
        if state in out:
            out[state].append(why)
    return out


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
    from eabc.experiments import results  # noqa: PLC0415

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


def prepare_datasets(runs: list[RunSpec], log=lambda line: print(line, flush=True)) -> None:
    """Make the missing built-in datasets once, here, before jobs that share them start."""
    seen = set()
    for run in runs:
        config = run.train_config()
        path = generate.dataset_path(config.dataset, config.cache_dir)
        if (
            config.dataset in generate.builtin_names()
            and path not in seen
            and not generate.is_current(path, config.dataset)
        ):
            seen.add(path)
            log(f"making {config.dataset} into {path}")
            generate.make(config.dataset, path)


def default_layout() -> str:
    import jax  # noqa: PLC0415

    return "vmap" if jax.default_backend() in ("gpu", "cuda", "rocm", "tpu") else "processes"


def jobs(runs: list[RunSpec], root: Path, layout: str) -> list[list[RunSpec]]:
    """The unfinished runs as jobs: a seed group per job (vmap) or one run per job."""
    todo = [r for r in runs if status(r, root)[0] in ("partial", "pending")]
    if layout == "vmap":
        return groups(todo)
    return [[r] for r in todo]


def execute(job: list[dict], root: str, eval_workers: Any = 0) -> list[dict]:
    """Run one job in this process: start or resume each run, then train them as one program
    (:func:`eabc.training.trainer.train_runs`); ``eval_workers``: evaluation processes, or an
    evaluation pool shared with other jobs (``eabc.training.eval_pool``; 0 evaluates in this
    process)."""
    from eabc.data.sources import load_dataset  # noqa: PLC0415
    from eabc.training import checkpoint, lifecycle  # noqa: PLC0415

    root_path = Path(root)
    specs = [RunSpec.from_json(j) for j in job]
    first = specs[0].train_config()
    compile_cache.enable(cache_root=first.cache_dir)  # a sweep's runs share their shapes
    loaded = {}  # one copy of each dataset for the whole group
    runs = []
    for spec in specs:
        if spec.dataset not in loaded:
            loaded[spec.dataset] = load_dataset(spec.dataset, first.cache_dir)
        dataset = loaded[spec.dataset]
        run_dir = root_path / RUNS / spec.run_id
        state, _, why = _status(spec, root_path)
        if state in ("changed", "broken"):
            raise ValueError(f"{why}; move that run directory away or use another sweep root")
        if (run_dir / checkpoint.CONFIG).exists():  # from step 0 if it has no checkpoint yet
            runs.append(lifecycle.resume(run_dir, dataset, steps=spec.train_config().steps))
        else:
            runs.append(
                lifecycle.start(spec.train_config(), run_dir, dict(spec.overrides), dataset)
            )
        identity = {"fingerprint": dataset.fingerprint(), **spec.to_json()}  # steps: the latest
        checkpoint.save_json(
            run_dir / SPEC, {"run_id": spec.run_id, "variant": spec.variant, **identity}
        )
    # Progress as lines in the job's log (ROOT/logs/NAME.log): its start with the estimate, one
    # a minute, its end.
    summaries = (
        trainer.train_runs(runs, progress=True, eval_workers=eval_workers)
        if len(runs) > 1
        else [trainer.train(runs[0], progress=True, eval_workers=eval_workers)]
    )
    return summaries


def _absolute(run: RunSpec) -> dict:
    """``run`` as JSON with its dataset file and cache directory as absolute paths."""
    data = run.to_json()
    if is_path(run.dataset):
        data["dataset"] = str(paths.expand(run.dataset).resolve())
    if data["train"].get("cache_dir"):
        data["train"]["cache_dir"] = str(paths.expand(data["train"]["cache_dir"]).resolve())
    return data


SINGLE_THREAD = {
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}


def archived_done(runs: list[RunSpec], archives: list[tuple[Any, Any]]) -> set[str]:
    """The ids of ``runs`` that an earlier report (``results.read_archive``) holds as done with
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
    from eabc.training.lock import in_use  # noqa: PLC0415

    for other in roots:
        if status(run, other)[0] == "done":
            return f"done in {other}"
        if in_use(other / RUNS / run.run_id):
            return f"being trained in {other}"
    return None


def parse_duration(text: str) -> float:
    """Seconds in ``90s``, ``45m``, ``2.5h`` (a bare number is minutes)."""
    units = {"s": 1.0, "m": 60.0, "h": 3600.0}
    value, unit = (text[:-1], text[-1]) if text and text[-1] in units else (text, "m")
    try:
        seconds = float(value) * units[unit]
    except ValueError:
        seconds = math.nan
    if not seconds > 0 or not math.isfinite(seconds):
        raise ValueError(
            f"a duration is a positive number with s, m or h (90s, 45m, 2.5h), got {text!r}"
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


def run_local(
    job_list: list[list[RunSpec]],
    root: Path,
    workers: int | None = None,
    single_thread: bool = True,
    log=lambda line: print(line, flush=True),  # a line in a log file as it happens
    deadline: float | None = None,
    taken: Any = None,
    speed: timing.HostSpeed = timing.REFERENCE,
) -> None:
    """A pool of ``workers`` subprocesses (default: one per CPU core), one job each at a time.

    Every job is ``python -m eabc.experiments.worker ROOT JOB_JSON``; a killed sweep (SIGINT,
    SIGTERM, or SIGKILL, which the workers notice themselves) stops its workers, and the runs
    resume from their checkpoints next time. With a ``deadline`` (``time.time()`` seconds) a job
    starts only if its estimate (:func:`job_estimates`, taken anew whenever a worker is free, so
    that the runs measured so far set the speeds) ends by then; the rest are left for a later
    sweep and named in the log (the reference rates times ``speed`` for runs not measured yet).
    Each start and end is a line of ``log``, with how many jobs are done. ``taken(run)`` (e.g. :func:`taken_elsewhere`), asked as a job is
    about to start, says why a run is not to be trained here after all (None: train it).
    """
    from eabc.experiments.worker import PARENT  # noqa: PLC0415

    workers = workers or os.cpu_count() or 1
    env = {**os.environ, **(SINGLE_THREAD if single_thread else {}), PARENT: str(os.getpid())}
    previous = _exit_on_sigterm()
    pending = list(job_list)
    total, ended = len(job_list), 0
    left_out: list[str] = []
    active: list[tuple[subprocess.Popen, list[RunSpec], Any]] = []
    logs = root / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    failures = []
    try:
        while pending or active:
            while pending and len(active) < workers:
                if deadline is not None:
                    costs = job_estimates(pending, root, speed)
                    index = next_job(pending, costs, time.time(), deadline)
                    index = len(pending) if index is None else index
                    for job in pending[:index]:  # they would not finish before the deadline
                        left_out.append(job_name(job))
                    del pending[:index]
                    if not pending:
                        break
                job = pending.pop(0)
                if taken is not None:
                    reasons = {run.run_id: taken(run) for run in job}
                    for run_id, why in reasons.items():
                        if why:
                            log(f"not starting {run_id}: {why}")
                    job = [run for run in job if not reasons[run.run_id]]
                    if not job:
                        continue
                name = job_name(job)
                payload = json.dumps([r.to_json() for r in job])
                cmd = [sys.executable, "-m", "eabc.experiments.worker", str(root), payload]
                out = None
                try:  # a job that cannot start fails alone: the running ones go on
                    out = open(logs / f"{name}.log", "ab")  # noqa: SIM115
                    proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=out)
                except OSError as error:
                    if out is not None:
                        out.close()
                    failures.append(name)
                    log(f"FAILED {name}: it could not start ({error}); the other jobs go on")
                    continue
                active.append((proc, job, out))
                log(
                    f"started {name} ({len(job)} run{'s' * (len(job) > 1)}; {ended} of {total} jobs done)"
                )
            time.sleep(0.2)
            for proc, job, out in list(active):
                if proc.poll() is None:
                    continue
                active.remove((proc, job, out))
                out.close()
                ended += 1
                name = job_name(job)
                if proc.returncode:
                    failures.append(name)
                    log(
                        f"FAILED {name} (exit {proc.returncode}); see {logs / (name + '.log')} "
                        f"({ended} of {total} jobs done)"
                    )
                else:
                    log(f"finished {name} ({ended} of {total} jobs done)")
    finally:
        for proc, _, _out in active:
            proc.terminate()
        for proc, _, out in active:
            proc.wait()
            out.close()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if left_out:
        log(
            f"left for a later sweep ({len(left_out)}, their estimates end after the deadline): "
            + ", ".join(left_out)
        )
    if failures:
        raise RuntimeError(f"{len(failures)} job(s) failed: {', '.join(failures)}")


def _exit_on_sigterm():
    """Make SIGTERM unwind like Ctrl-C (so the pool stops its workers); the old handler, or
    None off the main thread, where Python cannot set one."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def stop(signum, frame):
        raise SystemExit(128 + signum)

    return signal.signal(signal.SIGTERM, stop)


def run_ray(
    job_list: list[list[RunSpec]],
    root: Path,
    address: str = "auto",
    num_cpus: float = 1.0,
    num_gpus: float = 0.0,
    log=lambda line: print(line, flush=True),
) -> None:
    """One Ray task per job with declared CPU/GPU resources; ``root`` must be a shared directory.

    Paths go to the workers absolute (the root, dataset files, the cache directory): a worker's
    working directory is not the driver's.
    """
    try:
        import ray  # noqa: PLC0415
    except ImportError:
        raise RuntimeError("--backend ray needs the ray package: pip install 'eabc[ray]'") from None

    root = paths.expand(root).resolve()
    if not ray.is_initialized():
        ray.init(address=address, log_to_driver=False)
    env_vars = SINGLE_THREAD if num_gpus == 0 and num_cpus <= 1 else {}
    remote = ray.remote(execute).options(
        num_cpus=num_cpus, num_gpus=num_gpus, runtime_env={"env_vars": env_vars}, max_retries=2
    )
    futures = {remote.remote([_absolute(r) for r in job], str(root)): job for job in job_list}
    failures = []
    while futures:
        done, _ = ray.wait(list(futures), num_returns=1)
        job = futures.pop(done[0])
        name = job_name(job)
        try:
            ray.get(done[0])
            log(f"finished {name}")
        except Exception as error:  # noqa: BLE001 (report every failed job, then raise)
            failures.append(name)
            log(f"FAILED {name}: {error}")
    if failures:
        raise RuntimeError(f"{len(failures)} Ray job(s) failed: {', '.join(failures)}")
