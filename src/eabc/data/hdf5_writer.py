"""A dataset written as a file: D4RL's HDF5 layout plus our metadata, atomically (a temporary file,
then a rename), and with Ctrl-C and SIGTERM acted on only where h5py can be interrupted safely.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
import time
from pathlib import Path

import h5py

from eabc.data.dataset import Dataset

ARRAYS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")
"""The arrays of a dataset file, in the order they are written."""


def save_hdf5(dataset: Dataset, path: str | os.PathLike) -> Path:
    """Write D4RL's HDF5 layout plus our metadata; atomic (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_orphans(path)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")  # two makers never share a file
    try:
        with _signals_held() as raise_held, h5py.File(tmp, "w") as f:
            for key in ARRAYS:
                raise_held()
                f.create_dataset(
                    key, data=getattr(dataset, key), compression="gzip", compression_opts=1
                )
            f.attrs["name"] = dataset.name
            f.attrs["env_id"] = dataset.env_id or ""
            if dataset.ref_min_score is not None:
                f.attrs["ref_min_score"] = dataset.ref_min_score
                f.attrs["ref_max_score"] = dataset.ref_max_score
            if dataset.reward_offset is not None:
                f.attrs["reward_offset"] = dataset.reward_offset
            f.attrs["metadata"] = json.dumps(dataset.metadata)
            f.close()
            raise_held()
        os.replace(tmp, path)
    except BaseException:  # interrupted (Ctrl-C, a terminate signal) or failed: no half file
        tmp.unlink(missing_ok=True)
        raise
    return path


_HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def _signals_held():
    """Ctrl-C and SIGTERM noted, not acted on, while h5py writes; yields a function that acts on
    a noted one (its own handler raises KeyboardInterrupt or SystemExit) at a point where that is
    safe. Why: h5py frees its objects in weakref callbacks, and an exception a signal handler
    raises there is printed as "Exception ignored" and dropped, so Ctrl-C during a write was lost
    and the command ended 0 as if never interrupted."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None  # only the main thread receives signals or may set handlers
        return
    noted: list[tuple[int, object]] = []
    previous = {number: signal.getsignal(number) for number in _HELD_SIGNALS}
    for number, handler in previous.items():
        if callable(handler):  # one that is ignored stays ignored
            signal.signal(number, lambda signum, frame: noted.append((signum, frame)))

    def raise_held() -> None:
        if noted:
            signum, frame = noted[0]
            previous[signum](signum, frame)

    try:
        yield raise_held
    finally:
        for number, handler in previous.items():
            if handler is not None:
                signal.signal(number, handler)
        raise_held()  # a signal noted after the last check still ends the command


def _remove_orphans(path: Path, quiet_s: float = 60.0) -> None:
    """Remove temporary files of ``path`` left by makers killed outright (no chance to clean up):
    their process is gone from this machine and they have not changed for ``quiet_s`` seconds
    (a maker on another machine sharing the cache keeps writing to its own)."""
    for tmp in path.parent.glob(f"{path.name}.*.tmp"):
        pid = tmp.name.removeprefix(f"{path.name}.").removesuffix(".tmp")
        if not pid.isdigit():
            continue
        try:
            os.kill(int(pid), 0)
            continue  # alive
        except ProcessLookupError:
            pass
        except PermissionError:
            continue  # alive, another user's
        with contextlib.suppress(FileNotFoundError):
            if time.time() - tmp.stat().st_mtime > quiet_s:
                tmp.unlink()
