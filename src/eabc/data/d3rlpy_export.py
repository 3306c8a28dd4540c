"""Our datasets as d3rlpy's own ``MDPDataset``, in memory or as d3rlpy's HDF5 file.

Not through ``d3rlpy.datasets.get_minari``: d3rlpy 2.8.1 there puts each Minari episode's final
observation into the observation array, so from the second episode on every observation is
shifted against its action (tests/data/test_d3rlpy.py shows it). d3rlpy cuts episodes at terminals and
timeouts and takes ``s'`` from the next row of the same episode; the last step of an episode that
did not terminate it drops (it has no next row), as D4RL's ``qlearning_dataset`` does.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
from pathlib import Path

import numpy as np

from eabc import paths
from eabc.data.dataset import Dataset, DatasetError


def _d3rlpy():
    try:
        with contextlib.redirect_stderr(io.StringIO()):  # gym's "unmaintained" notice; unused here
            import d3rlpy  # noqa: PLC0415
    except ImportError:
        raise DatasetError(
            "exporting to d3rlpy needs the d3rlpy package: pip install 'eabc[d3rlpy]'"
        ) from None
    return d3rlpy


def _episode_flags(dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The terminals and timeouts d3rlpy gets: a timeout never on a terminal, and a timeout on the
    last row if nothing ends the data's last episode (d3rlpy would drop that episode whole)."""
    terminals = np.asarray(dataset.terminals, bool)
    timeouts = np.asarray(dataset.timeouts, bool) & ~terminals
    if dataset.size and not (terminals[-1] or timeouts[-1]):
        timeouts = timeouts.copy()
        timeouts[-1] = True
    return terminals, timeouts


def to_d3rlpy(dataset: Dataset):
    """A ``d3rlpy.dataset.MDPDataset`` with continuous actions whose transitions are our rows.

    Every row is a transition there except the last step of each episode that ends in a timeout.
    Raises :class:`DatasetError` if the rows do not run episode by episode (a row's
    ``next_observations`` not the next row's observation inside an episode), since d3rlpy takes
    ``s'`` from the next row.
    """
    d3rlpy = _d3rlpy()
    terminals, timeouts = _episode_flags(dataset)
    inside = ~(terminals | timeouts)[:-1]
    same = np.isclose(dataset.next_observations[:-1], dataset.observations[1:], rtol=1e-6, atol=0)
    broken = np.flatnonzero(inside & ~same.all(axis=1))
    if len(broken):
        i = int(broken[0])
        raise DatasetError(
            f"{dataset.name}: row {i}'s next_observations is not row {i + 1}'s observations, yet "
            f"no terminal or timeout ends an episode there ({len(broken)} such rows); d3rlpy takes "
            "s' from the next row, so the rows must run episode by episode"
        )
    return d3rlpy.dataset.MDPDataset(
        observations=dataset.observations,
        actions=dataset.actions,
        rewards=dataset.rewards,
        terminals=terminals.astype(np.float32),
        timeouts=timeouts.astype(np.float32),
        action_space=d3rlpy.constants.ActionSpace.CONTINUOUS,  # never guessed from the values
        action_size=dataset.actions.shape[1],
    )


def check_target(path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Fail before any work if d3rlpy is missing or ``path`` cannot be written."""
    _d3rlpy()
    path = paths.expand(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists already; pass --force to replace it")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"directory {path.parent} does not exist; make it first")
    return path


def export_d3rlpy(dataset: Dataset, path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write :func:`to_d3rlpy`'s dataset with d3rlpy's ``dump`` (HDF5), atomically.

    Read it with ``d3rlpy.dataset.ReplayBuffer.load(f, d3rlpy.dataset.InfiniteBuffer())``.
    d3rlpy's log lines go to stderr, so stdout keeps only what the caller prints.
    """
    path = check_target(path, overwrite)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with contextlib.redirect_stdout(sys.stderr):
            replay = to_d3rlpy(dataset)
            with open(tmp, "w+b") as f:
                replay.dump(f)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    first = replay.episodes[0].actions
    if np.array_equal(first, np.round(first)):
        print(
            f"note: the first episode's actions are whole numbers, so d3rlpy's ReplayBuffer.load "
            f"will take them for discrete ones; pass its episodes to d3rlpy.dataset.ReplayBuffer("
            f"..., action_space=ActionSpace.CONTINUOUS, action_size={dataset.actions.shape[1]})",
            file=sys.stderr,
        )
    return path
