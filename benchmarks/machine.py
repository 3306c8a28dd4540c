"""What machine a benchmark ran on, and its fp32 matmul ceiling measured with XLA's own products.

    python benchmarks/machine.py            # the host line and both peaks

The ceiling every speed figure is stated against is XLA's: the library the training runs on,
compiling large square products (1024-4096) chained in one scan so that no dispatch is timed. NumPy's
OpenBLAS peak is printed beside it for reference, measured in a subprocess with the environment's
``OPENBLAS_CORETYPE`` / ``OPENBLAS_L2_SIZE`` overrides lifted for that measurement only (some hosts
pin an older kernel, which measures a library setting, not the machine) and its kernel named.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

from eabc.training.provenance import cores, cpu_model, vector_isa  # noqa: F401 (benchmarks use them)

SQUARE_SIZES = (1024, 2048, 4096)


def host_line() -> str:
    """One line naming the host, printed with every benchmark table."""
    return (
        f"host: {cpu_model()}, {vector_isa()}, {cores()} cores; "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    )


def xla_peak(sizes=SQUARE_SIZES, chain: int = 4, seconds: float = 1.0) -> tuple[float, int]:
    """``(GFLOP/s, n)``: XLA's best float32 ``[n, n] x [n, n]`` product rate on the default device.

    Each timing is ``chain`` products in one compiled scan (the output feeds the next product, so
    none can be skipped), repeated for ``seconds``; best of three per size.
    """
    import jax
    import jax.numpy as jnp

    best, best_n = 0.0, 0
    for n in sizes:
        a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jnp.float32) / jnp.sqrt(n)

        @jax.jit
        def chained(x, a=a):
            return jax.lax.scan(lambda c, _: (c @ a, None), x, None, length=chain)[0]

        x = jnp.ones((n, n), jnp.float32)
        chained(x).block_until_ready()
        for _ in range(3):
            reps, start = 0, time.perf_counter()
            while time.perf_counter() - start < seconds / 3:
                chained(x).block_until_ready()
                reps += 1
            rate = chain * 2 * n**3 * reps / (time.perf_counter() - start) / 1e9
            if rate > best:
                best, best_n = rate, n
    return best, best_n


def openblas_peak() -> dict:
    """NumPy's sgemm peak with the kernel overrides lifted, in a subprocess: ``{gflops, kernel,
    overrides}`` (``kernel`` from threadpoolctl when installed)."""
    env = dict(os.environ)
    overrides = {k: env.pop(k) for k in ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE") if k in env}
    code = (
        "import json, sys; sys.path.insert(0, sys.argv[1]); import machine; print(json.dumps("
        "{'gflops': machine._numpy_peak(), 'kernel': machine._blas_kernel()}))"
    )
    here = os.path.dirname(os.path.abspath(__file__))
    out = subprocess.run(
        [sys.executable, "-c", code, here], env=env, capture_output=True, text=True, check=True
    )
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "overrides": overrides}


def _numpy_peak(seconds: float = 0.5) -> float:
    import numpy as np

    seconds = float(os.environ.get("EABC_BENCH_SECONDS", seconds))
    best = 0.0
    for n in (1024, 2048):
        a = np.random.rand(n, n).astype(np.float32)
        a @ a
        for _ in range(3):
            reps, start = 0, time.perf_counter()
            while time.perf_counter() - start < seconds:
                a @ a
                reps += 1
            best = max(best, 2 * n**3 * reps / (time.perf_counter() - start) / 1e9)
    return best


def _blas_kernel() -> str:
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return "unknown (pip install threadpoolctl to name it)"
    blas = [i for i in threadpool_info() if i.get("user_api") == "blas"]
    return ", ".join(f"{i['internal_api']} {i.get('architecture', '?')}" for i in blas) or "none"


def ceiling_lines(peak: float, n: int, blas: dict | None) -> list[str]:
    lines = [f"ceiling: XLA fp32 [{n}, {n}] product, {peak:.0f} GFLOP/s (measured now)"]
    if blas is not None:
        lifted = ", ".join(f"{k}={v}" for k, v in blas["overrides"].items()) or "none set"
        lines.append(
            f"beside it: NumPy/OpenBLAS sgemm {blas['gflops']:.0f} GFLOP/s, kernel "
            f"{blas['kernel']} (environment overrides lifted for this measurement: {lifted})"
        )
    return lines


def main() -> None:
    print(host_line())
    peak, n = xla_peak()
    for line in ceiling_lines(peak, n, openblas_peak()):
        print(line)


if __name__ == "__main__":
    main()
