"""Experiment sweeps: a grid of runs, each in its own directory, resumable, local or on Ray.

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
``datasets: [...]`` replaces the spec's for it, so one spec can put runs in any priority order. Runs live in ``ROOT/runs/RUN_ID``; a sweep started again skips the
finished runs and resumes the interrupted ones from their checkpoints.

Seeds of one setting form a *group*. A group runs either as one process that trains its seeds
together, vectorised with ``vmap`` (fastest on a GPU), or as one single-threaded process per seed
(fastest on a few CPU cores); ``layout="auto"`` picks by the JAX backend.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pydantic

from eabc import compile_cache
from eabc.agents import get_algorithm, validation
from eabc.data import generate
from eabc.training.trainer import SUMMARY, TrainConfig

RUNS = "runs"
SPEC = "sweep.json"
"""What a sweep knows about one of its runs (its spec and variant label)."""
TRAIN_FIELDS = {f.name for f in dataclasses.fields(TrainConfig)} - {"dataset", "algo", "seed"}

# Issue 14's study: where published EABC fails on our data and what fixes it, at lengths this
# machine affords (final = mean of the last 10 of the evaluations every 5,000 steps x 10 episodes).
STUDY_DATASETS = [
    "hopper-medium",
    "halfcheetah-medium",
    "hopper-medium-replay",
    "walker2d-medium",
    "hopper-random",
]
STUDY_TRAIN = {"eval_interval": 5000, "eval_episodes": 10}
SCREEN_VARIANTS = [  # in order of priority: a screen stopped early has run the first ones
    {"algo": "td3bc"},
    {"algo": "eabc"},  # published: Table 3's p
    # Full cloning on LayerNorm critics: on hopper-medium every LayerNorm run scored best while its
    # p was still near 1 (94 at 10K steps, 79 at 20K) and lost it as p fell.
    {"algo": "eabc", "confidence_level": 1.0, "critic_layer_norm": True},
    {"algo": "eabc-robust"},  # auto p with a calibrated target, on LayerNorm critics
    # No p: clone where the ensemble rates the data's action at least as high as the policy's.
    {"algo": "eabc", "bc_weight": "advantage", "critic_layer_norm": True},
    {"algo": "eabc", "confidence_level": 1.0},
    {"algo": "eabc", "critic_layer_norm": True},
    {"algo": "eabc-auto", "critic_layer_norm": True},
    {"algo": "eabc-quantile"},
    {"algo": "eabc-auto", "critic_layer_norm": True, "independent_targets": True},
    {"algo": "eabc-auto"},
    {"algo": "eabc", "independent_targets": True, "pessimism_beta": 2.0},
    {"algo": "eabc", "pessimism_beta": 2.0},
]


PRESETS: dict[str, dict[str, Any]] = {
    # Table 1: EABC against BC, TD3, TD3+BC, CQL, IQL and wPC on the 15 datasets, 5 seeds, 1M steps.
    "table1": {
        "datasets": generate.builtin_names(),
        "algos": ["bc", "td3", "td3bc", "cql", "iql", "wpc", "eabc"],
        "seeds": [0, 1, 2, 3, 4],
    },
    # Table 6: BEAR, MOReL, MOPO, UWAC (its column order), EDAC (50 critics), EDAC-10 and EABC.
    "table6": {
        "datasets": generate.builtin_names(),
        "algos": ["bear", "morel", "mopo", "uwac", "edac", "edac-10", "eabc"],
        "seeds": [0, 1, 2, 3, 4],
    },
    # Figure 2: K in {3, 5, 7, 10, 20, 30} with Table 3's p.
    "ablation-k": {
        "datasets": generate.builtin_names(),
        "algos": ["eabc"],
        "seeds": [0, 1, 2, 3, 4],
        "grid": {"num_critics": [3, 5, 7, 10, 20, 30]},
    },
    # Figure 3: p in {0, 0.05, 0.25, 0.5, 0.75, 0.95, 1} at K = 10.
    "ablation-p": {
        "datasets": generate.builtin_names(),
        "algos": ["eabc"],
        "seeds": [0, 1, 2, 3, 4],
        "grid": {"confidence_level": [0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0]},
    },
    # Issue 14's screen: every variant against published EABC and TD3+BC, 2 seeds, 50K steps.
    "study-screen": {
        "datasets": STUDY_DATASETS,
        "variants": SCREEN_VARIANTS,
        "seeds": [0, 1],
        "steps": 50_000,
        "train": STUDY_TRAIN,
    },
    # Issue 14's confirmation: TD3+BC, published EABC, EABC at p = 1 and the recommended variant.
    "study": {
        "datasets": STUDY_DATASETS,
        "variants": [
            {"algo": "td3bc"},
            {"algo": "eabc"},
            {"algo": "eabc", "confidence_level": 1.0},
            {"algo": "eabc-robust"},
        ],
        "seeds": [0, 1, 2],
        "steps": 100_000,
        "train": STUDY_TRAIN,
    },
    # Whether the short protocol's ranking holds at the paper's length.
    "study-1m": {
        "datasets": ["halfcheetah-medium"],
        "variants": [{"algo": "td3bc"}, {"algo": "eabc"}, {"algo": "eabc-robust"}],
        "seeds": [0, 1, 2],
        "steps": 1_000_000,
        "train": STUDY_TRAIN,
    },
    # Figure 4: the pessimism operator at K = 10 with Table 3's p.
    "ablation-pess": {
        "datasets": generate.builtin_names(),
        "algos": ["eabc"],
        "seeds": [0, 1, 2, 3, 4],
        "grid": {"pessimism": ["mean-std", "min", "min2"]},
    },
}


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


def status(run: RunSpec, root: Path) -> tuple[str, int]:
    """The state of a run and the steps done so far: ``done`` (also when it stopped on NaN/inf),
    ``partial`` (has a checkpoint), ``pending``, ``changed`` (its directory holds a run of another
    spec, or of more steps than asked) or ``broken`` (a file of it cannot be read)."""
    return _status(run, root)[:2]


def _status(run: RunSpec, root: Path) -> tuple[str, int, str]:
    """:func:`status` and why, in words (for ``changed`` and ``broken``)."""
    from eabc.training import checkpoint  # noqa: PLC0415

    run_dir = root / RUNS / run.run_id
    target = run.train_config().steps
    if (run_dir / SPEC).exists():
        try:
            stored = RunSpec.from_json(json.loads((run_dir / SPEC).read_text()))
        except (OSError, ValueError, KeyError, TypeError) as error:
            return "broken", 0, f"{run_dir / SPEC} cannot be read ({type(error).__name__})"
        changed = differences(stored, run)
        if changed:
            return "changed", 0, f"{run_dir} was trained with {'; '.join(changed)}"
    summary = _read_json(run_dir / SUMMARY)  # an unreadable summary is rewritten by the run
    steps = summary.get("steps", 0)
    if summary.get("diverged_step") is not None:
        return "done", steps, ""
    if steps > target:
        return "changed", steps, f"{run_dir} has trained {steps} steps, the spec asks {target}"
    if summary and steps == target:
        return "done", steps, ""
    if (run_dir / checkpoint.CHECKPOINT).exists():
        try:
            return "partial", int(checkpoint.load_raw(run_dir)["agent"]["step"]), ""
        except (ValueError, KeyError, TypeError) as error:
            return "broken", 0, str(error)
    return "pending", 0, ""


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def problems(runs: list[RunSpec], root: Path) -> dict[str, list[str]]:
    """``changed`` and ``broken`` runs of a sweep, each with why."""
    out: dict[str, list[str]] = {"changed": [], "broken": []}
    for run in runs:
        state, _, why = _status(run, root)
        if state in out:
            out[state].append(why)
    return out


def estimate_seconds(run: RunSpec, steps_done: int = 0) -> float:
    """A rough cost of the remaining steps on one machine like ours (2 CPU cores), from the
    algorithm's contract: its preset's measured steps/s, scaled by its settings' relative cost."""
    algorithm = get_algorithm(run.algo)
    config = dataclasses.replace(algorithm.preset, **dict(run.overrides))
    rate = algorithm.steps_per_s / max(algorithm.relative_cost(config), 1e-9)
    train = run.train_config()
    left = max(train.steps - steps_done, 0)
    evaluations = left // train.eval_interval * train.eval_episodes
    return left / rate + evaluations * EPISODE_SECONDS


EPISODE_SECONDS = 0.15
"""A 1000-step MuJoCo evaluation episode with the NumPy policy."""


def plan(runs: list[RunSpec], root: Path) -> list[dict[str, Any]]:
    rows = []
    for run in runs:
        state, steps = status(run, root)
        rows.append(
            {
                "run": run,
                "status": state,
                "steps_done": steps,
                "seconds": estimate_seconds(run, steps),
            }
        )
    return rows


def prepare_datasets(runs: list[RunSpec], log=print) -> None:
    """Make the missing built-in datasets once, here, before jobs that share them start."""
    seen = set()
    for run in runs:
        config = run.train_config()
        path = generate.dataset_path(config.dataset, config.cache_dir)
        if (
            config.dataset in generate.builtin_names()
            and path not in seen
            and not generate.is_current(path, config.dataset)
        ):
            seen.add(path)
            log(f"making {config.dataset} into {path}")
            generate.make(config.dataset, path)


def default_layout() -> str:
    import jax  # noqa: PLC0415

    return "vmap" if jax.default_backend() in ("gpu", "cuda", "rocm", "tpu") else "processes"


def jobs(runs: list[RunSpec], root: Path, layout: str) -> list[list[RunSpec]]:
    """The unfinished runs as jobs: a seed group per job (vmap) or one run per job."""
    todo = [r for r in runs if status(r, root)[0] in ("partial", "pending")]
    if layout == "vmap":
        return groups(todo)
    return [[r] for r in todo]


def execute(job: list[dict], root: str) -> list[dict]:
    """Run one job in this process: start or resume each run, then train (seeds vmapped)."""
    from eabc.data.sources import load_dataset  # noqa: PLC0415
    from eabc.training import checkpoint, trainer  # noqa: PLC0415

    root_path = Path(root)
    specs = [RunSpec.from_json(j) for j in job]
    first = specs[0].train_config()
    compile_cache.enable(cache_root=first.cache_dir)  # a sweep's runs share their shapes
    dataset = load_dataset(first.dataset, first.cache_dir)  # one copy for the whole seed group
    runs = []
    for spec in specs:
        run_dir = root_path / RUNS / spec.run_id
        state, _, why = _status(spec, root_path)
        if state in ("changed", "broken"):
            raise ValueError(f"{why}; move that run directory away or use another sweep root")
        if (run_dir / checkpoint.CONFIG).exists():  # from step 0 if it has no checkpoint yet
            runs.append(trainer.resume(run_dir, dataset, steps=spec.train_config().steps))
        else:
            runs.append(trainer.start(spec.train_config(), run_dir, dict(spec.overrides), dataset))
        identity = {"fingerprint": dataset.fingerprint(), **spec.to_json()}  # steps: the latest
        checkpoint.save_json(
            run_dir / SPEC, {"run_id": spec.run_id, "variant": spec.variant, **identity}
        )
    summaries = (
        trainer.train_seeds(runs, progress=False)
        if len(runs) > 1
        else [trainer.train(runs[0], progress=False)]
    )
    return summaries


def _absolute(run: RunSpec) -> dict:
    """``run`` as JSON with its dataset file and cache directory as absolute paths."""
    data = run.to_json()
    if is_path(run.dataset):
        data["dataset"] = str(Path(run.dataset).expanduser().resolve())
    if data["train"].get("cache_dir"):
        data["train"]["cache_dir"] = str(Path(data["train"]["cache_dir"]).expanduser().resolve())
    return data


SINGLE_THREAD = {
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}


def run_local(
    job_list: list[list[RunSpec]],
    root: Path,
    workers: int | None = None,
    single_thread: bool = True,
    log=print,
) -> None:
    """A pool of ``workers`` subprocesses (default: one per CPU core), one job each at a time.

    Every job is ``python -m eabc.experiments.worker ROOT JOB_JSON``; a killed sweep (SIGINT,
    SIGTERM, or SIGKILL, which the workers notice themselves) stops its workers, and the runs
    resume from their checkpoints next time.
    """
    from eabc.experiments.worker import PARENT  # noqa: PLC0415

    workers = workers or os.cpu_count() or 1
    env = {**os.environ, **(SINGLE_THREAD if single_thread else {}), PARENT: str(os.getpid())}
    previous = _exit_on_sigterm()
    pending = list(job_list)
    active: list[tuple[subprocess.Popen, list[RunSpec], Any]] = []
    logs = root / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    failures = []
    try:
        while pending or active:
            while pending and len(active) < workers:
                job = pending.pop(0)
                name = job[0].group_id if len(job) > 1 else job[0].run_id
                out = open(logs / f"{name}.log", "ab")  # noqa: SIM115
                payload = json.dumps([r.to_json() for r in job])
                cmd = [sys.executable, "-m", "eabc.experiments.worker", str(root), payload]
                active.append((subprocess.Popen(cmd, env=env, stdout=out, stderr=out), job, out))
                log(f"started {name} ({len(job)} run{'s' * (len(job) > 1)})")
            time.sleep(0.2)
            for proc, job, out in list(active):
                if proc.poll() is None:
                    continue
                active.remove((proc, job, out))
                out.close()
                name = job[0].group_id if len(job) > 1 else job[0].run_id
                if proc.returncode:
                    failures.append(name)
                    log(f"FAILED {name} (exit {proc.returncode}); see {logs / (name + '.log')}")
                else:
                    log(f"finished {name}")
    finally:
        for proc, _, _out in active:
            proc.terminate()
        for proc, _, out in active:
            proc.wait()
            out.close()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if failures:
        raise RuntimeError(f"{len(failures)} job(s) failed: {', '.join(failures)}")


def _exit_on_sigterm():
    """Make SIGTERM unwind like Ctrl-C (so the pool stops its workers); the old handler, or
    None off the main thread, where Python cannot set one."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def stop(signum, frame):
        raise SystemExit(128 + signum)

    return signal.signal(signal.SIGTERM, stop)


def run_ray(
    job_list: list[list[RunSpec]],
    root: Path,
    address: str = "auto",
    num_cpus: float = 1.0,
    num_gpus: float = 0.0,
    log=print,
) -> None:
    """One Ray task per job with declared CPU/GPU resources; ``root`` must be a shared directory.

    Paths go to the workers absolute (the root, dataset files, the cache directory): a worker's
    working directory is not the driver's.
    """
    try:
        import ray  # noqa: PLC0415
    except ImportError:
        raise RuntimeError("--backend ray needs the ray package: pip install 'eabc[ray]'") from None

    root = Path(root).expanduser().resolve()
    if not ray.is_initialized():
        ray.init(address=address, log_to_driver=False)
    env_vars = SINGLE_THREAD if num_gpus == 0 and num_cpus <= 1 else {}
    remote = ray.remote(execute).options(
        num_cpus=num_cpus, num_gpus=num_gpus, runtime_env={"env_vars": env_vars}, max_retries=2
    )
    futures = {remote.remote([_absolute(r) for r in job], str(root)): job for job in job_list}
    failures = []
    while futures:
        done, _ = ray.wait(list(futures), num_returns=1)
        job = futures.pop(done[0])
        name = job[0].group_id if len(job) > 1 else job[0].run_id
        try:
            ray.get(done[0])
            log(f"finished {name}")
        except Exception as error:  # noqa: BLE001 (report every failed job, then raise)
            failures.append(name)
            log(f"FAILED {name}: {error}")
    if failures:
        raise RuntimeError(f"{len(failures)} Ray job(s) failed: {', '.join(failures)}")
