"""Every setting's type, range and meaning, declared once beside its field, and the one check
every entry point goes through.

A settings dataclass (an algorithm's config, the run's :class:`TrainConfig`, a command's options)
says each field's range in its type, ``episodes: Positive = 10`` or ``tau: Annotated[float,
Interval(gt=0, le=1)] = 0.005``, with :mod:`annotated_types` constraints (which tyro ignores and
pydantic understands), and its meaning in the docstring under it (which tyro shows as the flag's
help). Literal choices, ``bool``, ``str``, optional (``X | None``) and ``tuple[X, ...]`` types are
checked as well. A class derived from :class:`Settings` checks every field when it is made, so
the Python API, the command line, a sweep spec and a run's ``config.json`` refuse a value in the
same words: ``num_critics must be an integer in [2, 2147483647], got 1``. What comes as text,
YAML or JSON (``--set``, a spec, ``config.json``) is first converted to the declared type by
:func:`validated` (``1`` to ``1.0``, a list to a tuple), then checked by the same constructor.
Rules between settings (an interval that divides another) stay in the class's own
``__post_init__``, after ``super().__post_init__()``.

Seeds are unsigned 32-bit integers: they go to NumPy and to ``jax.random.PRNGKey``, which keeps
only the low 32 bits of a larger seed (``PRNGKey(2**32 + 5)`` is ``PRNGKey(5)``), so a seed outside
``[0, 2**32 - 1]`` would silently be another run's. Step counts, intervals of steps, batch sizes
and every count an algorithm declares are at most ``2**31 - 1``: an agent's step counter is a
32-bit integer (``jnp.int32``), as are the indices a batch is sampled with, so a longer run would
wrap its counter round.

What no type can bound, the memory a setting asks for (a batch, a dataset, a replay buffer), is
checked by :func:`check_memory` against what this machine has free, before anything is written.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import operator
import os
import types
import typing
from collections.abc import Mapping
from typing import Annotated, Any, Literal

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
Count = Annotated[int, annotated_types.Interval(ge=1, le=INT32_MAX)]
"""A number of things an algorithm makes (networks, samples, steps): an integer in
[1, 2**31 - 1]."""
NonNegativeCount = Annotated[int, annotated_types.Interval(ge=0, le=INT32_MAX)]
"""A count that may be zero (warm-up steps, patience): an integer in [0, 2**31 - 1]."""
Ensemble = Annotated[int, annotated_types.Interval(ge=2, le=INT32_MAX)]
"""An ensemble whose spread (a standard deviation, ddof 1) or the minimum of two of its members
is used: an integer in [2, 2**31 - 1]."""
Fraction = Annotated[float, annotated_types.Interval(gt=0, le=1)]
"""A rate in (0, 1], e.g. a Polyak rate."""
Probability = Annotated[float, annotated_types.Interval(ge=0, le=1)]
"""A probability or a share: a number in [0, 1]."""
Discount = Annotated[float, annotated_types.Interval(ge=0, lt=1)]
"""gamma, in [0, 1): a return must stay finite."""
LearningRate = PositiveNumber
"""An optimiser's learning rate: a finite number > 0."""
Weight = NonNegativeNumber
"""A weight, a temperature, a noise scale or a clip: a finite number >= 0."""
Widths = Annotated[tuple[Count, ...], annotated_types.MinLen(1)]
"""Hidden layer widths: one or more integers in [1, 2**31 - 1]."""


def _parts(hint) -> tuple[Any, list]:
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


def _optional(hint) -> tuple[Any, bool]:
    """``hint`` without ``| None``, and whether it had it."""
    hint = _unwrapped(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            return args[0], len(args) < len(typing.get_args(hint))
    return hint, False


def _min_length(constraints: list) -> int:
    return max([c.min_length for c in constraints if hasattr(c, "min_length")], default=0)


def describe(hint) -> str:
    """What a value of ``hint`` is, in words: ``an integer in [0, 4294967295]``,
    ``an integer >= 1``, ``a finite number in (0, 1]``, ``one of mean-std, min``, ``true or
    false``, ``one or more integers in [1, 2147483647]`` (an optional one may be None besides)."""
    return _describe(_optional(hint)[0])


def _describe(hint) -> str:
    base, constraints = _parts(hint)
    if typing.get_origin(base) is Literal:
        return "one of " + ", ".join(map(str, typing.get_args(base)))
    if base is bool:
        return "true or false"
    if base is str:
        return "text"
    if typing.get_origin(base) is tuple:
        item = _describe(typing.get_args(base)[0]).replace("an integer", "integers")
        item = item.replace("a finite number", "finite numbers")
        return f"{'one or more' if _min_length(constraints) else 'any number of'} {item}"
    if dataclasses.is_dataclass(base):
        return f"a {base.__name__}"
    kind = "an integer" if base is int else "a finite number"
    bounds = dict(_bounds(constraints))
    low = next(((op, bounds[op]) for op in (">=", ">") if op in bounds), None)
    high = next(((op, bounds[op]) for op in ("<=", "<") if op in bounds), None)
    if low and high:
        left, right = "[" if low[0] == ">=" else "(", "]" if high[0] == "<=" else ")"
        return f"{kind} in {left}{low[1]}, {high[1]}{right}"
    return " ".join([kind, *(f"{op} {bound}" for op, bound in bounds.items())])


def within(value, hint) -> bool:
    """Whether ``value`` is of ``hint``'s kind and range: an int (not a bool), a finite number, one
    of a Literal's choices, a bool, text, a tuple of such items, an instance of a dataclass; any
    value for a type this module does not know."""
    base, constraints = _parts(hint)
    if typing.get_origin(base) is Literal:
        return any(value == c and type(value) is type(c) for c in typing.get_args(base))
    if base is bool:
        return isinstance(value, bool)
    if base is str:
        return isinstance(value, str)
    if typing.get_origin(base) is tuple:
        item = typing.get_args(base)[0]
        return (
            isinstance(value, tuple)
            and len(value) >= _min_length(constraints)
            and all(within(v, item) for v in value)
        )
    if dataclasses.is_dataclass(base):
        return isinstance(value, base)
    if base not in (int, float):
        return True
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
        if typing.get_origin(inner) is tuple and _parts(hint)[1]:
            break  # the constraints are the tuple's own (MinLen)
        hint = inner
    return hint


def check(value, hint, name: str):
    """``value`` if it fits ``hint`` (None too where ``hint`` is optional), else ``ValueError``
    in one line: ``NAME must be an integer >= 1, got 0``."""
    inner, optional = _optional(hint)
    if optional and value is None:
        return value
    if typing.get_origin(inner) is tuple and not _parts(inner)[1] and isinstance(value, tuple):
        for item in value:  # tuple[Seed, ...]: each item in range, named by the setting
            check(item, typing.get_args(inner)[0], name)
        return value
    if not within(value, inner):
        raise ValueError(f"{name} must be {describe(hint)}, got {value!r}")
    return value


def constrained(hint) -> bool:
    """Whether ``hint`` (or what it is optional or a tuple of) carries a range."""
    hint = _unwrapped(hint)
    for arg in (hint, *typing.get_args(hint)):
        if _parts(arg)[1]:
            return True
    return False


@functools.cache
def hints(cls: type) -> dict[str, Any]:
    """The declared types of a settings dataclass's fields, constraints included."""
    return typing.get_type_hints(cls, include_extras=True)


class Settings:
    """Base of the settings dataclasses: making one checks every field against its declared
    type and range (:func:`check`), so the Python API refuses a bad value in the words the
    command line and a sweep spec use. A subclass with rules between its settings defines
    ``__post_init__`` and calls ``super().__post_init__()`` first."""

    def __post_init__(self) -> None:
        declared = hints(type(self))
        for field in dataclasses.fields(self):
            check(getattr(self, field.name), declared[field.name], field.name)


class SettingError(ValueError):
    """A setting of the wrong type or outside its range, in one line naming it."""


def groups(cls: type) -> dict[str, type]:
    """The fields of a settings dataclass that are settings dataclasses themselves (a group of
    settings with a config of its own), by name: their settings are set by their own names."""
    declared = hints(cls)
    return {
        f.name: _optional(declared[f.name])[0]
        for f in dataclasses.fields(cls)
        if dataclasses.is_dataclass(_optional(declared[f.name])[0])
    }


def names(cls: type) -> list[str]:
    """Every setting's name, a group's settings in its place (:func:`groups`)."""
    inner = groups(cls)
    out = []
    for field in dataclasses.fields(cls):
        out += names(inner[field.name]) if field.name in inner else [field.name]
    return out


def flat(config: Any) -> dict[str, Any]:
    """``config``'s settings by name, a group's settings in its place: what ``config.json``
    records and ``--set`` and a sweep spec take."""
    out = {}
    inner = groups(type(config))
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if field.name in inner:
            out |= flat(value)
        else:
            out[field.name] = value
    return out


def value_of(config: Any, name: str) -> Any:
    """The setting ``name`` of ``config``, in a group's config too."""
    return flat(config)[name]


def validated(config: Any, values: Mapping[str, Any], who: str = "") -> Any:
    """``config`` (a :class:`Settings` dataclass) with ``values`` from text, YAML or JSON, each
    converted to its declared type (:func:`convert`: ``1`` to ``1.0``, a list to a tuple) and the
    whole checked as the constructor checks it; a group's settings (:func:`groups`) by their own
    names. :class:`SettingError` names the setting, after ``who`` (``eabc setting ``)."""
    cls = type(config)
    inner = groups(cls)
    where = {name: group for group, sub in inner.items() for name in names(sub)}
    own: dict[str, Any] = {}
    grouped: dict[str, dict[str, Any]] = {}
    declared = hints(cls)
    for name, value in values.items():
        if name in inner and isinstance(value, Mapping):  # a group given as one mapping
            grouped.setdefault(name, {}).update(value)
        elif name in where:
            grouped.setdefault(where[name], {})[name] = value
        else:
            own[name] = convert(value, declared[name]) if name in declared else value
    try:
        for group, settings in grouped.items():
            own[group] = validated(getattr(config, group), settings)
        return dataclasses.replace(config, **own)
    except (ValueError, TypeError) as error:  # SettingError is a ValueError too
        raise SettingError(f"{who}{error}") from None


def convert(value: Any, hint: Any) -> Any:
    """``value`` as ``hint``'s type where text, YAML or JSON give it another form of the same
    number or list (``"5"`` or ``5.0`` for an integer, ``1`` for a float, a list for a tuple);
    anything else as it is, for the check to refuse in words. A bool stays a bool (it is not
    1 or 0 here, and ``"yes"`` is not true)."""
    inner, _ = _optional(hint)
    base, _ = _parts(inner)
    if value is None or isinstance(value, bool):
        return value
    if typing.get_origin(base) is tuple and isinstance(value, list | tuple):
        return tuple(convert(v, typing.get_args(base)[0]) for v in value)
    if base is int:
        number = _number(value)
        if isinstance(number, float) and number.is_integer():
            return int(number)
        return number if isinstance(number, int) else value
    if base is float:
        number = _number(value)
        return float(number) if isinstance(number, int | float) else value
    return value


def _number(value: Any) -> Any:
    if isinstance(value, str):
        for kind in (int, float):
            try:
                return kind(value.strip())
            except ValueError:
                pass
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value)
    return value


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
