"""Gradient steps per second of the EABC update, its FLOPs, and the fraction of the machine's peak.

Measures, in one run:
- the host (CPU model, vector ISA, cores) and its fp32 matmul ceiling, measured with XLA's own
  large products (``machine.py``), with NumPy/OpenBLAS's sgemm peak beside it (kernel overrides
  lifted for that measurement only; the kernel named) and, for reference, XLA's rate on the
  ensemble's own ``[K, 256, 256]`` product shape (``kernels.py``);
- steps/s of the compiled training chunk for K = 2 and K = 10 on hopper- and halfcheetah-sized data
  (median of repeats), using all cores in one process;
- the same for one process per core, all running side by side (the multi-seed layout on a CPU).

With ``--layer-norm``: what LayerNorm critics (``critic_layer_norm``, as in ``eabc-ln``) cost per
step, EABC at K = 10 with and without them in one single-threaded process pinned to one core, the
two compiled chunks alternating (ABBA...) so that a busy machine slows both alike; medians of the
chunks, and of the per-round ratios, in wall-clock and in the process's CPU time.

    python benchmarks/speed.py                # full table (a few minutes)
    python benchmarks/speed.py --repeats 3 --steps 500
    python benchmarks/speed.py --layer-norm   # LayerNorm's cost per step (a few minutes)
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


def chunk_setup(env: str, k: int, layer_norm: bool = False):
    """The EABC state, update and dataset the timed chunks run (p = 0.5: a Bernoulli mask is drawn)."""
    import dataclasses
    import functools

    import jax

    from eabc.agents import eabc

    obs_dim, act_dim = SHAPES[env]
    config = dataclasses.replace(
        eabc.PRESETS["eabc"], num_critics=k, confidence_level=0.5, critic_layer_norm=layer_norm
    )
    state = eabc.init(jax.random.PRNGKey(0), obs_dim, act_dim, config)
    update = functools.partial(eabc.update, config=config, max_action=1.0)
    return state, update, fake_data(obs_dim, act_dim)


def schedule(update, state) -> tuple[int, int]:
    """The chunk's ``period`` and ``start`` as the trainer passes them: EABC's actor steps on a
    fixed schedule (every policy_freq-th step; :mod:`eabc.agents.td3_core`), no branch."""
    return update.keywords["config"].policy_freq, int(state.step)


def measure(env: str, k: int, steps: int, repeats: int) -> list[float]:
    """steps/s of the real training chunk (sampling from a device-resident dataset included)."""
    import jax

    from eabc.training.chunks import train_chunk

    state, update, data = chunk_setup(env, k)
    key = jax.random.PRNGKey(1)
    state, key, _ = train_chunk(
        state, key, data, update, 256, steps, *schedule(update, state)
    )  # compile and warm up
    jax.block_until_ready(state)
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        state, key, m = train_chunk(state, key, data, update, 256, steps, *schedule(update, state))
        jax.block_until_ready((state, m))
        rates.append(steps / (time.perf_counter() - start))
    return rates


def measure_layer_norm(env: str, k: int, steps: int, rounds: int) -> dict[str, list[float]]:
    """Seconds per chunk of ``steps`` steps, wall-clock and CPU, without and with LayerNorm critics,
    the two alternating: ``{"plain_wall": [...], "plain_cpu": [...], "ln_wall": ..., "ln_cpu": ...}``."""
    import jax

    from eabc.training.chunks import train_chunk

    runs = {}
    for name, layer_norm in (("plain", False), ("ln", True)):
        state, update, data = chunk_setup(env, k, layer_norm)
        state, key, _ = train_chunk(
            state, jax.random.PRNGKey(1), data, update, 256, steps, *schedule(update, state)
        )
        jax.block_until_ready(state)  # compiled and warm
        runs[name] = [state, key, data, update]
    times: dict[str, list[float]] = {f"{n}_{c}": [] for n in runs for c in ("wall", "cpu")}
    for round_ in range(rounds):
        for name in ("plain", "ln") if round_ % 2 == 0 else ("ln", "plain"):
            state, key, data, update = runs[name]
            wall, cpu = time.perf_counter(), time.process_time()
            state, key, metrics = train_chunk(
                state, key, data, update, 256, steps, *schedule(update, state)
            )
            jax.block_until_ready((state, metrics))
            times[f"{name}_wall"].append(time.perf_counter() - wall)
            times[f"{name}_cpu"].append(time.process_time() - cpu)
            runs[name][:2] = state, key
    return times


def layer_norm_table(envs, k: int, steps: int, rounds: int) -> list[str]:
    """The ``--layer-norm`` table: one pinned single-threaded worker per dataset shape."""
    core = sorted(os.sched_getaffinity(0))[-1]
    lines = [
        f"EABC K = {k}, batch 256: one single-threaded process pinned to core {core}, chunks of "
        f"{steps} steps, {rounds} rounds alternating the two networks; medians",
        "",
        "| data | critics | ms/step (wall) | ms/step (CPU) | steps/s (wall) |",
        "|---|---|---|---|---|",
    ]
    ratios = []
    for env in envs:
        command = [sys.executable, __file__, "--ln-worker", env, str(k), str(steps), str(rounds)]
        out = subprocess.run(
            ["taskset", "-c", str(core), *command],
            env=single_thread_env(core),
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        times = json.loads(out.strip().splitlines()[-1])
        for name, label in (("plain", "plain"), ("ln", "LayerNorm")):
            wall = 1e3 * statistics.median(times[f"{name}_wall"]) / steps
            cpu = 1e3 * statistics.median(times[f"{name}_cpu"]) / steps
            lines.append(f"| {env} | {label} | {wall:.2f} | {cpu:.2f} | {1e3 / wall:.1f} |")
        per_round = {
            c: statistics.median(
                ln / plain for ln, plain in zip(times[f"ln_{c}"], times[f"plain_{c}"])
            )
            for c in ("wall", "cpu")
        }
        ratios.append(
            f"{env}: LayerNorm / plain = {per_round['wall']:.3f} wall-clock, "
            f"{per_round['cpu']:.3f} CPU time (median of the {rounds} rounds' ratios)"
        )
    return [*lines, "", *ratios]


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
    parser.add_argument(
        "--steps", type=int, help="steps per timed chunk (default 1000; 200 with --layer-norm)"
    )
    parser.add_argument("--repeats", type=int, default=5, help="timed chunks per setting (median)")
    parser.add_argument(
        "--layer-norm",
        action="store_true",
        help="EABC K = 10 with and without LayerNorm critics, one pinned thread, alternating",
    )
    parser.add_argument("--rounds", type=int, default=9, help="--layer-norm: chunks of each")
    parser.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
    parser.add_argument("--ln-worker", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    args.steps = args.steps or (200 if args.layer_norm else 1000)
    if args.worker:
        env, k, steps, repeats = args.worker
        print(json.dumps(measure(env, int(k), int(steps), int(repeats))))
        return
    if args.ln_worker:
        env, k, steps, rounds = args.ln_worker
        print(json.dumps(measure_layer_norm(env, int(k), int(steps), int(rounds))))
        return

    import machine  # benchmarks/machine.py, beside this file

    if args.layer_norm:
        print(machine.host_line())
        for line in layer_norm_table(SHAPES, 10, args.steps, args.rounds):
            print(line, flush=True)
        return
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
