"""Throughput against the run axis's width: what N runs trained as one compiled program gain.

    python benchmarks/width.py                                   # eabc and td3bc, widths 1 2 4 8
    python benchmarks/width.py --algos eabc eabc-ln td3bc rebrac --widths 1 2 4 8 16
    python benchmarks/width.py --steps 1000 --widths 1 2 4 8 16 32 64   # on a GPU

It times ``chunks.train_chunk_seeds``, the program that trains a group of runs as one: the scanned
update (batch sampling inside) vmapped over a leading axis of agent states and keys. Every width
runs on JAX's default device, on a device-resident dataset of ``--size`` random transitions with
hopper-medium's shapes (11-d observations, 3-d actions; speed does not depend on the values), each
algorithm with its hopper-medium preset (EABC: K = 10) and its own batch size (ReBRAC's 1024).
Width 1 is ``chunks.train_chunk``, the program the trainer runs for a run alone, so the speed-up
is over training the runs one after another.

Each width's program is compiled and run once untimed, then the widths take turns, chunk by chunk,
for ``--repeats`` rounds (a busy host slows every width alike); a figure is the median of its
chunks. steps/s counts program steps (each advances every run once); seed-steps/s is width x
steps / seconds. The host's load average before and after is printed beside the table: on a shared
machine it says how much of the CPU the timings had.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

OBS_DIM, ACT_DIM = 11, 3  # hopper
HEADER = "| algorithm | width | steps/s | seed-steps/s | speed-up over width 1 |"


def setup(algo: str, size: int):
    """``(algorithm, config, data)``: ``algo`` with its hopper-medium settings, and the data."""
    from speed import fake_data

    from eabc.agents import get_algorithm
    from eabc.agents.common import BatchWithNextActions

    algorithm = get_algorithm(algo)
    config = algorithm.resolved(algorithm.preset, "hopper-medium", 1_000_000, set())
    data = fake_data(OBS_DIM, ACT_DIM, size)
    if algorithm.next_actions:  # reversed actions stand in for the data's next actions
        data = BatchWithNextActions(**vars(data), next_actions=data.actions[::-1])
    return algorithm, config, data


def runs(algorithm, config, width: int):
    """``(states, keys)`` of ``width`` runs, each initialised from its own seed as the trainer
    initialises a run (one compiled init program, whatever the width), stacked on a leading axis
    (one state and key, not stacked, at width 1)."""
    import jax
    import numpy as np

    from eabc.training.lifecycle import init_agent

    init_keys = jax.random.split(jax.random.PRNGKey(0), width)
    each = [init_agent(algorithm.init, key, OBS_DIM, ACT_DIM, config) for key in init_keys]
    keys = jax.random.split(jax.random.PRNGKey(1), width)
    if width == 1:
        return each[0], keys[0]
    return jax.tree.map(lambda *xs: jax.numpy.asarray(np.stack(xs)), *each), keys


def measure(algo: str, widths, steps: int, repeats: int, size: int) -> dict[int, list[float]]:
    """Each width's seed-steps/s, one figure per timed chunk of ``steps`` program steps."""
    import jax

    from eabc.training.chunks import train_chunk, train_chunk_seeds

    algorithm, config, data = setup(algo, size)
    update = functools.partial(algorithm.update, config=config, max_action=1.0)
    period = algorithm.delayed_period(config) if algorithm.delayed_period else None
    programs = {}
    for width in widths:
        states, keys = runs(algorithm, config, width)
        chunk = functools.partial(
            train_chunk if width == 1 else train_chunk_seeds,
            data=data, update=update, batch_size=algorithm.batch_size, length=steps, period=period,
        )  # fmt: skip
        states, keys, _ = chunk(states, keys, start=0)  # compiles; the warm-up
        jax.block_until_ready(states)
        programs[width] = [chunk, states, keys]
    rates = {width: [] for width in widths}
    for done in range(steps, steps * (repeats + 1), steps):
        for width in widths:
            chunk, states, keys = programs[width]
            start = time.perf_counter()
            states, keys, metrics = chunk(states, keys, start=done)
            jax.block_until_ready((states, metrics))
            rates[width].append(width * steps / (time.perf_counter() - start))
            programs[width][1:] = states, keys
    return rates


def rows(algo: str, rates: dict[int, list[float]]) -> list[dict]:
    """One row per width: medians, and the speed-up over width 1."""
    medians = {width: statistics.median(r) for width, r in rates.items()}
    base = medians[1]
    return [
        {
            "algorithm": algo,
            "width": width,
            "steps_per_s": seed_rate / width,
            "seed_steps_per_s": seed_rate,
            "speed_up": seed_rate / base,
            "seed_steps_per_s_each_chunk": rates[width],
        }
        for width, seed_rate in medians.items()
    ]


def table_line(row: dict) -> str:
    return (
        f"| {row['algorithm']} | {row['width']} | {row['steps_per_s']:.1f} | "
        f"{row['seed_steps_per_s']:.1f} | {row['speed_up']:.2f} |"
    )


def load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f} {five:.2f} {fifteen:.2f} (1, 5, 15 min)"


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line (``argv``, else ``sys.argv``); widths sorted, 1 among them."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--algos", nargs="+", default=["eabc", "td3bc"])
    parser.add_argument(
        "--widths",
        nargs="+",
        type=int,
        default=[1, 2, 4, 8],
        help="runs in one program (1, the speed-up's base, is always measured)",
    )
    parser.add_argument("--steps", type=int, default=100, help="program steps per timed chunk")
    parser.add_argument("--repeats", type=int, default=3, help="timed chunks per width (median)")
    parser.add_argument("--size", type=int, default=1_000_000, help="transitions in the dataset")
    parser.add_argument("--json", help="also write the figures, every chunk's too, to this file")
    args = parser.parse_args(argv)
    args.widths = sorted({1, *args.widths})
    if args.widths[0] < 1 or args.steps < 1 or args.repeats < 1 or args.size < 1:
        parser.error("--widths, --steps, --repeats and --size must be at least 1")
    return args


def main() -> None:
    args = parse()
    widths = args.widths

    import jax
    import machine

    from eabc.agents import get_algorithm
    from eabc.training.chunks import fast_compile

    for algo in args.algos:
        get_algorithm(algo)  # an unknown name fails before anything is timed
    device = jax.devices()[0]
    print(machine.host_line())
    build = "; EABC_FAST_COMPILE (XLA at O0)" if fast_compile() else ""
    print(f"device: {device.platform} {device.device_kind}; JAX {jax.__version__}{build}")
    print(f"load average before: {load()}")
    print(
        f"hopper shapes, {args.size:,} transitions; median of {args.repeats} chunks of "
        f"{args.steps} steps per width, compilation excluded\n"
    )
    print(HEADER)
    print("|---|---|---|---|---|")
    figures = []
    for algo in args.algos:
        for row in rows(algo, measure(algo, widths, args.steps, args.repeats, args.size)):
            print(table_line(row), flush=True)
            figures.append(row)
    print(f"\nload average after: {load()}")
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {
                    "host": machine.host_line(),
                    "device": f"{device.platform} {device.device_kind}",
                    "steps": args.steps,
                    "repeats": args.repeats,
                    "rows": figures,
                },
                indent=2,
            )
        )


if __name__ == "__main__":
    main()
