"""Classes 1 and 2 of the probe: another run's files put into a run, and a run's files deleted,
cut short or edited."""

from __future__ import annotations

from pathlib import Path

from probe_cases.case import Case
from probe_cases.common import (
    EVAL,
    EXPORT,
    RESULTS,
    RESUME,
    copy_from,
    edit,
    edit_json,
    intact_after_resume,
    listed,
    run_copy,
    then,
    unchanged_and_says,
    write,
)


def foreign_files(base: Path) -> list[Case]:
    """Another run's checkpoint or config.json in a run: every reader refuses it (results lists
    the run as damaged or broken); another run's log.csv or summary.json is reported as damaged
    by results, and resume rebuilds the log from the checkpoint or refuses."""
    cases = []
    for target in ("A", "B"):
        for source in ("A", "B", "C", "D", "E", "F", "R"):
            if source == target:
                continue
            for file in ("checkpoint.msgpack", "config.json"):
                prepare = then(run_copy(base, target), copy_from(base, source, file))
                label = f"{target}'s run with {source}'s {file}"
                names = ("run/checkpoint.msgpack", "run/config.json")
                cases += [
                    Case(1, f"{label}: evaluate", EVAL, "refuse", prepare, names),
                    Case(1, f"{label}: resume", RESUME, "refuse", prepare, names),
                    Case(1, f"{label}: export-policy", EXPORT, "refuse", prepare, names),
                    Case(1, f"{label}: results", RESULTS, "work", prepare,
                         check=listed(base, target, names, contradiction=True)),
                ]  # fmt: skip
    for source in ("B", "C", "F", "R"):
        for file in ("log.csv", "summary.json"):
            prepare = then(run_copy(base), copy_from(base, source, file))
            label = f"A's run with {source}'s {file}"
            cases += [
                Case(1, f"{label}: results", RESULTS, "work", prepare,
                     check=listed(base, "A", ("run/log.csv", "run/summary.json"), True)),
                Case(1, f"{label}: resume", RESUME, "either", prepare, (f"run/{file}",),
                     check=intact_after_resume(base)),
            ]  # fmt: skip
    return cases


# ----------------------------------------------------------------------------------------------
# 2. A run's files deleted, cut short or edited


def _log_lines(change):
    """An edit of log.csv by its lines (header first, each with its line end)."""
    return edit("run/log.csv", lambda text: "".join(change(text.splitlines(keepends=True))))


def _edit_cell(column: str, value: str, row: int = 2):
    def change(lines):
        header = lines[0].rstrip("\r\n").split(",")
        cells = lines[row].rstrip("\r\n").split(",")
        cells[header.index(column)] = value
        return [*lines[:row], ",".join(cells) + "\n", *lines[row + 1 :]]

    return _log_lines(change)


def _summary(change):
    return edit_json("run/summary.json", change)


DAMAGE = {
    # what is done to the finished run A: (the change, whether the files then contradict)
    "checkpoint deleted": (write("run/checkpoint.msgpack", None), False),
    "log.csv deleted": (write("run/log.csv", None), True),
    "summary.json deleted": (write("run/summary.json", None), False),
    "log.csv and summary.json deleted": (
        then(write("run/log.csv", None), write("run/summary.json", None)), True),
    "checkpoint and summary.json deleted": (
        then(write("run/checkpoint.msgpack", None), write("run/summary.json", None)), False),
    "checkpoint and log.csv deleted": (
        then(write("run/checkpoint.msgpack", None), write("run/log.csv", None)), True),
    "config.json deleted": (write("run/config.json", None), True),
    "curve.png deleted": (write("run/curve.png", None), False),
    "tb deleted": (write("run/tb", None), False),
    "provenance.json deleted": (write("run/provenance.json", None), False),
    "log.csv header only": (_log_lines(lambda lines: lines[:1]), True),
    "log.csv empty": (write("run/log.csv", ""), True),
    "log.csv cut mid-line": (edit("run/log.csv", lambda text: text[:-30]), True),
    "log.csv last row dropped": (_log_lines(lambda lines: lines[:-1]), True),
    "log.csv first row dropped": (_log_lines(lambda lines: lines[:1] + lines[2:]), True),
    "log.csv return edited": (_edit_cell("return_mean", "-1.5"), True),
    "log.csv return emptied": (_edit_cell("return_mean", ""), True),
    "log.csv step edited": (_edit_cell("step", "150"), True),
    "log.csv row repeated": (_log_lines(lambda lines: [*lines, lines[-1]]), True),
    "log.csv row beyond the end": (
        _log_lines(lambda lines: [*lines, lines[-1].replace("200,", "300,", 1)]), True),
    "log.csv binary junk": (write("run/log.csv", b"\x00\xff" * 50), True),
    "summary.json {}": (write("run/summary.json", "{}"), True),
    "summary.json empty": (write("run/summary.json", ""), True),
    "summary.json not JSON": (write("run/summary.json", "{steps: 200"), True),
    "summary.json a list": (write("run/summary.json", "[200]"), True),
    "summary.json steps as text": (_summary(lambda s: {**s, "steps": "200"}), True),
    "summary.json steps 100": (_summary(lambda s: {**s, "steps": 100}), True),
    "summary.json return edited": (_summary(lambda s: {**s, "final_return": 1.0}), True),
    "summary.json evaluations edited": (_summary(lambda s: {**s, "evaluations": 7}), True),
    "temporary files of a killed writer": (
        then(write("run/.checkpoint.msgpack.k1.tmp", b"half"), write("run/.log.csv.k2.tmp", "x")),
        False),
}  # fmt: skip


def deleted_or_edited(base: Path) -> list[Case]:
    """A finished run's files deleted, cut short or edited: results lists it as damaged or
    broken (naming the file) or with its own numbers, never with other numbers or not at all;
    resume refuses (nothing changed) or leaves the run finished with its own numbers, never
    retrained from step 0; evaluate reads and changes nothing."""
    cases = []
    files = ("checkpoint.msgpack", "log.csv", "summary.json", "config.json")
    for name, (damage, contradiction) in DAMAGE.items():
        prepare = then(run_copy(base), damage)
        names = tuple(f"run/{f}" for f in files) + ("run",)
        cases += [
            Case(2, f"{name}: results", RESULTS, "work", prepare,
                 check=listed(base, "A", names, contradiction)),
            Case(2, f"{name}: resume", RESUME, "either", prepare, names,
                 check=intact_after_resume(base)),
            Case(2, f"{name}: evaluate", EVAL, "either", prepare, names, read_only=True,
                 check=unchanged_and_says('"step": 200')),
        ]  # fmt: skip
    # A run killed before its first checkpoint loses nothing by starting again.
    early = then(run_copy(base), write("run/checkpoint.msgpack", None),
                 write("run/summary.json", None), _log_lines(lambda lines: lines[:2]))  # fmt: skip
    cases.append(Case(2, "killed before its first checkpoint: resume", RESUME, "work", early,
                      check=intact_after_resume(base), timeout=120))  # fmt: skip
    return cases
