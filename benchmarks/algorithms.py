"""Steps/s of every algorithm, and of seed groups in the two layouts (vmap vs one process per core).

    python benchmarks/algorithms.py                     # every algorithm, hopper-sized data
    python benchmarks/algorithms.py --algos eabc td3bc  # a subset
    python benchmarks/algorithms.py --seeds 5           # also: 5 EABC seeds vmapped vs per core
    python benchmarks/algorithms.py --paired eabc eabc-ln --rounds 9  # the second's cost over the first's

Each figure is the median of ``--repeats`` compiled chunks of ``--steps`` gradient steps (the
algorithm's batch: 256, ReBRAC's 1024) on a 1M-transition dataset with hopper's shapes (11-d
observations, 3-d actions) resident in device memory, the same ``train_chunk`` the trainer runs.
MOPO and MOReL are timed with an untrained dynamics model (its rollouts cost the same; fitting it,
once per run, is not included).

``--paired A B`` times what B costs over A on a busy machine: one single-threaded process pinned to
one core compiles both, then runs their chunks in turn (A B, B A, A B, ...) for ``--rounds``
rounds, so that whatever else the machine does slows both alike; it prints each one's median
ms/step (wall-clock and the process's CPU time) and the median of the rounds' B / A ratios.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import subprocess
import sys
import time

from speed import fake_data  # benchmarks/speed.py, beside this file

OBS_DIM, ACT_DIM = 11, 3
SLOW = ("edac", "uwac")
"""Algorithms timed on a fifth of --steps."""


def agent(algo: str, steps_total: int = 1_000_000):

    import jax

    from eabc.agents import get_algorithm

    algorithm = get_algorithm(algo)
    # The settings a run on hopper-medium gets (Table 3's p, IQL's schedule over the run, ...).
    config = algorithm.resolved(algorithm.preset, "hopper-medium", steps_total, set())
    state = algorithm.init(jax.random.PRNGKey(0), OBS_DIM, ACT_DIM, config)
    update = functools.partial(algorithm.update, config=config, max_action=1.0)
    return state, update, algorithm.delayed_period(config) if algorithm.delayed_period else None


def measure(algo: str, steps: int, repeats: int, seeds: int = 1) -> list[float]:
    """Total steps/s (summed over ``seeds`` vmapped seeds when seeds > 1)."""
    import jax

    from eabc.agents import get_algorithm
    from eabc.agents.common import BatchWithNextActions
    from eabc.training.chunks import train_chunk, train_chunk_seeds

    algorithm = get_algorithm(algo)
    data = fake_data(OBS_DIM, ACT_DIM)
    if algorithm.next_actions:  # random next actions: speed does not depend on values
        data = BatchWithNextActions(**vars(data), next_actions=data.actions[::-1])
    batch_size = algorithm.batch_size
    state, update, period = agent(algo)
    key = jax.random.PRNGKey(1)
    if seeds > 1:
        state = jax.tree.map(lambda x: jax.numpy.stack([x] * seeds), state)
        key = jax.random.split(key, seeds)
        chunk = train_chunk_seeds
    else:
        chunk = train_chunk
    # period, start: the TD3 family's actor on its fixed schedule, as the trainer runs it
    state, key, _ = chunk(
        state, key, data, update, batch_size, steps, period, 0
    )  # compile, warm up
    jax.block_until_ready(state)
    rates = []
    for i in range(repeats):
        start = time.perf_counter()
        done = (i + 1) * steps
        state, key, metrics = chunk(state, key, data, update, batch_size, steps, period, done)
        jax.block_until_ready((state, metrics))
        rates.append(seeds * steps / (time.perf_counter() - start))
    return rates


def paired(algos: tuple[str, str], steps: int, rounds: int) -> dict[str, list[float]]:
    """Seconds per chunk of each algorithm, wall-clock and CPU, their chunks alternating:
    ``{"A_wall": [...], "A_cpu": [...], "B_wall": ..., "B_cpu": ...}``."""
    import jax

    from eabc.agents import get_algorithm
    from eabc.agents.common import BatchWithNextActions
    from eabc.training.chunks import train_chunk

    runs = {}
    for algo in algos:
        algorithm = get_algorithm(algo)
        data = fake_data(OBS_DIM, ACT_DIM)
        if algorithm.next_actions:
            data = BatchWithNextActions(**vars(data), next_actions=data.actions[::-1])
        state, update, period = agent(algo)
        run = [state, jax.random.PRNGKey(1), data, update, algorithm.batch_size, period]
        run[:2] = train_chunk(state, run[1], data, update, run[4], steps, period, 0)[:2]
        jax.block_until_ready(run[0])  # compiled and warm
        runs[algo] = run
    times: dict[str, list[float]] = {f"{a}_{c}": [] for a in algos for c in ("wall", "cpu")}
    for round_ in range(rounds):
        for algo in algos if round_ % 2 == 0 else algos[::-1]:
            state, key, data, update, batch_size, period = runs[algo]
            done = int(state.step)
            wall, cpu = time.perf_counter(), time.process_time()
            state, key, metrics = train_chunk(
                state, key, data, update, batch_size, steps, period, done
            )
            jax.block_until_ready((state, metrics))
            times[f"{algo}_wall"].append(time.perf_counter() - wall)
            times[f"{algo}_cpu"].append(time.process_time() - cpu)
            runs[algo][:2] = state, key
    return times


def paired_lines(algos: tuple[str, str], steps: int, rounds: int) -> list[str]:
    """The ``--paired`` report: the worker pinned to the last core, one thread."""
    from speed import single_thread_env

    first, second = algos
    core = sorted(os.sched_getaffinity(0))[-1]
    command = [sys.executable, __file__, "--paired-worker", first, second, str(steps), str(rounds)]
    out = subprocess.run(
        ["taskset", "-c", str(core), *command],
        env=single_thread_env(core),
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    times = json.loads(out.strip().splitlines()[-1])
    lines = [
        f"one single-threaded process pinned to core {core}, hopper shapes, chunks of {steps} "
        f"steps, {rounds} rounds alternating {first} and {second}; medians",
        "",
        "| algorithm | ms/step (wall) | ms/step (CPU) | steps/s (CPU) |",
        "|---|---:|---:|---:|",
    ]
    for algo in algos:
        wall = 1e3 * statistics.median(times[f"{algo}_wall"]) / steps
        cpu = 1e3 * statistics.median(times[f"{algo}_cpu"]) / steps
        lines.append(f"| {algo} | {wall:.2f} | {cpu:.2f} | {1e3 / cpu:.1f} |")
    ratios = {
        c: [b / a for a, b in zip(times[f"{first}_{c}"], times[f"{second}_{c}"])]
        for c in ("wall", "cpu")
    }
    lines += [
        "",
        f"{second} / {first}: {statistics.median(ratios['cpu']):.3f} in CPU time, "
        f"{statistics.median(ratios['wall']):.3f} wall-clock (medians of the {rounds} rounds' "
        f"ratios; CPU-time ratios {min(ratios['cpu']):.3f}-{max(ratios['cpu']):.3f})",
    ]
    return lines


def per_core(algo: str, steps: int, repeats: int) -> list[float]:
    """One single-threaded process per core, side by side: each one's median steps/s."""
    from eabc.experiments.job_process import SINGLE_THREAD

    env = {**os.environ, **SINGLE_THREAD}
    procs = [
        subprocess.Popen(
            [
                "taskset",
                "-c",
                str(core),
                sys.executable,
                __file__,
                "--worker",
                algo,
                str(steps),
                str(repeats),
            ],
            env=env,
            stdout=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for core in sorted(os.sched_getaffinity(0))
    ]
    return [statistics.median(json.loads(p.communicate()[0])) for p in procs]


def main() -> None:
    from eabc.agents import ALGORITHMS

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--algos", nargs="*", default=list(ALGORITHMS))
    parser.add_argument("--steps", type=int, default=500, help="steps per timed chunk")
    parser.add_argument("--repeats", type=int, default=3, help="timed chunks (median)")
    parser.add_argument("--seeds", type=int, default=0, help="also compare layouts for N seeds")
    parser.add_argument(
        "--paired", nargs=2, metavar=("A", "B"), help="B's cost over A's, chunks alternating"
    )
    parser.add_argument("--rounds", type=int, default=9, help="--paired: chunks of each")
    parser.add_argument("--worker", nargs=3, help=argparse.SUPPRESS)
    parser.add_argument("--paired-worker", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        algo, steps, repeats = args.worker
        print(json.dumps(measure(algo, int(steps), int(repeats))))
        return
    if args.paired_worker:
        first, second, steps, rounds = args.paired_worker
        print(json.dumps(paired((first, second), int(steps), int(rounds))))
        return
    if args.paired:
        import machine  # benchmarks/machine.py, beside this file

        print(machine.host_line())
        for line in paired_lines(tuple(args.paired), args.steps, args.rounds):
            print(line, flush=True)
        return

    import jax

    print(f"{jax.default_backend()} backend, {os.cpu_count()} cores; hopper shapes\n")
    print(f"{'algorithm':14s} {'steps/s':>9s} {'h per 1M steps':>15s}")
    for algo in args.algos:
        # The slow ones in shorter chunks: EDAC's 50 critics, UWAC's 100 dropout passes per estimate.
        steps = max(args.steps // 5, 20) if algo in SLOW else args.steps
        rate = statistics.median(measure(algo, steps, args.repeats))
        print(f"{algo:14s} {rate:9.1f} {1e6 / rate / 3600:15.2f}", flush=True)
    if args.seeds > 1:
        print(f"\n{args.seeds} EABC (K = 10) seeds, total steps/s:")
        vmapped = statistics.median(measure("eabc", args.steps, args.repeats, args.seeds))
        print(f"  one process, seeds vmapped:      {vmapped:8.1f}")
        alone = statistics.median(measure("eabc", args.steps, args.repeats))
        print(f"  one process, one seed at a time: {alone:8.1f}")
        cores = per_core("eabc", args.steps, args.repeats)
        print(f"  one single-threaded process per core, side by side: {sum(cores):8.1f} "
              f"({' + '.join(f'{r:.1f}' for r in cores)})")  # fmt: skip


if __name__ == "__main__":
    main()
