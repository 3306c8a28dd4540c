"""D4RL-style datasets made here, by D4RL's recipe, into a cache directory.

Random datasets need no behaviour policy (uniform random actions); medium, expert, medium-replay and
medium-expert roll out the SAC policies of the behaviour-policy zoo (:mod:`eabc.data.zoo`); the
AntMaze datasets steer the zoo's low-level Ant policy through the maze with D4RL's waypoint
controller (:mod:`eabc.data.antmaze_collect`).
"""

from __future__ import annotations

import difflib
import json
import os
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np

from eabc import progress, timing
from eabc.data import antmaze_collect, parallel, tasks, zoo
from eabc.data.dataset import Dataset, DatasetError, concatenate
from eabc.data.hdf5_writer import ARRAYS, save_hdf5
from eabc.data.loaders import load_file
from eabc.paths import cache_dir

FORMAT_VERSION = 2
"""2: policies roll out in float64 (``networks.numpy_mlp``), so that a dataset no longer depends on
the CPU's BLAS kernel; policy datasets of version 1 are made again on next use."""
DATASET_SIZE = 1_000_000
"""D4RL's size of the random, medium and expert datasets."""

ActionFn = Callable[[np.ndarray, np.random.Generator], np.ndarray]


def mujoco_names() -> list[str]:
    """The 15 MuJoCo locomotion datasets of the paper's Table 1."""
    return [
        f"{env}-{kind}" for env in ("hopper", "halfcheetah", "walker2d") for kind in tasks.KINDS
    ]


def antmaze_names() -> list[str]:
    """The six AntMaze datasets of the paper's Table 5."""
    return [f"antmaze-{kind}" for kind in tasks.ANTMAZE_KINDS]


def antmaze_recipe_names() -> list[str]:
    """The AntMaze datasets by their other recipes, ``antmaze-KIND@RECIPE`` (the plain names use
    :data:`eabc.data.antmaze_collect.DEFAULT_RECIPE`)."""
    others = [r for r in antmaze_collect.RECIPES if r != antmaze_collect.DEFAULT_RECIPE]
    return [f"{name}@{r}" for r in others for name in antmaze_names()]


def builtin_names() -> list[str]:
    """Every dataset ``eabc data make`` makes: MuJoCo locomotion, then AntMaze (by the default
    recipe, then by the others)."""
    return mujoco_names() + antmaze_names() + antmaze_recipe_names()


def did_you_mean(name: str) -> str:
    """`` (did you mean X?)`` for the built-in name closest to a mistyped one, else ``""``."""
    close = difflib.get_close_matches(name.lower(), builtin_names(), n=1, cutoff=0.8)
    return f" (did you mean {close[0]}?)" if close else ""


def dataset_path(name: str, cache: str | os.PathLike | None = None) -> Path:
    return cache_dir(cache) / "datasets" / f"{name}.hdf5"


def load_or_make(name: str, cache_dir: str | os.PathLike | None = None, seed: int = 0) -> Dataset:
    """The cached dataset ``name``, made first if it is not in the cache yet."""
    path = dataset_path(name, cache_dir)
    if tasks.parse_task(name)[0] == "antmaze":
        adopt_recipe_file(path, name)
    current = is_current(path, name)
    if path.exists() and not current:
        print(f"{path} was made from an older behaviour-policy zoo; making it again")
    if not current:
        make(name, path, seed=seed)
    return load_file(path)


def is_current(path: str | os.PathLike, name: str, zoo_root=None) -> bool:
    """Whether ``path`` exists and was made from the zoo's present policies (see zoo.fingerprint)
    by this version of the rollout code (random datasets: always, they use no policy)."""
    path = Path(path)
    if not path.is_file():  # missing, or a directory or FIFO in its place: made again
        return False
    env_name, kind = tasks.parse_task(name)
    try:
        with h5py.File(path, "r") as f:
            metadata = json.loads(f.attrs.get("metadata", "{}"))
    except (OSError, ValueError, TypeError):  # unreadable (junk, truncated): made again
        return False
    if kind == "random":
        return True
    if metadata.get("version") != FORMAT_VERSION:
        return False
    try:
        if env_name == "antmaze":
            made_by = metadata.get("antmaze_recipe", antmaze_collect.LEGACY_RECIPE)
            if made_by != antmaze_collect.split_name(name)[1]:
                return False
            return metadata.get("zoo") == antmaze_collect.policy_fingerprint(zoo_root)
        return metadata.get("zoo") == zoo.fingerprint(env_name, kind, zoo_root)
    except (DatasetError, FileNotFoundError):
        return True  # no zoo here to compare with: the cached file is all there is


MEDIUM_REPLAY_SIZE = {"hopper": 402_000, "halfcheetah": 202_000, "walker2d": 302_000}
"""D4RL's medium-replay sizes (v2, rounded)."""

RECIPES = {
    "random": "uniform random actions",
    "medium": "actions sampled from the zoo's medium SAC policy (stopped early near D4RL's medium level)",
    "expert": "actions sampled from the zoo's expert SAC policy (fully trained)",
    "medium-replay": (
        "the zoo's SAC training snapshots up to the medium point, each rolled out (actions sampled, "
        "uniform random during the warm-up) in proportion to how long it was the acting policy"
    ),
    "medium-expert": "the medium dataset followed by the expert dataset (same seed)",
    "antmaze": (
        "the zoo's direction-following Ant policy steered by D4RL's BFS waypoint controller, "
        "Gaussian action noise 0.2, whole episodes ending in a timeout, rewards 1 (and terminals) "
        "where the next position is within 0.5 of the evaluation goal"
    ),
}


def making_time(name: str, size: int | None = None, speed=None) -> str:
    """About how long making ``size`` transitions (default the dataset's) of the built-in
    dataset ``name`` takes, and on what speed that rests (:mod:`eabc.timing`; ``speed``: a
    :class:`~eabc.timing.HostSpeed`, by default this host's, measured when it matters)."""
    size = size or default_size(name)
    if speed is None:
        quick = timing.dataset_seconds(name, size)[1] < 10  # not worth a probe
        speed = timing.host_speed(measure=not quick)
    return f"{timing.making_time(name, size, speed)} {speed.basis()}"


def default_size(name: str) -> int:
    env, kind = tasks.parse_task(name)
    if env == "antmaze":
        return DATASET_SIZE
    if kind == "medium-replay":
        return MEDIUM_REPLAY_SIZE[env]
    return 2 * DATASET_SIZE if kind == "medium-expert" else DATASET_SIZE


def make(
    name: str,
    path: str | os.PathLike,
    seed: int = 0,
    size: int | None = None,
    zoo_root: str | os.PathLike | None = None,
    workers: int = 1,
) -> Path:
    """Make the built-in dataset ``name`` and write it to ``path`` in D4RL's HDF5 layout.

    Deterministic: the same name, seed, size and zoo give a bit-identical file, whatever the
    number of ``workers`` (processes; see :mod:`eabc.data.parallel` for where they help).
    """
    task = tasks.parse_task(name)
    if name not in builtin_names() or task is None:
        raise DatasetError(
            f"no recipe for {name!r}{did_you_mean(name)}; built-in names: "
            f"{', '.join(builtin_names())}"
        )
    env_name, kind = task
    size = size or default_size(name)
    progress.say(
        f"making {name}: {size:,} transitions into {path}, "
        f"{making_time(name, -(-size // max(workers, 1)))}"  # workers share the rows
    )
    if env_name == "antmaze":
        return _make_antmaze(name, kind, path, seed, size, zoo_root, workers)
    env = tasks.ENVS[env_name]
    metadata = {"recipe": RECIPES[kind], "seed": seed, "version": FORMAT_VERSION}
    if kind != "random":
        metadata["zoo"] = zoo.fingerprint(env_name, kind, zoo_root)
    if kind != "medium-expert":
        dataset = concatenate(_rollouts(rollouts(name, seed, size, zoo_root), workers, name), name)
    if kind in ("medium", "expert"):
        card = zoo.card(env_name, zoo_root)
        metadata["policy"] = {**card[kind], "training_steps": card["training_steps"]}
    elif kind == "medium-replay":
        metadata["phases"] = _replay_phases(env_name, size, zoo_root)
    elif kind == "medium-expert":
        parts = [
            _load_or_make_part(
                Path(path).parent / f"{env_name}-{part}.hdf5",
                size // 2 + (size % 2) * (part == "medium"),
                seed,
                zoo_root,
                workers,
            )
            for part in ("medium", "expert")
        ]
        dataset = concatenate(parts, name)
        metadata["policy"] = {
            part: d.metadata.get("policy") for part, d in zip(("medium", "expert"), parts)
        }
    dataset = Dataset(
        **{k: getattr(dataset, k) for k in ARRAYS},
        name=name,
        env_id=env.env_id,
        ref_min_score=env.ref_min_score,
        ref_max_score=env.ref_max_score,
        metadata=metadata,
    )
    return save_hdf5(dataset, path)


def _make_antmaze(name: str, kind: str, path, seed: int, size: int, zoo_root, workers) -> Path:
    """An AntMaze dataset with its conventions as its own settings: the evaluation environment,
    reference scores 0 and 1 (the score is 100 x the success rate) and the reward offset -1."""
    actor, card = antmaze_collect.load_policy(zoo_root)
    num_envs = antmaze_collect.NUM_ENVS
    recipe = antmaze_collect.split_name(name)[1]
    if workers == 1:
        dataset, controller = antmaze_collect.make_dataset(
            name, kind, size, seed, actor, num_envs, recipe
        )
    else:
        maze, family = antmaze_collect.dataset_family(kind)
        episodes = antmaze_collect.episodes_for(kind, size, recipe)
        policy = antmaze_collect.policy_path(zoo_root)
        data = parallel.collect_antmaze(
            maze, family, episodes, seed, policy, num_envs, workers, desc=name, recipe_name=recipe
        )
        dataset, controller = antmaze_collect.relabelled(name, kind, size, data, num_envs, recipe)
    env = tasks.env_info(("antmaze", kind))
    keep_other_recipe(Path(path), name)
    metadata = {
        "recipe": RECIPES["antmaze"],
        "antmaze_recipe": recipe,
        "seed": seed,
        "version": FORMAT_VERSION,
        "zoo": antmaze_collect.policy_fingerprint(zoo_root),
        "policy": {k: card.get(k) for k in ("training_steps", "direction_return", "controller")},
        "controller": controller,
    }
    dataset = Dataset(
        **{k: getattr(dataset, k) for k in ARRAYS},
        name=name,
        env_id=env.env_id,
        ref_min_score=env.ref_min_score,
        ref_max_score=env.ref_max_score,
        reward_offset=tasks.reward_offset(("antmaze", kind)),
        metadata=metadata,
    )
    return save_hdf5(dataset, path)


def _file_recipe(path: Path) -> str | None:
    """The AntMaze recipe the file ``path`` was made by (None: no readable AntMaze file)."""
    try:
        with h5py.File(path, "r") as f:
            metadata = json.loads(f.attrs.get("metadata", "{}"))
    except (OSError, ValueError, TypeError):
        return None
    return metadata.get("antmaze_recipe", antmaze_collect.LEGACY_RECIPE)


def keep_other_recipe(path: Path, name: str) -> Path | None:
    """Before ``name`` is made at ``path``: a file there made by another AntMaze recipe is moved
    to that recipe's name beside it (``antmaze-umaze.hdf5`` made by ``planner-v0`` becomes
    ``antmaze-umaze@planner-v0.hdf5``) where nothing has that name yet; the new place, or None."""
    base, wanted = antmaze_collect.split_name(name)
    made_by = _file_recipe(path) if path.is_file() else None
    if made_by is None or made_by == wanted:
        return None
    other = path.with_name(f"{base}@{made_by}{path.suffix}")
    if made_by == antmaze_collect.DEFAULT_RECIPE:
        other = path.with_name(f"{base}{path.suffix}")
    if other.exists():
        return None
    os.replace(path, other)
    print(f"{path} was made by the AntMaze recipe {made_by}: kept as {other}")
    return other


def adopt_recipe_file(path: Path, name: str) -> None:
    """Before ``name`` is looked up at ``path``: where no file is there yet but the file of the
    same dataset under its other name was made by ``name``'s recipe (a cache from before recipes
    had names: ``antmaze-umaze.hdf5`` by ``planner-v0``, asked for as
    ``antmaze-umaze@planner-v0``), that file is moved here."""
    base, wanted = antmaze_collect.split_name(name)
    if path.exists():
        return
    plain = path.with_name(f"{base}{path.suffix}")
    if plain != path and plain.is_file() and _file_recipe(plain) == wanted:
        os.replace(plain, path)
        print(f"{plain} was made by the AntMaze recipe {wanted}: moved to {path}")


def rollouts(name: str, seed: int, size: int, zoo_root=None) -> list[parallel.Rollout]:
    """The rollouts the MuJoCo dataset ``name`` (not medium-expert: its parts are the medium and
    expert datasets) is made of, in order: one, or medium-replay's one per training phase."""
    env_name, kind = tasks.parse_task(name)
    env_id = tasks.ENVS[env_name].env_id
    if kind == "random":
        return [parallel.Rollout(env_id, None, size, seed, desc=name)]
    if kind in ("medium", "expert"):
        policy = str(zoo.policy_path(env_name, kind, zoo_root))
        return [parallel.Rollout(env_id, policy, size, seed, desc=name)]
    if kind != "medium-replay":
        raise DatasetError(f"{name} is not made by rollouts of its own")
    phases = zoo.replay_schedule(env_name, zoo_root)
    specs = []
    for i, ((_, _, policy), count) in enumerate(zip(phases, _replay_counts(phases, size))):
        if count:
            path = None if policy is None else str(zoo.policy_path(env_name, policy, zoo_root))
            desc = f"{env_name}-medium-replay {i + 1}/{len(phases)}"
            specs.append(parallel.Rollout(env_id, path, count, seed + i, desc=desc))
    return specs


def _replay_counts(phases: list, size: int) -> list[int]:
    """Every training phase's share of ``size`` transitions, in proportion to its length."""
    total = phases[-1][1]
    bounds = np.round(np.cumsum([0] + [stop - start for start, stop, _ in phases]) * size / total)
    return [int(hi - lo) for lo, hi in zip(bounds[:-1], bounds[1:])]


def _replay_phases(env_name: str, size: int, zoo_root) -> list[dict]:
    """medium-replay's phases as its metadata describes them."""
    phases = zoo.replay_schedule(env_name, zoo_root)
    return [
        {"policy": policy or "uniform random", "train_steps": [start, stop], "transitions": count}
        for (start, stop, policy), count in zip(phases, _replay_counts(phases, size))
        if count
    ]


def _rollouts(specs: list[parallel.Rollout], workers: int, desc: str) -> list[Dataset]:
    """The rollouts ``specs``, made by ``workers`` processes where :mod:`eabc.data.parallel` can,
    else by this one: the same rows either way."""
    made = parallel.make_rollouts(specs, workers, desc) if workers > 1 else [None] * len(specs)
    datasets = []
    for spec, rows in zip(specs, made):
        if rows is None:
            datasets.append(_one_process(spec))
            continue
        if not (rows["terminals"][-1] or rows["timeouts"][-1]):
            rows["timeouts"][-1] = True
        datasets.append(Dataset(**rows, name=spec.desc, env_id=spec.env_id))
    return datasets


def _one_process(spec: parallel.Rollout) -> Dataset:
    act = parallel.action_fn(spec.policy)
    return rollout(spec.env_id, act, spec.size, spec.seed, spec.max_episode_steps, spec.desc)


def episode_starts(path: str | os.PathLike, zoo_root=None, spacing: int = parallel.SPACING) -> dict:
    """:data:`eabc.data.parallel.TABLE`'s entries for the rollouts of the dataset file ``path``
    (made by one process with the present zoo): an episode start every ~``spacing`` rows."""
    data = load_file(path)
    if not is_current(path, data.name, zoo_root):
        raise DatasetError(f"{path} was not made from the present zoo: its starts would not fit")
    seed = data.metadata["seed"]
    entries, lo = {}, 0
    for spec in rollouts(data.name, seed, data.size, zoo_root):
        ends = data.terminals[lo : lo + spec.size - 1] | data.timeouts[lo : lo + spec.size - 1]
        rows = np.flatnonzero(ends) + 1  # every episode start but row 0; its episode: the index
        starts, wanted = [], spacing
        for episode, row in enumerate(rows, start=1):
            if row >= wanted:
                starts.append([int(row), episode])
                wanted = (row // spacing + 1) * spacing
        entries[spec.key()] = {"transitions": spec.size, "starts": starts}
        lo += spec.size
    return entries


def add_episode_starts(
    paths: list[str | os.PathLike], table: Path | None = None, spacing: int = parallel.SPACING
) -> Path:
    """Add the episode starts of the dataset files ``paths`` to the table (made if missing); how
    the shipped one is made: ``python -c "from eabc.data import generate;
    generate.add_episode_starts(['PATH/hopper-medium.hdf5', ...])"``."""
    table = parallel.TABLE if table is None else Path(table)
    content = json.loads(table.read_text()) if table.exists() else {
        "what": "episode starts [row, episode] of the rollouts that make the built-in MuJoCo "
        "datasets, by environment, policy file digest and seed (eabc.data.parallel)",
        "rollouts": {},
    }  # fmt: skip
    for path in paths:
        for key, entry in episode_starts(path, spacing=spacing).items():
            known = content["rollouts"].get(key, {"transitions": 0})
            if entry["transitions"] > known["transitions"]:  # a rollout's prefix: the same starts
                content["rollouts"][key] = entry
    rollouts = ",\n".join(  # a rollout a line
        f"  {json.dumps(key)}: {json.dumps(entry)}"
        for key, entry in sorted(content["rollouts"].items())
    )
    table.write_text(
        f'{{"what": {json.dumps(content["what"])},\n"rollouts": {{\n{rollouts}\n}}}}\n'
    )
    return table


def _load_or_make_part(path: Path, size: int, seed: int, zoo_root, workers: int) -> Dataset:
    """A part of medium-expert: the cached dataset if it was made with this seed and size."""
    if is_current(path, path.stem, zoo_root):
        cached = load_file(path)
        if cached.metadata.get("seed") == seed and cached.size == size:
            return cached
    tmp = path.with_name(f".{path.stem}-part-{seed}-{size}.hdf5")
    try:
        return load_file(make(path.stem, tmp, seed, size, zoo_root, workers))
    finally:
        tmp.unlink(missing_ok=True)


def rollout(
    env_id: str,
    act: ActionFn | None,
    num_transitions: int,
    seed: int,
    max_episode_steps: int = 1000,
    desc: str = "rollout",
) -> Dataset:
    """Collect ``num_transitions`` transitions with ``act`` (uniform random actions when None).

    Episodes end at a terminal or after ``max_episode_steps`` (a timeout); the last transition is
    flagged as a timeout when the budget cuts an episode short. Deterministic for a given seed.
    """
    env = parallel.make_env(env_id, max_episode_steps)
    rng = np.random.default_rng(seed)
    out = parallel.empty_rows(env, num_transitions)
    obs, _ = env.reset(seed=seed)
    bar = progress.bar(
        num_transitions, desc, iterable=range(num_transitions), mininterval=1.0, leave=False
    )  # a bar on a terminal, else a line every minute (logs, CI)
    parallel.step_rows(env, act, rng, obs, out, bar, num_transitions)
    if not (out["terminals"][-1] or out["timeouts"][-1]):
        out["timeouts"][-1] = True
    env.close()
    return Dataset(**out, name=desc, env_id=env_id)
