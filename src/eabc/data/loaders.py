"""Reading datasets: D4RL-layout HDF5 files, plain ``.npz`` files and local Minari datasets.

Names (built-in datasets, Minari ids) are resolved one layer up, in :mod:`eabc.data.sources`.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
import warnings
import zipfile
import zlib
from pathlib import Path

import h5py
import numpy as np
from gymnasium import spaces

from eabc import paths
from eabc.data import schema, tasks
from eabc.data.dataset import Dataset, DatasetError

REQUIRED = ("observations", "actions", "rewards", "terminals")


def load_file(path: str | os.PathLike) -> Dataset:
    """A dataset from a ``.npz`` or D4RL-layout HDF5 file, checked against
    :mod:`eabc.data.schema` before any array is read."""
    path = paths.expand(path)
    schema.regular_file(path)  # before anything opens it: a FIFO would block forever
    if path.suffix == ".npz":
        arrays, attrs = _read_npz(path)
    elif path.suffix in (".hdf5", ".h5"):
        arrays, attrs = _read_hdf5(path)
    else:
        raise DatasetError(f"{path}: unsupported file type {path.suffix!r}; use .hdf5, .h5 or .npz")
    try:
        return from_arrays(arrays, attrs, default_name=path.stem)
    except DatasetError as error:  # the values' checks name the dataset: name the file too
        raise DatasetError(f"{path}: {error}" if str(path) not in str(error) else error) from None


_UNREADABLE = (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError, RuntimeError,
               NotImplementedError, zlib.error)  # fmt: skip
"""What reading a damaged archive raises (zipfile, zlib and numpy's .npy reader)."""


def _read_npz(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    with open(path, "rb") as f:
        if f.read(6) == b"\x93NUMPY":
            raise DatasetError(
                f"{path}: a single .npy array named .npz; a dataset .npz holds named arrays: "
                "numpy.savez(path, observations=..., actions=..., rewards=..., terminals=...)"
            )
    try:
        with zipfile.ZipFile(path) as archive:
            headers = schema.npz_headers(path, archive)
            schema.check(path, headers)
            values = {}
            for key, header in headers.items():
                with archive.open(header.where) as member:
                    values[key] = np.lib.format.read_array(member, allow_pickle=False)
    except DatasetError:
        raise
    except _UNREADABLE as error:
        raise DatasetError(
            f"{path}: not a readable .npz archive ({type(error).__name__}: "
            f"{' '.join(str(error).split())}); the file is truncated or corrupt: make or copy it "
            "again"
        ) from None
    arrays = {k: v for k, v in values.items() if k in schema.ARRAYS}
    return arrays, schema.attributes(path, {k: v for k, v in values.items() if k not in arrays})


def _read_hdf5(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    try:
        with h5py.File(path, "r") as f:
            headers = schema.hdf5_headers(path, f)
            schema.check(path, headers)
            arrays = {key: f[key][()] for key in headers}
            raw = {k: f.attrs[k] for k in schema.ATTRIBUTES if k in f.attrs}
    except DatasetError:
        raise
    except (OSError, KeyError, RuntimeError, ValueError, TypeError) as error:
        raise DatasetError(
            f"{path}: not a readable HDF5 file ({' '.join(str(error).split())}); it is truncated "
            "or corrupt: make or copy it again"
        ) from None
    return arrays, schema.attributes(path, raw)


def from_arrays(arrays: dict[str, np.ndarray], attrs: dict, default_name: str) -> Dataset:
    """Build a dataset from D4RL-style arrays; derive ``next_observations`` when they are absent."""
    name = str(attrs.get("name", default_name))
    missing = [k for k in REQUIRED if k not in arrays]
    if missing:
        raise DatasetError(
            f"{name}: missing keys {missing}; a dataset needs {list(REQUIRED)} and may have "
            "timeouts and next_observations"
        )
    n = len(arrays["observations"])
    if n == 0:
        raise DatasetError(
            f"{name}: holds no transitions (its observations have 0 rows); save the data's "
            "transitions, one row each"
        )
    for key in ("actions", "rewards", "terminals", "timeouts", "next_observations"):
        if key in arrays and len(arrays[key]) != n:
            raise DatasetError(
                f"{name}: {key} has {len(arrays[key])} rows but observations have {n}; every field "
                "needs one row per transition"
            )
    arrays = dict(arrays)
    arrays.setdefault("timeouts", np.zeros(n, bool))
    if "next_observations" not in arrays:
        if n == 1:  # s' is the next row's observation: one row has none
            raise DatasetError(
                f"{name}: holds one row, and without next_observations a transition's next "
                "observation is the next row's: store next_observations, or save more rows"
            )
        if np.asarray(arrays["timeouts"], bool)[:-1].all():
            raise DatasetError(
                f"{name}: all {n} rows are timeouts, so no transition has a next observation (a "
                "timeout step's would be the next episode's first, and is dropped): store "
                "next_observations, or mark only each episode's last step as a timeout"
            )
        arrays = _with_next_observations(arrays)
    task = tasks.parse_task(name)
    env = tasks.env_info(task)
    metadata = json.loads(attrs["metadata"]) if "metadata" in attrs else {}
    return Dataset(
        **{k: arrays[k] for k in (*REQUIRED, "timeouts", "next_observations")},
        name=name,
        env_id=str(attrs.get("env_id", env.env_id if env else "")) or None,
        ref_min_score=_float(attrs.get("ref_min_score", env.ref_min_score if env else None)),
        ref_max_score=_float(attrs.get("ref_max_score", env.ref_max_score if env else None)),
        reward_offset=_float(attrs.get("reward_offset", tasks.reward_offset(task))),
        metadata=metadata,
    )


def _with_next_observations(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """D4RL's ``qlearning_dataset``: ``s'`` is the next row; a timeout step has no ``s'`` and is dropped.

    The step before a dropped timeout step then ends its episode, so it becomes the timeout: the
    episode boundaries stay where they were (Minari export, episode counts), and training, which
    ends an episode's return only at terminals, is unchanged.
    """
    timeouts = np.asarray(arrays["timeouts"], bool)
    keep = ~timeouts
    keep[-1] = False
    out = {k: np.asarray(v)[keep] for k, v in arrays.items()}
    out["next_observations"] = np.asarray(arrays["observations"])[1:][keep[:-1]]
    before_timeout = np.append(timeouts[1:], False) & ~np.asarray(arrays["terminals"], bool)
    out["timeouts"] = before_timeout[keep]
    return out


def _float(value) -> float | None:
    return None if value is None else float(value)


def save_npz(dataset: Dataset, path: str | os.PathLike) -> None:
    """Write a dataset as a plain ``.npz`` (no pickled objects) that :func:`load_file` reads back."""
    attrs = {"name": dataset.name, "env_id": dataset.env_id or ""}
    if dataset.ref_min_score is not None:
        attrs |= {"ref_min_score": dataset.ref_min_score, "ref_max_score": dataset.ref_max_score}
    if dataset.reward_offset is not None:
        attrs["reward_offset"] = dataset.reward_offset
    arrays = {k: getattr(dataset, k) for k in ("observations", "actions", "rewards", "terminals")}
    arrays |= {"timeouts": dataset.timeouts, "next_observations": dataset.next_observations}
    np.savez(path, **arrays, **{k: np.asarray(v) for k, v in attrs.items()})


MINARI_ID = re.compile(r"[-\w]+(?:/[-\w]+)*-v\d+")
"""A Minari id: ``NAMESPACE/.../NAME-vN`` of letters, digits, ``-`` and ``_`` (Minari's own
pattern, its version required): never ``..``, ``.``, an empty or an absolute path, so that the
dataset's folder lies inside the Minari path."""


def check_minari_id(dataset_id: str, what: str) -> None:
    """Refuse, in one line naming ``what`` (the flag or ``minari:ID``), an id that is not
    :data:`MINARI_ID`, before any folder is looked at or made."""
    if not MINARI_ID.fullmatch(dataset_id):
        raise DatasetError(
            f"{what}: {dataset_id!r} is not a Minari id; an id is NAMESPACE/NAME-vN (e.g. "
            "eabc/hopper/medium-v0) of letters, digits, - and _, with its version -vN, and "
            "names a folder inside the Minari path (no '..', '.', '~' or leading '/')"
        )


def minari_root() -> Path:
    """The local Minari path, as Minari finds it ($MINARI_DATASETS_PATH, else
    ~/.minari/datasets), without making it."""
    return Path(os.environ.get("MINARI_DATASETS_PATH") or Path.home() / ".minari" / "datasets")


def has_minari(dataset_id: str) -> bool:
    """Whether ``dataset_id`` is a folder of the local Minari path (intact or not: reading it
    says which). Minari's own listing is not asked: one broken folder makes it raise for all."""
    try:
        import minari  # noqa: F401, PLC0415
    except ImportError:
        return False
    return bool(MINARI_ID.fullmatch(dataset_id)) and (minari_root() / dataset_id / "data").is_dir()


def check_minari(dataset_id: str) -> Path:
    """Refuse what :func:`load_minari` would refuse before reading any episode: Minari's AntMaze
    data, an id that is not one, a missing minari package, a dataset that is not in the local
    Minari path, and one whose ``metadata.json`` is missing or not its own (damaged). The
    dataset's ``data`` folder otherwise. A sweep checks every ``minari:`` dataset so."""
    refuse_minari_antmaze(dataset_id)  # with or without minari
    check_minari_id(dataset_id, f"minari:{dataset_id}")
    try:
        import minari  # noqa: F401, PLC0415
    except ImportError:
        raise DatasetError(
            f"minari:{dataset_id} needs the minari package: pip install 'eabc[minari]'"
        ) from None
    folder = minari_root() / dataset_id / "data"
    if not folder.is_dir():
        raise DatasetError(
            f"Minari dataset {dataset_id!r} is not in the local Minari path ({minari_root()}); "
            "set MINARI_DATASETS_PATH or make it there first"
        )
    metadata = folder / "metadata.json"
    try:
        recorded = json.loads(paths.read_file(metadata).decode()).get("dataset_id")
    except (OSError, ValueError, AttributeError) as error:
        why = getattr(error, "strerror", None) or type(error).__name__
        raise DatasetError(_damaged(dataset_id, f"{metadata} cannot be read ({why})")) from None
    if recorded != dataset_id:
        raise DatasetError(_damaged(dataset_id, f"{metadata} names dataset {recorded!r}"))
    return folder


def _damaged(dataset_id: str, problem: str) -> str:
    return (
        f"minari:{dataset_id} is damaged: {problem}; it is truncated, corrupt or half written: "
        f"export or download it again (remove {minari_root() / dataset_id} first)"
    )


GOAL_KEYS = frozenset({"observation", "achieved_goal", "desired_goal"})
"""The keys of a Gymnasium-Robotics goal-conditioned observation (its AntMaze, PointMaze, ...)."""
GYMNASIUM_ROBOTICS_ANTMAZE = "D4RL/antmaze/"
"""Minari's namespace of the AntMaze data it re-created on Gymnasium-Robotics' ``AntMaze_*-v4``."""


def refuse_minari_antmaze(dataset_id: str) -> None:
    """Refuse Minari's AntMaze ids (``D4RL/antmaze/*``) by name, in one line that says why and
    what to use instead; other ids pass."""
    if dataset_id.startswith(GYMNASIUM_ROBOTICS_ANTMAZE):
        raise DatasetError(_gymnasium_robotics_antmaze(dataset_id, None))


def load_minari(dataset_id: str) -> Dataset:
    """A Minari dataset from the local Minari path (never downloads); its observations must be
    flat vectors. Minari's AntMaze data (``D4RL/antmaze/*``, or any goal-dict dataset of an
    AntMaze task) are refused: see :func:`_gymnasium_robotics_antmaze`."""
    folder = check_minari(dataset_id)
    import minari  # noqa: PLC0415

    try:
        data = minari.MinariDataset(folder)
        _check_flat_observations(dataset_id, data.observation_space, data.env_spec)
        parts = {k: [] for k in ("observations", "actions", "rewards", "next_observations")}
        terminals, timeouts = [], []
        for episode in data.iterate_episodes():
            parts["observations"].append(episode.observations[:-1])
            parts["next_observations"].append(episode.observations[1:])
            parts["actions"].append(episode.actions)
            parts["rewards"].append(episode.rewards)
            terminals.append(episode.terminations)
            timeouts.append(episode.truncations)
        metadata = data.storage.metadata
        env_spec = data.env_spec
    except DatasetError:
        raise
    except Exception as error:  # noqa: BLE001 (h5py, pyarrow and Minari raise many kinds)
        files = ", ".join(sorted(str(p) for p in folder.iterdir() if p.name != "metadata.json"))
        why = " ".join(str(error).split())[:200] or type(error).__name__
        raise DatasetError(
            _damaged(dataset_id, f"{files or folder} cannot be read ({why})")
        ) from None
    return Dataset(
        **{k: np.concatenate(v) for k, v in parts.items()},
        terminals=np.concatenate(terminals),
        timeouts=np.concatenate(timeouts),
        name=dataset_id,
        env_id=env_spec.id if env_spec is not None else None,
        ref_min_score=_float(metadata.get("ref_min_score")),
        ref_max_score=_float(metadata.get("ref_max_score")),
        reward_offset=tasks.reward_offset(tasks.parse_task(dataset_id)),
        metadata={"source": "minari", "minari_id": dataset_id},
    )


def _check_flat_observations(dataset_id: str, space, env_spec) -> None:
    """Refuse, in one line, observations that are not one flat vector per step."""
    if isinstance(space, spaces.Box) and len(space.shape) == 1:
        return
    keys = set(space.spaces) if isinstance(space, spaces.Dict) else set()
    env_id = env_spec.id if env_spec is not None else None
    task = tasks.parse_task(dataset_id)
    antmaze = (task is not None and task[0] == "antmaze") or (env_id or "").startswith("AntMaze")
    if keys >= GOAL_KEYS and antmaze:
        raise DatasetError(_gymnasium_robotics_antmaze(dataset_id, env_id))
    raise DatasetError(
        f"minari:{dataset_id}: its observations are {space}, not one flat vector per step; "
        "eabc trains on flat Box observations: flatten them (gymnasium.spaces.flatten) into a "
        ".npz or HDF5 file and train on that"
    )


def _gymnasium_robotics_antmaze(dataset_id: str, env_id: str | None) -> str:
    """Why Minari's AntMaze data cannot train here: they were recorded on another robot, in
    another frame, than the evaluation environments (docs/datasets.md, "Minari's AntMaze data").

    Gymnasium-Robotics' ``AntMaze_*-v4`` runs Gymnasium's ant (motors of gear 150, 0.05 s per
    step; ours is D4RL's: torques of +-30, 0.1 s per step) in a maze centred on the origin with y
    decreasing with the row (D4RL's: the start cell at the origin, y growing with the row). Its
    umaze data are ours shifted by (-4, -4) m (Minari flipped its map upside down); its medium and
    large data are the mirror image of our mazes, which no shift of x, y undoes. Either way a
    policy learnt from them would be scored on a different robot."""
    task = tasks.parse_task(dataset_id)
    name = f"antmaze-{task[1]}" if task is not None and task[0] == "antmaze" else "antmaze-umaze"
    recorded = f"Gymnasium-Robotics' {env_id}" if env_id else "Gymnasium-Robotics' AntMaze"
    return (
        f"minari:{dataset_id} was recorded on {recorded} (goal-dict observations of Gymnasium's "
        "ant: gear-150 motors, 0.05 s steps, the maze centred on the origin), which eabc cannot "
        "evaluate: its AntMaze environments are D4RL's ant (torques of +-30, 0.1 s steps) in "
        f"D4RL's coordinates. Use D4RL's HDF5 file ({name}-v2.hdf5) or make the data here: eabc "
        f"data make {name}"
    )


def minari_id(name: str) -> str:
    """The Minari id a built-in dataset is exported under, e.g. ``eabc/hopper/medium-v0``."""
    task = tasks.parse_task(name)
    if task is None:
        return f"eabc/{Path(name).stem}-v0"
    return f"eabc/{task[0]}/{task[1]}-v0"


def export_minari(dataset: Dataset, dataset_id: str, overwrite: bool = False) -> str:
    """Write ``dataset`` as a local Minari dataset (episodes split at terminals and timeouts).

    Readers such as d3rlpy or CORL can then use it with ``minari.load_dataset(dataset_id)``;
    :func:`load_minari` reads it back to the same transitions. Minari writes into a hidden
    folder of the Minari path (which its listing skips), renamed into place when complete: an
    export that fails or is killed half way never leaves a folder that Minari lists.
    """
    check_export_target(dataset_id, overwrite)
    import minari  # noqa: PLC0415
    from minari.data_collector import EpisodeBuffer  # noqa: PLC0415

    ends = np.flatnonzero(dataset.terminals | dataset.timeouts)
    if len(ends) == 0 or ends[-1] != dataset.size - 1:
        ends = np.append(ends, dataset.size - 1)
    starts = np.concatenate([[0], ends[:-1] + 1])
    episodes = []
    for i, (lo, hi) in enumerate(zip(starts, ends + 1)):
        episodes.append(
            EpisodeBuffer(
                id=i,
                observations=np.concatenate(
                    [dataset.observations[lo:hi], dataset.next_observations[hi - 1 : hi]]
                ),
                actions=dataset.actions[lo:hi],
                rewards=dataset.rewards[lo:hi].astype(np.float64),
                terminations=dataset.terminals[lo:hi],
                truncations=~dataset.terminals[lo:hi] & (np.arange(lo, hi) == hi - 1),
            )
        )
    env = tasks.make_env(dataset.env_id) if dataset.env_id else None
    root = minari_root()
    root.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=root, prefix=".eabc-export.", suffix=".tmp"))
    try:
        with _minari_path(staging), warnings.catch_warnings():
            for message in MINARI_UNSET if env else MINARI_UNSET + MINARI_NO_ENV:
                warnings.filterwarnings("ignore", message, UserWarning, r"minari\.utils")
            _create(minari, dataset, dataset_id, episodes, env)
        _move_into_place(staging, root, dataset_id)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return dataset_id


def check_export_target(dataset_id: str, overwrite: bool) -> None:
    """Refuse, before any data is loaded or made, an export id that is not a Minari id
    (:func:`check_minari_id`), a missing minari package, and an id that is taken (without
    ``--force``)."""
    check_minari_id(dataset_id, "--dataset-id")
    try:
        import minari  # noqa: F401, PLC0415
    except ImportError:
        raise DatasetError(
            "exporting to Minari needs the minari package: pip install 'eabc[minari]'"
        ) from None
    target = minari_root() / dataset_id
    if (target.exists() or target.is_symlink()) and not overwrite:
        raise FileExistsError(
            f"Minari dataset {dataset_id!r} exists already ({target}); pass --force to replace it"
        )


@contextlib.contextmanager
def _minari_path(folder: Path):
    """Minari's path set to ``folder`` while Minari writes (it takes the path from there only)."""
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(folder)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def _move_into_place(staging: Path, root: Path, dataset_id: str) -> None:
    """Rename the complete dataset from ``staging`` to ``root / dataset_id`` (an existing one
    there moved into ``staging`` first, removed with it), with the namespace files Minari wrote
    for namespaces that ``root`` does not have yet."""
    target = root / dataset_id
    parts = Path(dataset_id).parts
    for depth in range(1, len(parts)):  # the namespaces: eabc, eabc/hopper, ...
        made = staging.joinpath(*parts[:depth], "namespace_metadata.json")
        kept = root.joinpath(*parts[:depth], "namespace_metadata.json")
        kept.parent.mkdir(exist_ok=True)
        if made.is_file() and not kept.exists():
            os.replace(made, kept)
    if target.exists() or target.is_symlink():
        os.replace(target, staging / ".replaced")
    os.replace(staging / dataset_id, target)


MINARI_UNSET = (r"`code_permalink` is set to None\.", r"`author_email` is set to None\.")
"""Minari's warnings about dataset fields an export leaves unset: no link to the code or e-mail
address is eabc's to give (a made-up one would mislead whoever reads the dataset)."""
MINARI_NO_ENV = (r"`eval_env` is set to None\.", r"env_spec is None, no environment spec")
"""Minari's warnings about a dataset without an environment (data that names none)."""


def _create(minari, dataset: Dataset, dataset_id: str, episodes: list, env) -> None:
    """Minari's own writer, into the Minari path of the moment."""
    minari.create_dataset_from_buffers(
        dataset_id,
        episodes,
        env=env,
        eval_env=env,
        algorithm_name="eabc " + dataset.metadata.get("recipe", "dataset"),
        author="eabc",
        ref_min_score=dataset.ref_min_score,
        ref_max_score=dataset.ref_max_score,
        description=f"{dataset.name}, exported by eabc; metadata: {json.dumps(dataset.metadata)}",
        observation_space=None if env else _box(dataset.observations),
        action_space=None if env else _box(dataset.actions),
    )


def _box(array: np.ndarray):
    return spaces.Box(-np.inf, np.inf, array.shape[1:], np.float32)
