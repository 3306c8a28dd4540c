"""GFLOP/s of the matmul shapes a K-critic step is made of, in XLA, beside the big-sgemm peak.

    python benchmarks/kernels.py
    XLA_FLAGS=--xla_cpu_experimental_onednn_fusion_type=dot python benchmarks/kernels.py

A K = 10 training step is mostly ``[10, 256, 256] x [10, 256, 256]`` batched products (hidden
layers of the critic ensemble, forward and backward). If XLA runs that shape well below the sgemm
peak, the training step cannot reach the peak either; this script says how far below. Each figure
is the best of 3 timings of 20 chained products in one compiled scan (no dispatch in the loop).
"""

from __future__ import annotations

import time

SHAPES = [(10, 256, 256), (2, 256, 256), (1, 1024, 1024), (1, 2048, 2048)]
"""(members K, batch B, width H): a [K, B, H] x [K, H, H] product."""


def gflops(k: int, b: int, h: int, chain: int = 20, seconds: float = 2.0) -> float:
    import jax
    import jax.numpy as jnp

    x = jax.random.normal(jax.random.PRNGKey(0), (k, b, h))
    w = jax.random.normal(jax.random.PRNGKey(1), (k, h, h)) / h

    @jax.jit
    def chained(x, w):
        def body(c, _):
            return jnp.einsum("kbi,kio->kbo", c, w), None

        return jax.lax.scan(body, x, None, length=chain)[0]

    chained(x, w).block_until_ready()
    best = 0.0
    for _ in range(3):
        reps, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds / 3:
            chained(x, w).block_until_ready()
            reps += 1
        best = max(best, chain * 2 * k * b * h * h * reps / (time.perf_counter() - start) / 1e9)
    return best


def main() -> None:
    import os

    import machine  # benchmarks/machine.py, beside this file

    print(machine.host_line())
    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    peak, n = machine.xla_peak()
    for line in machine.ceiling_lines(peak, n, machine.openblas_peak()):
        print(line)
    for k, b, h in SHAPES:
        print(f"XLA [{k}, {b}, {h}] x [{k}, {h}, {h}]: {gflops(k, b, h):6.0f} GFLOP/s")


if __name__ == "__main__":
    main()
