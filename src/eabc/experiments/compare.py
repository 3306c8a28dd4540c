"""Every algorithm against one baseline, dataset by dataset: is it above, below, or within noise?

The study (docs/results/study/README.md) asks of a candidate that at 100K steps it is not below
its baseline on any of the five datasets (beyond seed noise: its 95% bootstrap interval reaches
the baseline's mean) and above it on average. :func:`comparison_table` answers exactly that for
every label of a sweep:

- per dataset, the label's mean final score over its seeds and the 95% percentile bootstrap
  interval of that mean (seeds resampled with replacement), against the baseline's mean there;
  the verdict is ``above`` when the interval lies above the baseline's mean, ``below`` when it lies
  under it, ``tie`` when it reaches it, and ``-`` with fewer than :data:`MIN_RUNS` (3) runs: the
  percentile bootstrap of two seeds' mean is little more than the two scores, so two runs both
  below the baseline's mean would read as "below beyond seed noise" (the study's report said so
  of walker2d-medium, 68.7 and 68.9 against 69.4, one of them partial);
- ``Average``: over the datasets both were run on, the label's mean of per-dataset means with a
  stratified-bootstrap interval (each dataset's seeds resampled on their own), against the
  baseline's mean of per-dataset means on the same datasets.

The baseline's own seed noise is not in the interval: the question is whether the candidate's
interval reaches the baseline's point estimate, as the study's criterion puts it.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from eabc.agents import ALGORITHMS
from eabc.experiments.labels import dataset_names, display_name, labelled, ordered_labels
from eabc.experiments.stats import stratified_bootstrap_ci
from eabc.experiments.tables import AVERAGE, MIN_RUNS, MISSING

PUBLISHED, RECOMMENDED = next(
    ((name, a.recommended_variant) for name, a in ALGORITHMS.items() if a.recommended_variant),
    (None, None),
)
"""The first registered algorithm with a recommended variant (``Algorithm.recommended_variant``)
and that variant: the two sides of a report's ``failures.md``."""
COLUMNS = ["runs", "mean", "low", "high", "baseline_runs", "baseline_mean", "difference", "verdict"]


def _verdict(low: float, high: float, reference: float, runs: int) -> str:
    if runs < MIN_RUNS or not np.isfinite(reference):
        return MISSING
    if low > reference:
        return "above"
    if high < reference:
        return "below"
    return "tie"


def _mean_of_means(draws: list[np.ndarray]) -> np.ndarray:
    """Mean over datasets of each dataset's mean, for every bootstrap resample at once."""
    return np.mean([d.mean(axis=-1) for d in draws], axis=0)


def comparison_table(
    runs: pd.DataFrame,
    baseline: str,
    metric: str = "final_score",
    reps: int = 2000,
    alpha: float = 0.05,
    seed: int = 0,
) -> pd.DataFrame:
    """One row per (label, dataset) for every label but ``baseline``, plus each label's
    ``Average`` row; columns :data:`COLUMNS`. Raises ``ValueError`` when no run with a finite
    ``metric`` has the baseline's label (the message lists the labels there are)."""
    runs = labelled(runs)
    every = ordered_labels(runs)
    runs = runs[np.isfinite(pd.to_numeric(runs[metric], errors="coerce"))]
    labels = ordered_labels(runs) if len(runs) else []
    if baseline not in labels:
        if baseline in every:
            why = f"the runs labelled {baseline!r} have no {metric} yet (no evaluation)"
        else:
            why = f"no run is labelled {baseline!r}"
        having = f"; labels with a {metric}: {', '.join(labels)}" if labels else ""
        raise ValueError(f"{why}; the labels are: {', '.join(every)}{having}")
    scores = {
        (label, dataset): group[metric].to_numpy(dtype=float)
        for (label, dataset), group in runs.groupby(["label", "dataset"])
    }
    rows = []
    for label in labels:
        if label == baseline:
            continue
        mine = [d for d in dataset_names(runs) if (label, d) in scores]
        shared = [d for d in mine if (baseline, d) in scores]
        for dataset in mine:
            values = scores[(label, dataset)]
            reference = scores.get((baseline, dataset), np.array([]))
            low, high = stratified_bootstrap_ci(values, np.mean, reps, alpha, seed)
            baseline_mean = reference.mean() if reference.size else np.nan
            rows.append(
                _row(label, dataset, values.mean(), low, high, values.size, values.size,
                     baseline_mean, reference.size)
            )  # fmt: skip
        if len(shared) > 1:
            per_task = [scores[(label, d)] for d in shared]
            low, high = stratified_bootstrap_ci(per_task, _mean_of_means, reps, alpha, seed, True)
            references = [scores[(baseline, d)] for d in shared]
            rows.append(
                _row(label, AVERAGE, np.mean([t.mean() for t in per_task]), low, high,
                     sum(t.size for t in per_task),
                     min(t.size for t in per_task),  # a verdict needs an interval on every dataset
                     np.mean([r.mean() for r in references]), sum(r.size for r in references))
            )  # fmt: skip
    frame = pd.DataFrame(rows, columns=["label", "dataset", *COLUMNS])
    return frame.set_index(["label", "dataset"])


def _row(label, dataset, mean, low, high, runs, fewest, baseline_mean, baseline_runs) -> dict:
    """One row; ``fewest``: the fewest runs behind the interval (under MIN_RUNS: no verdict)."""
    mean, low, high, baseline_mean = (float(v) for v in (mean, low, high, baseline_mean))
    return {
        "label": label,
        "dataset": dataset,
        "runs": int(runs),
        "mean": mean,
        "low": low,
        "high": high,
        "baseline_runs": int(baseline_runs),
        "baseline_mean": baseline_mean,
        "difference": mean - baseline_mean,
        "verdict": _verdict(low, high, baseline_mean, int(fewest)),
    }


def comparison_to_markdown(
    table: pd.DataFrame, baseline: str, alpha: float = 0.05, what: str = "score"
) -> str:
    """The comparison as Markdown, one block per label (``what``: the metric's name)."""
    name = display_name(baseline)
    level = f"{100 * (1 - alpha):g}%"
    lines = [
        f"Each algorithm against {name}: its mean final {what} over seeds with the {level} "
        f"bootstrap interval of that mean, {name}'s mean, the difference, and whether the "
        f"interval lies above {name}'s mean, below it, or reaches it (tie; `–`: fewer than "
        f"{MIN_RUNS} runs, too few for an interval to mean anything). Average: mean of the per-dataset means over the datasets both ran, with a "
        "stratified-bootstrap interval.\n",
        f"| Algorithm | Dataset | Runs | Mean [{level} CI] | {name} (runs) | Difference | Verdict |",
        "|---|---|---:|:---:|:---:|---:|:---:|",
    ]
    for (label, dataset), row in table.iterrows():
        reference = (
            f"{row['baseline_mean']:.1f} ({int(row['baseline_runs'])})"
            if np.isfinite(row["baseline_mean"])
            else MISSING
        )
        difference = f"{row['difference']:+.1f}" if np.isfinite(row["difference"]) else MISSING
        dataset_cell = f"**{dataset}**" if dataset == AVERAGE else dataset
        lines.append(
            f"| {display_name(label)} | {dataset_cell} | {int(row['runs'])} | "
            f"{row['mean']:.1f} [{row['low']:.1f}, {row['high']:.1f}] | {reference} | "
            f"{difference} | {row['verdict']} |"
        )
    return "\n".join(lines) + "\n"


def default_baseline(runs: pd.DataFrame) -> str | None:
    """The first registered algorithm whose description makes it the comparison baseline
    (``Algorithm.comparison_baseline``) and that the sweep ran with its preset, else none."""
    labels = ordered_labels(labelled(runs)) if len(runs) else []
    baselines = (name for name, a in ALGORITHMS.items() if a.comparison_baseline)
    return next((name for name in baselines if name in labels), None)
