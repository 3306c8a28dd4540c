"""What a probe case is (:class:`Case`) and what its command did (:class:`Outcome`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path


@dataclasses.dataclass
class Outcome:
    """What one command did."""

    code: int
    out: str
    err: str
    seconds: float
    timed_out: bool = False


@dataclasses.dataclass
class Case:
    """One probe: a directory made by ``prepare``, one ``eabc`` command run in it, a verdict."""

    group: int
    """Its class (``CLASSES`` in benchmarks/probe.py)."""
    name: str
    argv: list[str]
    """The command's arguments, relative to the case's directory."""
    expect: str
    """``refuse`` (bad input), ``work`` (good input), ``either`` (a refusal or a correct result)
    or ``interrupted`` (Ctrl-C, see ``interrupt``)."""
    prepare: Callable[[Path], None] = lambda folder: None
    """Makes the case's files in its (empty) directory."""
    names: tuple[str, ...] = ()
    """What a refusal must name (any one of them): a file, a flag, a key."""
    check: Callable[[Path, Outcome], str | None] | None = None
    """Why the result of a command that worked is wrong (None: it is right)."""
    read_only: bool = False
    """Whether a command that worked must leave the directory as it was (evaluate, dry runs)."""
    timeout: float = 60.0
    env: dict[str, str] = dataclasses.field(default_factory=dict)
    """Environment variables for the command (paths relative to the case's directory)."""
    interrupt: str | None = None
    """Ctrl-C (SIGINT) to the command 1 s after this path of the case's directory appears (a
    run's log.csv: it trains); ``expect`` is then ``interrupted``: exit code 130 and one line."""
