"""What a sweep runs: its specification and the runs it expands to.

A sweep specification (YAML, or the same keys from the command line or a preset) names

    datasets: [hopper-medium, walker2d-medium]     # any --dataset value
    algos: [ALGO, ...]                              # any --algo value
    seeds: [0, 1, 2]
    steps: 1000000
    grid: {num_critics: [5, 10], confidence_level: [0.25, 1.0], pessimism: [mean-std, min]}
    train: {eval_interval: 5000, eval_episodes: 10}  # any other TrainConfig field

and expands to the product datasets x algos x grid x seeds (grid settings apply only to the
algorithms that have them). ``variants:`` lists named combinations instead of (or beside) a grid,
``{algo: ALGO, critic_layer_norm: true}``, run breadth first in the order given; a variant's own
``datasets: [...]`` replaces the spec's for it, so one spec can put runs in any priority order.

Before it expands, the whole specification is checked by one model (:class:`SweepSpec`): lists are
lists (a bare ``datasets: hopper-random`` or ``seeds: 5`` is refused, naming the key, rather than
read as one run per character or guessed at), seeds are whole numbers in [0, 2**32 - 1], nothing
that makes runs is empty, ``steps`` and the ``train:`` settings have their TrainConfig types
(1000, not "1000" or 1000.0) and ranges.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import os
from pathlib import Path
from typing import Any

import pydantic
import yaml

from eabc import paths, ranges
from eabc.agents import get_algorithm
from eabc.data import sources, tasks
from eabc.training.config import TrainConfig

TRAIN_FIELDS = {f.name for f in dataclasses.fields(TrainConfig)} - {"dataset", "algo", "seed"}


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One training run of a sweep."""

    dataset: str
    algo: str
    seed: int
    overrides: tuple[tuple[str, Any], ...] = ()
    """Algorithm settings that differ from the preset, sorted by name."""
    train: tuple[tuple[str, Any], ...] = ()
    """TrainConfig fields (steps, eval_interval, ...), sorted by name."""

    @property
    def variant(self) -> str:
        """A short label of the overrides, e.g. ``K=5 p=0.25`` (empty for the preset)."""
        short = get_algorithm(self.algo).short_names
        return " ".join(f"{short.get(k, k)}={_text(v)}" for k, v in self.overrides)

    @property
    def group_id(self) -> str:
        short = get_algorithm(self.algo).short_names
        slug = "_".join(f"{short.get(k, k)}{_text(v)}" for k, v in self.overrides)
        name = self.dataset
        if is_path(name):  # pendA.npz in two folders are two datasets: a hash of the full path
            full = str(paths.expand(name).resolve())
            name = f"{Path(name).stem}-{hashlib.sha256(full.encode()).hexdigest()[:6]}"
        return "__".join(filter(None, [name.replace(":", "-").replace("/", "-"), self.algo, slug]))

    @property
    def run_id(self) -> str:
        return f"{self.group_id}__seed{self.seed}"

    def train_config(self) -> TrainConfig:
        return TrainConfig(dataset=self.dataset, algo=self.algo, seed=self.seed, **dict(self.train))

    def to_json(self) -> dict:
        return {
            "dataset": self.dataset,
            "algo": self.algo,
            "seed": self.seed,
            "overrides": dict(self.overrides),
            "train": dict(self.train),
        }

    @classmethod
    def from_json(cls, data: dict) -> RunSpec:
        return cls(
            data["dataset"],
            data["algo"],
            int(data["seed"]),
            _frozen(data.get("overrides", {})),
            _frozen(data.get("train", {})),
        )


def is_path(dataset: str) -> bool:
    """Whether a --dataset value names a file (rather than a built-in name or a Minari id):
    :func:`eabc.data.sources.kind` decides."""
    return sources.kind(dataset) == "file"


def differences(stored: RunSpec, run: RunSpec) -> list[str]:
    """What makes ``run`` another run than ``stored`` (steps aside: more steps extend a run; where
    built-in datasets are cached neither: their content fingerprint is checked on resume)."""
    out = [
        f"{name} {getattr(stored, name)!r} -> {getattr(run, name)!r}"
        for name in ("dataset", "algo", "seed", "overrides")
        if getattr(stored, name) != getattr(run, name)
    ]
    old, new = dict(stored.train), dict(run.train)
    for key in sorted((set(old) | set(new)) - {"steps", "cache_dir"}):
        if old.get(key) != new.get(key):
            out.append(f"{key} {old.get(key)!r} -> {new.get(key)!r}")
    return out


def _freeze(value):
    """Lists (from YAML or JSON) as tuples, so settings are hashable like the config fields."""
    return tuple(_freeze(v) for v in value) if isinstance(value, list | tuple) else value


def _frozen(mapping: dict) -> tuple[tuple[str, Any], ...]:
    return tuple(sorted((k, _freeze(v)) for k, v in mapping.items()))


def _text(value) -> str:
    return "-".join(map(str, value)) if isinstance(value, tuple) else str(value)


def load_spec(path: str | os.PathLike) -> dict[str, Any]:
    """A sweep specification from a YAML file: a regular file (a FIFO would block), UTF-8 text,
    YAML, a mapping; :func:`check_spec` checks its keys."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"sweep specification {path} does not exist")
    if not path.is_file():
        raise ValueError(f"sweep specification {path} is not a regular file; give a YAML file")
    try:
        spec = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not UTF-8 text; a sweep specification is a YAML file") from None
    except RecursionError:  # brackets nested thousands deep
        raise ValueError(
            f"{path}: nested too deeply for a sweep specification; fix the file"
        ) from None
    except yaml.YAMLError as error:
        where = getattr(error, "problem_mark", None)
        line = f" at line {where.line + 1}" if where is not None else ""
        problem = " ".join(str(getattr(error, "problem", None) or error).split())
        raise ValueError(f"{path}: not valid YAML{line} ({problem}); fix the file") from None
    if not isinstance(spec, dict):
        raise ValueError(f"{path}: a sweep specification is a mapping (datasets:, algos:, ...)")
    return spec


KEYS = ("datasets", "algos", "variants", "seeds", "steps", "grid", "train")


def _names(key: str, value) -> list[str]:
    """A list of non-empty names (datasets, algorithms); a bare name is refused, as a variant's
    bare ``datasets:`` is: the list says what runs, with no guess."""
    if isinstance(value, str):
        raise ValueError(f"{key} must be a list, e.g. {key}: [{value}]")
    if not isinstance(value, list | tuple):
        raise ValueError(f"{key} must be a list of names, e.g. {key}: [a, b], got {value!r}")
    for i, name in enumerate(value):
        if not isinstance(name, str) or not name.strip():
            raise ValueError(f"{key}[{i}] must be a name (text), got {name!r}")
        try:
            paths.expand(name)  # a file's ~user that is no user: named here, not mid-expansion
        except ValueError as error:
            raise ValueError(f"{key}[{i}]: {error}") from None
    return list(value)


class SweepSpec(pydantic.BaseModel):
    """A sweep specification (YAML, preset and flags merged), checked as a whole before it
    expands to runs: each key's type and range, in one line that names the key."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True)

    datasets: list[str]
    """Any --dataset value; at least one."""
    algos: list[str] = []
    """Any --algo value (run with their presets and the grid)."""
    variants: list[dict[str, Any]] = []
    """Named combinations (:func:`variant_entries`), a bare name as ``{algo: NAME}``."""
    seeds: list[int] = [0]
    """Whole numbers in [0, 2**32 - 1]; at least one."""
    steps: int | None = None
    """Gradient steps per run (replaces train's steps)."""
    grid: dict[str, list[Any]] = {}
    """Setting -> the values to try (a single value: that value only)."""
    train: dict[str, Any] = {}
    """TrainConfig fields, each of its declared type (no conversion: 1000, not "1000")."""

    @pydantic.model_validator(mode="before")
    @classmethod
    def _keys(cls, spec):
        if not isinstance(spec, dict):
            raise ValueError(
                f"a sweep specification is a mapping (datasets:, algos:, ...), got {spec!r}"
            )
        unknown = set(spec) - set(KEYS)
        if unknown:
            raise ValueError(
                f"unknown sweep key(s) {sorted(map(str, unknown))}; use {sorted(KEYS)}"
            )
        if not spec.get("datasets"):
            raise ValueError("the sweep needs at least one entry in 'datasets'")
        if not spec.get("algos") and not spec.get("variants"):
            raise ValueError("the sweep needs at least one entry in 'algos' or 'variants'")
        return spec

    @pydantic.field_validator("datasets", "algos", mode="before")
    @classmethod
    def _name_list(cls, value, info):
        return _names(info.field_name, value)

    @pydantic.field_validator("variants", mode="before")
    @classmethod
    def _variant_list(cls, value):
        return variant_entries(value)

    @pydantic.field_validator("seeds", mode="before")
    @classmethod
    def _seed_list(cls, value):
        if isinstance(value, int) and not isinstance(value, bool):
            raise ValueError(
                f"seeds must be a list, e.g. seeds: [{value}] for the seed {value}, or "
                f"[0, 1, 2] for three seeds; got the single number {value}"
            )
        if not isinstance(value, list | tuple):
            raise ValueError(
                f"seeds must be a list of whole numbers, e.g. seeds: [0, 1, 2], got {value!r}"
            )
        if not value:
            raise ValueError("seeds is empty: list at least one seed, e.g. seeds: [0]")
        for i, seed in enumerate(value):
            ranges.check(seed, _TRAIN_TYPES["seed"], f"seeds[{i}]")  # TrainConfig's range
        return list(value)

    @pydantic.field_validator("steps", mode="before")
    @classmethod
    def _steps(cls, value):
        return ranges.check(value, _TRAIN_TYPES["steps"], "steps")

    @pydantic.field_validator("grid", mode="before")
    @classmethod
    def _grid(cls, value):
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise ValueError(
                f"grid must be a mapping of setting -> values, e.g. grid: {{num_critics: [5, 10]}}, got {value!r}"
            )
        grid = {}
        for key, values in value.items():
            if not isinstance(key, str):
                raise ValueError(f"grid key {key!r} must be a setting's name")
            values = list(values) if isinstance(values, list | tuple) else [values]
            if not values:
                raise ValueError(
                    f"grid.{key} is empty: give at least one value, e.g. {key}: [5, 10]"
                )
            grid[key] = values
        return grid

    @pydantic.field_validator("train", mode="before")
    @classmethod
    def _train(cls, value):
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise ValueError(
                f"train must be a mapping of TrainConfig settings, e.g. train: {{eval_interval: 5000}}, got {value!r}"
            )
        bad = set(value) - TRAIN_FIELDS
        if bad:
            raise ValueError(
                f"unknown train setting(s) {sorted(map(str, bad))}; use {sorted(TRAIN_FIELDS)}"
            )
        return dict(value)  # each of its type and range: TrainConfig's own check (below)

    @pydantic.model_validator(mode="after")
    def _train_config(self):
        """The train settings as TrainConfig checks them: each of its declared type and range
        (no conversion: 1000, not "1000"), and together (intervals that divide, a cache_dir that
        can be one)."""
        settings = self.train_settings()
        try:
            if settings.get("cache_dir"):
                paths.expand(settings["cache_dir"])  # a ~user that is not one: named
            TrainConfig(**settings)
        except ValueError as error:
            raise ValueError(f"bad train setting: {error}") from None
        return self

    def train_settings(self) -> dict[str, Any]:
        """``train`` with ``steps`` (which replaces train's)."""
        return self.train | ({"steps": self.steps} if self.steps is not None else {})


_TRAIN_TYPES = ranges.hints(TrainConfig)


def check_spec(spec: dict[str, Any]) -> SweepSpec:
    """The specification checked by :class:`SweepSpec`; ``ValueError`` of one line otherwise."""
    try:
        return SweepSpec.model_validate(spec)
    except pydantic.ValidationError as error:
        first = error.errors()[0]
        message = first["msg"].removeprefix("Value error, ")
        if first["type"] != "value_error":  # pydantic's own: name the key and the value
            where = ".".join(map(str, first["loc"])) or "sweep specification"
            message = f"{where}: {message}, got {first.get('input')!r}"
        raise ValueError(message) from None


def expand(spec: dict[str, Any]) -> list[RunSpec]:
    """Every run of a specification, in a stable order (see the module docstring for the keys),
    after :func:`check_spec` checked it."""
    checked = check_spec(spec)
    datasets = [_dataset(d) for d in checked.datasets]
    variants = [_variant(v, datasets) for v in checked.variants]
    seeds = list(checked.seeds)
    train = checked.train_settings()
    if train.get("cache_dir"):  # absolute, as dataset files below: workers start elsewhere
        train["cache_dir"] = str(paths.expand(train["cache_dir"]).resolve())
    grid = dict(checked.grid)
    runs = []
    algos = checked.algos
    for dataset in datasets:
        for algo in algos:
            axes = {k: v for k, v in grid.items() if k in _fields(algo)}
            for key, values in axes.items():
                _one_way_each(algo, key, values)
            for values in itertools.product(*axes.values()):
                overrides = _frozen(dict(zip(axes, values)))
                try:
                    _settings(algo, dict(overrides))
                except ranges.SettingError as error:
                    raise ValueError(f"grid: {error}") from None
                for seed in seeds:
                    runs.append(RunSpec(dataset, algo, seed, overrides, _frozen(train)))
    # Named combinations, beside the grid's product; breadth first (seed, then variant, then
    # dataset), so that a sweep stopped early has compared every variant on every dataset.
    for seed, (algo, overrides, only) in itertools.product(seeds, variants):
        for dataset in only:
            runs.append(RunSpec(dataset, algo, seed, overrides, _frozen(train)))
    unused = set(grid) - {k for a in algos for k in _fields(a)}
    if grid and unused:
        raise ValueError(f"no algorithm of the sweep has the setting(s) {sorted(unused)}")
    unique: dict[str, RunSpec] = {}
    for run in runs:  # a run listed twice keeps its first place
        unique.setdefault(run.run_id, run)
    return list(unique.values())


def _one_way_each(algo: str, key: str, values: list) -> None:
    """Refuse a grid axis that lists one value written two ways (``[1, 1.0]``, ``[5, "5"]``):
    the algorithm reads them as one setting, so the sweep would train the same run twice under
    two labels. (A value listed twice as the same text is one run, as a seed listed twice is.)"""
    seen: dict[Any, Any] = {}
    for value in values:
        try:
            read = ranges.value_of(_settings(algo, {key: _freeze(value)}), key)
        except ranges.SettingError as error:
            raise ValueError(f"grid: {error}") from None
        first = seen.setdefault(repr(read), value)
        if _text(_freeze(first)) != _text(_freeze(value)):
            raise ValueError(
                f"grid.{key} lists {first!r} and {value!r}, one {algo} setting ({key}={read!r}) "
                "written two ways, which would train it twice under two labels; list it once"
            )


def _dataset(name: str) -> str:
    return str(paths.expand(name).resolve()) if is_path(name) else name


def variant_entries(value) -> list[dict[str, Any]]:
    """The ``variants:`` list as mappings ``{algo: NAME, datasets: [...], SETTING: VALUE}`` (a
    bare name is ``{algo: NAME}``), each checked for its shape; :func:`_variant` checks the
    settings against the algorithm's own."""
    if not isinstance(value, list | tuple):
        raise ValueError(f"variants must be a list of {{algo: ..., SETTING: VALUE}}, got {value!r}")
    entries = []
    for entry in value:
        entry = {"algo": entry} if isinstance(entry, str) else entry
        if not isinstance(entry, dict) or not isinstance(entry.get("algo"), str):
            raise ValueError(f"a sweep variant is a mapping with an 'algo' key, got {entry!r}")
        if not all(isinstance(key, str) for key in entry):
            raise ValueError(f"variant {entry!r}: each setting is named by text")
        only = entry.get("datasets")
        named = isinstance(only, list | tuple) and all(isinstance(d, str) and d for d in only)
        if "datasets" in entry and not (named and only):
            raise ValueError(
                f"variant {entry!r}: 'datasets' must be a non-empty list of dataset names, got {only!r}"
            )
        if "datasets" in entry:
            _names("datasets", only)
        entries.append(dict(entry))
    return entries


def _variant(
    entry: dict, datasets: list[str]
) -> tuple[str, tuple[tuple[str, Any], ...], list[str]]:
    """A ``variants:`` entry (:func:`variant_entries`), ``{algo: ALGO, critic_layer_norm: true}``:
    one algorithm with fixed settings (checked against the algorithm's own), and the datasets it
    runs on (its own ``datasets:`` list, else the spec's)."""
    settings = {k: v for k, v in entry.items() if k not in ("algo", "datasets")}
    unknown = set(settings) - _fields(entry["algo"])
    if unknown:
        raise ValueError(
            f"variant {entry!r}: {entry['algo']} has no setting(s) {sorted(unknown)}; it has "
            f"{sorted(_fields(entry['algo']))}"
        )
    _settings(entry["algo"], settings)  # each value of its declared type and range
    only = entry.get("datasets", datasets)
    return entry["algo"], _frozen(settings), [_dataset(d) for d in only]


def _fields(algo: str) -> set[str]:
    return get_algorithm(algo).settings()


def _settings(algo: str, values: dict[str, Any]) -> Any:
    """``algo``'s preset with ``values`` (from YAML), converted and checked by its config's own
    declaration (:func:`eabc.ranges.validated`), as the command line and the Python API check
    them."""
    return ranges.validated(get_algorithm(algo).preset, values, f"{algo} setting ")


def groups(runs: list[RunSpec]) -> list[list[RunSpec]]:
    """Runs that can train as one compiled program (:func:`eabc.training.trainer.train_runs`),
    together, in the order of their first run: the same algorithm, training settings and
    algorithm settings but for its ``traced_settings``, on datasets of one shape (the built-in
    datasets of one environment; any other dataset only with itself). Runs that differ only in
    their seed are always in one group."""
    out: dict[tuple, list[RunSpec]] = {}
    for run in runs:
        traced = get_algorithm(run.algo).traced_settings
        fixed = tuple((k, v) for k, v in run.overrides if k not in traced)
        out.setdefault((run.algo, shape_family(run.dataset), fixed, run.train), []).append(run)
    return list(out.values())


def job_name(job: list[RunSpec]) -> str:
    """A job's name in logs: its run's id, its seed group's (``hopper-medium__ALGO``), or the
    first group's and how many more it trains (``hopper-medium__ALGO+2``)."""
    if len(job) == 1:
        return job[0].run_id
    more = len(dict.fromkeys(run.group_id for run in job)) - 1
    return job[0].group_id + (f"+{more}" if more else "")


def shape_family(dataset: str) -> str:
    """A name that datasets whose observations and actions have one shape share: a built-in
    dataset's environment (``hopper`` for hopper-medium and hopper-random, ``antmaze`` for every
    maze); any other dataset's own name."""
    task = tasks.parse_task(dataset) if sources.kind(dataset) == "builtin" else None
    return task[0] if task is not None else f"dataset {dataset}"
