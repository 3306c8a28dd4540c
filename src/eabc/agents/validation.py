"""Algorithm settings checked where they enter: each converted to its declared type (pydantic reads
the config dataclass's annotations) and checked against the range its name implies.

The ranges live here once, by field name, rather than in every algorithm file: any algorithm with a
``tau`` or an ``actor_lr`` gets the same check.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from collections.abc import Callable
from typing import Any

import pydantic

from eabc import ranges

Check = tuple[Callable[[Any], bool], str]

RANGES: dict[str, Check] = {
    "tau": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "discount": (lambda v: 0 <= v < 1, "in [0, 1)"),
    "confidence_level": (lambda v: v is None or 0 <= v <= 1, "in [0, 1]"),
    "expectile": (lambda v: 0 < v < 1, "in (0, 1)"),
    "policy_freq": (lambda v: v >= 1, "an integer >= 1"),
    "num_critics": (lambda v: v >= 1, "an integer >= 1"),
    "num_sampled_actions": (lambda v: v >= 1, "an integer >= 1"),
    "total_steps": (lambda v: v is None or v >= 1, "an integer >= 1"),
    "hidden_dims": (lambda v: len(v) >= 1 and all(d >= 1 for d in v), "one or more sizes >= 1"),
    "init_alpha": (lambda v: v > 0, "> 0"),
    "max_weight": (lambda v: v > 0, "> 0"),
}
"""Ranges by exact field name; learning rates (``*_lr``) must be > 0 and every other number
finite and >= 0 (weights, temperatures, noise scales) unless listed here or in SIGNED. Every
integer (a count, a size, a number of steps) is at most ``2**31 - 1`` besides
(:data:`eabc.ranges.INT32_MAX`): the step counters and sample indices are 32-bit; the memory the
sizes ask for is checked when a run starts, against the machine's."""
SIGNED = {"target_entropy", "target_action_gap"}
"""Numbers that may be negative."""


class SettingError(ValueError):
    """An algorithm setting of the wrong type or outside its range."""


@functools.cache
def _adapter(cls: type) -> pydantic.TypeAdapter:
    return pydantic.TypeAdapter(cls)


def validate(preset: Any, algo: str, overrides: dict[str, Any] | None = None) -> Any:
    """``preset`` (a config dataclass instance) with ``overrides``, every field converted to its
    declared type, or :class:`SettingError` naming the first bad setting and what it must be."""
    cls = type(preset)
    values = {f.name: getattr(preset, f.name) for f in dataclasses.fields(cls)}
    values |= overrides or {}
    hints = typing.get_type_hints(cls)
    for name, value in values.items():  # pydantic would take "yes", 1 or "on" for True
        if hints.get(name) is bool and not isinstance(value, bool):
            raise SettingError(f"{algo} setting {name}={value!r} must be true or false")
    try:
        checked = _adapter(cls).validate_python(values)
    except pydantic.ValidationError as error:
        first = error.errors()[0]
        if not first["loc"]:  # raised by the config's own __post_init__ check
            raise SettingError(f"{algo}: {first['msg'].removeprefix('Value error, ')}") from None
        name = ".".join(str(part) for part in first["loc"])
        field = str(first["loc"][0])
        raise SettingError(
            f"{algo} setting {name}={values.get(field)!r} is not valid: {first['msg']} "
            f"(declared type {_type_name(hints.get(field))})"
        ) from None
    for name in values:
        value = getattr(checked, name)
        if name in RANGES:
            ok, text = RANGES[name]
        elif name.endswith("_lr"):
            ok, text = (lambda v: v > 0), "> 0"
        elif isinstance(value, int | float) and not isinstance(value, bool) and name not in SIGNED:
            ok, text = (lambda v: v >= 0), ">= 0"
        else:
            ok, text = (lambda v: True), ""
        finite = not isinstance(value, float) or math.isfinite(value)
        if not finite or not ok(value):  # NaN fails every comparison: say finite first
            must = text if finite else " and ".join(filter(None, ("finite", text)))
            raise SettingError(f"{algo} setting {name}={value!r} must be {must}")
        items = value if isinstance(value, tuple) else (value,)
        if any(isinstance(v, int) and v > ranges.INT32_MAX for v in items):
            raise SettingError(
                f"{algo} setting {name}={value!r} must be at most {ranges.INT32_MAX} (counts, "
                "sizes and steps are 32-bit integers); give a smaller value"
            )
    return checked


def _type_name(hint: Any) -> str:
    if typing.get_origin(hint) is None and hasattr(hint, "__name__"):
        return hint.__name__
    return str(hint).replace("typing.", "")
