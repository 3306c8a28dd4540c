"""Synthetic results as the results store holds them, for the report's, the archive's and
provenance's tests: 2 datasets x 3 algorithms x 3 seeds, plus EABC with K=5."""

from __future__ import annotations

import numpy as np
import pandas as pd

DATASETS = ("walker2d-medium", "hopper-random")  # out of table order on purpose
LEVELS = {"td3bc": 55.0, "iql": 45.0, "eabc": 70.0, "eabc K=5": 62.0}
SEEDS = (0, 1, 2)
STEPS = np.arange(1, 7) * 5000


def make_results(seed: int = 0) -> tuple[pd.DataFrame, pd.DataFrame]:
    """2 datasets x 3 algorithms x 3 seeds, plus EABC with K=5 (an ablation with 2 values of K)."""
    rng = np.random.default_rng(seed)
    settings = {
        "td3bc": ("td3bc", "", 2.0, 1.0, "min", 270.0),
        "iql": ("iql", "", np.nan, np.nan, None, 200.0),
        "eabc": ("eabc", "", 10.0, 0.25, "mean-std", 64.0),
        "eabc K=5": ("eabc", "K=5", 5.0, 0.25, "mean-std", 120.0),
    }
    runs, evaluations = [], []
    for dataset in DATASETS:
        for label, (algo, variant, k, p, pessimism, speed) in settings.items():
            for s in SEEDS:
                run_id = f"{dataset}__{algo}__{variant}__seed{s}"
                curve = LEVELS[label] * (0.5 + STEPS / STEPS[-1] / 2) + rng.normal(0, 4, STEPS.size)
                evaluations += [
                    {"run_id": run_id, "step": int(t), "score": v, "return_mean": 30 * v}
                    for t, v in zip(STEPS, curve)
                ]
                steps_per_s = speed * rng.uniform(0.8, 1.2)
                runs.append(
                    {
                        "run_id": run_id,
                        "dataset": dataset,
                        "algo": algo,
                        "seed": s,
                        "num_critics": k,
                        "confidence_level": p,
                        "pessimism": pessimism,
                        "steps": int(STEPS[-1]),
                        "status": "done",
                        "wall_time_s": STEPS[-1] / steps_per_s,
                        "steps_per_s": steps_per_s,
                        "final_score": LEVELS[label] + rng.normal(0, 5),
                        "variant": variant,
                    }
                )
    return pd.DataFrame(runs), pd.DataFrame(evaluations)
