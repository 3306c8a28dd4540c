"""``eabc data {make,list,info,export}`` and ``eabc zoo {build,pack}``."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Annotated

import tyro

from eabc import ranges, timing
from eabc.ranges import Finite, Positive, Seed, Steps


@dataclasses.dataclass(frozen=True)
class DataMake:
    """Make a built-in D4RL-style dataset (e.g. hopper-random) in the cache directory."""

    name: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    seed: Seed = 0
    """Seed of the environment and the actions; the same seed gives the same file."""
    size: Steps | None = None
    """Transitions (default D4RL's size)."""
    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""
    force: bool = False
    """Remake the dataset even if it is cached."""
    workers: Positive = 1
    """Processes that make it (e.g. the number of cores); any number gives the same file. AntMaze
    data use them always, MuJoCo data at seed 0 (from the shipped table of episode starts)."""


DataMake.__doc__ = (  # the figures of eabc.timing, the one source of time estimates
    "Make a built-in D4RL-style dataset (e.g. hopper-random) in the cache directory: "
    f"{timing.making_time('hopper-medium')} per 1M transitions, AntMaze "
    f"{timing.making_time('antmaze-umaze')}, at the reference host's speed ({timing.REFERENCE_HOST}; "
    "the command says how long on this host when it starts)."
)


@dataclasses.dataclass(frozen=True)
class DataInfo:
    """Describe a dataset: size, episodes, returns and normalised score; for AntMaze data also the
    controller's success rate, the reward-1 transitions and the position jumps. Makes nothing: a
    built-in dataset not made yet is named with the command that makes it."""

    name: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    """A built-in name, a file path or minari:ID."""
    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""
    plot: Annotated[str | None, tyro.conf.arg(metavar="PNG")] = None
    """AntMaze data: also draw the torso positions over the maze's walls into this PNG file."""


@dataclasses.dataclass(frozen=True)
class DataList:
    """List the built-in datasets and which of them are in the cache."""

    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""


@dataclasses.dataclass(frozen=True)
class ZooBuild:
    """Choose the medium and expert policies of an `eabc sac` run into the behaviour-policy zoo."""

    run_dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    """The `eabc sac` run directory (its actor snapshots and log)."""
    env: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="ENV")]
    """hopper, halfcheetah, walker2d, or antmaze (the AntMaze low-level policy, from an `eabc sac`
    run on eabc/AntDirection-v0)."""
    root: str | None = None
    """Zoo directory (default: the package's, or $EABC_ZOO_DIR)."""
    episodes: Positive = 10
    """Episodes per measured snapshot (sampled actions, as the datasets are made)."""
    expert_candidates: Positive = 5
    """The expert is the best of this many last snapshots."""
    medium_return: Finite | None = None
    """Return the medium policy aims at (default: D4RL's medium level)."""
    rechoose_medium: bool = False
    """Search for the medium policy again even if the zoo already has one."""
    step: Positive | None = None
    """antmaze: the snapshot to ship (default the run's latest)."""


@dataclasses.dataclass(frozen=True)
class ZooPack:
    """Copy a SAC run's checkpoint, log and float16 snapshots (no replay buffer) into DEST."""

    run_dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    """The `eabc sac` run directory."""
    dest: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="DEST")]
    """Where the copy goes (made if missing)."""


def run_zoo(cmd: ZooBuild | ZooPack) -> None:
    from eabc.data import zoo  # noqa: PLC0415
    from eabc.training import zoo_build  # noqa: PLC0415

    if isinstance(cmd, ZooPack):
        print(zoo_build.pack(cmd.run_dir, cmd.dest))
        return
    if cmd.env == "antmaze":
        card = zoo_build.build_antmaze(cmd.run_dir, cmd.root, cmd.step, cmd.episodes)
        print(
            json.dumps(
                {k: card[k] for k in ("training_steps", "controller", "open_plane")}, indent=2
            )
        )
        return
    medium_step = None
    if (zoo.zoo_dir(cmd.root) / cmd.env / zoo.CARD).exists() and not cmd.rechoose_medium:
        medium_step = zoo.card(cmd.env, cmd.root)["medium"]["step"]
        print(f"keeping the zoo's medium policy (step {medium_step}); --rechoose-medium to search")
    card = zoo_build.build(
        cmd.run_dir,
        cmd.env,
        cmd.root,
        cmd.episodes,
        expert_candidates=cmd.expert_candidates,
        medium_return=cmd.medium_return,
        medium_step=medium_step,
    )
    print(json.dumps({k: card[k] for k in ("expert", "medium")}, indent=2))


@dataclasses.dataclass(frozen=True)
class DataExport:
    """Export a dataset to the local Minari path (CORL and other Minari readers) or, with
    --d3rlpy PATH, as d3rlpy's own dataset file."""

    name: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    """A built-in name (made first if needed), a file path or minari:ID."""
    minari: bool = True
    """Export as a Minari dataset (the default; --d3rlpy writes d3rlpy's file instead)."""
    dataset_id: str | None = None
    """The Minari id (default eabc/ENV/KIND-v0, e.g. eabc/hopper/medium-v0)."""
    d3rlpy: Annotated[str | None, tyro.conf.arg(metavar="PATH")] = None
    """Write d3rlpy's MDPDataset (continuous actions) to this HDF5 file instead; read it with
    d3rlpy.dataset.ReplayBuffer.load(f, d3rlpy.dataset.InfiniteBuffer())."""
    force: bool = False
    """Replace an existing Minari dataset of that id, or the --d3rlpy file."""
    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""


def run_data(cmd: DataMake | DataInfo | DataList | DataExport) -> None:
    from eabc.data import describe, generate, loaders, sources  # noqa: PLC0415
    from eabc.data.dataset import DatasetError  # noqa: PLC0415
    from eabc.training.config import check_cache_dir  # noqa: PLC0415

    if cmd.cache_dir is not None:  # checked before minutes of making a dataset, not after
        check_cache_dir(cmd.cache_dir, "--cache-dir")
    elif os.environ.get("EABC_CACHE_DIR"):
        check_cache_dir(os.environ["EABC_CACHE_DIR"], "$EABC_CACHE_DIR")
    if isinstance(cmd, DataMake):
        _check_making_memory(cmd)
        path = generate.dataset_path(cmd.name, cmd.cache_dir)
        if path.exists() and not cmd.force:
            if generate.is_current(path, cmd.name):
                print(f"{path} (cached; --force to remake)")
                return
            print(f"{path} was made from older zoo policies; making it again", file=sys.stderr)
        print(_make(cmd, path))
    elif isinstance(cmd, DataList):
        names = generate.builtin_names()
        wide = max(len("dataset"), *map(len, names))  # the names column fits the longest name
        header = f"{'dataset':{wide}s} {'transitions':>11s} {'episodes':>8s} {'return':>17s} {'score':>6s} {'D4RL':>5s}  file"
        print(header)
        unknown = f"{'-':>11s} {'-':>8s} {'-':>17s} {'-':>6s}"  # no file to describe
        for name in names:
            path = generate.dataset_path(name, cmd.cache_dir)
            level = _number(describe.d4rl_level(name), 5, ".0f")
            if not path.exists():
                print(f"{name:{wide}s} {unknown} {level}  (not made)")
                continue
            try:  # one unreadable file is one row, not the end of the list
                info = describe.describe(path)
            except (DatasetError, OSError) as error:
                why = " ".join(str(error).split())
                print(
                    f"{name:{wide}s} {unknown} {level}  {path} "
                    f"(unreadable: {why[:160]}; eabc data make {name} --force)"
                )
                continue
            spread = f"{info['return_mean']:.0f} +- {info['return_std']:.0f}"
            score = _number(info["normalized_return"], 6, ".1f")
            episodes = info["episodes"]
            if "antmaze" in info:  # whole controller episodes; terminals mark goal visits
                rate = info["antmaze"]["controller_success_rate"]
                spread = "-" if rate is None else f"{rate:.0%} reach goal"
                episodes, score = info["timeouts"], _number(None, 6, "")
            print(
                f"{name:{wide}s} {info['transitions']:11d} {episodes:8d} {spread:>17s} "
                f"{score} {level}  {path}"
            )
    elif isinstance(cmd, DataExport) and cmd.d3rlpy is not None:
        from eabc.data import d3rlpy_export  # noqa: PLC0415

        d3rlpy_export.check_target(cmd.d3rlpy, cmd.force)  # before a dataset is made
        dataset = sources.load_dataset(cmd.name, cmd.cache_dir)
        print(d3rlpy_export.export_d3rlpy(dataset, cmd.d3rlpy, overwrite=cmd.force))
    elif isinstance(cmd, DataExport):
        if cmd.dataset_id is not None:  # before a dataset is made or anything written
            loaders.check_export_target(cmd.dataset_id, cmd.force)
        dataset = sources.load_dataset(cmd.name, cmd.cache_dir)
        dataset_id = cmd.dataset_id or loaders.minari_id(dataset.name)
        print(loaders.export_minari(dataset, dataset_id, overwrite=cmd.force))
    else:
        if cmd.plot is not None and not Path(cmd.plot).expanduser().parent.is_dir():
            raise ValueError(f"--plot {cmd.plot}: its directory does not exist; make it first")
        dataset = sources.load_dataset(cmd.name, cmd.cache_dir, make=False)  # describes only
        print(json.dumps(describe.describe_dataset(dataset), indent=2))
        if cmd.plot is not None:
            from eabc.data import antmaze_collect  # noqa: PLC0415

            print(antmaze_collect.plot_coverage(dataset, Path(cmd.plot).expanduser()))


def _make(cmd: DataMake, path: Path) -> Path:
    """``generate.make``; Ctrl-C ends it in one line that says what is in the cache and how to
    go on. A Ctrl-C that Python dropped (raised inside a weakref callback or a ``__del__``, where
    an exception is only printed) still ends the command once the dataset is written."""
    from eabc.cli.options import Interrupted  # noqa: PLC0415
    from eabc.data import generate  # noqa: PLC0415

    before = _file_state(path)
    noted: list[int] = []

    def interrupt(signum, frame):
        noted.append(signum)
        raise KeyboardInterrupt

    own = threading.current_thread() is threading.main_thread()
    own = own and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    if own:
        signal.signal(signal.SIGINT, interrupt)
    try:
        made = generate.make(cmd.name, path, cmd.seed, cmd.size, workers=cmd.workers)
        if noted:
            raise KeyboardInterrupt
    except KeyboardInterrupt:
        raise Interrupted(_after_interrupt(cmd, path, before)) from None
    finally:
        if own:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    return made


def _file_state(path: Path) -> tuple[int, int] | None:
    try:
        stat = path.stat()
    except OSError:
        return None
    return stat.st_ino, stat.st_mtime_ns


def _after_interrupt(cmd: DataMake, path: Path, before: tuple[int, int] | None) -> str:
    """One line: what an interrupted ``eabc data make`` left at ``path`` and how to go on."""
    from eabc.data import generate  # noqa: PLC0415

    flags = "".join(
        f" --{field.name.replace('_', '-')} {getattr(cmd, field.name)}"
        for field in dataclasses.fields(cmd)
        if field.name in ("seed", "size", "cache_dir", "workers")
        and getattr(cmd, field.name) != field.default
    )
    again = f"eabc data make {cmd.name}{flags}"
    now = _file_state(path)
    if now is not None and now != before and generate.is_current(path, cmd.name):
        return f"interrupted after {path} was written: it is complete and kept"
    if now is not None and now == before:
        return (
            f"interrupted: {path} is as it was, nothing written; to make it again: {again} --force"
        )
    return (
        f"interrupted: {cmd.name} was not made, nothing of it kept in {path.parent}; "
        f"to make it (from the start): {again}"
    )


def _check_making_memory(cmd: DataMake) -> None:
    """Refuse a ``--size`` whose arrays (float32 observations, next observations, actions,
    rewards, terminals and timeouts) would not fit in the memory free, before minutes of making."""
    from eabc.data import generate, tasks  # noqa: PLC0415
    from eabc.evaluation import space_sizes  # noqa: PLC0415

    info = tasks.env_info(tasks.parse_task(cmd.name))
    if cmd.size is None or info is None or cmd.name not in generate.builtin_names():
        return  # the default sizes fit; an unknown name is refused by make, naming it
    obs_dim, act_dim, _ = space_sizes(info.env_id)
    need = cmd.size * 4 * (2 * obs_dim + act_dim + 3)
    ranges.check_memory([("--size", str(cmd.size), f"{cmd.name}'s arrays", need)])


def _number(value: float | None, width: int, spec: str) -> str:
    return f"{'-':>{width}s}" if value is None else f"{value:{width}{spec}}"
