"""One sweep job: its datasets made beforehand, then its runs started or resumed and trained in
this process as one program (:func:`execute`, what a worker process or a Ray task runs).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from eabc import compile_cache, paths
from eabc.data import generate, sources
from eabc.data.sources import load_dataset
from eabc.experiments.run_status import RUNS, SPEC, status_with_reason
from eabc.experiments.spec import RunSpec, is_path
from eabc.training import checkpoint, lifecycle, trainer

SINGLE_THREAD = {
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}
"""A job process's environment: one thread, for a pool of one process per CPU core."""


def prepare_datasets(runs: list[RunSpec], log=lambda line: print(line, flush=True)) -> None:
    """Make the missing built-in datasets once, here, before jobs that share them start."""
    seen = set()
    for run in runs:
        config = run.train_config()
        path = generate.dataset_path(config.dataset, config.cache_dir)
        if (
            sources.kind(config.dataset) == "builtin"
            and path not in seen
            and not generate.is_current(path, config.dataset)
        ):
            seen.add(path)
            log(f"making {config.dataset} into {path}")
            generate.make(config.dataset, path)


def execute(
    job: list[dict], root: str, eval_workers: Any = 0, deadline: float | None = None
) -> list[dict]:
    """Run one job in this process: start or resume each run, then train them as one program
    (:func:`eabc.training.trainer.train_runs`); ``eval_workers``: evaluation processes, or an
    evaluation pool shared with other jobs (``eabc.training.eval_pool``; 0 evaluates in this
    process). With a ``deadline`` (a ``time.time()``) the job stops with
    :class:`~eabc.training.trainer.PastDeadline` once its first chunks show it would end later."""
    root_path = Path(root)
    specs = [RunSpec.from_json(j) for j in job]
    first = specs[0].train_config()
    compile_cache.enable(cache_root=first.cache_dir)  # a sweep's runs share their shapes
    loaded = {}  # one copy of each dataset for the whole group
    runs = []
    for spec in specs:
        if spec.dataset not in loaded:
            loaded[spec.dataset] = load_dataset(spec.dataset, first.cache_dir)
        dataset = loaded[spec.dataset]
        run_dir = root_path / RUNS / spec.run_id
        state, _, why = status_with_reason(spec, root_path)
        if state in ("changed", "broken"):
            raise ValueError(f"{why}; move that run directory away or use another sweep root")
        if (run_dir / checkpoint.CONFIG).exists():  # from step 0 if it has no checkpoint yet
            runs.append(lifecycle.resume(run_dir, dataset, steps=spec.train_config().steps))
        else:
            runs.append(
                lifecycle.start(spec.train_config(), run_dir, dict(spec.overrides), dataset)
            )
        identity = {"fingerprint": dataset.fingerprint(), **spec.to_json()}  # steps: the latest
        checkpoint.save_json(
            run_dir / SPEC, {"run_id": spec.run_id, "variant": spec.variant, **identity}
        )
    # Progress as lines in the job's log (ROOT/logs/NAME.log): its start with the estimate, one
    # a minute, its end.
    summaries = (
        trainer.train_runs(runs, progress=True, eval_workers=eval_workers, deadline=deadline)
        if len(runs) > 1
        else [trainer.train(runs[0], progress=True, eval_workers=eval_workers, deadline=deadline)]
    )
    return summaries


def absolute_spec(run: RunSpec) -> dict:
    """``run`` as JSON with its dataset file and cache directory as absolute paths."""
    data = run.to_json()
    if is_path(run.dataset):
        data["dataset"] = str(paths.expand(run.dataset).resolve())
    if data["train"].get("cache_dir"):
        data["train"]["cache_dir"] = str(paths.expand(data["train"]["cache_dir"]).resolve())
    return data
