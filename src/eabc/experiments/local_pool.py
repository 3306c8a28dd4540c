"""A sweep's jobs on this machine: a pool of worker processes
(``python -m eabc.experiments.worker``), one job each at a time, within an optional deadline.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from eabc import timing
from eabc.experiments.job_process import SINGLE_THREAD
from eabc.experiments.planning import job_estimates, next_job
from eabc.experiments.spec import RunSpec, job_name
from eabc.experiments.worker import PARENT


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
