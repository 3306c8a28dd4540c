"""The paper's figures from experiment results (see :mod:`eabc.experiments.report` for the frames).

Figure 1: :func:`plot_learning_curves`; Figures 2-4: :func:`plot_ablation`; Figure 5:
:func:`plot_runtime`; and :func:`plot_performance_profiles` (score distributions with bootstrap CIs).

Why one file of about 340 lines: every figure shares the panel layout, colours, legend and saving
helpers at the top, so that all of them look alike in a paper; each figure itself is short.
"""

from __future__ import annotations

import math
import typing
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import EngFormatter

from eabc.agents import ALGORITHMS, get_algorithm
from eabc.experiments.labels import (
    ABLATION_PARAMETERS,
    dataset_sort_key,
    display_name,
    is_missing,
    labelled,
    ordered_labels,
    require_columns,
)
from eabc.experiments.stats import _profile_batched, performance_profile, stratified_bootstrap_ci
from eabc.experiments.tables import runtime_table, task_scores


def _new_figure(panels: int, panel_size=(4.0, 3.0), bottom: float = 0.6, top: float = 0.6):
    """A figure on the Agg canvas (no pyplot, so no global state), and its axes.

    Margins are fixed in inches (``bottom``, ``top``) rather than found by ``tight_layout``, which
    would draw every figure twice.
    """
    cols = min(panels, 3) or 1
    rows = max(math.ceil(panels / cols), 1)
    width, height = panel_size[0] * cols, panel_size[1] * rows + bottom + top
    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    fig.subplots_adjust(
        left=0.75 / width,
        right=1 - 0.2 / width,
        bottom=bottom / height,
        top=1 - top / height,
        wspace=0.35,
        hspace=0.5,
    )
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax in axes[panels:]:
        ax.set_visible(False)
    return fig, axes


def _colors(keys: Sequence[str]) -> dict[str, tuple]:
    cmap = colormaps["tab10" if len(keys) <= 10 else "tab20"]
    return {key: cmap(i % cmap.N) for i, key in enumerate(keys)}


PRINT_DPI = 300
"""PNG resolution: print quality; a PDF or SVG asked for beside a PNG is a vector graphic."""
VECTOR_FORMATS = (".pdf", ".svg")
"""The vector formats a figure can also be written in (each plot function's ``vector``)."""


def legend_columns(labels: list[str], width_inches: float, most: int = 6) -> int:
    """Columns for a figure-wide legend whose entries fit the figure's width: about 11 characters
    per inch at the default font size, plus room for each entry's line sample."""
    widest = max((len(label) for label in labels), default=1) + 6
    fits = int(width_inches * 11 // widest)
    return max(1, min(most, len(labels), fits))


def _save(fig, path: str | Path, vector: Sequence[str] = ()) -> Path:
    """The figure as ``path`` (PNG at print resolution) and in each of the ``vector`` formats
    (``.pdf``, ``.svg``) beside it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=PRINT_DPI, bbox_inches="tight")  # nothing outside the canvas is lost
    unknown = set(vector) - set(VECTOR_FORMATS)
    if unknown:
        raise ValueError(f"no vector format {sorted(unknown)}; there are {list(VECTOR_FORMATS)}")
    for suffix in vector:
        undated = {"Date": None} if suffix == ".svg" else {"CreationDate": None}  # reproducible
        fig.savefig(path.with_suffix(suffix), metadata=undated, bbox_inches="tight")
    return path


def _curve_stats(
    runs: pd.DataFrame, evaluations: pd.DataFrame, by: str, curve: str = "score"
) -> pd.DataFrame:
    """Mean and std over seeds of ``curve`` (the score, or the return) at each step, per
    ``(dataset, by)``."""
    require_columns(evaluations, ("run_id", "step", curve), "evaluations")
    merged = evaluations[["run_id", "step", curve]].merge(
        runs[["run_id", "dataset", by]], on="run_id"
    )
    merged = merged[np.isfinite(merged[curve].astype(float))]
    per_run = merged.groupby(["dataset", by, "run_id", "step"], as_index=False)[curve].mean()
    stats = per_run.groupby(["dataset", by, "step"])[curve].agg(["mean", "std", "count"])
    return stats.reset_index().fillna({"std": 0.0})


def band_text(stats: pd.DataFrame, by: str) -> str:
    """What the curves of ``stats`` (from :func:`_curve_stats`) show, by how many seeds each
    rests on: ``mean ± 1 std over 3 seeds``, ``one seed each (no band)``, or with a mix
    ``mean ± 1 std over 1-3 seeds (one seed: no band)``."""
    seeds = stats.groupby(["dataset", by])["count"].max() if len(stats) else pd.Series([0])
    low, high = int(seeds.min()), int(seeds.max())
    if high <= 1:
        return "one seed each (no band)"
    if low == high:
        return f"mean ± 1 std over {high} seeds"
    also = " (one seed: no band)" if low == 1 else ""
    return f"mean ± 1 std over {low}-{high} seeds{also}"


def _plot_curves(
    stats: pd.DataFrame,
    by: str,
    keys: list[str],
    path,
    title: str,
    names=str,
    ylabel: str = "normalised score",
    vector: Sequence[str] = (),
) -> Path:
    datasets = sorted(stats["dataset"].unique(), key=dataset_sort_key)
    fig, axes = _new_figure(len(datasets), bottom=0.7 + 0.3 * math.ceil(len(keys) / 6))
    colors, handles = _colors(keys), {}
    for ax, dataset in zip(axes, datasets):
        for key in keys:
            curve = stats[(stats["dataset"] == dataset) & (stats[by] == key)]
            if curve.empty:
                continue
            curve = curve.sort_values("step")
            x, m, s = curve["step"].to_numpy(), curve["mean"].to_numpy(), curve["std"].to_numpy()
            (handles[key],) = ax.plot(x, m, color=colors[key], label=names(key), lw=1.5)
            ax.fill_between(x, m - s, m + s, color=colors[key], alpha=0.2, lw=0)
        ax.set_title(dataset)
        ax.set_xlabel("gradient steps")
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))  # 500k, 1M
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    if not datasets:
        axes[0].set_visible(True)
        axes[0].text(0.5, 0.5, "no evaluations", ha="center", va="center")
        axes[0].set_axis_off()
    ordered = [k for k in keys if k in handles]
    if ordered:
        labels = [names(k) for k in ordered]
        fig.legend(
            [handles[k] for k in ordered],
            labels,
            loc="upper center",
            bbox_to_anchor=(0.5, 0.0),  # below the panels; _save keeps it inside the image
            ncol=legend_columns(labels, fig.get_figwidth()),
        )
    fig.suptitle(title)
    return _save(fig, path, vector)


def plot_learning_curves(
    runs: pd.DataFrame,
    evaluations: pd.DataFrame,
    path: str | Path,
    curve: str = "score",
    ylabel: str = "normalised score",
    vector: Sequence[str] = (),
) -> Path:
    """Figure 1: per dataset, the score (or ``curve``: ``return_mean``) of each algorithm label
    over gradient steps; ``vector``: the formats (``.pdf``, ``.svg``) written beside the PNG.

    The line is the mean over seeds, the band +-1 std over seeds (ddof 1; none with one seed);
    the title says over how many (:func:`band_text`).
    """
    runs = labelled(runs)
    stats = _curve_stats(runs, evaluations, "label", curve)
    title = f"Learning curves: {band_text(stats, 'label')}"
    labels = ordered_labels(runs)
    return _plot_curves(
        stats, "label", labels, path, title, names=display_name, ylabel=ylabel, vector=vector
    )


def _value_key(value):
    """A hashable, comparable form of a setting (NaN/None -> None, floats rounded)."""
    if is_missing(value):
        return None
    return round(float(value), 9) if isinstance(value, int | float | np.number) else str(value)


def _value_label(parameter: str, value, algo: str) -> str:
    if value is None:
        return "none"
    short = get_algorithm(algo).short_names.get(parameter) if algo in ALGORITHMS else None
    if short is not None and isinstance(value, int | float):
        return f"{short}={value:g}"
    return str(value)


def _value_sort(parameter: str, value, algo: str) -> tuple:
    choices = _choices(algo, parameter)
    if value in choices:  # a Literal setting: the order its declaration gives
        return (0, choices.index(value), "")
    if isinstance(value, float):
        return (0, value, "")
    return (1, 0, str(value))


def _choices(algo: str, parameter: str) -> tuple:
    if algo not in ALGORITHMS or parameter not in get_algorithm(algo).settings():
        return ()
    hint = typing.get_type_hints(type(get_algorithm(algo).preset)).get(parameter)
    args = typing.get_args(hint)
    return args if typing.get_origin(hint) is typing.Literal else ()


def _paper_value(algo: str, other: str, dataset: str):
    """What the algorithm's own preset gives ``other`` on ``dataset`` (resolved for it: the
    paper's default there)."""
    if algo not in ALGORITHMS:
        return None
    algorithm = get_algorithm(algo)
    try:
        config = algorithm.resolved(algorithm.preset, dataset, 0, set())
    except ValueError:  # no paper default for this dataset
        config = algorithm.preset
    return getattr(config, other, None)


def _reference(group: pd.DataFrame, other: str, dataset: str, algo: str):
    """The value an ablation holds ``other`` at: the default runs', else the algorithm's preset
    (resolved for the dataset), else the mode."""
    default = group[group["variant"] == ""]
    values = [_value_key(v) for v in (default if len(default) else group)[other]]
    paper = _paper_value(algo, other, dataset)
    if not len(default) and _value_key(paper) in values:
        return _value_key(paper)
    return Counter(values).most_common(1)[0][0]


def _ablation_runs(runs: pd.DataFrame, parameter: str, algo: str) -> pd.DataFrame:
    """Runs of ``algo`` that differ from the reference setting in ``parameter`` only.

    The other ablation settings are held at the dataset's default runs' values (variant ``""``),
    else at the paper's defaults if such runs exist, else at their most common value. Identical
    settings reached through different variants (``""`` and ``K=10``) are counted once per seed.
    """
    if parameter not in ABLATION_PARAMETERS:
        raise ValueError(f"unknown ablation parameter {parameter!r}; use {ABLATION_PARAMETERS}")
    require_columns(runs, ABLATION_PARAMETERS, "runs")
    runs = labelled(runs)
    sub = runs[runs["algo"] == algo]
    kept = []
    for dataset, group in sub.groupby("dataset"):
        mask = np.ones(len(group), dtype=bool)
        for other in ABLATION_PARAMETERS:
            if other != parameter:
                ref = _reference(group, other, dataset, algo)
                mask &= np.array([_value_key(v) == ref for v in group[other]])
        kept.append(group[mask])
    if not kept:
        return sub.assign(value=pd.Series(dtype=object))
    out = pd.concat(kept)
    out["value"] = [_value_key(v) for v in out[parameter]]
    out = out.sort_values(["variant", "run_id"]).drop_duplicates(["dataset", "value", "seed"])
    return out


def default_ablation_algo(parameter: str) -> str:
    """The first registered algorithm whose reports compare ``parameter``
    (``Algorithm.report_settings``)."""
    for name, algorithm in ALGORITHMS.items():
        if parameter in algorithm.report_settings:
            return name
    raise ValueError(f"unknown ablation parameter {parameter!r}; use {ABLATION_PARAMETERS}")


def ablation_values(runs: pd.DataFrame, parameter: str, algo: str | None = None) -> list:
    """The values of ``parameter`` that :func:`plot_ablation` would compare, in order (``algo``
    None: :func:`default_ablation_algo`)."""
    algo = algo or default_ablation_algo(parameter)
    values = set(_ablation_runs(runs, parameter, algo)["value"])
    return sorted(values, key=lambda v: _value_sort(parameter, v, algo))


def plot_ablation(
    runs: pd.DataFrame,
    evaluations: pd.DataFrame,
    parameter: str,
    path: str | Path,
    algo: str | None = None,
    curve: str = "score",
    ylabel: str = "normalised score",
    vector: Sequence[str] = (),
) -> Path:
    """Figures 2-4: per dataset, learning curves of ``algo`` (None: :func:`default_ablation_algo`)
    for each value of ``parameter``.

    ``parameter`` is ``num_critics``, ``confidence_level`` or ``pessimism``; the other two are held
    fixed (see :func:`ablation_values`). Mean +- 1 std over seeds, the title says how many.
    """
    algo = algo or default_ablation_algo(parameter)
    sub = _ablation_runs(runs, parameter, algo)
    if sub.empty:
        raise ValueError(f"no runs of {algo!r} to plot an ablation of {parameter!r}")
    values = ablation_values(runs, parameter, algo)
    sub = sub.assign(key=[_value_label(parameter, v, algo) for v in sub["value"]])
    stats = _curve_stats(sub, evaluations, "key", curve)
    keys = [_value_label(parameter, v, algo) for v in values]
    title = f"Ablation of {parameter} ({display_name(algo)})\n{band_text(stats, 'key')}"
    return _plot_curves(stats, "key", keys, path, title, ylabel=ylabel, vector=vector)


def plot_runtime(runs: pd.DataFrame, path: str | Path, vector: Sequence[str] = ()) -> Path:
    """Figure 5: bars of wall-clock time per 1M gradient steps per label, std over runs as errors.

    The unit is hours, or minutes when every bar is under an hour.
    """
    table = runtime_table(runs)
    minutes = len(table) > 0 and table["mean"].max() < 1.0
    scale, unit = (60.0, "minutes") if minutes else (1.0, "hours")
    fig, axes = _new_figure(1, (max(4.0, 0.9 * len(table) + 1.5), 3.0), bottom=0.9, top=0.6)
    ax = axes[0]
    labels = list(table.index)
    means = table["mean"].to_numpy() * scale
    errors = table["std"].fillna(0.0).to_numpy() * scale
    colors = _colors(labels)
    ax.bar(
        [display_name(k) for k in labels],
        means,
        yerr=errors,
        capsize=4,
        color=[colors[k] for k in labels],
    )
    top = max(means + errors, default=1.0)
    for x, m, e in zip(range(len(labels)), means, errors):
        ax.text(x, m + e + 0.02 * top, f"{m:.2g}", ha="center", va="bottom", fontsize="small")
    ax.set_ylim(0, 1.15 * top)
    ax.set_ylabel(f"{unit} per 1M gradient steps")
    ax.set_title("Runtime: mean ± std over runs\n(training chunks' steps/s)", fontsize="medium")
    for tick in ax.get_xticklabels():
        tick.set(rotation=30, ha="right")
    if not labels:
        ax.text(0.5, 0.5, "no runs with a measured speed", ha="center", va="center")
    return _save(fig, path, vector)


def plot_performance_profiles(
    runs: pd.DataFrame,
    path: str | Path,
    metric: str = "final_score",
    taus: Sequence[float] | None = None,
    reps: int = 2000,
    seed: int = 0,
    vector: Sequence[str] = (),
) -> Path:
    """Score distributions: per label, the fraction of runs above each score, with a 95% CI band."""
    scores = task_scores(runs, metric)
    if taus is None:
        pooled = np.concatenate([np.concatenate(s) for s in scores.values()] or [np.zeros(1)])
        taus = np.linspace(min(0.0, pooled.min()), max(100.0, pooled.max()), 101)
    taus = np.asarray(taus, dtype=float)
    fig, axes = _new_figure(1, (5.5, 3.5), bottom=0.6, top=0.4)
    ax, colors = axes[0], _colors(list(scores))
    for label, task_list in scores.items():
        profile = performance_profile(task_list, taus)
        low, high = stratified_bootstrap_ci(
            task_list, lambda draws: _profile_batched(draws, taus), reps, seed=seed, batched=True
        )
        ax.step(taus, profile, where="post", color=colors[label], label=display_name(label))
        ax.fill_between(taus, low, high, step="post", color=colors[label], alpha=0.2, lw=0)
    ax.set_xlabel("normalised score τ")
    ax.set_ylabel("fraction of runs with score > τ")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.set_title("Performance profiles (95% stratified-bootstrap CIs)")
    if scores:
        ax.legend(fontsize="small")
    return _save(fig, path, vector)


def _ablation_algo(runs: pd.DataFrame, parameter: str) -> str | None:
    """The first algorithm in the registry's order whose runs vary ``parameter``, else None."""
    if any(column not in runs for column in ABLATION_PARAMETERS):
        return None
    order = list(ALGORITHMS)
    algos = sorted(runs["algo"].unique(), key=lambda a: (order.index(a) if a in order else 99, a))
    return next((a for a in algos if len(ablation_values(runs, parameter, a)) > 1), None)
