"""Seconds per evaluation (10 episodes of Hopper-v4 by the shipped medium actor): in the training
process one episode after another (what training does with --eval-workers 0), the same episodes
side by side in one process, and a pool of evaluation processes (--eval-workers N), which costs the
training process only the hand-over.

    python benchmarks/evaluation.py [--evaluations 4] [--workers 2]

Every way gives the same returns (checked here); a pool's figure is its throughput once its
workers have started and made their environments.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from eabc.data import zoo
from eabc.data.dataset import Normalizer
from eabc.evaluation import Evaluator, Policy
from eabc.training import eval_pool

ENV_ID, SEED, EPISODES = "Hopper-v4", 100, 10


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--evaluations", type=int, default=4, help="evaluations timed per way")
    parser.add_argument("--workers", type=int, default=2, help="the pool's processes")
    args = parser.parse_args()
    try:
        import machine  # noqa: PLC0415 (beside this script)

        print(machine.host_line())
    except Exception:  # noqa: BLE001 (the host line is a courtesy)
        pass
    actor = zoo.load_actor(zoo.policy_path("hopper", "medium"))
    obs_dim = actor["w0"].shape[0]
    policy = Policy(actor, Normalizer.identity(obs_dim), 1.0, gaussian=True)
    evaluator = Evaluator(ENV_ID, SEED, EPISODES)
    expected = evaluator.returns(policy)
    print(f"{ENV_ID}, {EPISODES} episodes, returns {np.round(expected, 1).tolist()}")

    for name, vectorised in (("one by one, in process", False), ("side by side, in process", True)):
        started = time.perf_counter()
        for _ in range(args.evaluations):
            assert evaluator.returns(policy, vectorised=vectorised) == expected
        seconds = (time.perf_counter() - started) / args.evaluations
        print(f"{name:<34} {seconds:6.2f} s per evaluation")

    normalizer = Normalizer.identity(obs_dim)
    task = eval_pool.Task(
        ENV_ID, SEED, EPISODES, None, None, 0, actor, normalizer.mean, normalizer.std, 1.0, True
    )
    with eval_pool.EvaluationPool(args.workers) as pool:
        warm = [pool.submit(task) for _ in range(args.workers)]  # start the workers, make envs
        for future in warm:
            future.result()
        started = time.perf_counter()
        futures = [pool.submit(task) for _ in range(args.evaluations)]
        handed = (time.perf_counter() - started) / args.evaluations
        for future in futures:
            assert future.result()["return_mean"] == float(np.mean(expected))
        seconds = (time.perf_counter() - started) / args.evaluations
    print(
        f"{f'pool of {args.workers} processes':<34} {seconds:6.2f} s per evaluation (throughput); "
        f"the training process spends {1e3 * handed:.1f} ms handing one over"
    )


if __name__ == "__main__":
    main()
