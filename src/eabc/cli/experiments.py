"""``eabc sweep``, ``eabc results`` and ``eabc report``."""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from pathlib import Path
from typing import Annotated, Literal

import tyro

from eabc import paths, timing
from eabc.cli.options import Interrupted, parse_value
from eabc.experiments.presets import PRESETS as _SWEEP_PRESETS
from eabc.ranges import BatchSize, NonNegativeNumber, Positive, PositiveNumber, Seed, Steps

SWEEP_PRESETS = tuple(_SWEEP_PRESETS)
"""The names of ``eabc.experiments.presets.PRESETS``, the choices of ``eabc sweep --preset``."""


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
    """The paper's grids (table1, table6, ablation-*: 15 datasets x 5 seeds) or the study of where
    published EABC fails (study-screen: every EABC variant, 2 seeds x 50K steps; study: 3 seeds x
    100K; study-1m: 1M steps), whose results are in docs/results/."""
    root: str = "sweeps/default"
    """The sweep's directory (runs, logs, results)."""
    datasets: tuple[str, ...] = ()
    """Datasets (replace the spec's or preset's, and narrow its variants' own lists)."""
    algos: tuple[str, ...] = ()
    """Algorithms (replace the spec's or preset's; of its variants, those of these algorithms)."""
    seeds: tuple[Seed, ...] = ()
    """Seeds (replace the spec's or preset's)."""
    steps: Steps | None = None
    """Gradient steps per run (default the spec's, else 1M), e.g. to shorten a preset."""
    grid: tuple[str, ...] = ()
    """Extra grid axes as KEY=V1,V2 (e.g. num_critics=5,10 pessimism=min,mean-std); put
    tuple-valued settings such as hidden_dims in a YAML spec."""
    backend: Literal["local", "ray"] = "local"
    """local: a process pool on this machine; ray: one Ray task per job."""
    ray_address: str = "auto"
    """Ray cluster address (auto: the running cluster, or HOST:PORT)."""
    workers: Positive | None = None
    """Local processes at once (default: one per CPU core)."""
    layout: Literal["auto", "vmap", "processes"] = "auto"
    """vmap: a seed group trains in one process, vectorised (GPU); processes: one single-threaded
    process per run (CPU); auto: vmap on an accelerator, processes on a CPU."""
    cpus_per_job: PositiveNumber = 1.0
    """Ray: CPUs declared per job."""
    gpus_per_job: NonNegativeNumber = 0.0
    """Ray: GPUs declared per job (e.g. 0.25 to pack four jobs per GPU)."""
    dry_run: bool = False
    """List the runs, their state and the estimated cost, then stop."""
    include: tuple[str, ...] = ()
    """Earlier reports (directories `eabc report` wrote, e.g. docs/results/study) or other sweep
    roots on this machine: runs they hold as done, at the spec's steps, are not run again here,
    nor runs another root is training when their turn comes (so one sweep per core, each in its
    own root, never trains a run twice). Give the same to `eabc report --include` to report them
    with ROOT's."""
    within: str | None = None
    """Start only the runs whose estimate (as --dry-run shows it) ends within this time from now,
    e.g. 150m or 2.5h; the others wait for a later sweep. For machines that are not kept: a run
    begun and not finished when the machine goes is lost. Local backend only."""
    eval_interval: Steps | None = None
    """Evaluate every this many steps (default the spec's, else 5000)."""
    eval_episodes: Positive | None = None
    """Episodes per evaluation (default the spec's, else 10)."""
    log_interval: Steps | None = None
    """Steps per compiled chunk and log row (default the spec's, else 1000)."""
    checkpoint_interval: Steps | None = None
    """Checkpoint every this many steps (default the spec's, else 5000)."""
    batch_size: BatchSize | None = None
    """Mini-batch size (default the spec's, else each algorithm's own: 256; ReBRAC 1024)."""


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


ReportFormat = Literal["png", "md", "pdf", "svg", "html", "tex"]
"""eabc.experiments.report.FORMATS, spelled out so that --help needs no import of the report."""


@dataclasses.dataclass(frozen=True)
class Report:
    """Make the paper's tables (Markdown) and figures (PNG) from a sweep's results; --formats
    adds PDF and SVG figures, HTML and LaTeX tables."""

    root: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="ROOT")]
    out: str | None = None
    """Output directory (default ROOT/report)."""
    baseline: str | None = None
    """Label every other algorithm is compared with, dataset by dataset, in comparison.md
    (mean with its 95% bootstrap interval: above, below or tie); default td3bc when the sweep
    ran it. A label is the algorithm plus its variant, as in the tables (`eabc p=1.0`)."""
    fix: str | None = None
    """Label set beside published EABC (label `eabc`) in failures.md, dataset by dataset: where
    the published rule's critics leave the value range, how far, and the ensemble's spread at
    the policy's actions as they did, against the same for this label (default eabc-ln, the
    recommended variant, when the sweep ran it)."""
    include: tuple[str, ...] = ()
    """Earlier reports (directories `eabc report` wrote, e.g. docs/results/study) or other sweep
    roots whose runs join ROOT's, so that runs measured on a machine since lost, or in another
    root, still count. A run in both counts once:
    the copy that trained more steps, ROOT's on a tie. report.md says how many runs came from
    where."""
    finished: bool = False
    """Leave out the runs that have not reached their steps yet (partial), e.g. to commit a
    report while its sweep still runs: a partial run would be scored on its evaluations so far,
    and its row would stand in the committed report until a later copy trained more."""
    formats: tuple[ReportFormat, ...] = ("png", "md")
    """Formats to write: PNG figures and Markdown tables always (report.md links them); add pdf
    and svg for every figure as a vector graphic, html for table.html and report.html (the
    whole report as one page), tex for table.tex, e.g. --formats png md pdf svg html tex."""


def _narrow_variants(spec: dict, algos: tuple[str, ...], datasets: tuple[str, ...]) -> dict:
    """``--algos`` and ``--datasets`` on a spec with ``variants:``: keep the variants of those
    algorithms, on those datasets (a variant's own ``datasets:`` list too); an algorithm that no
    variant names runs with its preset settings, as in a spec without variants."""
    from eabc.experiments.spec import variant_entries  # noqa: PLC0415

    entries = variant_entries(spec["variants"])  # each a mapping of the right shape
    if algos:
        entries = [v for v in entries if v.get("algo") in algos]
    if datasets:
        narrowed = []
        for entry in entries:
            if "datasets" in entry:
                own = [d for d in entry["datasets"] if d in datasets]
                if not own:
                    continue
                entry = {**entry, "datasets": own}
            narrowed.append(entry)
        entries = narrowed
    spec = {**spec, "variants": entries}
    if algos:
        named = {v["algo"] for v in entries}
        spec["algos"] = [a for a in algos if a not in named]
    return spec


def sweep_spec(cmd: Sweep) -> dict:
    from eabc.experiments.presets import PRESETS  # noqa: PLC0415
    from eabc.experiments.spec import load_spec  # noqa: PLC0415

    spec: dict = {}
    if cmd.preset:
        spec = {**PRESETS[cmd.preset]}
    if cmd.spec:
        spec = {**spec, **load_spec(cmd.spec)}
    replaced = ["datasets", "algos", "seeds"]
    if spec.get("variants") and (cmd.algos or cmd.datasets):
        spec = _narrow_variants(spec, cmd.algos, cmd.datasets)
        replaced.remove("algos")  # set there: the algorithms that no variant names
    for key in replaced:
        if getattr(cmd, key):
            spec[key] = list(getattr(cmd, key))
    if cmd.steps is not None:
        spec["steps"] = cmd.steps
    # Flags join the spec's train: and grid: mappings; a spec whose key is no mapping is left
    # as it is, for the spec's check to refuse naming the key.
    train = {k: getattr(cmd, k) for k in SWEEP_TRAIN_FLAGS if getattr(cmd, k) is not None}
    if train and isinstance(spec.get("train") or {}, dict):
        spec["train"] = {**(spec.get("train") or {}), **train}  # the flags replace its keys
    if cmd.grid and isinstance(spec.get("grid") or {}, dict):
        grid, given = dict(spec.get("grid") or {}), set()
        for item in cmd.grid:
            key, sep, values = item.partition("=")
            if not sep:
                raise ValueError(f"bad --grid {item!r}; use KEY=V1,V2")
            if key in given:
                raise ValueError(f"--grid gives {key} twice; list its values once, {key}=V1,V2")
            given.add(key)
            grid[key] = [parse_value(v) for v in values.split(",")]
        spec["grid"] = grid
    return spec


def run_sweep(cmd: Sweep) -> None:
    """``eabc sweep``; Ctrl-C before its first run started (making data, probing this host's
    speed) ends in one line too."""
    try:
        _run_sweep(cmd)
    except Interrupted:
        raise
    except KeyboardInterrupt:
        raise Interrupted(
            f"sweep interrupted before its runs started; run the same `eabc sweep` command "
            f"again (root {cmd.root})"
        ) from None


def _run_sweep(cmd: Sweep) -> None:
    import yaml  # noqa: PLC0415

    from eabc.experiments import (  # noqa: PLC0415
        archive_merge,
        job_process,
        local_pool,
        planning,
        ray_pool,
        results,
        run_status,
    )
    from eabc.experiments.spec import expand  # noqa: PLC0415

    # The options first, so that a dry run refuses what the sweep would.
    budget = None if cmd.within is None else planning.parse_duration(cmd.within, "--within")
    if budget is not None and cmd.backend != "local":
        raise ValueError("--within works with the local backend only")
    root = paths.expand(cmd.root)
    runs = expand(sweep_spec(cmd))
    run_status.check_startable(runs, root)  # every dataset and run name, in a dry run too
    if cmd.include:
        archived = run_status.archived_done(
            runs, [archive_merge.read_archive(d) for d in cmd.include]
        )
        if archived:
            print(f"{len(archived)} runs done in {', '.join(cmd.include)}: not run again")
        runs = [r for r in runs if r.run_id not in archived]
    rows, speed = planning.plan(runs, root), timing.REFERENCE
    hinted = [r["seconds"] for r in rows if r["status"] != "done" and not r["measured"]]
    if sum(hinted) > 10:  # long enough for this host's speed to matter: probe it
        speed = timing.host_speed()
        rows = planning.plan(runs, root, speed)
    left = [r for r in rows if r["status"] != "done"]
    hours = sum(r["seconds"] for r in left) / 3600
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "partial", "pending")}
    measured = sum(r["measured"] for r in left)
    basis = (
        speed.basis()
        if not measured
        else "at speeds measured in the root"
        if measured == len(left)
        else f"at speeds measured in the root for {measured} of {len(left)}, for the rest "
        + speed.basis()
    )
    print(
        f"{len(rows)} runs in {root}: {counts['done']} done, {counts['partial']} partial, "
        f"{counts['pending']} pending; about {hours:.1f} CPU-core-hours left {basis}",
        flush=True,
    )
    found = run_status.problems(runs, root)
    for why in found["broken"]:  # one unreadable run does not stop the others
        print(f"skipping a broken run: {why}", file=sys.stderr)
    changed = (
        f"{len(found['changed'])} run(s) in {root} were trained with another spec, e.g. "
        f"{found['changed'][0]}; use another --root, or move those run directories away"
        if found["changed"]
        else None
    )
    if changed and not cmd.dry_run:
        raise ValueError(changed)
    if cmd.dry_run:
        for r in rows:
            spec = r["run"]
            print(
                f"  {r['status']:8s} {r['steps_done']:>8d}  ~{r['seconds'] / 3600:6.2f} h  {spec.run_id}"
            )
        if changed:  # what the sweep itself would refuse, said by its dry run
            print(f"the sweep would refuse to start: {changed}", file=sys.stderr)
        return
    deadline = None if budget is None else time.time() + budget
    layout = planning.default_layout() if cmd.layout == "auto" else cmd.layout
    job_list = planning.jobs(runs, root, layout)
    job_process.prepare_datasets([job[0] for job in job_list])
    root.mkdir(parents=True, exist_ok=True)
    (root / "sweep.yaml").write_text(yaml.safe_dump(sweep_spec(cmd), sort_keys=False))
    try:
        if cmd.backend == "ray":
            ray_pool.run_ray(job_list, root, cmd.ray_address, cmd.cpus_per_job, cmd.gpus_per_job)
        else:
            others = [
                Path(d)
                for d in cmd.include
                if not (Path(d) / archive_merge.ARCHIVE_FILES[0]).is_file()
            ]
            local_pool.run_local(
                job_list, root, cmd.workers, single_thread=layout == "processes",
                deadline=deadline, speed=speed,
                taken=(lambda run: run_status.taken_elsewhere(run, others)) if others else None,
            )  # fmt: skip
    except KeyboardInterrupt:  # the pool has stopped its workers; their runs resume exactly
        raise Interrupted(
            f"sweep interrupted; its runs continue from their last checkpoints when the same "
            f"`eabc sweep` command runs again (root {root})"
        ) from None
    finally:
        table, _ = results.collect(root)
        print(f"results: {root / results.DATABASE} ({len(table)} runs)")


def run_results(cmd: Results) -> None:
    from eabc.experiments import results  # noqa: PLC0415

    if not paths.expand(cmd.root).is_dir():
        raise FileNotFoundError(f"{cmd.root} does not exist; give a sweep root or a run directory")
    every, evaluations = results.collect(cmd.root, write=False)
    missing = [c for c in cmd.columns if c not in every.columns]
    if missing:
        raise ValueError(
            f"--columns: unknown column(s) {missing}; choose from {', '.join(every.columns)}"
        )
    runs = results.query(every, list(cmd.filter))  # a bad filter is refused before the store
    results.store(cmd.root, every, evaluations)
    if every.empty:
        print(f"no runs under {cmd.root}")
        return
    unusable = every["status"].isin(results.UNUSABLE)
    for state, why in zip(every.loc[unusable, "status"], every.loc[unusable, "config"]):
        print(f"{state}: {why}", file=sys.stderr)
    if runs.empty:
        print(f"none of the {len(every)} runs under {cmd.root} match {' '.join(cmd.filter)}")
        return
    table = runs[list(cmd.columns)]
    if cmd.csv:
        print(table.to_csv(index=False), end="")
    else:
        print(shown(table).to_string(index=False))
        if "final_score" in cmd.columns:
            print(final_score_note(runs, evaluations))


def final_score_note(runs, evaluations) -> str:
    """What ``final_score`` averages, naming the runs with fewer evaluations than that."""
    from eabc.training.config import FINAL_EVALUATIONS  # noqa: PLC0415

    counts = evaluations.groupby("run_id").size() if len(evaluations) else {}
    fewer = {
        run_id: int(counts.get(run_id, 0))
        for run_id in runs["run_id"]
        if 0 < counts.get(run_id, 0) < FINAL_EVALUATIONS
    }
    note = f"final_score: the mean of a run's last {FINAL_EVALUATIONS} evaluations"
    if not fewer:
        return note
    named = ", ".join(f"{run_id}: {n}" for run_id, n in list(fewer.items())[:5])
    more = f" and {len(fewer) - 5} more" if len(fewer) > 5 else ""
    return f"{note}; of all of them where it has fewer ({named}{more})"


def shown(table):
    """``table`` as text cells: numbers with one decimal, a missing value (NaN, None) as "–"."""
    import pandas as pd  # noqa: PLC0415

    def cell(value) -> str:
        if value is None or value is pd.NA or (isinstance(value, float) and math.isnan(value)):
            return "–"
        return f"{value:.1f}" if isinstance(value, float) else str(value)

    return table.map(cell)


def run_report(cmd: Report) -> None:
    from eabc.experiments import archive_merge, report, results  # noqa: PLC0415
    from eabc.experiments.labels import labelled  # noqa: PLC0415

    if not paths.expand(cmd.root).is_dir() and not cmd.include:
        raise FileNotFoundError(f"{cmd.root} does not exist; give a sweep root or a run directory")
    if cmd.out:
        paths.check_directory(cmd.out, "--out")
    # Stored only once every input is checked: a refused report changes nothing.
    every, evaluations = results.collect(cmd.root, write=False)  # none on a new machine: --include
    runs = every
    unusable = runs["status"].isin(results.UNUSABLE)
    for state, why in zip(runs.loc[unusable, "status"], runs.loc[unusable, "config"]):
        print(f"leaving out a {state} run: {why}", file=sys.stderr)
    runs = runs[~unusable]
    repeats = archive_merge.combined_repeats()  # none without --include: one root holds a run once
    if cmd.include:
        archives = [archive_merge.read_archive(d) for d in cmd.include]
        live = (runs, evaluations)
        repeats = archive_merge.combined_repeats(
            archive_merge.repeats(live, *archives, live_source=str(cmd.root)),
            *(archive_merge.read_repeats(d) for d in cmd.include),
        )
        runs, evaluations = archive_merge.merge(live, *archives, live_source=str(cmd.root))
    for row in repeats[~repeats["identical"].astype(bool)].itertuples():
        print(
            f"warning: {row.run_id} was trained in {row.sources} and the copies disagree (largest "
            f"score difference {row.max_score_difference:.3g}); the report keeps the first",
            file=sys.stderr,
        )
    if cmd.finished:
        partial = runs["status"] == "partial"
        if partial.any():
            print(f"leaving out {int(partial.sum())} runs not finished yet (--finished)")
        runs = runs[~partial]
        evaluations = evaluations[evaluations["run_id"].isin(runs["run_id"])]
    if runs.empty:
        left_out = int(unusable.sum())
        also = f" ({left_out} broken or damaged, listed above)" if left_out else ""
        raise ValueError(f"no runs to report under {cmd.root}{also}")
    labels = set(labelled(runs)["label"])
    for option, label in (("--baseline", cmd.baseline), ("--fix", cmd.fix)):
        if label is not None and label not in labels:
            raise ValueError(
                f"{option} {label}: no runs with that label; labels: {', '.join(sorted(labels))}"
            )
    out = Path(cmd.out) if cmd.out else paths.expand(cmd.root) / "report"
    paths.check_directory(out, "--out" if cmd.out else "the report's folder")
    if not cmd.out and not os.access(paths.expand(cmd.root), os.W_OK):
        raise ValueError(
            f"{cmd.root} is read-only, and the report goes to {out} by default: give --out DIR "
            "to write it elsewhere (the runs are only read)"
        )
    if paths.expand(cmd.root).is_dir():
        results.store(cmd.root, every, evaluations)
    fix = cmd.fix or report.RECOMMENDED
    written = report.write_report(
        runs, evaluations, out, cmd.baseline, fix, repeats=repeats, formats=cmd.formats
    )
    for name, path in written.items():
        print(f"{name}: {path}")
