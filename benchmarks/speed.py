"""Gradient steps per second of the EABC update, its FLOPs, and the fraction of the machine's peak.

Measures, in one run:
- the host (CPU model, vector ISA, cores) and its fp32 matmul ceiling, measured with XLA's own
  large products (``machine.py``), with NumPy/OpenBLAS's sgemm peak beside it (kernel overrides
  lifted for that measurement only; the kernel named) and, for reference, XLA's rate on the
  ensemble's own ``[K, 256, 256]`` product shape (``kernels.py``);
- steps/s of the compiled training chunk for K = 2 and K = 10 on hopper- and halfcheetah-sized data
  (median of repeats), using all cores in one process;
- the same for one process per core, all running side by side (the multi-seed layout on a CPU).

    python benchmarks/speed.py                # full table (a few minutes)
    python benchmarks/speed.py --repeats 3 --steps 500
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

SHAPES = {"hopper": (11, 3), "halfcheetah": (17, 6)}


def step_flops(
    obs_dim: int, act_dim: int, k: int, hidden=(256, 256), batch=256, policy_freq=2
) -> float:
    """Matmul FLOPs of one gradient step (elementwise work is negligible at these widths)."""

    def layers(sizes):
        return [(a, b) for a, b in zip(sizes[:-1], sizes[1:])]

    critic = layers((obs_dim + act_dim, *hidden, 1))
    actor = layers((obs_dim, *hidden, act_dim))
    fwd = lambda ls, members=1: sum(2 * batch * a * b * members for a, b in ls)  # noqa: E731
    critic_fwd, actor_fwd = fwd(critic, k), fwd(actor)
    # Backward: weight gradients of every layer, input gradients of every layer but the first.
    critic_bwd = 2 * critic_fwd - fwd(critic[:1], k)
    actor_bwd = 2 * actor_fwd - fwd(actor[:1])
    critic_step = actor_fwd + 2 * critic_fwd + critic_bwd  # target actor + target & online critics
    # Actor step: actor forward, critics forward and input gradient (no weight gradient), actor back.
    actor_step = actor_fwd + 2 * critic_fwd + actor_bwd
    return critic_step + actor_step / policy_freq


def fake_data(obs_dim: int, act_dim: int, n: int = 1_000_000):
    """A random device-resident dataset of ``n`` transitions (speed does not depend on values)."""
    import jax.numpy as jnp
    import numpy as np

    from eabc.agents.common import Batch

    rng = np.random.default_rng(0)
    return Batch(
        observations=jnp.asarray(rng.normal(size=(n, obs_dim)), jnp.float32),
        actions=jnp.asarray(rng.uniform(-1, 1, size=(n, act_dim)), jnp.float32),
        rewards=jnp.asarray(rng.normal(size=n), jnp.float32),
        next_observations=jnp.asarray(rng.normal(size=(n, obs_dim)), jnp.float32),
        dones=jnp.zeros(n, jnp.float32),
    )


def measure(env: str, k: int, steps: int, repeats: int) -> list[float]:
    """steps/s of the real training chunk (sampling from a device-resident dataset included)."""
    import dataclasses
    import functools

    import jax

    from eabc.agents import eabc
    from eabc.training.chunks import train_chunk

    obs_dim, act_dim = SHAPES[env]
    data = fake_data(obs_dim, act_dim)
    config = dataclasses.replace(eabc.PRESETS["eabc"], num_critics=k, confidence_level=0.5)
    state = eabc.init(jax.random.PRNGKey(0), obs_dim, act_dim, config)
    update = functools.partial(eabc.update, config=config, max_action=1.0)
    key = jax.random.PRNGKey(1)
    state, key, _ = train_chunk(state, key, data, update, 256, steps)  # compile and warm up
    jax.block_until_ready(state)
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        state, key, m = train_chunk(state, key, data, update, 256, steps)
        jax.block_until_ready((state, m))
        rates.append(steps / (time.perf_counter() - start))
    return rates


def single_thread_env(core: int) -> dict[str, str]:
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "")
        + " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
    ).strip()
    env["OMP_NUM_THREADS"] = "1"
    return env


def side_by_side(env: str, k: int, steps: int, repeats: int) -> list[float]:
    """One single-threaded process per core, started together; returns each one's median steps/s."""
    cores = sorted(os.sched_getaffinity(0))
    procs = [
        subprocess.Popen(
            [
                "taskset",
                "-c",
                str(core),
                sys.executable,
                __file__,
                "--worker",
                env,
                str(k),
                str(steps),
                str(repeats),
            ],
            env=single_thread_env(core),
            stdout=subprocess.PIPE,
            text=True,
        )
        for core in cores
    ]
    return [statistics.median(json.loads(p.communicate()[0])) for p in procs]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=1000, help="steps per timed chunk")
    parser.add_argument("--repeats", type=int, default=5, help="timed chunks per setting (median)")
    parser.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        env, k, steps, repeats = args.worker
        print(json.dumps(measure(env, int(k), int(steps), int(repeats))))
        return

    import machine  # benchmarks/machine.py, beside this file
    from kernels import gflops as shape_gflops

    print(machine.host_line())
    peak, n = machine.xla_peak()
    for line in machine.ceiling_lines(peak, n, machine.openblas_peak()):
        print(line)
    shape_peak = {k: shape_gflops(k, 256, 256) for k in (2, 10)}
    print(
        "XLA on the ensemble's own product shape [K, 256, 256] x [K, 256, 256]: "
        + ", ".join(f"K = {k}: {g:.0f} GFLOP/s" for k, g in shape_peak.items())
        + "\n"
    )
    header = (
        f"{'data':12s} {'K':>3s} {'GFLOP/step':>10s} {'ceiling':>8s} {'steps/s':>8s} "
        f"{'GFLOP/s':>8s} {'% ceil':>7s} {'% shape':>8s} {'1 proc/core, total':>19s} {'% ceil':>7s}"
    )
    print(header)
    print("-" * len(header))
    for env in SHAPES:
        for k in (2, 10):
            gflop = step_flops(*SHAPES[env], k) / 1e9
            rate = statistics.median(measure(env, k, args.steps, args.repeats))
            per_core = side_by_side(env, k, args.steps, args.repeats)
            print(
                f"{env:12s} {k:3d} {gflop:10.2f} {peak / gflop:8.0f} {rate:8.1f} "
                f"{rate * gflop:8.0f} {100 * rate * gflop / peak:6.0f}% "
                f"{100 * rate * gflop / shape_peak[k]:7.0f}% "
                f"{sum(per_core):10.1f} ({' + '.join(f'{r:.1f}' for r in per_core)}) "
                f"{100 * sum(per_core) * gflop / peak:6.0f}%",
                flush=True,
            )
    print(
        "\nceiling = XLA's large-product peak / FLOPs per step: the steps/s a perfect matmul kernel "
        "would reach; % shape = against XLA's rate on the [K, 256, 256] product alone."
    )


if __name__ == "__main__":
    main()
