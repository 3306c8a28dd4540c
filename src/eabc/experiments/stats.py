"""Aggregate statistics that show the uncertainty of RL results, in NumPy.

Agarwal et al., 2021, "Deep RL at the edge of the statistical precipice" (the ``rliable`` library):
the interquartile mean, stratified-bootstrap confidence intervals and performance profiles.

Why not ``rliable`` itself (its release 1.2.0): it needs
``arch < 8``, and arch 7.2 does not import under pandas 3 (``deprecate_kwarg()`` TypeError), while
arch 8 breaks rliable's bootstrap (``random_state=None`` refused); it would also bring seaborn and
absl, and it takes one score matrix of equal runs per task, where a sweep stopped early has ragged
tasks. The methods here are rliable's, on the same definitions (``tests/experiments/test_stats.py`` checks the
IQM against SciPy's trimmed mean, the profile against a hand computation, and that the bootstrap
resamples runs within each task).

A *score matrix* is either a 2-D array ``[runs_per_task, tasks]`` or a list of 1-D arrays, one per
task, which allows tasks with different numbers of seeds.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd

ScoreMatrix = np.ndarray | Sequence[Sequence[float]]


def _layout(scores) -> str:
    """``matrix`` (2-D, ``[runs, tasks]``), ``flat`` (the runs of one task) or ``tasks`` (a list)."""
    if isinstance(scores, pd.DataFrame):
        return "matrix"
    if isinstance(scores, np.ndarray):
        if scores.ndim > 2:
            raise ValueError(f"a score matrix is [runs, tasks]; got shape {scores.shape}")
        return "matrix" if scores.ndim == 2 else "flat"
    return "flat" if all(np.ndim(score) == 0 for score in scores) else "tasks"


def _tasks(scores) -> list[np.ndarray]:
    """A score matrix as one 1-D array per task."""
    layout = _layout(scores)
    if layout == "matrix":
        out = list(np.asarray(scores, dtype=float).T)
    elif layout == "flat":
        out = [np.asarray(scores, dtype=float).ravel()]
    else:
        out = [np.asarray(task, dtype=float).ravel() for task in scores]
    if not out or any(task.size == 0 for task in out):
        raise ValueError("every task of a score matrix needs at least one run")
    if any(not np.all(np.isfinite(task)) for task in out):
        raise ValueError("scores must be finite (leave out the runs without a score)")
    return out


def iqm(scores: ScoreMatrix) -> float:
    """Interquartile mean of the pooled run scores, as ``scipy.stats.trim_mean(x, 0.25)``.

    ``floor(n / 4)`` scores are cut from each end of the sorted scores (so with ``n`` not a multiple
    of 4 a little more than half of them is kept), which is what rliable computes.
    """
    pooled = np.sort(np.concatenate(_tasks(scores)))
    cut = int(0.25 * pooled.size)
    return float(pooled[cut : pooled.size - cut].mean())


def aggregate_mean(scores: ScoreMatrix) -> float:
    """Mean over tasks of the per-task mean score."""
    return float(np.mean([task.mean() for task in _tasks(scores)]))


def aggregate_median(scores: ScoreMatrix) -> float:
    """Median over tasks of the per-task mean score (rliable's aggregate median)."""
    return float(np.median([task.mean() for task in _tasks(scores)]))


def optimality_gap(scores: ScoreMatrix, gamma: float = 100.0) -> float:
    """How far below ``gamma`` (an expert's score) the runs stay: mean of ``max(0, gamma - score)``.

    Averaged over the runs of each task, then over tasks (the pooled mean when seeds are balanced).
    """
    return float(np.mean([np.maximum(0.0, gamma - task).mean() for task in _tasks(scores)]))


def stratified_bootstrap_ci(
    score_matrix: ScoreMatrix,
    statistic: Callable,
    reps: int = 2000,
    alpha: float = 0.05,
    seed: int = 0,
    batched: bool = False,
) -> tuple:
    """Percentile interval of ``statistic`` over stratified bootstrap resamples.

    Each resample draws, independently for each task, as many runs as the task has, with
    replacement from that task's runs. ``statistic`` gets one resample in the input's form (a
    ``[runs, tasks]`` array, a 1-D array for a single task, or a list of per-task arrays) and
    returns a number or a 1-D array. With ``batched=True`` it is called once with every resample,
    with a leading ``reps`` axis on each array, and returns ``[reps]`` or ``[reps, k]`` (much faster).
    Returns ``(low, high)``, the ``alpha / 2`` and ``1 - alpha / 2`` percentiles (floats, or arrays
    when the statistic returns an array).
    """
    if reps < 1 or not 0.0 < alpha < 1.0:
        raise ValueError(f"need reps >= 1 and 0 < alpha < 1; got reps={reps}, alpha={alpha}")
    per_task = _tasks(score_matrix)
    rng = np.random.default_rng(seed)
    draws = [task[rng.integers(0, task.size, size=(reps, task.size))] for task in per_task]
    form = {
        "matrix": lambda arrays, axis: np.stack(arrays, axis=axis),  # [(reps,) runs, tasks]
        "flat": lambda arrays, axis: arrays[0],
        "tasks": lambda arrays, axis: arrays,
    }[_layout(score_matrix)]
    if batched:
        values = np.asarray(statistic(form(draws, 2)), dtype=float)
    else:
        values = np.stack(
            [np.asarray(statistic(form([d[r] for d in draws], 1))) for r in range(reps)]
        )
    low, high = np.percentile(values, [50 * alpha, 100 - 50 * alpha], axis=0)
    return (float(low), float(high)) if np.ndim(low) == 0 else (low, high)


def _aggregates_batched(draws: list[np.ndarray], gamma: float = 100.0) -> np.ndarray:
    """Median, IQM, mean and optimality gap of each resample (``draws``: ``[reps, runs]`` per task)."""
    means = np.stack([d.mean(axis=1) for d in draws], axis=1)
    pooled = np.sort(np.concatenate(draws, axis=1), axis=1)
    cut = int(0.25 * pooled.shape[1])
    iqms = pooled[:, cut : pooled.shape[1] - cut].mean(axis=1)
    gaps = np.stack([np.maximum(0.0, gamma - d).mean(axis=1) for d in draws], axis=1)
    return np.stack([np.median(means, axis=1), iqms, means.mean(axis=1), gaps.mean(axis=1)], 1)


STATISTICS: dict[str, Callable] = {
    "median": aggregate_median,
    "iqm": iqm,
    "mean": aggregate_mean,
    "optimality_gap": optimality_gap,
}


def performance_profile(score_matrix: ScoreMatrix, taus: Sequence[float]) -> np.ndarray:
    """For each ``tau``, the fraction of runs scoring above it, averaged over tasks (rliable)."""
    taus = np.asarray(taus, dtype=float)
    fractions = [(task[:, None] > taus[None, :]).mean(axis=0) for task in _tasks(score_matrix)]
    return np.mean(fractions, axis=0)


def _profile_batched(draws: list[np.ndarray], taus: np.ndarray) -> np.ndarray:
    """:func:`performance_profile` of each resample: ``[reps, len(taus)]``."""
    return np.mean([(d[:, :, None] > taus).mean(axis=1) for d in draws], axis=0)
