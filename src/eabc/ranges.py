"""The ranges of the numbers a user gives (flags, configs, sweep specs), declared once.

A field says its range in its type, ``episodes: Positive = 10``, with :mod:`annotated_types`
constraints that pydantic enforces too (the sweep spec's model); :func:`check` checks one value
against such a type where no pydantic model runs (a dataclass's ``__post_init__``, the command
line's flags) and says what is wrong in one line.

Seeds are unsigned 32-bit integers: they go to NumPy and to ``jax.random.PRNGKey``, which keeps
only the low 32 bits of a larger seed (``PRNGKey(2**32 + 5)`` is ``PRNGKey(5)``), so a seed outside
``[0, 2**32 - 1]`` would silently be another run's. Step counts, intervals of steps and batch sizes
are at most ``2**31 - 1``: an agent's step counter is a 32-bit integer (``jnp.int32``), as are the
indices a batch is sampled with, so a longer run would wrap its counter round.

What no type can bound, the memory a setting asks for (a batch, a dataset, a replay buffer), is
checked by :func:`check_memory` against what this machine has free, before anything is written.
"""

from __future__ import annotations

import math
import numbers
import operator
import os
import types
import typing
from typing import Annotated

import annotated_types

SEED_MAX = 2**32 - 1
Seed = Annotated[int, annotated_types.Interval(ge=0, le=SEED_MAX)]
"""A seed: an integer in [0, 2**32 - 1]."""
INT32_MAX = 2**31 - 1
Steps = Annotated[int, annotated_types.Interval(ge=1, le=INT32_MAX)]
"""A number of steps or an interval of steps: an integer in [1, 2**31 - 1] (int32 counters)."""
NonNegativeSteps = Annotated[int, annotated_types.Interval(ge=0, le=INT32_MAX)]
"""A number of steps that may be zero: an integer in [0, 2**31 - 1]."""
BatchSize = Annotated[int, annotated_types.Interval(ge=1, le=INT32_MAX)]
"""A mini-batch size: an integer in [1, 2**31 - 1] (int32 sample indices); its memory is
checked against the machine's (:func:`check_memory`) once the data's shapes are known."""
Positive = Annotated[int, annotated_types.Ge(1)]
"""A count or an interval of steps: an integer >= 1."""
NonNegative = Annotated[int, annotated_types.Ge(0)]
"""A count that may be zero: an integer >= 0."""
PositiveNumber = Annotated[float, annotated_types.Gt(0)]
"""A finite number > 0 (a rate, a temperature, a share of a CPU)."""
NonNegativeNumber = Annotated[float, annotated_types.Ge(0)]
"""A finite number >= 0."""
Finite = Annotated[float, annotated_types.Predicate(math.isfinite)]
"""Any finite number (not NaN, not inf)."""


def _parts(hint) -> tuple[type, list]:
    """The base type of an ``Annotated`` hint and its constraints."""
    if typing.get_origin(hint) is Annotated:
        base, *metadata = typing.get_args(hint)
        constraints = []
        for item in metadata:  # Interval(ge=0, le=...) is Ge(0) and Le(...) grouped
            if isinstance(item, annotated_types.GroupedMetadata):
                constraints += list(item)
            elif isinstance(item, annotated_types.BaseMetadata):
                constraints.append(item)
        return base, constraints
    return hint, []


def _bounds(constraints: list) -> list[tuple[str, float]]:
    """``(operator, bound)`` pairs of the constraints, e.g. ``[(">=", 0), ("<=", 4294967295)]``."""
    out = []
    for item in constraints:
        for name, symbol in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            bound = getattr(item, name, None)
            if bound is not None:
                out.append((symbol, bound))
    return out


def describe(hint) -> str:
    """What a value of ``hint`` is, in words: ``an integer in [0, 4294967295]``,
    ``an integer >= 1``, ``a finite number > 0``."""
    base, constraints = _parts(hint)
    kind = "an integer" if base is int else "a finite number"
    bounds = dict(_bounds(constraints))
    if ">=" in bounds and "<=" in bounds:
        return f"{kind} in [{bounds['>=']}, {bounds['<=']}]"
    return " ".join([kind, *(f"{op} {bound}" for op, bound in bounds.items())])


def within(value, hint) -> bool:
    """Whether ``value`` is of ``hint``'s kind (an int, not a bool; a finite number) and range."""
    base, constraints = _parts(hint)
    kinds = numbers.Integral if base is int else numbers.Real  # NumPy's integers too
    if isinstance(value, bool) or not isinstance(value, kinds):
        return False
    if base is not int and not math.isfinite(value):
        return False
    compare = {">": operator.gt, ">=": operator.ge, "<": operator.lt, "<=": operator.le}
    predicates = [c.func for c in constraints if isinstance(c, annotated_types.Predicate)]
    return all(compare[op](value, bound) for op, bound in _bounds(constraints)) and all(
        test(value) for test in predicates
    )


def _unwrapped(hint):
    """``hint`` without an outer ``Annotated`` around an optional or tuple type (a command line's
    help settings on ``Positive | None`` or ``tuple[Seed, ...]``): the range is the inner type's."""
    while typing.get_origin(hint) is Annotated:
        inner = typing.get_args(hint)[0]
        if typing.get_origin(inner) not in (typing.Union, types.UnionType, tuple):
            break
        hint = inner
    return hint


def check(value, hint, name: str):
    """``value`` if it fits ``hint`` (None too where ``hint`` is optional, each item of a
    ``tuple[...]`` hint), else ``ValueError``: ``NAME must be an integer >= 1, got 0``."""
    hint = _unwrapped(hint)
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        if value is None:
            return value
        hint = args[0]
    if typing.get_origin(hint) is tuple:
        for item in value:
            check(item, typing.get_args(hint)[0], name)
        return value
    if not within(value, hint):
        raise ValueError(f"{name} must be {describe(hint)}, got {value!r}")
    return value


def constrained(hint) -> bool:
    """Whether ``hint`` (or what it is optional or a tuple of) carries a range."""
    hint = _unwrapped(hint)
    for arg in (hint, *typing.get_args(hint)):
        if _parts(arg)[1]:
            return True
    return False


def available_memory() -> int:
    """Bytes of memory this machine can give now without swapping (Linux's MemAvailable; else
    the free physical pages)."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 2**63  # unknown: nothing is refused


def gib(nbytes: float) -> str:
    """``nbytes`` in words: ``123.4 GiB``, ``512 MiB``."""
    return f"{nbytes / 2**30:.1f} GiB" if nbytes >= 2**30 else f"{nbytes / 2**20:.0f} MiB"


def check_memory(parts: list[tuple[str, str, str, float]], available: int | None = None) -> None:
    """``ValueError`` in one line when ``parts``, what needs memory as ``(flag, value, what,
    bytes)`` (``("--batch-size", "1000000", "a batch", 4e10)``), need more than the
    ``available`` bytes (default :func:`available_memory`); it names the flag of the largest
    part, the one to make smaller."""
    available = available_memory() if available is None else available
    total = sum(part[-1] for part in parts)
    if total <= available:
        return
    flag, value, what, size = max(parts, key=lambda part: part[-1])
    rest = f" ({gib(total)} with the rest)" if total - size >= 2**20 else ""
    raise ValueError(
        f"{' '.join(filter(None, (flag, value)))}: {what} would take {gib(size)} of memory{rest}, "
        f"more than the {gib(available)} free here; give a smaller {flag}"
    )
