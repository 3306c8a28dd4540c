"""Pytree dataclasses and their plain serialisation: nested dicts of arrays, written as msgpack.

The agents' states are frozen dataclasses registered with JAX as pytrees (:func:`dataclass`;
a field made with ``field(static=True)`` is part of the tree's structure, not a leaf). A state
becomes nested dicts of arrays and plain values with :func:`to_state_dict` (dataclasses by field
name, named tuples such as optax's states by field name, lists and tuples by position as
``"0"``, ``"1"``, ...) and comes back into a template's structure with :func:`from_state_dict`.

:func:`find` reads an entry such as ``actor`` from a state dict wherever the state keeps it.

:func:`dumps` and :func:`loads` write and read those dicts as msgpack with NumPy arrays as
extension type 1, ``(shape, dtype name, C-order bytes)``, and NumPy scalars as type 3,
``(dtype name, bytes)``: the layout flax's ``msgpack_serialize`` writes, so checkpoints written
before this module (with flax) load unchanged, and the other way round.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import msgpack
import numpy as np

_NDARRAY = 1
_NPSCALAR = 3
_MAX_EXT_BYTES = 2**32 - 1


def field(*, static: bool = False, **kwargs) -> Any:
    """A dataclass field; ``static=True`` keeps it out of the pytree's leaves (a setting, not
    an array that transforms and checkpoints carry)."""
    metadata = {**kwargs.pop("metadata", {}), "static": static}
    return dataclasses.field(metadata=metadata, **kwargs)


def dataclass(cls: type) -> type:
    """A frozen dataclass registered as a JAX pytree, with ``replace(**changes)``."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    fields = dataclasses.fields(cls)
    jax.tree_util.register_dataclass(
        cls,
        data_fields=[f.name for f in fields if not f.metadata.get("static")],
        meta_fields=[f.name for f in fields if f.metadata.get("static")],
    )
    if "replace" not in cls.__dict__:
        cls.replace = lambda self, **changes: dataclasses.replace(self, **changes)
    return cls


def _data_fields(x: Any) -> list[str]:
    return [f.name for f in dataclasses.fields(x) if not f.metadata.get("static")]


def _is_namedtuple(x: Any) -> bool:
    return isinstance(x, tuple) and hasattr(x, "_fields")


def to_state_dict(x: Any) -> Any:
    """``x`` as nested dicts with string keys; arrays and plain values are left as they are."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {name: to_state_dict(getattr(x, name)) for name in _data_fields(x)}
    if isinstance(x, dict):
        if len({str(k) for k in x}) != len(x):
            raise ValueError(f"keys {list(x)} are not distinct as strings")
        return {str(k): to_state_dict(v) for k, v in x.items()}
    if _is_namedtuple(x):
        return {name: to_state_dict(getattr(x, name)) for name in x._fields}
    if isinstance(x, (list, tuple)):
        return {str(i): to_state_dict(v) for i, v in enumerate(x)}
    return x


def from_state_dict(template: Any, state: Any, path: str = "") -> Any:
    """``state`` (from :func:`to_state_dict`) back in ``template``'s structure. Leaves come from
    ``state``; a ``None`` template takes ``state`` as it is."""

    def missing(keys) -> ValueError:
        return ValueError(f"the state lacks {sorted(keys)} at {path or 'its top level'}")

    if dataclasses.is_dataclass(template) and not isinstance(template, type):
        names = _data_fields(template)
        if set(names) - set(state):
            raise missing(set(names) - set(state))
        changes = {n: from_state_dict(getattr(template, n), state[n], f"{path}/{n}") for n in names}
        return template.replace(**changes)
    if isinstance(template, dict):
        keys = {str(k): k for k in template}
        if set(keys) - set(state):
            raise missing(set(keys) - set(state))
        return {k: from_state_dict(template[k], state[s], f"{path}/{s}") for s, k in keys.items()}
    if _is_namedtuple(template):
        if set(template._fields) - set(state):
            raise missing(set(template._fields) - set(state))
        values = {n: from_state_dict(getattr(template, n), state[n], f"{path}/{n}")
                  for n in template._fields}  # fmt: skip
        return type(template)(**values)
    if isinstance(template, (list, tuple)):
        if len(state) != len(template):
            raise ValueError(f"{path or 'the state'} has {len(state)} items, not {len(template)}")
        items = [from_state_dict(t, state[str(i)], f"{path}/{i}") for i, t in enumerate(template)]
        return type(template)(items)
    return state


def find(state: dict[str, Any], name: str) -> Any:
    """The entry ``name`` of a state dict (of :func:`to_state_dict`): at its top level, or inside
    the one nested state that holds it (a state that holds its base algorithm's state as one
    field, like wPC's TD3+BC state, keeps ``actor`` and ``step`` there). ``KeyError`` when no
    nested state or more than one holds it."""
    if name in state:
        return state[name]
    holders = [k for k, v in state.items() if isinstance(v, dict) and _holds(v, name)]
    if len(holders) != 1:
        where = f"both {holders[0]!r} and {holders[1]!r} hold it" if holders else "nothing holds it"
        raise KeyError(f"the state has no single {name!r} ({where})")
    return find(state[holders[0]], name)


def _holds(state: dict[str, Any], name: str) -> bool:
    return name in state or any(isinstance(v, dict) and _holds(v, name) for v in state.values())


def _pack(x: Any) -> msgpack.ExtType:
    if isinstance(x, (np.ndarray, jax.Array)):
        x = np.asarray(x)
        data = msgpack.packb((x.shape, x.dtype.name, x.tobytes("C")), use_bin_type=True)
        if len(data) > _MAX_EXT_BYTES:
            raise ValueError(f"an array of {x.nbytes:,} bytes is too large for one msgpack entry")
        return msgpack.ExtType(_NDARRAY, data)
    if isinstance(x, np.generic):
        return msgpack.ExtType(
            _NPSCALAR, msgpack.packb((x.dtype.name, x.tobytes()), use_bin_type=True)
        )
    raise TypeError(f"cannot write a {type(x).__name__} to msgpack (arrays, numbers, str, dicts)")


def _dtype(name: bytes) -> np.dtype:
    name = name.decode()
    try:
        return np.dtype(name)
    except TypeError:  # e.g. bfloat16, which NumPy knows only through JAX's ml_dtypes
        return np.dtype(getattr(jax.numpy, name))


def _unpack(code: int, data: bytes) -> Any:
    if code == _NDARRAY:
        shape, dtype, buffer = msgpack.unpackb(data, raw=True)
        return np.frombuffer(buffer, dtype=_dtype(dtype)).reshape(shape)
    if code == _NPSCALAR:
        dtype, buffer = msgpack.unpackb(data, raw=True)
        return np.frombuffer(buffer, dtype=_dtype(dtype))[0]
    raise ValueError(f"unknown msgpack extension type {code}")


def dumps(state: Any) -> bytes:
    """A state dict (of :func:`to_state_dict`) as msgpack bytes, every mapping's keys sorted (as
    flax wrote them, so the bytes of a state are the same as before)."""
    return msgpack.packb(_sorted(state), default=_pack, strict_types=True)


def _sorted(x: Any) -> Any:
    return {k: _sorted(x[k]) for k in sorted(x)} if isinstance(x, dict) else x


def loads(data: bytes) -> Any:
    """The state dict :func:`dumps` wrote."""
    return msgpack.unpackb(data, ext_hook=_unpack, raw=False)
