"""Checkpoints as msgpack (never pickle), written atomically: a temporary file, then a rename.

A checkpoint file is the msgpack payload followed by a 40-byte trailer, ``EABCSUM1`` and the
payload's SHA-256, checked on every read. Files from before the trailer (version 0) still load.
Every file, with a checksum or without, is checked for NaN/inf values (:func:`check_values`):
a checksum tells a damaged file from an intact one, not an edited one from the original, since
whoever edits the payload can recompute it.

A training run's payload records its agent state's layout (``state_layout``, the algorithm's
:attr:`~eabc.agents.contract.Algorithm.state_layout`; absent in files from before it: layout 1),
so that a checkpoint of another layout is refused with a message that says why, and the identity
of the run that wrote it (``run``, :mod:`eabc.training.identity`), so that no other run's file is
used as this run's.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import jax
import numpy as np

from eabc import paths, pytree

CHECKPOINT = "checkpoint.msgpack"
CONFIG = "config.json"
TRAILER = b"EABCSUM1"
"""Marks a checkpoint that ends in its payload's SHA-256 (format version 1)."""
LAYOUT = "state_layout"
"""The payload's entry that records the agent state's layout."""
IDENTITY = "run"
"""The payload's entry that records which run wrote it (:mod:`eabc.training.identity`)."""


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the message names the file and what to do."""


def file_mode() -> int:
    """The mode ``open()`` gives a new file under this process's umask (0644 under the usual
    022). ``mkstemp`` makes its files 0600 whatever the umask, which left run files unreadable to
    the group a team shares run directories with; the writers set this mode instead."""
    try:  # Linux: read it without changing it (changing it races other threads' new files)
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file of a unique name beside ``path``, then rename it over
    ``path``: a reader sees the old file or the new one, never a mix, whoever else is writing.
    The file gets the mode a plain ``open()`` would (:func:`file_mode`)."""
    path = Path(path)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.fchmod(fd, file_mode())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as error:  # a full disk, no permission: said of the file, not the temporary
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise OSError(error.errno, error.strerror or str(error), str(path)) from None
    except BaseException:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise


def save(
    run_dir: Path,
    payload: dict[str, Any],
    state_layout: int | None = None,
    identity: dict[str, Any] | None = None,
) -> None:
    """Save a pytree of arrays and plain values (train state, key, normaliser, history), with
    the agent state's layout and the identity of the run that writes it when given."""
    if state_layout is not None:
        payload = {**payload, LAYOUT: state_layout}
    if identity is not None:
        payload = {**payload, IDENTITY: identity}
    write_tree(Path(run_dir) / CHECKPOINT, payload)


def write_tree(path: Path, tree: Any) -> None:
    """A pytree of arrays and plain values as msgpack with its checksum trailer, atomically."""
    data = pytree.dumps(pytree.to_state_dict(jax.device_get(tree)))
    atomic_write(Path(path), data + TRAILER + hashlib.sha256(data).digest())


_REDO = (
    "move it away and resume from a good copy, or delete it to train the run again from the start"
)


def load_raw(run_dir: Path, *, infinite: frozenset[str] = frozenset()) -> dict[str, Any]:
    """The checkpoint as nested dicts of arrays and plain values, its checksum verified, and its
    values checked (:func:`check_values`; ``infinite``: the algorithm's
    :attr:`~eabc.agents.contract.Algorithm.infinite_state`)."""
    path = Path(run_dir) / CHECKPOINT
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint in {run_dir}; the run has not saved one yet")
    raw, _ = _read(path)
    check_values({k: raw.get(k) for k in ("agent", "normalizer")}, path, infinite)
    return raw


def read_tree(path: Path) -> dict[str, Any]:
    """What :func:`write_tree` wrote to ``path``, its checksum verified (:class:`CheckpointError`
    when it does not match or the file is not one of ours)."""
    raw, checked = _read(Path(path))
    if not checked:
        raise CheckpointError(f"{path} has no checksum: it is not a file this package wrote")
    check_values(raw, Path(path), frozenset())
    return raw


def check_values(tree: Any, path: Path, infinite: frozenset[str]) -> None:
    """Refuse NaN in any float of ``tree``, and +-inf anywhere but in the entries named
    ``infinite`` (an algorithm's state entries that may start infinite:
    :attr:`~eabc.agents.contract.Algorithm.infinite_state`): training never writes them (a run
    whose losses turn NaN/inf stops before it checkpoints), so they are corruption or an edit,
    whatever the checksum says (a checksum can be recomputed)."""
    for name, leaf in _leaves(tree):
        array = np.asarray(leaf)
        if array.dtype.kind not in "fc":
            continue
        allowed = name.rsplit("/", 1)[-1] in infinite
        if np.isnan(array).any() or (not allowed and not np.isfinite(array).all()):
            raise CheckpointError(
                f"{path} holds NaN/inf in {name}, which training never writes: the file is "
                f"corrupt or was edited; {_REDO}"
            )


def _read(path: Path) -> tuple[dict[str, Any], bool]:
    """The file's nested dicts and whether it carried a checksum (verified)."""
    try:
        data = paths.read_file(path)
    except OSError as error:
        raise CheckpointError(f"{path} cannot be read ({error.strerror}); {_REDO}") from None
    checked = len(data) >= 40 and data[-40:-32] == TRAILER
    if checked:
        data, digest = data[:-40], data[-32:]
        if hashlib.sha256(data).digest() != digest:
            raise CheckpointError(f"{path} is corrupt (its checksum does not match); {_REDO}")
    try:
        raw = pytree.loads(data)
    except Exception as error:  # noqa: BLE001 (msgpack raises many kinds on bad bytes)
        raise CheckpointError(
            f"{path} is corrupt or truncated ({type(error).__name__}); {_REDO}"
        ) from None
    if not isinstance(raw, dict):
        raise CheckpointError(f"{path} is not a checkpoint of this package; {_REDO}")
    return raw, checked


def restore(
    raw: dict[str, Any],
    run_dir: Path,
    template: dict[str, Any],
    what: str = "this run",
    algo: str = "this algorithm",
    state_layout: int = 1,
) -> dict[str, Any]:
    """Restore a payload already read (and its identity checked and removed) into the structure
    of ``template``, refusing a checkpoint of another state layout than ``state_layout``
    (``algo``'s) or whose structure, shapes or dtypes differ from it (another run's checkpoint:
    ``what`` names this run's settings)."""
    raw = check_layout(raw, run_dir, algo, state_layout)
    check_structure(raw, pytree.to_state_dict(template), Path(run_dir) / CHECKPOINT, what)
    return pytree.from_state_dict(template, raw)


def check_layout(raw: dict[str, Any], run_dir: Path, algo: str, state_layout: int) -> dict:
    """``raw`` without its recorded layout; :class:`CheckpointError` when that layout (1 where
    none is recorded) is not ``state_layout``, the one this version of ``algo`` reads."""
    found = int(raw.get(LAYOUT, 1))
    path = Path(run_dir) / CHECKPOINT
    if found < state_layout:
        raise CheckpointError(
            f"{path} was written by an older version of eabc, with an older state layout for "
            f"{algo} (layout {found}; this version reads layout {state_layout}), so it cannot be "
            "resumed or evaluated here: train the run again (in a fresh directory, or after "
            "deleting the checkpoint), or use the older package version to finish it"
        )
    if found > state_layout:
        raise CheckpointError(
            f"{path} was written by a newer version of eabc, with a newer state layout for "
            f"{algo} (layout {found}; this version reads layout {state_layout}): use that "
            "version (or a later one) to resume or evaluate it"
        )
    return {key: value for key, value in raw.items() if key != LAYOUT}


def check_structure(raw: Any, template: Any, path: Path, what: str, prefix: str = "") -> None:
    """Raise :class:`CheckpointError` at the first key, shape or dtype where ``raw`` differs from
    ``template`` (a ``None`` in ``template`` accepts anything)."""
    foreign = f"it is not a checkpoint of {what}: {_REDO}"
    if template is None:
        return
    if isinstance(template, dict):
        if not isinstance(raw, dict):
            raise CheckpointError(f"{path}: {prefix or 'the file'} is not a mapping; {foreign}")
        missing = sorted(set(template) - set(raw))
        extra = sorted(set(raw) - set(template))
        if missing or extra:
            where = f"{prefix}/" if prefix else ""
            raise CheckpointError(
                f"{path}: {where} has keys {sorted(raw)} where {what} has {sorted(template)}; "
                f"{foreign}"
            )
        for key in template:
            check_structure(raw[key], template[key], path, what, f"{prefix}/{key}".lstrip("/"))
        return
    want, got = np.asarray(template), np.asarray(raw)
    if want.shape != got.shape or (want.dtype.kind in "fiub" and want.dtype != got.dtype):
        raise CheckpointError(
            f"{path}: {prefix} has shape {got.shape} {got.dtype} where {what} needs "
            f"{want.shape} {want.dtype}; {foreign}"
        )


def _leaves(tree: Any, prefix: str = ""):
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from _leaves(value, f"{prefix}/{key}".lstrip("/"))
    else:
        yield prefix, tree


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
    try:
        config = json.loads(paths.read_file(path).decode())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise CheckpointError(
            f"{path} cannot be read ({type(error).__name__}: {error}); restore it from a copy "
            "or train the run again in a fresh directory"
        ) from None
    if not isinstance(config, dict):
        raise CheckpointError(f"{path} is not a run configuration (not a JSON object)")
    return config
