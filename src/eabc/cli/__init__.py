"""The ``eabc`` command line, generated from typed dataclasses (``eabc --help``, ``eabc train --help``).

One module per group of commands: :mod:`~eabc.cli.train` (train, evaluate, sac, export-policy),
:mod:`~eabc.cli.experiments` (sweep, results, report), :mod:`~eabc.cli.study` (study), :mod:`~eabc.cli.data` (data, zoo);
:mod:`~eabc.cli.options` holds what they share. :func:`main` dispatches.

A command module imports what a command runs (training, sweeps, reports, the data makers) inside
the function that runs it: building the parser needs only the settings' dataclasses, so every
``--help`` and every refused flag answers without loading the rest (about a fifth sooner).
Everywhere else in the package imports sit at the top of the module, unless an
optional extra needs them or the line says why (``tests/repository/test_architecture.py``).
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sys
import threading
from typing import Annotated, Any, Union

import tyro

from eabc import __version__, compile_cache
from eabc.cli.data import (
    DataExport,
    DataInfo,
    DataList,
    DataMake,
    ZooBuild,
    ZooPack,
    run_data,
    run_zoo,
)
from eabc.cli.experiments import (
    SWEEP_PRESETS,
    Report,
    Results,
    Sweep,
    run_report,
    run_results,
    run_sweep,
    sweep_spec,
)
from eabc.cli.options import (
    RESUME_OPTIONS,
    Interrupted,
    _checked,
    check_agent,
    check_flags,
    one_line_errors,
    parse_settings,
    quiet_unset_defaults,
    refuse_ignored_with_resume,
    refuse_repeated_flags,
)
from eabc.cli.study import Study, run_study
from eabc.cli.train import (
    Evaluate,
    ExportPolicy,
    Sac,
    Train,
    run_evaluate,
    run_sac,
    run_train,
    sac_agent_config,
)
from eabc.training.config import TrainConfig
from eabc.training.online import SACTrainConfig

__all__ = [
    "SWEEP_PRESETS", "DataExport", "DataInfo", "DataList", "DataMake", "Evaluate", "ExportPolicy",
    "Report", "Results", "Sac", "Study", "Sweep", "Train", "ZooBuild", "ZooPack", "main", "parse", "parse_settings",
    "sac_agent_config", "sweep_spec",
]  # fmt: skip


def _export_policy(cmd: ExportPolicy) -> None:
    from eabc import deploy, paths  # noqa: PLC0415

    # Never over the run's own files, nor over what is not a regular file (/dev/null, a folder).
    paths.check_output_file(cmd.onnx, "--onnx", protected=cmd.run_dir, ours=deploy.PRODUCER_MARK)
    print(deploy.export_onnx(cmd.run_dir, cmd.onnx))


HANDLERS = {
    Train: run_train, Evaluate: run_evaluate, Sac: run_sac, Sweep: run_sweep, Study: run_study,
    Results: run_results, Report: run_report, ExportPolicy: _export_policy,
    ZooBuild: run_zoo, ZooPack: run_zoo,
    DataMake: run_data, DataInfo: run_data, DataList: run_data, DataExport: run_data,
}  # fmt: skip
"""Each command's function, by the command's parsed dataclass."""


def main(argv: list[str] | None = None) -> None:
    """The ``eabc`` command; output piped into a reader that stops early (``eabc --help | head``)
    ends it quietly, and Ctrl-C in one line (exit code 130) that says how to continue."""
    try:
        _main(argv)
    except BrokenPipeError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # Python's advice: no second error at exit
        sys.exit(1)
    except KeyboardInterrupt as interrupt:  # Ctrl-C: one line, no traceback, a shell's 130
        if isinstance(interrupt, Interrupted):
            message = str(interrupt)
        else:  # a signal raised as an interrupt names itself (SIGTERM)
            message = "interrupted" + (f" ({interrupt.args[0]})" if interrupt.args else "")
        print(message, file=sys.stderr, flush=True)
        sys.exit(130)


COMMANDS: dict[str, type] = {
    "train": Train,
    "evaluate": Evaluate,
    "sac": Sac,
    "sweep": Sweep,
    "study": Study,
    "results": Results,
    "report": Report,
    "export-policy": ExportPolicy,
    "data": DataList,
    "zoo": ZooPack,
}
"""The commands of ``eabc``; ``data`` and ``zoo`` have a second level (:data:`GROUPS`)."""

GROUPS: dict[str, tuple[dict[str, type], str]] = {
    "data": (
        {"make": DataMake, "list": DataList, "info": DataInfo, "export": DataExport},
        "Datasets: make the built-in ones, list the cache, describe any dataset, export to Minari.",
    ),
    "zoo": (
        {"build": ZooBuild, "pack": ZooPack},
        "The behaviour-policy zoo: build an entry from an `eabc sac` run, or pack a run.",
    ),
}


def _subcommands(commands: dict[str, type]):
    """``commands`` as tyro's subcommands, each described by its docstring, and a group
    (``data``, ``zoo``) by its own text, not by the command class standing for it."""
    groups = {name: text for name, (_, text) in GROUPS.items()} if commands is COMMANDS else {}
    return Union[  # noqa: UP007 (built from a tuple, which X | Y cannot take)
        tuple(
            Annotated[
                Any,
                tyro.conf.subcommand(name=name, constructor=cls, description=groups.get(name)),
            ]
            for name, cls in commands.items()
        )
    ]


for _command in {*COMMANDS.values(), *(c for group, _ in GROUPS.values() for c in group.values())}:
    quiet_unset_defaults(_command)


def parse(argv: list[str]):
    """The command ``eabc ARGV`` names, parsed and checked as ``main`` does before running it: a
    bad flag or value raises ``ValueError`` in one line naming the flag (``--help`` exits)."""
    commands = COMMANDS
    prog = "eabc"
    description = "EABC: ensemble-based offline RL with adaptive behaviour cloning."
    if argv[:1] and argv[0] in GROUPS:  # eabc data {make,list,...}, eabc zoo {build,pack}
        commands, description = GROUPS[argv[0]]
        prog = f"eabc {argv[0]}"
        argv = argv[1:]
    command = f"{prog} {argv[0]}" if argv[:1] and argv[0] in commands else prog
    refuse_repeated_flags(argv)  # the parser would keep the last value without a word
    with one_line_errors(argv, command):  # a bad value: one error line, not tyro's box
        cmd = tyro.cli(
            _subcommands(commands),
            args=argv,
            prog=prog,  # not the interpreter's path to the entry point
            description=description,
            config=(tyro.conf.DisallowNone,),  # --env STR, not --env {None}|STR
        )
    if isinstance(cmd, Train | Sac):  # checked here, so that errors name the flags
        config_class = TrainConfig if isinstance(cmd, Train) else SACTrainConfig
        cmd = dataclasses.replace(cmd, config=_checked(cmd.config, config_class))
    if isinstance(cmd, Train | Sac) and cmd.resume:  # no option resume would silently ignore
        sac = {"resume", "progress", "no-progress"}
        refuse_ignored_with_resume(argv, RESUME_OPTIONS if isinstance(cmd, Train) else sac)
    if isinstance(cmd, Train) and not cmd.resume:  # the algorithm's settings, named as flags
        check_agent(cmd.config, cmd.agent, cmd.set)
    check_flags(cmd)  # the other numbers: ranges declared on the command's fields
    return cmd


def exit_on_sigterm() -> None:
    """SIGTERM (``kill PID``, a scheduler stopping a job) unwinds like Ctrl-C, so that a run lets
    go of its lock and removes ``RUN_DIR/.lock`` (a run killed by SIGKILL leaves the file; the
    next writer takes it over). Only the main thread may set a handler."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))


def _main(argv: list[str] | None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] in (["--version"], ["-V"]):
        print(f"eabc {__version__}")
        return
    try:
        cmd = parse(argv)
    except ValueError as error:  # invalid settings caught in a dataclass __post_init__
        sys.exit(f"error: {error}")
    options = getattr(cmd, "config", cmd)
    exit_on_sigterm()
    try:
        compile_cache.enable(cache_root=getattr(options, "cache_dir", None))
        HANDLERS[type(cmd)](cmd)
    except (ValueError, FileNotFoundError, FileExistsError, RuntimeError) as error:
        sys.exit(f"error: {error}")
    except BrokenPipeError:  # the reader stopped early: main ends quietly
        raise
    except OSError as error:  # e.g. a directory where a file should be, no permission
        if not error.filename:  # say what failed rather than an empty name
            sys.exit(f"error: {error.strerror or error}")
        sys.exit(f"error: {error.filename}: {error.strerror or error}; check that path")
