"""The GPU path: steps/s with many seeds vmapped in one program, evaluation cost, and Table 1's wall time.

    bash benchmarks/gpu.sh                  # on the GPU machine (installs carried wheels first)
    python benchmarks/gpu.py --smoke        # tiny sizes, any machine (the test suite runs this)

Measures, on JAX's default device:

1. steps/s of the real training chunk (``chunks.train_chunk_seeds``: the scanned EABC update with
   in-program batch sampling, vmapped over seeds) for K = 2 (TD3+BC's size) and K = 10, with 1, 5,
   25 and 75 seeds in one program, on a device-resident dataset of 1M hopper-shaped transitions;
2. the wall time of one evaluation round for 75 policies (10 episodes of 1,000 steps each, the
   NumPy actor on MuJoCo's Hopper-v4) spread over the host's CPU cores; every episode is run to its
   full 1,000 steps (reset on a fall), the worst case of a real round;
3. from these, the projected wall time of Table 1: 15 datasets x 5 seeds x 1M steps for EABC
   (K = 10) and for TD3+BC (K = 2), evaluating every 5,000 steps, for each number of seeds per
   program. Today's sweeps vmap the seeds of one setting (5); 25 and 75 assume runs of one
   observation shape packed into one program, which the measurement times but the sweep does not
   yet do.

Output: Markdown tables (what README's GPU section quotes) and, with ``--json PATH``, the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

TABLE1_RUNS = 15 * 5
TABLE1_STEPS = 1_000_000
EVAL_INTERVAL = 5000
OBS_DIM, ACT_DIM = 11, 3  # hopper


def steps_per_s(k: int, seeds: int, steps: int, repeats: int, size: int) -> float:
    """Program steps/s (each step advances every seed once) of ``seeds`` vmapped EABC runs."""
    import dataclasses
    import functools

    import jax
    import jax.numpy as jnp
    from speed import fake_data

    from eabc.agents import eabc
    from eabc.training.chunks import train_chunk_seeds

    data = fake_data(OBS_DIM, ACT_DIM, size)
    config = dataclasses.replace(eabc.PRESETS["eabc"], num_critics=k, confidence_level=0.5)
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    states = jax.vmap(lambda key: eabc.init(key, OBS_DIM, ACT_DIM, config))(keys)
    update = functools.partial(eabc.update, config=config, max_action=1.0)
    loop_keys = jax.random.split(jax.random.PRNGKey(1), seeds)
    states, loop_keys, _ = train_chunk_seeds(
        states, loop_keys, data, update, 256, steps, config.policy_freq, int(states.step[0])
    )
    jax.block_until_ready(states)  # compiled and warm
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        states, loop_keys, metrics = train_chunk_seeds(
            states, loop_keys, data, update, 256, steps, config.policy_freq, int(states.step[0])
        )
        jax.block_until_ready((states, metrics))
        rates.append(steps / (time.perf_counter() - start))
    del jnp
    return statistics.median(rates)


def _evaluate_policy(args: tuple[int, int, int]) -> float:
    """One policy's evaluation: ``episodes`` x ``length`` MuJoCo steps with a NumPy actor."""
    seed, episodes, length = args
    import gymnasium as gym
    import numpy as np

    from eabc import networks

    rng = np.random.default_rng(seed)  # PyTorch-style initial weights; the cost is the same
    sizes = (OBS_DIM, 256, 256, ACT_DIM)
    params = {}
    for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        bound = 1 / np.sqrt(fan_in)
        params[f"w{i}"] = rng.uniform(-bound, bound, (fan_in, fan_out)).astype(np.float32)
        params[f"b{i}"] = rng.uniform(-bound, bound, fan_out).astype(np.float32)
    act = networks.numpy_actor(params, 1.0)
    env = gym.make("Hopper-v4")
    start = time.perf_counter()
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed * 1000 + episode)
        for _ in range(length):
            obs, _, terminated, truncated, _ = env.step(act(np.asarray(obs, np.float32)))
            if terminated or truncated:
                obs, _ = env.reset()
    return time.perf_counter() - start


def evaluation_round(policies: int, episodes: int, length: int) -> dict:
    """Wall time of evaluating ``policies`` policies on the host's CPU cores (one process each)."""
    try:
        import gymnasium  # noqa: F401
        import mujoco  # noqa: F401
    except ImportError as error:
        return {"error": f"{error.name} is not installed: carry its wheels (see gpu.sh)"}
    workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    # Spawned, not forked: this process runs JAX's threads, which a fork would deadlock.
    spawn = multiprocessing.get_context("spawn")
    env = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}  # one core per process
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        return _round(spawn, workers, policies, episodes, length)
    finally:
        for k, v in saved.items():
            os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)


def _round(spawn, workers: int, policies: int, episodes: int, length: int) -> dict:
    with ProcessPoolExecutor(max_workers=workers, mp_context=spawn) as pool:
        list(pool.map(_evaluate_policy, [(0, 1, 10)] * workers))  # start the workers
        start = time.perf_counter()
        per_policy = list(
            pool.map(_evaluate_policy, [(i, episodes, length) for i in range(policies)])
        )
        wall = time.perf_counter() - start
    return {
        "policies": policies,
        "episodes": episodes,
        "episode_steps": length,
        "cpu_workers": workers,
        "wall_s": wall,
        "per_policy_s": statistics.median(per_policy),
    }


def projection(rates: dict[tuple[int, int], float], evaluation: dict, policies: int) -> list[dict]:
    """Table 1's wall time per algorithm and seeds per program: programs run one after another,
    each training ``seeds`` runs for 1M steps, evaluating them every 5,000 steps on the CPUs."""
    rows = []
    per_policy_eval = evaluation.get("wall_s", math.nan) / policies
    for (k, seeds), rate in sorted(rates.items()):
        programs = math.ceil(TABLE1_RUNS / seeds)
        train = TABLE1_STEPS / rate
        evals = TABLE1_STEPS // EVAL_INTERVAL * per_policy_eval * seeds
        rows.append(
            {
                "algorithm": "EABC (K = 10)" if k == 10 else f"TD3+BC (K = {k})",
                "k": k,
                "seeds_per_program": seeds,
                "programs": programs,
                "hours": programs * (train + evals) / 3600,
                "train_hours": programs * train / 3600,
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--smoke", action="store_true", help="tiny sizes (a CPU check, ~30 s)")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args()

    import jax
    import machine

    if args.smoke:
        ks, seed_counts, steps, repeats, size = (2,), (2,), 20, 1, 2000
        policies, episodes, length = 2, 1, 50
    else:
        ks, seed_counts, steps, repeats, size = (2, 10), (1, 5, 25, 75), 500, 3, 1_000_000
        policies, episodes, length = 75, 10, 1000
    device = jax.devices()[0]
    print(machine.host_line())
    print(f"device: {device.platform} {device.device_kind}; JAX {jax.__version__}\n")

    rates = {}
    print("| K | seeds in one program | program steps/s | seed-steps/s |")
    print("|---|---|---|---|")
    for k in ks:
        for seeds in seed_counts:
            rates[(k, seeds)] = steps_per_s(k, seeds, steps, repeats, size)
            print(f"| {k} | {seeds} | {rates[(k, seeds)]:.1f} | {rates[(k, seeds)] * seeds:.0f} |")
            sys.stdout.flush()

    evaluation = evaluation_round(policies, episodes, length)
    print()
    if "error" in evaluation:
        print(f"evaluation round: not measured ({evaluation['error']})")
    else:
        print(
            f"evaluation round: {policies} policies x {episodes} episodes x {length} steps on "
            f"{evaluation['cpu_workers']} CPU processes: {evaluation['wall_s']:.1f} s "
            f"({evaluation['per_policy_s']:.2f} s per policy in its process)"
        )
    rows = projection(rates, evaluation, policies)
    print(
        f"\nTable 1 projected ({TABLE1_RUNS} runs x {TABLE1_STEPS:,} steps per algorithm, "
        f"evaluations every {EVAL_INTERVAL:,} steps):\n"
    )
    print("| algorithm | seeds per program | programs | hours (training only) |")
    print("|---|---|---|---|")
    for row in rows:
        hours = "n/a" if math.isnan(row["hours"]) else f"{row['hours']:.1f}"
        print(
            f"| {row['algorithm']} | {row['seeds_per_program']} | {row['programs']} | "
            f"{hours} ({row['train_hours']:.1f}) |"
        )
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {
                    "host": machine.host_line(),
                    "device": f"{device.platform} {device.device_kind}",
                    "steps_per_s": [
                        {"k": k, "seeds": s, "program_steps_per_s": r}
                        for (k, s), r in rates.items()
                    ],
                    "evaluation": evaluation,
                    "projection": rows,
                },
                indent=2,
            )
        )


if __name__ == "__main__":
    main()
