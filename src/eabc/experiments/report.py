"""The paper's tables and figures from experiment results, and aggregate statistics with CIs.

Inputs are the two frames of the results store (:mod:`eabc.experiments.results`): ``runs``, one row
per training run (``run_id, dataset, algo, variant, seed, num_critics, confidence_level, pessimism,
status, steps, wall_time_s, steps_per_s, final_score``), and ``evaluations``, one row per evaluation
(``run_id, step, score``). A run's *label* is its algorithm plus its variant (``eabc``, ``eabc K=5``).

- Table 1 / 6: :func:`score_table` and its renderers :func:`to_markdown`, :func:`to_html`,
  :func:`to_latex` (mean +- std over seeds of each run's final score; best mean per row in bold).
- Figure 1: :func:`plot_learning_curves`; Figures 2-4: :func:`plot_ablation`; Figure 5:
  :func:`plot_runtime`.
- Statistics that show the uncertainty (Agarwal et al., 2021, "Deep RL at the edge of the
  statistical precipice", the ``rliable`` library, re-implemented in NumPy): :func:`iqm`,
  :func:`stratified_bootstrap_ci`, :func:`aggregate_table`, :func:`performance_profile`.
- :func:`write_report` writes all of it, plus a ``report.md`` that shows everything in one file.

A *score matrix* is either a 2-D array ``[runs_per_task, tasks]`` or a list of 1-D arrays, one per
task, which allows tasks with different numbers of seeds.
"""

from __future__ import annotations

import html
import math
import re
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from eabc.data import tasks

ENV_ORDER = ("hopper", "halfcheetah", "walker2d")
KIND_ORDER = ("random", "medium", "medium-replay", "medium-expert", "expert")
ALGO_ORDER = ("bc", "td3", "td3bc", "cql", "iql", "wpc", "sac-n", "edac", "edac-10", "eabc")
"""Table 1's column order, then Table 6's; unknown algorithms go just before EABC."""
ABLATION_PARAMETERS = ("num_critics", "confidence_level", "pessimism")
PESSIMISM_ORDER = ("mean-std", "min", "min2")
PAPER_DEFAULTS = {"num_critics": 10.0, "pessimism": "mean-std"}
"""EABC's defaults (p comes from Table 3 per dataset): what an ablation holds fixed."""
AVERAGE = "Average"

ScoreMatrix = np.ndarray | Sequence[Sequence[float]]


# ----------------------------------------------------------------------------------------------
# Labels and ordering


def algo_label(algo: str, variant: str | None = "") -> str:
    """``algo`` plus its variant when it has one, e.g. ``eabc K=5``."""
    variant = "" if _missing(variant) else str(variant).strip()
    return f"{algo} {variant}" if variant else str(algo)


def dataset_sort_key(name: str) -> tuple:
    """Hopper, HalfCheetah, Walker2d, then other environments; random ... expert within each."""
    task = tasks.parse_task(name)
    env, _, kind = name.partition("-") if task is None else (task[0], "", task[1])
    env_rank = ENV_ORDER.index(env) if env in ENV_ORDER else len(ENV_ORDER)
    kind_rank = KIND_ORDER.index(kind) if kind in KIND_ORDER else len(KIND_ORDER)
    return (env_rank, env, kind_rank, kind, name)


def _natural_key(text: str) -> tuple:
    """Numbers compare as numbers, so ``K=5`` comes before ``K=10``."""
    parts = re.split(r"(-?\d+(?:\.\d+)?)", text)
    return tuple((0, float(p), "") if i % 2 else (1, 0.0, p) for i, p in enumerate(parts) if p)


def _label_key(algo: str, variant: str) -> tuple:
    rank = ALGO_ORDER.index(algo) if algo in ALGO_ORDER else ALGO_ORDER.index("eabc") - 0.5
    return (rank, algo, variant != "", _natural_key(variant))


def _missing(value) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def _labelled(runs: pd.DataFrame) -> pd.DataFrame:
    _require(runs, ("run_id", "dataset", "algo", "seed"), "runs")
    if runs.empty:
        raise ValueError("there are no runs to report on")
    runs = runs.copy()
    variant = runs["variant"] if "variant" in runs else pd.Series("", index=runs.index)
    runs["variant"] = ["" if _missing(v) else str(v).strip() for v in variant]
    runs["label"] = [algo_label(a, v) for a, v in zip(runs["algo"], runs["variant"])]
    return runs


def _labels(runs: pd.DataFrame) -> list[str]:
    pairs = runs[["algo", "variant", "label"]].drop_duplicates("label")
    ordered = sorted(pairs.itertuples(index=False), key=lambda r: _label_key(r.algo, r.variant))
    return [r.label for r in ordered]


def _datasets(runs: pd.DataFrame) -> list[str]:
    return sorted(runs["dataset"].unique(), key=dataset_sort_key)


def _require(frame: pd.DataFrame, columns: Sequence[str], name: str) -> None:
    missing = [c for c in columns if c not in frame.columns]
    if missing:
        raise ValueError(f"{name} lacks column(s) {missing}; it has {list(frame.columns)}")


# ----------------------------------------------------------------------------------------------
# Table 1


def score_table(runs: pd.DataFrame, metric: str = "final_score") -> pd.DataFrame:
    """Mean and std over seeds of ``metric`` per dataset (rows) and algorithm label (columns).

    Columns are a MultiIndex ``(label, stat)`` with ``stat`` in ``mean``, ``std`` (sample std,
    ddof 1, NaN with one seed) and ``runs`` (runs with a finite value); e.g.
    ``table.xs("mean", axis=1, level="stat")`` is the frame of means. Runs whose value is NaN are
    left out. The last row, ``Average``, holds the mean of the per-dataset means and of the
    per-dataset stds (the paper's "average standard deviation"), each over the datasets where that
    column has a value, and the total number of runs.
    """
    _require(runs, (metric,), "runs")
    runs = _labelled(runs)
    labels, datasets = _labels(runs), _datasets(runs)
    valid = runs[np.isfinite(runs[metric].astype(float))]
    stats = valid.groupby(["dataset", "label"])[metric].agg(["mean", "std", "count"])
    frames = {}
    for stat, column in (("mean", "mean"), ("std", "std"), ("runs", "count")):
        frame = stats[column].unstack("label").reindex(index=datasets, columns=labels)
        frame = frame.astype(float)
        if stat == "runs":
            frame = frame.fillna(0)
        summary = frame.sum(axis=0) if stat == "runs" else frame.mean(axis=0, skipna=True)
        frames[stat] = pd.concat([frame, summary.to_frame(AVERAGE).T])
    table = pd.concat(frames, axis=1, names=["stat", "label"]).swaplevel(axis=1)
    table = table.reindex(columns=pd.MultiIndex.from_product([labels, list(frames)]))
    table.columns.names = ["label", "stat"]
    table.index.name = "dataset"
    return table


def _cells(table: pd.DataFrame, pm: str, missing: str) -> list[tuple[str, list[tuple[str, bool]]]]:
    """Each row's name and its cells as ``(text, is_best)``; best = highest mean as displayed."""
    mean = table.xs("mean", axis=1, level="stat")
    std = table.xs("std", axis=1, level="stat")
    rows = []
    for name in mean.index:
        shown = {c: float(f"{mean.at[name, c]:.1f}") for c in mean.columns}
        finite = [v for v in shown.values() if math.isfinite(v)]
        best = max(finite) if finite else math.nan
        cells = []
        for column in mean.columns:
            m, s = mean.at[name, column], std.at[name, column]
            if not math.isfinite(m):
                cells.append((missing, False))
                continue
            text = f"{m:.1f}" + (f" {pm} {s:.1f}" if math.isfinite(s) else "")
            cells.append((text, shown[column] == best))
        rows.append((str(name), cells))
    return rows


def _columns(table: pd.DataFrame) -> list[str]:
    return [str(c) for c in table.columns.get_level_values("label").unique()]


def to_markdown(table: pd.DataFrame) -> str:
    """A Markdown table of ``mean ± std`` (one decimal), the best mean of each row in bold."""
    escape = lambda text: text.replace("|", "\\|")
    lines = [
        "| " + " | ".join(["Dataset", *map(escape, _columns(table))]) + " |",
        "|" + "---|" + ":---:|" * len(_columns(table)),
    ]
    for name, cells in _cells(table, "±", "–"):
        texts = [f"**{t}**" if best else t for t, best in cells]
        lines.append("| " + " | ".join([escape(name), *texts]) + " |")
    return "\n".join(lines) + "\n"


def to_html(table: pd.DataFrame) -> str:
    """An HTML ``<table>`` of ``mean ± std``, the best mean of each row in ``<b>``."""
    head = "".join(f"<th>{html.escape(c)}</th>" for c in ["Dataset", *_columns(table)])
    body = []
    for name, cells in _cells(table, "&plusmn;", "&ndash;"):
        tds = "".join(f"<td><b>{t}</b></td>" if best else f"<td>{t}</td>" for t, best in cells)
        body.append(f"    <tr><th>{html.escape(name)}</th>{tds}</tr>")
    return "\n".join(
        ['<table class="scores">', f"  <thead><tr>{head}</tr></thead>", "  <tbody>", *body]
        + ["  </tbody>", "</table>"]
    )


def _latex_escape(text: str) -> str:
    special = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#"}
    special |= {"_": r"\_", "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\^{}"}
    return "".join(special.get(ch, ch) for ch in text)


def to_latex(table: pd.DataFrame) -> str:
    """A booktabs ``tabular`` of ``mean $\\pm$ std``, the best mean of each row in ``\\textbf``."""
    columns = _columns(table)
    lines = [
        "% needs \\usepackage{booktabs}",
        "\\begin{tabular}{l" + "c" * len(columns) + "}",
        "\\toprule",
        " & ".join(["Dataset", *map(_latex_escape, columns)]) + " \\\\",
        "\\midrule",
    ]
    for name, cells in _cells(table, "$\\pm$", "--"):
        if name == AVERAGE:
            lines.append("\\midrule")
        texts = [f"\\textbf{{{t}}}" if best else t for t, best in cells]
        lines.append(" & ".join([_latex_escape(name), *texts]) + " \\\\")
    return "\n".join([*lines, "\\bottomrule", "\\end{tabular}"]) + "\n"


# ----------------------------------------------------------------------------------------------
# Figures 1-5


def _new_figure(panels: int, panel_size=(4.0, 3.0), bottom: float = 0.6, top: float = 0.6):
    """A figure on the Agg canvas (no pyplot, so no global state), and its axes.

    Margins are fixed in inches (``bottom``, ``top``) rather than found by ``tight_layout``, which
    would draw every figure twice.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415
    from matplotlib.figure import Figure  # noqa: PLC0415

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
    from matplotlib import colormaps  # noqa: PLC0415

    cmap = colormaps["tab10" if len(keys) <= 10 else "tab20"]
    return {key: cmap(i % cmap.N) for i, key in enumerate(keys)}


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path


def _curve_stats(runs: pd.DataFrame, evaluations: pd.DataFrame, by: str) -> pd.DataFrame:
    """Mean and std over seeds of the score at each step, per ``(dataset, by)``."""
    _require(evaluations, ("run_id", "step", "score"), "evaluations")
    merged = evaluations[["run_id", "step", "score"]].merge(
        runs[["run_id", "dataset", by]], on="run_id"
    )
    merged = merged[np.isfinite(merged["score"].astype(float))]
    per_run = merged.groupby(["dataset", by, "run_id", "step"], as_index=False)["score"].mean()
    stats = per_run.groupby(["dataset", by, "step"])["score"].agg(["mean", "std", "count"])
    return stats.reset_index().fillna({"std": 0.0})


def _plot_curves(stats: pd.DataFrame, by: str, keys: list[str], path, title: str) -> Path:
    from matplotlib.ticker import EngFormatter  # noqa: PLC0415

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
            (handles[key],) = ax.plot(x, m, color=colors[key], label=key, lw=1.5)
            ax.fill_between(x, m - s, m + s, color=colors[key], alpha=0.2, lw=0)
        ax.set_title(dataset)
        ax.set_xlabel("gradient steps")
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))  # 500k, 1M
        ax.set_ylabel("normalised score")
        ax.grid(alpha=0.3)
    if not datasets:
        axes[0].set_visible(True)
        axes[0].text(0.5, 0.5, "no evaluations", ha="center", va="center")
        axes[0].set_axis_off()
    ordered = [k for k in keys if k in handles]
    if ordered:
        fig.legend(
            [handles[k] for k in ordered], ordered, loc="lower center", ncol=min(6, len(ordered))
        )
    fig.suptitle(title)
    return _save(fig, path)


def plot_learning_curves(runs: pd.DataFrame, evaluations: pd.DataFrame, path: str | Path) -> Path:
    """Figure 1: per dataset, the score of each algorithm label over gradient steps.

    The line is the mean over seeds, the band +-1 std over seeds (ddof 1; none with one seed).
    """
    runs = _labelled(runs)
    stats = _curve_stats(runs, evaluations, "label")
    title = "Learning curves: mean ± 1 std over seeds"
    return _plot_curves(stats, "label", _labels(runs), path, title)


def _value_key(value):
    """A hashable, comparable form of a setting (NaN/None -> None, floats rounded)."""
    if _missing(value):
        return None
    return round(float(value), 9) if isinstance(value, int | float | np.number) else str(value)


def _value_label(parameter: str, value) -> str:
    if value is None:
        return "none"
    if parameter == "num_critics":
        return f"K={value:g}"
    if parameter == "confidence_level":
        return f"p={value:g}"
    return str(value)


def _value_sort(parameter: str, value) -> tuple:
    if parameter == "pessimism" and value in PESSIMISM_ORDER:
        return (0, PESSIMISM_ORDER.index(value), "")
    if isinstance(value, float):
        return (0, value, "")
    return (1, 0, str(value))


def _reference(group: pd.DataFrame, other: str, dataset: str):
    """The value an ablation holds ``other`` at: the default runs', else the paper's, else the mode."""
    default = group[group["variant"] == ""]
    values = [_value_key(v) for v in (default if len(default) else group)[other]]
    paper = PAPER_DEFAULTS.get(other)
    if other == "confidence_level":
        paper = tasks.default_confidence_level(tasks.parse_task(dataset))
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
    _require(runs, ABLATION_PARAMETERS, "runs")
    runs = _labelled(runs)
    sub = runs[runs["algo"] == algo]
    kept = []
    for dataset, group in sub.groupby("dataset"):
        mask = np.ones(len(group), dtype=bool)
        for other in ABLATION_PARAMETERS:
            if other != parameter:
                ref = _reference(group, other, dataset)
                mask &= np.array([_value_key(v) == ref for v in group[other]])
        kept.append(group[mask])
    if not kept:
        return sub.assign(value=pd.Series(dtype=object))
    out = pd.concat(kept)
    out["value"] = [_value_key(v) for v in out[parameter]]
    out = out.sort_values(["variant", "run_id"]).drop_duplicates(["dataset", "value", "seed"])
    return out


def ablation_values(runs: pd.DataFrame, parameter: str, algo: str = "eabc") -> list:
    """The values of ``parameter`` that :func:`plot_ablation` would compare, in order."""
    values = set(_ablation_runs(runs, parameter, algo)["value"])
    return sorted(values, key=lambda v: _value_sort(parameter, v))


def plot_ablation(
    runs: pd.DataFrame,
    evaluations: pd.DataFrame,
    parameter: str,
    path: str | Path,
    algo: str = "eabc",
) -> Path:
    """Figures 2-4: per dataset, learning curves of ``algo`` for each value of ``parameter``.

    ``parameter`` is ``num_critics``, ``confidence_level`` or ``pessimism``; the other two are held
    fixed (see :func:`ablation_values`). Mean +- 1 std over seeds.
    """
    sub = _ablation_runs(runs, parameter, algo)
    if sub.empty:
        raise ValueError(f"no runs of {algo!r} to plot an ablation of {parameter!r}")
    values = ablation_values(runs, parameter, algo)
    sub = sub.assign(key=[_value_label(parameter, v) for v in sub["value"]])
    stats = _curve_stats(sub, evaluations, "key")
    keys = [_value_label(parameter, v) for v in values]
    return _plot_curves(stats, "key", keys, path, f"Ablation of {parameter} ({algo})")


def runtime_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Hours of wall-clock time per 1M gradient steps (``1e6 / steps_per_s``) per label.

    Columns ``mean``, ``std`` (over runs, all datasets pooled; ddof 1) and ``runs``; runs without a
    positive ``steps_per_s`` are left out.
    """
    _require(runs, ("steps_per_s",), "runs")
    runs = _labelled(runs)
    rate = runs["steps_per_s"].astype(float)
    runs = runs[np.isfinite(rate) & (rate > 0)]
    hours = 1e6 / runs["steps_per_s"].astype(float) / 3600.0
    table = hours.groupby(runs["label"]).agg(["mean", "std", "count"])
    table = table.rename(columns={"count": "runs"})
    return table.reindex([label for label in _labels(runs) if label in table.index])


def _runtime_markdown(table: pd.DataFrame) -> str:
    lines = ["| Algorithm | Runs | Hours per 1M steps |", "|---|---:|:---:|"]
    for label, row in table.iterrows():
        std = 0.0 if math.isnan(row["std"]) else row["std"]
        lines.append(f"| {label} | {int(row['runs'])} | {row['mean']:.2f} ± {std:.2f} |")
    return "\n".join(lines) + "\n"


def plot_runtime(runs: pd.DataFrame, path: str | Path) -> Path:
    """Figure 5: bars of wall-clock time per 1M gradient steps per label, std over runs as errors.

    The unit is hours, or minutes when every bar is under an hour.
    """
    table = runtime_table(runs)
    minutes = len(table) > 0 and table["mean"].max() < 1.0
    scale, unit = (60.0, "minutes") if minutes else (1.0, "hours")
    fig, axes = _new_figure(1, (max(4.0, 0.9 * len(table) + 1.5), 3.0), bottom=0.9, top=0.4)
    ax = axes[0]
    labels = list(table.index)
    means = table["mean"].to_numpy() * scale
    errors = table["std"].fillna(0.0).to_numpy() * scale
    colors = _colors(labels)
    ax.bar(labels, means, yerr=errors, capsize=4, color=[colors[k] for k in labels])
    top = max(means + errors, default=1.0)
    for x, m, e in zip(range(len(labels)), means, errors):
        ax.text(x, m + e + 0.02 * top, f"{m:.2g}", ha="center", va="bottom", fontsize="small")
    ax.set_ylim(0, 1.15 * top)
    ax.set_ylabel(f"wall-clock {unit} per 1M gradient steps")
    ax.set_title("Runtime: mean ± std over runs")
    for tick in ax.get_xticklabels():
        tick.set(rotation=30, ha="right")
    if not labels:
        ax.text(0.5, 0.5, "no runs with a measured speed", ha="center", va="center")
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------
# Aggregate statistics (Agarwal et al., 2021)


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


def task_scores(runs: pd.DataFrame, metric: str = "final_score") -> dict[str, list[np.ndarray]]:
    """Per algorithm label, the finite ``metric`` values of its runs, one array per dataset."""
    runs = _labelled(runs)
    runs = runs[np.isfinite(runs[metric].astype(float))]
    out = {}
    for label in _labels(runs):
        mine = runs[runs["label"] == label]
        out[label] = [
            mine.loc[mine["dataset"] == d, metric].to_numpy(dtype=float) for d in _datasets(mine)
        ]
    return out


def aggregate_table(
    runs: pd.DataFrame,
    metric: str = "final_score",
    reps: int = 2000,
    alpha: float = 0.05,
    seed: int = 0,
) -> pd.DataFrame:
    """Median, IQM, mean and optimality gap per label, each with a stratified-bootstrap CI.

    Columns: ``tasks``, ``runs``, then ``NAME``, ``NAME_low``, ``NAME_high`` for each statistic.
    Each label is aggregated over the datasets it was run on (compare labels with equal ``tasks``).
    """
    rows = {}
    for label, scores in task_scores(runs, metric).items():
        low, high = stratified_bootstrap_ci(scores, _aggregates_batched, reps, alpha, seed, True)
        estimates = [statistic(scores) for statistic in STATISTICS.values()]
        row = {"tasks": len(scores), "runs": sum(s.size for s in scores)}
        for i, (name, estimate) in enumerate(zip(STATISTICS, estimates)):
            row |= {name: estimate, f"{name}_low": low[i], f"{name}_high": high[i]}
        rows[label] = row
    columns = ["tasks", "runs"] + [f"{n}{s}" for n in STATISTICS for s in ("", "_low", "_high")]
    return pd.DataFrame.from_dict(rows, orient="index", columns=columns).rename_axis("label")


def aggregate_to_markdown(table: pd.DataFrame, alpha: float = 0.05) -> str:
    """The aggregate table as Markdown: ``estimate [low, high]`` per statistic."""
    names = {"median": "Median", "iqm": "IQM", "mean": "Mean", "optimality_gap": "Optimality gap"}
    lines = [
        "| Algorithm | Tasks | Runs | " + " | ".join(names.values()) + " |",
        "|---|---:|---:|" + ":---:|" * len(names),
    ]
    for label, row in table.iterrows():
        cells = [f"{row[n]:.1f} [{row[n + '_low']:.1f}, {row[n + '_high']:.1f}]" for n in names]
        lines.append(
            f"| {label} | {int(row['tasks'])} | {int(row['runs'])} | " + " | ".join(cells) + " |"
        )
    note = (
        f"\nPoint estimates with {100 * (1 - alpha):g}% stratified-bootstrap confidence intervals "
        "(Agarwal et al., 2021). Median and mean are over the per-dataset mean scores, IQM over all "
        "runs pooled; a lower optimality gap (mean of max(0, 100 - score)) is better.\n"
    )
    return "\n".join(lines) + "\n" + note


def performance_profile(score_matrix: ScoreMatrix, taus: Sequence[float]) -> np.ndarray:
    """For each ``tau``, the fraction of runs scoring above it, averaged over tasks (rliable)."""
    taus = np.asarray(taus, dtype=float)
    fractions = [(task[:, None] > taus[None, :]).mean(axis=0) for task in _tasks(score_matrix)]
    return np.mean(fractions, axis=0)


def _profile_batched(draws: list[np.ndarray], taus: np.ndarray) -> np.ndarray:
    """:func:`performance_profile` of each resample: ``[reps, len(taus)]``."""
    return np.mean([(d[:, :, None] > taus).mean(axis=1) for d in draws], axis=0)


def plot_performance_profiles(
    runs: pd.DataFrame,
    path: str | Path,
    metric: str = "final_score",
    taus: Sequence[float] | None = None,
    reps: int = 2000,
    seed: int = 0,
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
        ax.step(taus, profile, where="post", color=colors[label], label=label)
        ax.fill_between(taus, low, high, step="post", color=colors[label], alpha=0.2, lw=0)
    ax.set_xlabel("normalised score τ")
    ax.set_ylabel("fraction of runs with score > τ")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.set_title("Performance profiles (95% stratified-bootstrap CIs)")
    if scores:
        ax.legend(fontsize="small")
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------
# The report


def _ablation_algo(runs: pd.DataFrame, parameter: str) -> str | None:
    """EABC if its runs vary ``parameter``, else the first algorithm whose runs do, else None."""
    if any(column not in runs for column in ABLATION_PARAMETERS):
        return None
    algos = sorted(runs["algo"].unique(), key=lambda a: (a != "eabc", a))
    return next((a for a in algos if len(ablation_values(runs, parameter, a)) > 1), None)


def write_report(
    runs: pd.DataFrame, evaluations: pd.DataFrame, out_dir: str | Path
) -> dict[str, Path]:
    """Every table and figure into ``out_dir``, and ``report.md`` that shows them all.

    Writes ``table.{md,html,tex}``, ``aggregate.md``, ``curves.png``, ``profiles.png``,
    ``runtime.png``, ``ablation_PARAMETER.png`` for each parameter that some algorithm's runs vary
    (EABC's first) and ``report.md``. Returns the paths by file name.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}

    def write(name: str, text: str) -> None:
        paths[name] = out / name
        paths[name].write_text(text, encoding="utf-8")

    table = score_table(runs)
    write("table.md", to_markdown(table))
    write("table.html", to_html(table) + "\n")
    write("table.tex", to_latex(table))
    aggregate = aggregate_to_markdown(aggregate_table(runs))
    write("aggregate.md", aggregate)
    paths["curves.png"] = plot_learning_curves(runs, evaluations, out / "curves.png")
    paths["profiles.png"] = plot_performance_profiles(runs, out / "profiles.png")
    ablations = []
    for parameter in ABLATION_PARAMETERS:
        algo = _ablation_algo(runs, parameter)
        if algo is not None:
            name = f"ablation_{parameter}.png"
            paths[name] = plot_ablation(runs, evaluations, parameter, out / name, algo)
            ablations.append(f"### {parameter} ({algo})\n\n![{parameter}]({name})\n")
    paths["runtime.png"] = plot_runtime(runs, out / "runtime.png")

    status = runs["status"] if "status" in runs else pd.Series("done", index=runs.index)
    partial = runs[status == "partial"]
    sections = [
        "# Experiment report\n",
        f"{len(runs)} runs ({len(runs) - len(partial)} done, {len(partial)} partial) of "
        f"{runs['algo'].nunique()} algorithms on {runs['dataset'].nunique()} datasets.\n",
    ]
    if len(partial):
        steps = partial["steps"] if "steps" in partial else pd.Series("?", index=partial.index)
        listed = ", ".join(f"`{r}` ({s} steps)" for r, s in zip(partial["run_id"], steps))
        sections.append(f"Partial runs, scored on their evaluations so far: {listed}.\n")
    sections += [
        "## Scores (Table 1)\n",
        "D4RL-normalised score of each run (mean of its last 10 evaluations): mean ± std over "
        "seeds; best mean per row in bold; the Average row averages the per-dataset means and "
        "stds. Also as [HTML](table.html) and [LaTeX](table.tex).\n",
        to_markdown(table),
        "## Aggregate statistics\n",
        aggregate,
        "![Performance profiles](profiles.png)\n",
        "## Learning curves (Figure 1)\n",
        "![Learning curves](curves.png)\n",
        *(["## Ablations (Figures 2-4)\n", *ablations] if ablations else []),
        "## Runtime (Figure 5)\n",
        _runtime_markdown(runtime_table(runs)),
        "![Runtime](runtime.png)\n",
    ]
    write("report.md", "\n".join(sections))
    return paths
