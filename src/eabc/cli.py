"""The ``eabc`` command line, generated from typed dataclasses (``eabc --help``, ``eabc train --help``)."""

from __future__ import annotations

import dataclasses
import functools
import json
import operator
import re
import sys
import types
import typing
from pathlib import Path
from typing import Annotated, Literal

import tyro

from eabc import __version__, compile_cache
from eabc.experiments.presets import PRESETS as _SWEEP_PRESETS
from eabc.training.online import SACTrainConfig
from eabc.training.trainer import TrainConfig


def _parsed_unchecked(config_class: type) -> type:
    """``config_class`` without its ``__post_init__`` checks, for parsing only.

    tyro reports an error raised while it builds a nested dataclass under the dataclass's internal
    name (``__tyro-dummy-inner__.config``); checked in :func:`_checked` instead, the message can
    name the user's flags (``--eval-interval must be a multiple of --log-interval=300``).
    """
    namespace = {"__post_init__": lambda self: None, "__doc__": config_class.__doc__}
    return dataclasses.dataclass(frozen=True)(
        type(config_class.__name__, (config_class,), namespace)
    )


def _checked(options, config_class: type):
    """The parsed ``options`` as a checked ``config_class``; field names in errors as flags."""
    values = {f.name: getattr(options, f.name) for f in dataclasses.fields(config_class)}
    try:
        return config_class(**values)
    except ValueError as error:
        message = str(error)
        for name in values:
            message = re.sub(rf"\b{name}\b", "--" + name.replace("_", "-"), message)
        raise ValueError(message) from None


TrainOptions = _parsed_unchecked(TrainConfig)
SACTrainOptions = _parsed_unchecked(SACTrainConfig)

SWEEP_PRESETS = tuple(_SWEEP_PRESETS)
"""The names of ``eabc.experiments.presets.PRESETS``, the choices of ``eabc sweep --preset``."""


def _agent_overrides() -> type:
    """The typed algorithm flags of ``eabc train``, made from the algorithm contracts: every
    setting some algorithm lists in ``cli_flags``, unset by default (the preset's value)."""
    from eabc.agents import ALGORITHMS  # noqa: PLC0415
    from eabc.agents.contract import field_docs  # noqa: PLC0415

    fields, users = {}, {}
    for algorithm in ALGORITHMS.values():
        hints = typing.get_type_hints(type(algorithm.preset))
        docs = field_docs(type(algorithm.preset))
        for name in algorithm.cli_flags:
            users.setdefault(name, []).append(
                f"{algorithm.name}: {getattr(algorithm.preset, name)}"
            )
            fields.setdefault(name, (hints[name], docs.get(name, "")))
    spec = []
    for name, (hint, doc) in fields.items():
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        optional = typing.get_origin(hint) in (typing.Union, types.UnionType)
        inner = functools.reduce(operator.or_, args) if optional else hint  # noqa: E501
        where = "; ".join(users[name]).replace(": None", ": Table 3's")
        help_text = f"{doc} Unset: the preset's ({where})."
        spec.append((name, Annotated[inner | None, tyro.conf.arg(help=help_text)], None))
    return dataclasses.make_dataclass(
        "AgentOverrides",
        spec,
        frozen=True,
        namespace={"__doc__": "Algorithm settings to change from the preset --algo chose."},
    )


AgentOverrides = _agent_overrides()


@dataclasses.dataclass(frozen=True)
class Train:
    """Train an offline RL agent with the paper's protocol: progress bar, logs, checkpoints, curve."""

    config: Annotated[TrainOptions, tyro.conf.OmitArgPrefixes]
    agent: Annotated[AgentOverrides, tyro.conf.OmitArgPrefixes]
    set: tuple[str, ...] = ()
    """Any other setting of the algorithm as KEY=VALUE, e.g. eta=0.5, expectile=0.8,
    hidden_dims=512,512 (the settings are listed in the README and in config.json of a run)."""
    run_dir: str | None = None
    """Where the run's config, checkpoint, log.csv, TensorBoard events and curve.png go
    (default runs/DATASET_ALGO_seedS)."""
    resume: str | None = None
    """Continue the run in this directory from its last checkpoint (other options are ignored)."""
    progress: bool = True
    """Show a progress bar."""


@dataclasses.dataclass(frozen=True)
class Evaluate:
    """Re-score a run's latest checkpoint in its evaluation environment."""

    run_dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    episodes: int = 10
    """Episodes to run."""
    seed: int | None = None
    """Environment seed (default: the run's seed + 100, as in training)."""


@dataclasses.dataclass(frozen=True)
class DataMake:
    """Make a built-in D4RL-style dataset (e.g. hopper-random) in the cache directory."""

    name: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    seed: int = 0
    """Seed of the environment and the actions; the same seed gives the same file."""
    size: int | None = None
    """Transitions (default D4RL's size)."""
    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""
    force: bool = False
    """Remake the dataset even if it is cached."""


@dataclasses.dataclass(frozen=True)
class DataInfo:
    """Describe a dataset: size, episodes, returns and normalised score."""

    name: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    """A built-in name, a file path or minari:ID."""
    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""


@dataclasses.dataclass(frozen=True)
class DataList:
    """List the built-in datasets and which of them are in the cache."""

    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""


@dataclasses.dataclass(frozen=True)
class Sac:
    """Train online SAC in a Gymnasium environment (the behaviour policies of the built-in datasets).

    Logs training and evaluation returns to log.csv, keeps the actor every --snapshot-interval
    steps under snapshots/, and checkpoints networks, optimisers and the replay buffer so that
    --resume continues a killed run.
    """

    config: Annotated[SACTrainOptions, tyro.conf.OmitArgPrefixes]
    run_dir: str | None = None
    """Where the run goes (default runs/sac_ENV_seedS)."""
    resume: str | None = None
    """Continue the run in this directory from its last checkpoint (other options are ignored)."""
    alpha: float | None = None
    """Fixed entropy temperature instead of automatic tuning (default: tuning toward -dim(A);
    walker2d: fixed 0.2, see README)."""
    lr: float | None = None
    """Adam learning rate of actor and critics (default 3e-4; walker2d 1e-3)."""
    progress: bool = True
    """Show a progress bar."""


def sac_agent_config(cmd: Sac):
    """The environment's online SAC preset with the command's overrides."""
    from eabc.agents import sac  # noqa: PLC0415

    agent = sac.online_preset(cmd.config.env)
    if cmd.alpha is not None:
        if cmd.alpha <= 0:
            raise ValueError(f"--alpha must be positive, got {cmd.alpha}")
        agent = dataclasses.replace(agent, init_alpha=cmd.alpha, autotune=False)
    if cmd.lr is not None:
        agent = dataclasses.replace(agent, actor_lr=cmd.lr, critic_lr=cmd.lr)
    return agent


def run_sac(cmd: Sac) -> dict:
    from eabc.training import online  # noqa: PLC0415

    if cmd.resume:
        run = online.resume_sac(cmd.resume)
    else:
        config = cmd.config
        run_dir = cmd.run_dir or f"runs/sac_{config.env}_seed{config.seed}"
        run = online.start_sac(config, run_dir, sac_agent_config(cmd))
    print(f"run directory: {run.run_dir}", file=sys.stderr)
    summary = online.train_sac(run, progress=cmd.progress)
    print(json.dumps(summary, indent=2))
    return summary


@dataclasses.dataclass(frozen=True)
class Sweep:
    """Run a grid of experiments: datasets x algorithms x settings x seeds, resumable.

    Each run gets its own directory under ROOT/runs; running the same sweep again skips finished
    runs and resumes interrupted ones. Results go to ROOT/results.sqlite (`eabc results ROOT`) and
    the paper's tables and figures come from `eabc report ROOT`.
    """

    spec: Annotated[str | None, tyro.conf.Positional, tyro.conf.arg(metavar="SPEC")] = None
    """A YAML file with datasets, algos, seeds, steps, grid and train keys (optional)."""
    preset: Literal[SWEEP_PRESETS] | None = None  # type: ignore[valid-type]
    """The paper's grids (table1, table6, ablation-*: 15 datasets x 5 seeds) or issue 14's study
    (study-screen: every EABC variant, 2 seeds x 50K steps; study: 3 seeds x 100K; study-1m)."""
    root: str = "sweeps/default"
    """The sweep's directory (runs, logs, results)."""
    datasets: tuple[str, ...] = ()
    """Datasets (replace the spec's or preset's)."""
    algos: tuple[str, ...] = ()
    """Algorithms (replace the spec's or preset's)."""
    seeds: tuple[int, ...] = ()
    """Seeds (replace the spec's or preset's)."""
    steps: int | None = None
    """Gradient steps per run (default the spec's, else 1M), e.g. to shorten a preset."""
    grid: tuple[str, ...] = ()
    """Extra grid axes as KEY=V1,V2 (e.g. num_critics=5,10 pessimism=min,mean-std); put
    tuple-valued settings such as hidden_dims in a YAML spec."""
    backend: Literal["local", "ray"] = "local"
    """local: a process pool on this machine; ray: one Ray task per job."""
    ray_address: str = "auto"
    """Ray cluster address (auto: the running cluster, or HOST:PORT)."""
    workers: int | None = None
    """Local processes at once (default: one per CPU core)."""
    layout: Literal["auto", "vmap", "processes"] = "auto"
    """vmap: a seed group trains in one process, vectorised (GPU); processes: one single-threaded
    process per run (CPU); auto: vmap on an accelerator, processes on a CPU."""
    cpus_per_job: float = 1.0
    """Ray: CPUs declared per job."""
    gpus_per_job: float = 0.0
    """Ray: GPUs declared per job (e.g. 0.25 to pack four jobs per GPU)."""
    dry_run: bool = False
    """List the runs, their state and the estimated cost, then stop."""
    eval_interval: int | None = None
    """Evaluate every this many steps (default the spec's, else 5000)."""
    eval_episodes: int | None = None
    """Episodes per evaluation (default the spec's, else 10)."""
    log_interval: int | None = None
    """Steps per compiled chunk and log row (default the spec's, else 1000)."""
    checkpoint_interval: int | None = None
    """Checkpoint every this many steps (default the spec's, else 5000)."""
    batch_size: int | None = None
    """Mini-batch size (default the spec's, else 256)."""


SWEEP_TRAIN_FLAGS = (
    "eval_interval", "eval_episodes", "log_interval", "checkpoint_interval", "batch_size",
)  # fmt: skip
"""The train options `eabc sweep` takes as flags (any other goes in a spec's train: key)."""


@dataclasses.dataclass(frozen=True)
class Results:
    """List the runs of a sweep root (or any directory of runs) from its results store."""

    root: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="ROOT")]
    """A sweep root or any directory that holds run directories."""
    filter: tuple[str, ...] = ()
    """KEY=VALUE filters, e.g. dataset=hopper-* algo=eabc status=done."""
    columns: tuple[str, ...] = (
        "run_id", "status", "steps", "final_score", "steps_per_s", "wall_time_s",
        "q_out_of_range_step",
    )  # fmt: skip
    """Columns to show."""
    csv: bool = False
    """Print CSV instead of a table."""


@dataclasses.dataclass(frozen=True)
class Report:
    """Make the paper's tables (Markdown, HTML, LaTeX) and figures from a sweep's results."""

    root: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="ROOT")]
    out: str | None = None
    """Output directory (default ROOT/report)."""


@dataclasses.dataclass(frozen=True)
class ExportPolicy:
    """Write a run's policy (the latest checkpoint's actor, observation normaliser inside) as ONNX,
    to run without Python or JAX (onnxruntime, ONNX Runtime Web, TensorRT, ...)."""

    run_dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    onnx: str
    """The ONNX file to write (input observation [batch, obs_dim], output action)."""


def sweep_spec(cmd: Sweep) -> dict:
    from eabc.experiments.presets import PRESETS  # noqa: PLC0415
    from eabc.experiments.spec import load_spec  # noqa: PLC0415

    spec: dict = {}
    if cmd.preset:
        spec = {**PRESETS[cmd.preset]}
    if cmd.spec:
        spec = {**spec, **load_spec(cmd.spec)}
    for key in ("datasets", "algos", "seeds"):
        if getattr(cmd, key):
            spec[key] = list(getattr(cmd, key))
    if cmd.steps is not None:
        spec["steps"] = cmd.steps
    train = {k: getattr(cmd, k) for k in SWEEP_TRAIN_FLAGS if getattr(cmd, k) is not None}
    if train:  # flags beside the spec's train: keys, which they replace
        spec["train"] = {**(spec.get("train") or {}), **train}
    grid = dict(spec.get("grid") or {})
    for item in cmd.grid:
        key, sep, values = item.partition("=")
        if not sep:
            raise ValueError(f"bad --grid {item!r}; use KEY=V1,V2")
        grid[key] = [_parse_value(v) for v in values.split(",")]
    if grid:
        spec["grid"] = grid
    return spec


def parse_settings(items: tuple[str, ...]) -> dict:
    """``KEY=VALUE`` strings as settings; a comma makes a tuple (``hidden_dims=512,512``)."""
    settings = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"bad --set {item!r}; use KEY=VALUE")
        parts = [_parse_value(v) for v in value.split(",")]
        settings[key] = tuple(parts) if "," in value else parts[0]
    return settings


def _parse_value(text: str):
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


def run_sweep(cmd: Sweep) -> None:
    import yaml  # noqa: PLC0415

    from eabc.experiments import results, sweep  # noqa: PLC0415
    from eabc.experiments.spec import expand  # noqa: PLC0415

    root = Path(cmd.root)
    runs = expand(sweep_spec(cmd))
    rows = sweep.plan(runs, root)
    left = [r for r in rows if r["status"] != "done"]
    hours = sum(r["seconds"] for r in left) / 3600
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "partial", "pending")}
    print(
        f"{len(rows)} runs in {root}: {counts['done']} done, {counts['partial']} partial, "
        f"{counts['pending']} pending; about {hours:.1f} CPU-core-hours left at this machine's "
        "measured speeds"
    )
    found = sweep.problems(runs, root)
    for why in found["broken"]:  # one unreadable run does not stop the others
        print(f"skipping a broken run: {why}", file=sys.stderr)
    if found["changed"] and not cmd.dry_run:
        raise ValueError(
            f"{len(found['changed'])} run(s) in {root} were trained with another spec, e.g. "
            f"{found['changed'][0]}; use another --root, or move those run directories away"
        )
    if cmd.dry_run:
        for r in rows:
            spec = r["run"]
            print(
                f"  {r['status']:8s} {r['steps_done']:>8d}  ~{r['seconds'] / 3600:6.2f} h  {spec.run_id}"
            )
        return
    layout = sweep.default_layout() if cmd.layout == "auto" else cmd.layout
    job_list = sweep.jobs(runs, root, layout)
    sweep.prepare_datasets([job[0] for job in job_list])
    root.mkdir(parents=True, exist_ok=True)
    (root / "sweep.yaml").write_text(yaml.safe_dump(sweep_spec(cmd), sort_keys=False))
    try:
        if cmd.backend == "ray":
            sweep.run_ray(job_list, root, cmd.ray_address, cmd.cpus_per_job, cmd.gpus_per_job)
        else:
            sweep.run_local(job_list, root, cmd.workers, single_thread=layout == "processes")
    finally:
        table, _ = results.collect(root)
        print(f"results: {root / results.DATABASE} ({len(table)} runs)")


def run_results(cmd: Results) -> None:
    from eabc.experiments import results  # noqa: PLC0415

    if not Path(cmd.root).is_dir():
        raise FileNotFoundError(f"{cmd.root} does not exist; give a sweep root or a run directory")
    runs, _ = results.collect(cmd.root)
    if runs.empty:
        print(f"no runs under {cmd.root}")
        return
    found = len(runs)
    runs = results.query(runs, list(cmd.filter))
    if runs.empty:
        print(f"none of the {found} runs under {cmd.root} match {' '.join(cmd.filter)}")
        return
    missing = [c for c in cmd.columns if c not in runs.columns]
    if missing:
        raise ValueError(f"unknown column(s) {missing}; choose from {', '.join(runs.columns)}")
    table = runs[list(cmd.columns)]
    if cmd.csv:
        print(table.to_csv(index=False), end="")
    else:
        print(table.to_string(index=False, float_format=lambda x: f"{x:.1f}"))


def run_report(cmd: Report) -> None:
    from eabc.experiments import report, results  # noqa: PLC0415

    runs, evaluations = results.collect(cmd.root)
    broken = runs[runs["status"] == "broken"]
    for why in broken["config"]:
        print(f"leaving out a broken run: {why}", file=sys.stderr)
    runs = runs[runs["status"] != "broken"]
    if runs.empty:
        raise ValueError(f"no runs under {cmd.root}")
    out = Path(cmd.out) if cmd.out else Path(cmd.root) / "report"
    for name, path in report.write_report(runs, evaluations, out).items():
        print(f"{name}: {path}")


def run_train(cmd: Train) -> dict:
    from eabc.training import trainer  # noqa: PLC0415

    if cmd.resume:
        run = trainer.resume(cmd.resume)
    else:
        config = cmd.config
        run_dir = cmd.run_dir or f"runs/{Path(config.dataset).stem}_{config.algo}_seed{config.seed}"
        overrides = dataclasses.asdict(cmd.agent) | parse_settings(cmd.set)
        run = trainer.start(config, run_dir, overrides)
    print(f"run directory: {run.run_dir}", file=sys.stderr)
    summary = trainer.train(run, progress=cmd.progress)
    print(json.dumps(summary, indent=2))
    if summary.get("diverged_step") is not None:
        raise RuntimeError(f"training stopped at step {summary['diverged_step']} on NaN/inf")
    return summary


def run_evaluate(cmd: Evaluate) -> dict:
    from eabc.training import trainer  # noqa: PLC0415

    run = trainer.resume(cmd.run_dir, lock=False)  # reads only: a running run can be scored
    run.evaluator.episodes = cmd.episodes
    if cmd.seed is not None:
        run.evaluator.seed = cmd.seed
    result = {"run_dir": cmd.run_dir, "step": run.step, **trainer.evaluate(run)}
    print(json.dumps(result, indent=2))
    return result


@dataclasses.dataclass(frozen=True)
class ZooBuild:
    """Choose the medium and expert policies of an `eabc sac` run into the behaviour-policy zoo."""

    run_dir: tyro.conf.Positional[str]
    """The `eabc sac` run directory (its actor snapshots and log)."""
    env: tyro.conf.Positional[str]
    """hopper, halfcheetah or walker2d."""
    root: str | None = None
    """Zoo directory (default: the package's, or $EABC_ZOO_DIR)."""
    episodes: int = 10
    """Episodes per measured snapshot (sampled actions, as the datasets are made)."""
    expert_candidates: int = 5
    """The expert is the best of this many last snapshots."""
    medium_return: float | None = None
    """Return the medium policy aims at (default: D4RL's medium level)."""
    rechoose_medium: bool = False
    """Search for the medium policy again even if the zoo already has one."""


@dataclasses.dataclass(frozen=True)
class ZooPack:
    """Copy a SAC run's checkpoint, log and float16 snapshots (no replay buffer) into DEST."""

    run_dir: tyro.conf.Positional[str]
    dest: tyro.conf.Positional[str]


def run_zoo(cmd: ZooBuild | ZooPack) -> None:
    from eabc.data import zoo  # noqa: PLC0415
    from eabc.training import zoo_build  # noqa: PLC0415

    if isinstance(cmd, ZooPack):
        print(zoo_build.pack(cmd.run_dir, cmd.dest))
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
    """Export a dataset to the local Minari path, for d3rlpy, CORL and other Minari readers."""

    name: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    """A built-in name (made first if needed), a file path or minari:ID."""
    minari: bool = True
    """Export as a Minari dataset (the only format for now)."""
    dataset_id: str | None = None
    """The Minari id (default eabc/ENV/KIND-v0, e.g. eabc/hopper/medium-v0)."""
    force: bool = False
    """Replace an existing Minari dataset of that id."""
    cache_dir: str | None = None
    """Cache directory (default $EABC_CACHE_DIR or ~/.cache/eabc)."""


def run_data(cmd: DataMake | DataInfo | DataList | DataExport) -> None:
    from eabc.data import generate, loaders, sources  # noqa: PLC0415

    if isinstance(cmd, DataMake):
        path = generate.dataset_path(cmd.name, cmd.cache_dir)
        if path.exists() and not cmd.force:
            if generate.is_current(path, cmd.name):
                print(f"{path} (cached; --force to remake)")
                return
            print(f"{path} was made from older zoo policies; making it again", file=sys.stderr)
        print(generate.make(cmd.name, path, seed=cmd.seed, size=cmd.size))
    elif isinstance(cmd, DataList):
        header = f"{'dataset':26s} {'transitions':>11s} {'episodes':>8s} {'return':>17s} {'score':>6s} {'D4RL':>5s}  file"
        print(header)
        for name in generate.builtin_names():
            path = generate.dataset_path(name, cmd.cache_dir)
            level = generate.d4rl_level(name)
            if not path.exists():
                print(
                    f"{name:26s} {'-':>11s} {'-':>8s} {'-':>17s} {'-':>6s} {level:5.0f}  (not made)"
                )
                continue
            info = generate.describe(path)
            spread = f"{info['return_mean']:.0f} +- {info['return_std']:.0f}"
            print(
                f"{name:26s} {info['transitions']:11d} {info['episodes']:8d} {spread:>17s} "
                f"{info['normalized_return']:6.1f} {level:5.0f}  {path}"
            )
    elif isinstance(cmd, DataExport):
        dataset = sources.load_dataset(cmd.name, cmd.cache_dir)
        dataset_id = cmd.dataset_id or loaders.minari_id(dataset.name)
        print(loaders.export_minari(dataset, dataset_id, overwrite=cmd.force))
    else:
        dataset = sources.load_dataset(cmd.name, cmd.cache_dir)
        print(json.dumps(generate.describe_dataset(dataset), indent=2))


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    commands: dict[str, type] = {
        "train": Train,
        "evaluate": Evaluate,
        "sac": Sac,
        "sweep": Sweep,
        "results": Results,
        "report": Report,
        "export-policy": ExportPolicy,
        "data": DataList,
        "zoo": ZooPack,
    }
    description = "EABC: ensemble-based offline RL with adaptive behaviour cloning."
    if argv[:1] in (["--version"], ["-V"]):
        print(f"eabc {__version__}")
        return
    prog = "eabc"
    if argv[:1] == ["data"]:  # a second level: eabc data {make,list,info}
        commands = {"make": DataMake, "list": DataList, "info": DataInfo, "export": DataExport}
        argv = argv[1:]
        prog = "eabc data"
        description = "Datasets: make the built-in ones, list the cache, describe any dataset, export to Minari."
    elif argv[:1] == ["zoo"]:  # eabc zoo {build,pack}
        commands = {"build": ZooBuild, "pack": ZooPack}
        argv = argv[1:]
        prog = "eabc zoo"
        description = (
            "The behaviour-policy zoo: build an entry from an `eabc sac` run, or pack a run."
        )
    try:
        cmd = tyro.extras.subcommand_cli_from_dict(
            commands,
            args=argv,
            prog=prog,  # not the interpreter's path to the entry point
            description=description,
            config=(tyro.conf.DisallowNone,),  # --env STR, not --env {None}|STR
        )
        if isinstance(cmd, Train | Sac):  # checked here, so that errors name the flags
            config_class = TrainConfig if isinstance(cmd, Train) else SACTrainConfig
            cmd = dataclasses.replace(cmd, config=_checked(cmd.config, config_class))
    except ValueError as error:  # invalid settings caught in a dataclass __post_init__
        sys.exit(f"error: {error}")
    options = getattr(cmd, "config", cmd)
    compile_cache.enable(cache_root=getattr(options, "cache_dir", None))
    try:
        if isinstance(cmd, Train):
            run_train(cmd)
        elif isinstance(cmd, Evaluate):
            run_evaluate(cmd)
        elif isinstance(cmd, Sac):
            run_sac(cmd)
        elif isinstance(cmd, Sweep):
            run_sweep(cmd)
        elif isinstance(cmd, Results):
            run_results(cmd)
        elif isinstance(cmd, Report):
            run_report(cmd)
        elif isinstance(cmd, ExportPolicy):
            from eabc import deploy  # noqa: PLC0415

            print(deploy.export_onnx(cmd.run_dir, cmd.onnx))
        elif isinstance(cmd, ZooBuild | ZooPack):
            run_zoo(cmd)
        else:
            run_data(cmd)
    except (ValueError, FileNotFoundError, FileExistsError, RuntimeError) as error:
        sys.exit(f"error: {error}")
    except OSError as error:  # e.g. a directory where a file should be, no permission
        sys.exit(f"error: {error.filename or ''}: {error.strerror or error}; check that path")


if __name__ == "__main__":
    main()
