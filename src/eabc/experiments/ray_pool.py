"""A sweep's jobs on a Ray cluster: one task per job with declared CPU and GPU resources."""

from __future__ import annotations

from pathlib import Path

from eabc import paths
from eabc.experiments.job_process import SINGLE_THREAD, absolute_spec, execute
from eabc.experiments.spec import RunSpec, job_name


def run_ray(
    job_list: list[list[RunSpec]],
    root: Path,
    address: str = "auto",
    num_cpus: float = 1.0,
    num_gpus: float = 0.0,
    log=lambda line: print(line, flush=True),
) -> None:
    """One Ray task per job with declared CPU/GPU resources; ``root`` must be a shared directory.

    Paths go to the workers absolute (the root, dataset files, the cache directory): a worker's
    working directory is not the driver's.
    """
    try:
        import ray  # noqa: PLC0415
    except ImportError:
        raise RuntimeError("--backend ray needs the ray package: pip install 'eabc[ray]'") from None

    root = paths.expand(root).resolve()
    if not ray.is_initialized():
        ray.init(address=address, log_to_driver=False)
    env_vars = SINGLE_THREAD if num_gpus == 0 and num_cpus <= 1 else {}
    remote = ray.remote(execute).options(
        num_cpus=num_cpus, num_gpus=num_gpus, runtime_env={"env_vars": env_vars}, max_retries=2
    )
    futures = {remote.remote([absolute_spec(r) for r in job], str(root)): job for job in job_list}
    failures = []
    while futures:
        done, _ = ray.wait(list(futures), num_returns=1)
        job = futures.pop(done[0])
        name = job_name(job)
        try:
            ray.get(done[0])
            log(f"finished {name}")
        except Exception as error:  # noqa: BLE001 (report every failed job, then raise)
            failures.append(name)
            log(f"FAILED {name}: {error}")
    if failures:
        raise RuntimeError(f"{len(failures)} Ray job(s) failed: {', '.join(failures)}")
