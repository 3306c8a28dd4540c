"""Checkpoints as msgpack (never pickle), written atomically: a temporary file, then a rename."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import flax.serialization
import jax
import numpy as np

CHECKPOINT = "checkpoint.msgpack"
CONFIG = "config.json"


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file of a unique name beside ``path``, then rename it over
    ``path``: a reader sees the old file or the new one, never a mix, whoever else is writing."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def save(run_dir: Path, payload: dict[str, Any]) -> None:
    """Save a pytree of arrays and plain values (train state, key, normaliser, history)."""
    state = flax.serialization.to_state_dict(jax.device_get(payload))
    atomic_write(Path(run_dir) / CHECKPOINT, flax.serialization.msgpack_serialize(state))


def load_raw(run_dir: Path) -> dict[str, Any]:
    """The checkpoint as nested dicts of arrays and plain values."""
    path = Path(run_dir) / CHECKPOINT
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint in {run_dir}; the run has not saved one yet")
    return flax.serialization.msgpack_restore(path.read_bytes())


def load(run_dir: Path, template: dict[str, Any]) -> dict[str, Any]:
    """Restore into the structure of ``template`` (flax checks the structure)."""
    return flax.serialization.from_state_dict(template, load_raw(run_dir))


def save_json(path: Path, data: dict) -> None:
    atomic_write(Path(path), json.dumps(data, indent=2, default=_plain).encode())


def _plain(value):
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot write {type(value)} to JSON")


def read_config(run_dir: Path) -> dict:
    """A run directory's resolved configuration."""
    path = Path(run_dir) / CONFIG
    if not path.exists():
        raise FileNotFoundError(f"{run_dir} is not a run directory (no {CONFIG})")
    return json.loads(path.read_text())
