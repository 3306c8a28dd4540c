"""A probe of bad inputs, faults and misuses: some 830 cases in seven classes, each judged good or bad.

    nice python benchmarks/probe.py                  # every case, about 6.5 minutes on 2 cores
    nice python benchmarks/probe.py --classes 1 3    # only those classes
    python benchmarks/probe.py --list                # the cases, without running them
    nice python benchmarks/probe.py --subprocess     # each case as `python -m eabc.cli` (slower)

The classes: 1 another run's files (checkpoint, config.json, log.csv, summary.json) put into a
run; 2 a run's files deleted, cut short or edited (results must not be lost or replaced silently);
3 malformed input (dataset files, config.json, checkpoints, FIFOs, sweep specs) that could end in
a traceback or a hang; 4 inputs that could be found bad only after work (reference scores, cache
and run directories, environments, sweeps, reports); 5 numbers, settings and sweep specs of the
wrong shape; 6 reports and results of runs without reference scores; 7 Ctrl-C while train, sac or
sweep works (exit code 130, one line that says how to go on, no temporary file left).

The probe first trains a few tiny runs (TD3+BC and BC, 32-unit networks, 200 steps on 40
transitions; about a minute) into a scratch folder. Each case then gets a fresh directory with
copies of what it needs, runs one ``eabc`` command there with a timeout (forked from this process,
which imported eabc once, so that a case costs well under a second) and is judged:

- good: it worked correctly (exit code 0 and the case's check of the result holds), or it was
  refused in one ``error:`` line, with an exit code other than 0, naming the file, flag or key,
  and nothing in the directory changed;
- bad: a traceback, no answer within the timeout (a hang), exit code 0 on bad input, a refusal
  that names none of them or changed the directory, or a result that fails the case's check.

It prints every bad case, then the totals per class under the host line. The exit code is 1 when
any case is bad. docs/guarantees.md says what the probe covers.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import machine  # noqa: E402
import probe_cases  # noqa: E402
from probe_cases.case import Case, Outcome  # noqa: E402

MEMORY = 6 << 30
"""Each case's address-space limit: a reader that never stops (a link to /dev/zero) ends in a
MemoryError (a bad case) rather than in the kernel's OOM killer choosing among the machine's
processes."""
CLASSES = {
    1: "another run's files",
    2: "files deleted or edited",
    3: "malformed input",
    4: "checked too late",
    5: "numbers and specs",
    6: "no reference scores",
    7: "interrupted",
}


def snapshot(folder: Path) -> dict[str, str]:
    """Every path under ``folder`` and a hash of its content (its kind for other than files)."""
    out = {}
    for path in sorted(folder.rglob("*")):
        if path.is_symlink():
            out[str(path.relative_to(folder))] = "link:" + os.readlink(path)
        elif path.is_file():
            out[str(path.relative_to(folder))] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            out[str(path.relative_to(folder))] = "dir" if path.is_dir() else "other"
    return out


def changes(before: dict[str, str], after: dict[str, str]) -> str:
    """What differs between two snapshots, in a few words."""
    made = sorted(set(after) - set(before))
    gone = sorted(set(before) - set(after))
    edited = sorted(k for k in set(before) & set(after) if before[k] != after[k])
    parts = [f"{word} {', '.join(names[:3])}" for word, names in
             (("made", made), ("removed", gone), ("changed", edited)) if names]  # fmt: skip
    return "; ".join(parts)


def run_forked(
    argv: list[str], folder: Path, env: dict[str, str], timeout: float, interrupt=None
) -> Outcome:
    """``eabc ARGV`` in ``folder``, in a child forked from this process (which has imported eabc
    and started no thread, so the fork is safe); killed after ``timeout`` seconds."""
    from eabc import cli  # noqa: PLC0415

    out_path, err_path = (
        folder.parent / f".{folder.name}.out",
        folder.parent / f".{folder.name}.err",
    )
    start = time.perf_counter()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        code = 70
        try:
            resource.setrlimit(resource.RLIMIT_AS, (MEMORY, MEMORY))
            # Ctrl-C as a terminal gives it: a probe started in the background has SIGINT ignored
            # (as a shell does for its background jobs), and its children would inherit that.
            signal.signal(signal.SIGINT, signal.default_int_handler)
            os.chdir(folder)
            os.environ.update({k: str(folder / v) if v.startswith(".") else v
                               for k, v in env.items()})  # fmt: skip
            for fd, path in ((1, out_path), (2, err_path)):
                os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), fd)
            try:
                cli.main(argv)
                code = 0
            except SystemExit as exit_:
                code = exit_.code if isinstance(exit_.code, int) else 1
                if isinstance(exit_.code, str):
                    print(exit_.code, file=sys.stderr)
            except BaseException:  # noqa: BLE001 (what the interpreter would print, then exit 1)
                import traceback  # noqa: PLC0415

                traceback.print_exc()
                code = 1
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)
    timed_out, seen = False, None
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if interrupt is not None and seen is None and (folder / interrupt).exists():
            seen = time.perf_counter()
        if seen is not None and time.perf_counter() - seen > 1.0:
            os.kill(pid, signal.SIGINT)  # once: a second Ctrl-C is another case
            seen, interrupt = -math.inf, None
        if time.perf_counter() - start > timeout:
            os.kill(pid, signal.SIGKILL)
            _, status = os.waitpid(pid, 0)
            timed_out = True
            break
        time.sleep(0.02)
    seconds = time.perf_counter() - start
    out, err = (p.read_text(errors="replace") for p in (out_path, err_path))
    out_path.unlink()
    err_path.unlink()
    return Outcome(os.waitstatus_to_exitcode(status), out, err, seconds, timed_out)


def run_subprocess(
    argv: list[str], folder: Path, env: dict[str, str], timeout: float, interrupt=None
) -> Outcome:
    """``python -m eabc.cli ARGV`` in ``folder``."""
    environment = {**os.environ, **{k: str(folder / v) if v.startswith(".") else v
                                    for k, v in env.items()}}  # fmt: skip
    start = time.perf_counter()
    if interrupt is not None:
        proc = subprocess.Popen([sys.executable, "-m", "eabc.cli", *argv], cwd=folder,
                                env=environment, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, preexec_fn=_limit_memory)  # fmt: skip
        while proc.poll() is None and not (folder / interrupt).exists():
            if time.perf_counter() - start > timeout:
                break
            time.sleep(0.02)
        time.sleep(1.0)
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=max(timeout - (time.perf_counter() - start), 1))
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            return Outcome(-9, out, err, timeout, True)
        return Outcome(proc.returncode, out, err, time.perf_counter() - start)
    try:
        done = subprocess.run([sys.executable, "-m", "eabc.cli", *argv], cwd=folder,
                              env=environment, capture_output=True, text=True, timeout=timeout,
                              preexec_fn=_limit_memory)  # fmt: skip
    except subprocess.TimeoutExpired as error:
        text = lambda b: b.decode(errors="replace") if isinstance(b, bytes) else (b or "")  # noqa: E731
        return Outcome(-9, text(error.stdout), text(error.stderr), timeout, True)
    return Outcome(done.returncode, done.stdout, done.stderr, time.perf_counter() - start)


def _limit_memory() -> None:
    """In the command's process before it starts: the memory limit, and SIGINT at its default
    (ignored in a probe started in the background, which its children would inherit)."""
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY, MEMORY))
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def verdict(case: Case, outcome: Outcome, before: dict, after: dict, folder: Path) -> str | None:
    """Why the case went badly, or None when it went well (see the module docstring)."""
    if outcome.timed_out:
        return f"no answer within {case.timeout:.0f} s (a hang)"
    lines = [line for line in outcome.err.splitlines() if line.strip()]
    if any(line.startswith("Traceback (most recent call last)") for line in lines):
        return f"a traceback: {lines[-1][:200]}"
    if case.expect == "interrupted":
        last = lines[-1] if lines else ""
        if outcome.code != 130 or "interrupted" not in last:
            return f"Ctrl-C ended in exit {outcome.code}, not 130 with one line: {last[:200]!r}"
        if case.names and not any(name in last for name in case.names):
            return f"the interruption names none of {list(case.names)}: {last[:200]}"
        return case.check(folder, outcome) if case.check is not None else None
    if outcome.code != 0:
        last = lines[-1] if lines else ""
        if case.expect == "work":
            return f"refused a good input (exit {outcome.code}): {last[:200]}"
        if not last.startswith("error: "):
            return f"exit {outcome.code} without an error line: {last[:200]!r}"
        if sum(line.startswith("error") for line in lines) > 1:
            return f"more than one error line: {last[:200]}"
        if case.names and not any(name in last for name in case.names):
            return f"the error names none of {list(case.names)}: {last[:200]}"
        if before != after:
            return f"refused but changed the directory ({changes(before, after)}): {last[:150]}"
        return None
    if case.expect == "refuse":
        return f"exit 0 on bad input: {(lines or outcome.out.splitlines() or [''])[-1][:200]}"
    if case.read_only and before != after:
        return f"changed the directory ({changes(before, after)}) where it only reads"
    if case.check is not None:
        return case.check(folder, outcome)
    return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--classes", type=int, nargs="*", default=sorted(CLASSES))
    parser.add_argument("--list", action="store_true", help="list the cases and stop")
    parser.add_argument("--subprocess", action="store_true", help="each case as its own process")
    parser.add_argument("--scratch", help="scratch folder (default: a new temporary one, removed)")
    parser.add_argument("--keep", action="store_true", help="keep the scratch folder")
    parser.add_argument("--verbose", action="store_true", help="print every case as it ends")
    args = parser.parse_args()
    os.nice(10)

    scratch = Path(args.scratch or tempfile.mkdtemp(prefix="eabc-probe-")).resolve()
    scratch.mkdir(parents=True, exist_ok=True)
    base = scratch / "base"
    cases = [c for c in probe_cases.all_cases(base) if c.group in args.classes]
    if args.list:
        for case in cases:
            print(f"{case.group} {case.expect:<6} {case.name}: eabc {' '.join(case.argv)}")
        print(f"{len(cases)} cases")
        return 0
    os.environ.update({"EABC_CACHE_DIR": str(scratch / "cache"),
                       "EABC_COMPILE_CACHE": str(scratch / "xla"), "MPLBACKEND": "Agg"})  # fmt: skip
    from eabc import cli  # noqa: PLC0415, F401 (imported once, before any fork)

    run = run_subprocess if args.subprocess else run_forked
    start = time.perf_counter()
    probe_cases.make_base(base, lambda argv, folder: run(argv, folder, {}, 600))
    made = time.perf_counter() - start
    base_before = snapshot(base)
    shutil.rmtree(scratch / "cases", ignore_errors=True)  # an interrupted earlier probe's
    totals = {group: [0, 0] for group in CLASSES}
    bad = []
    for i, case in enumerate(cases):
        folder = scratch / "cases" / f"{i:04d}"
        folder.mkdir(parents=True)
        case.prepare(folder)
        before = snapshot(folder)
        outcome = run(case.argv, folder, case.env, case.timeout, case.interrupt)
        why = verdict(case, outcome, before, snapshot(folder), folder)
        totals[case.group][why is None] += 1
        if why is not None:
            bad.append((case, why))
        if args.verbose or why is not None:
            mark = "BAD " if why else "good"
            print(f"{mark} [{case.group}] {case.name} ({outcome.seconds:.1f} s): eabc "
                  f"{' '.join(case.argv)}" + (f"\n       {why}" if why else ""), flush=True)  # fmt: skip
        shutil.rmtree(folder, ignore_errors=True)
    if snapshot(base) != base_before:
        print(
            f"BAD: a case changed the shared runs and data: {changes(base_before, snapshot(base))}"
        )
        bad.append((None, "base changed"))
    print()
    print(machine.host_line())
    print(
        f"{len(cases)} cases in {time.perf_counter() - start:.0f} s ({made:.0f} s making the "
        f"tiny runs){' as subprocesses' if args.subprocess else ''}"
    )
    print("| class | cases | good | bad |")
    print("|---|---:|---:|---:|")
    for group, (bad_count, good) in totals.items():
        if good or bad_count:
            print(f"| {group} {CLASSES[group]} | {good + bad_count} | {good} | {bad_count} |")
    all_bad = sum(b for b, _ in totals.values())
    print(f"| all | {len(cases)} | {len(cases) - all_bad} | {all_bad} |")
    if not args.keep and not args.scratch:
        shutil.rmtree(scratch, ignore_errors=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
