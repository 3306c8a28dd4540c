"""Every time estimate eabc states, from one table of measurements scaled to the host it runs on.

The figures are measured by the benchmarks and stated for the reference host
(the reference host, :data:`REFERENCE_HOST`): training steps/s per algorithm by ``benchmarks/algorithms.py`` (kept in
each algorithm's contract, ``Algorithm.steps_per_s``), dataset making by
``benchmarks/datasets.py`` (:data:`DATASET_SECONDS_PER_1M`), and the host's speed by the probe
:func:`probe_gflops` (XLA's rate on the critic ensemble's own ``[10, 256, 256]`` product, the
bulk of a training step; ``benchmarks/kernels.py``). On any host an estimate is the reference
figure times :data:`REFERENCE_PROBE_GFLOPS` / this host's probe, measured when the estimate is
asked for (about a second, kept for :data:`PROBE_KEEP_SECONDS` in the cache directory): a busy or
slow host gets longer estimates, as it will take longer. The dry runs, the stage lines of long
commands, the help texts, README and docs (``tests/test_timing.py`` checks them) all read from here.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import time

from eabc import paths

REFERENCE_HOST = "a quiet 2-core AMD EPYC Zen 5 (AVX-512)"
"""The host the figures below and the algorithms' ``steps_per_s`` are stated for."""

REFERENCE_PROBE_GFLOPS = 353.0
"""The probe on the reference host: XLA's ``[10, 256, 256] x [10, 256, 256]`` product, one
process on both cores (``benchmarks/speed.py``, docs/speed.md)."""

DATASET_SECONDS_PER_1M = {"mujoco": (35.0, 75.0), "antmaze": (140.0, 215.0)}
"""Seconds to make 1M transitions at the reference host's speed, one process: the MuJoCo recipes
(halfcheetah fastest, hopper slowest) and AntMaze (10 environments at once), as
``python benchmarks/datasets.py`` states them from any host (from 20K-100K transitions of each
medium dataset and 10K-50K of antmaze-umaze on a loaded host, scaled by its probe; where and how:
docs/speed.md)."""

EPISODE_SECONDS = 0.15
"""A 1000-step MuJoCo evaluation episode with the NumPy policy, on the reference host."""

PROBE_KEEP_SECONDS = 600.0
"""How long a probe measurement stands for the host before it is taken again."""

PROBE_FILE = "host_speed.json"


@dataclasses.dataclass(frozen=True)
class HostSpeed:
    """This host against the reference host: ``factor`` = probe here / probe there (0.5: every
    step takes twice as long here); ``measured`` False when no probe was taken (factor 1)."""

    factor: float = 1.0
    gflops: float = REFERENCE_PROBE_GFLOPS
    measured: bool = False

    def basis(self) -> str:
        """Where the estimate comes from, in words."""
        if not self.measured:
            return f"at the reference host's speed ({REFERENCE_HOST})"
        return (
            f"at this host's measured speed, {self.factor:.0%} of the reference host's "
            f"({REFERENCE_HOST})"
        )


REFERENCE = HostSpeed()


def probe_gflops(seconds: float = 0.5) -> float:
    """XLA's GFLOP/s on the critic ensemble's ``[10, 256, 256]`` batched product, now: 20
    chained products in one compiled scan, best of 3 timings over ``seconds``."""
    import jax  # noqa: PLC0415 (the JAX-free data makers import this module)
    import jax.numpy as jnp  # noqa: PLC0415 (as above)

    k, b, h, chain = 10, 256, 256, 20
    x = jax.random.normal(jax.random.PRNGKey(0), (k, b, h))
    w = jax.random.normal(jax.random.PRNGKey(1), (k, h, h)) / h

    @jax.jit
    def chained(x, w):
        body = lambda c, _: (jnp.einsum("kbi,kio->kbo", c, w), None)  # noqa: E731
        return jax.lax.scan(body, x, None, length=chain)[0]

    chained(x, w).block_until_ready()
    best = 0.0
    for _ in range(3):
        reps, start = 0, time.perf_counter()
        while reps == 0 or time.perf_counter() - start < seconds / 3:
            chained(x, w).block_until_ready()
            reps += 1
        best = max(best, chain * 2 * k * b * h * h * reps / (time.perf_counter() - start) / 1e9)
    return best


def host_speed(cache_root=None, measure: bool = True) -> HostSpeed:
    """This host's :class:`HostSpeed`: the probe kept in the cache directory if it is recent and
    from this CPU, else measured now (``measure``), else the reference host's (factor 1).
    ``EABC_HOST_SPEED=FACTOR`` sets the factor instead (``1``: state reference figures)."""
    given = os.environ.get("EABC_HOST_SPEED")
    if given:
        factor = float(given)
        return HostSpeed(factor, factor * REFERENCE_PROBE_GFLOPS, measured=factor != 1.0)
    path = paths.cache_dir(cache_root) / PROBE_FILE
    host = _host()
    try:
        kept = json.loads(path.read_text())
        if kept["host"] == host and time.time() - kept["time"] < PROBE_KEEP_SECONDS:
            return _speed(float(kept["gflops"]))
    except (OSError, ValueError, KeyError, TypeError):
        pass
    if not measure:
        return REFERENCE
    gflops = probe_gflops()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"host": host, "time": time.time(), "gflops": gflops}))
    except OSError:  # a read-only cache: measured again next time
        pass
    return _speed(gflops)


def _speed(gflops: float) -> HostSpeed:
    return HostSpeed(gflops / REFERENCE_PROBE_GFLOPS, gflops, measured=True)


def _host() -> str:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{platform.node()} {platform.processor() or platform.machine()} {cores}"


def dataset_family(name: str) -> str:
    """``antmaze`` or ``mujoco``: which row of :data:`DATASET_SECONDS_PER_1M` a built-in name
    takes."""
    return "antmaze" if name.startswith("antmaze") else "mujoco"


def dataset_seconds(name: str, size: int, speed: HostSpeed = REFERENCE) -> tuple[float, float]:
    """``(low, high)`` seconds to make ``size`` transitions of the built-in dataset ``name``."""
    low, high = DATASET_SECONDS_PER_1M[dataset_family(name)]
    scale = size / 1e6 / speed.factor
    return low * scale, high * scale


def minutes(low: float, high: float) -> str:
    """A range of seconds as ``about 2-3 minutes`` (``less than a minute``, ``about 1.5-2.0
    hours``)."""
    if high < 60:
        return "less than a minute"
    if high < 5400:
        lo, hi = max(1, round(low / 60)), max(1, round(high / 60))
        return f"about {lo} minute{'s' * (hi > 1)}" if lo == hi else f"about {lo}-{hi} minutes"
    return f"about {low / 3600:.1f}-{high / 3600:.1f} hours"


def making_time(name: str, size: int = 1_000_000, speed: HostSpeed = REFERENCE) -> str:
    """How long making ``size`` transitions of ``name`` takes, e.g. ``about 1-2 minutes``."""
    return minutes(*dataset_seconds(name, size, speed))


def duration(seconds: float) -> str:
    """``45 s``, ``12 minutes``, ``2.5 hours`` (``less than a second``)."""
    if seconds < 1:
        return "less than a second"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} minutes"
    return f"{seconds / 3600:.1f} hours"


def hours_per_million(steps_per_s: float, speed: HostSpeed = REFERENCE) -> float:
    """Hours of training per 1M gradient steps at ``steps_per_s`` on the reference host."""
    return 1e6 / (steps_per_s * speed.factor) / 3600
