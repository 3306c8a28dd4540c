"""What a sweep runs: its specification and the runs it expands to.

A sweep specification (YAML, or the same keys from the command line or a preset) names

    datasets: [hopper-medium, walker2d-medium]     # any --dataset value
    algos: [eabc, td3bc]                            # any --algo value
    seeds: [0, 1, 2]
    steps: 1000000
    grid: {num_critics: [5, 10], confidence_level: [0.25, 1.0], pessimism: [mean-std, min]}
    train: {eval_interval: 5000, eval_episodes: 10}  # any other TrainConfig field

and expands to the product datasets x algos x grid x seeds (grid settings apply only to the
algorithms that have them). ``variants:`` lists named combinations instead of (or beside) a grid,
``{algo: eabc, critic_layer_norm: true}``, run breadth first in the order given; a variant's own
``datasets: [...]`` replaces the spec's for it, so one spec can put runs in any priority order.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import os
from pathlib import Path
from typing import Any

import pydantic

from eabc.agents import get_algorithm, validation
from eabc.training.trainer import TrainConfig

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
            full = str(Path(name).expanduser().resolve())
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
    """Whether a --dataset value names a file (rather than a built-in name or a Minari id)."""
    if dataset.startswith("minari:"):
        return False
    path = Path(dataset).expanduser()
    return path.suffix in (".hdf5", ".h5", ".npz") or path.exists()


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
    import yaml  # noqa: PLC0415

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"sweep specification {path} does not exist")
    spec = yaml.safe_load(path.read_text()) or {}
    if not isinstance(spec, dict):
        raise ValueError(f"{path}: a sweep specification is a mapping (datasets:, algos:, ...)")
    return spec


def expand(spec: dict[str, Any]) -> list[RunSpec]:
    """Every run of a specification, in a stable order (see the module docstring for the keys)."""
    known = {"datasets", "algos", "variants", "seeds", "steps", "grid", "train"}
    unknown = set(spec) - known
    if unknown:
        raise ValueError(f"unknown sweep key(s) {sorted(unknown)}; use {sorted(known)}")
    if not spec.get("datasets"):
        raise ValueError("the sweep needs at least one entry in 'datasets'")
    if not spec.get("algos") and not spec.get("variants"):
        raise ValueError("the sweep needs at least one entry in 'algos' or 'variants'")
    datasets = [_dataset(d) for d in spec["datasets"]]
    variants = [_variant(v, datasets) for v in spec.get("variants") or []]
    seeds = [int(s) for s in spec.get("seeds", [0])]
    train = dict(spec.get("train") or {})
    if "steps" in spec:
        train["steps"] = int(spec["steps"])
    bad = set(train) - TRAIN_FIELDS
    if bad:
        raise ValueError(f"unknown train setting(s) {sorted(bad)}; use {sorted(TRAIN_FIELDS)}")
    try:  # validate (and convert: "1000" -> 1000) early, before any run starts
        checked = pydantic.TypeAdapter(TrainConfig).validate_python(train)
    except pydantic.ValidationError as error:
        first = error.errors()[0]
        where = ".".join(map(str, first["loc"])) or "train"
        raise ValueError(f"bad train setting {where}: {first['msg']}") from None
    train = {k: getattr(checked, k) for k in train}
    if train.get("cache_dir"):  # absolute, as dataset files below: workers start elsewhere
        train["cache_dir"] = str(Path(train["cache_dir"]).expanduser().resolve())
    grid = {
        k: list(v) if isinstance(v, list | tuple) else [v]
        for k, v in (spec.get("grid") or {}).items()
    }
    runs = []
    algos = spec.get("algos") or []
    for dataset in datasets:
        for algo in algos:
            fields = {f.name for f in dataclasses.fields(get_algorithm(algo).preset)}
            axes = {k: v for k, v in grid.items() if k in fields}
            for values in itertools.product(*axes.values()):
                overrides = _frozen(dict(zip(axes, values)))
                validation.validate(get_algorithm(algo).preset, algo, dict(overrides))
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


def _dataset(name: str) -> str:
    return str(Path(name).expanduser().resolve()) if is_path(name) else name


def _variant(entry, datasets: list[str]) -> tuple[str, tuple[tuple[str, Any], ...], list[str]]:
    """A ``variants:`` entry, ``{algo: eabc, critic_layer_norm: true, ...}``: one algorithm with
    fixed settings (checked against the algorithm's own), and the datasets it runs on (its own
    ``datasets:`` list, else the spec's)."""
    if isinstance(entry, str):
        entry = {"algo": entry}
    if not isinstance(entry, dict) or "algo" not in entry:
        raise ValueError(f"a sweep variant is a mapping with an 'algo' key, got {entry!r}")
    settings = {k: v for k, v in entry.items() if k not in ("algo", "datasets")}
    only = entry.get("datasets", datasets)
    if isinstance(only, str) or not only or not all(isinstance(d, str) for d in only):
        raise ValueError(
            f"variant {entry!r}: 'datasets' must be a non-empty list of dataset names, got {only!r}"
        )
    unknown = set(settings) - _fields(entry["algo"])
    if unknown:
        raise ValueError(
            f"variant {entry!r}: {entry['algo']} has no setting(s) {sorted(unknown)}; it has "
            f"{sorted(_fields(entry['algo']))}"
        )
    return entry["algo"], _frozen(settings), [_dataset(d) for d in only]


def _fields(algo: str) -> set[str]:
    return {f.name for f in dataclasses.fields(get_algorithm(algo).preset)}


def groups(runs: list[RunSpec]) -> list[list[RunSpec]]:
    """Runs that differ only in their seed, together."""
    out: dict[str, list[RunSpec]] = {}
    for run in runs:
        out.setdefault(run.group_id, []).append(run)
    return list(out.values())
