"""``eabc study``: a queue of runs against a time budget on one accelerator."""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
from typing import Annotated

import tyro

from eabc import paths
from eabc.ranges import NonNegative, Positive, Steps

SMOKE = {"steps": 40, "log_interval": 20, "eval_interval": 20, "checkpoint_interval": 20,
         "eval_episodes": 1}  # fmt: skip
"""What ``--smoke`` shortens every run to (with datasets of :data:`SMOKE_DATASET_SIZE`)."""
SMOKE_DATASET_SIZE = 2_000
SMOKE_GROUPS, SMOKE_SEEDS = (3, 1), 2
"""``--smoke`` trains the first three groups of the first spec (its first algorithm on both
datasets, then the second's first) and the first of the second (or fewer, where the specs are
fewer), each with two seeds."""


@dataclasses.dataclass(frozen=True)
class Study:
    """Train a queue of runs on one machine within a time budget, streaming what finishes.

    For a borrowed accelerator: the runs of a spec that share their networks' shapes (seeds,
    datasets of one environment) train as one vectorised program, one program at a time (the
    GPU's memory is not pre-allocated); the queue's datasets are made by background processes
    while the first groups train, and each group's program is compiled in a thread of its own
    while its data are made or the group before it trains; a group starts only if its estimate
    (scaled by how long the groups so far took) ends before --within, and one whose first chunks
    show it would end later stops and starts again with as many of its runs as fit the time
    left; after each group, every finished run (log rows, evaluations, summary, provenance;
    never checkpoints) is written to --out in five files. `eabc report ROOT --include OUT`
    reports them; a later study given `--include OUT` skips them.
    """

    specs: Annotated[
        tuple[str, ...],
        tyro.conf.Positional,
        tyro.conf.arg(metavar="SPEC", help_behavior_hint="(one or more)"),
    ]
    """Sweep specs (YAML: datasets, algos or variants, seeds, steps, train): the queue's slices,
    in their order; within one, algorithm by algorithm in the spec's order (each on all the
    slice's datasets before the next), and the runs that can share one program
    (seeds, datasets of one environment) as one group."""
    out: str = "study-out"
    """Where the finished runs' results go (runs.csv, evaluations.csv, logs.csv, runs.jsonl,
    study.log); an empty directory or one a study wrote."""
    root: str = "sweeps/study"
    """The run directories (checkpoints stay here, not in --out)."""
    within: str | None = None
    """Start only the groups that end within this time from now (e.g. 520s, 45m)."""
    include: tuple[str, ...] = ()
    """Earlier results (a study's --out, a report's directory): runs they hold as done are not
    trained again."""
    data_workers: Positive | None = None
    """Processes that make each of the queue's missing datasets, one dataset after another while
    the groups before it train (default: the CPU cores less one, at least one)."""
    eval_workers: NonNegative | None = None
    """Processes that evaluate the runs while training goes on, one pool for the whole queue
    (default: the CPU cores less one; 0 evaluates in the training process between chunks)."""
    steps: Steps | None = None
    """Gradient steps per run (default the spec's)."""
    dry_run: bool = False
    """List the slices' groups in the order they would train, their datasets (made or to make)
    and estimates, then stop: nothing is made, trained or written."""
    smoke: bool = False
    """The same code path at toy sizes: the first slice's first three groups and the second's first,
    two seeds each, 40 steps per run, one evaluation episode every 20 steps, datasets of 2,000 transitions in a
    temporary cache; for a check on any machine."""


def run_study(cmd: Study) -> None:
    # Before JAX starts its backend: one process trains the whole queue, growing its memory as
    # the programs need it, instead of taking 75% of the GPU up front.
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

    if not cmd.specs:  # tyro takes none; a study of nothing would write an empty --out
        raise ValueError(
            "eabc study: no spec given; name at least one sweep spec (YAML), e.g. "
            "eabc study docs/results/study-1m/1-hopper-halfcheetah.yaml --within 45m"
        )
    if not cmd.smoke:
        _study(cmd, None)
        return
    # The smoke run's small datasets live only as long as the run; nothing is left in /tmp.
    with tempfile.TemporaryDirectory(prefix="eabc-study-smoke-") as cache:
        _study(cmd, cache)


def _study(cmd: Study, cache: str | None) -> None:
    from eabc.experiments import archive_merge, planning, run_status, study  # noqa: PLC0415
    from eabc.experiments.spec import expand, groups, load_spec  # noqa: PLC0415

    # The options first, so that a dry run refuses what the study would.
    budget = None if cmd.within is None else planning.parse_duration(cmd.within, "--within")
    out = study.check_out(cmd.out)  # checked by a dry run too; written only by the study
    size, slices = None, []
    for path in cmd.specs:
        spec = load_spec(path)
        if cmd.steps is not None:
            spec["steps"] = cmd.steps
        if cmd.smoke:
            spec["steps"] = SMOKE["steps"]
            train = {k: v for k, v in SMOKE.items() if k != "steps"}
            spec["train"] = {**(spec.get("train") or {}), **train, "cache_dir": cache}
            size = SMOKE_DATASET_SIZE
        slices.append(study.algorithm_major(expand(spec)))
    if cmd.smoke:  # a few groups, two seeds each: every stage of the path, in a minute
        seeds = sorted({r.seed for runs in slices for r in runs})[:SMOKE_SEEDS]
        slices = [
            [r for group in groups(runs)[:count] for r in group if r.seed in seeds]
            for runs, count in zip(slices, SMOKE_GROUPS)
        ]
    every = [r for runs in slices for r in runs]
    run_status.check_startable(every, paths.expand(cmd.root))  # before the first group
    if cmd.include:
        archives = [archive_merge.read_archive(d) for d in cmd.include]
        done = run_status.archived_done(every, archives)
        if done:
            print(f"{len(done)} runs done in {', '.join(cmd.include)}: not trained again")
        slices = [[r for r in runs if r.run_id not in done] for runs in slices]
    if cmd.dry_run:
        print("\n".join(study.plan(slices, paths.expand(cmd.root), list(cmd.specs))))
        return
    deadline = None if budget is None else time.time() + budget
    workers = cmd.data_workers or max(1, (os.cpu_count() or 2) - 1)
    evaluators = cmd.eval_workers
    if evaluators is None:
        evaluators = max(1, (os.cpu_count() or 2) - 1)
    report = study.run_study(
        slices, paths.expand(cmd.root), out, deadline, workers, size, eval_workers=evaluators
    )
    if report["failed"]:
        raise SystemExit(f"error: {len(report['failed'])} group(s) failed; see {out / 'study.log'}")
