"""The paper's tables from a sweep's results, and their renderers.

Inputs are the two frames of the results store (:mod:`eabc.experiments.results`): ``runs``, one row
per training run (``run_id, dataset, algo, variant, seed, num_critics, confidence_level, pessimism,
status, steps, wall_time_s, steps_per_s, final_score``), and ``evaluations``, one row per evaluation
(``run_id, step, score``). A run's label is its algorithm plus its variant
(:mod:`eabc.experiments.labels`).

- Table 1 / 6: :func:`score_table` and its renderers :func:`to_markdown`, :func:`to_html`,
  :func:`to_latex` (mean +- std over seeds of each run's final score; best mean per row in bold).
- :func:`runtime_table` (Figure 5's numbers) and :func:`aggregate_table` (median, IQM, mean and
  optimality gap with stratified-bootstrap CIs, from :mod:`eabc.experiments.stats`).
- :func:`stability_table`: where each algorithm's critics fail, dataset by dataset (the study's
  diagnostics).
- :func:`failure_table`: a published rule beside its fix, dataset by dataset: where it fails and
  what the ensemble's spread at the policy's actions was as the runaway began.
"""

from __future__ import annotations

import dataclasses
import html
import math

import numpy as np
import pandas as pd

from eabc import timing
from eabc.experiments.labels import (
    dataset_names,
    dataset_sort_key,
    display_name,
    is_missing,
    labelled,
    ordered_labels,
    require_columns,
)
from eabc.experiments.stats import STATISTICS, _aggregates_batched, stratified_bootstrap_ci

AVERAGE = "Average"
MIN_RUNS = 3
"""Fewer runs per dataset than this and a bootstrap interval or a std says little: flagged."""


@dataclasses.dataclass(frozen=True)
class Metric:
    """What a report's numbers are: each run's final value (a ``runs`` column), the curve it
    comes from (an ``evaluations`` column) and their names in the text."""

    column: str
    curve: str
    name: str
    """A short name for column headers and sentences (``score``, ``return``)."""
    title: str
    """What a table caption says the numbers are."""


MISSING = "–"
"""How every table shows a value that is missing (NaN, None): an en dash."""

SCORE = Metric("final_score", "score", "score", "D4RL-normalised score")
RETURN = Metric(
    "final_return",
    "return_mean",
    "return",
    "Raw return: these runs have no reference scores, so no D4RL-normalised score",
)
"""For runs on data without reference returns (a user's own file): returns as they were."""


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
    require_columns(runs, (metric,), "runs")
    runs = labelled(runs)
    labels, datasets = ordered_labels(runs), dataset_names(runs)
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
    """Each row's name and its cells as ``(text, is_best)``; best = highest mean as displayed.

    In the Average row, a column that lacks some dataset is averaged over fewer datasets, so it
    says over how many (``(3/5)``) and is never marked best."""
    mean = table.xs("mean", axis=1, level="stat")
    std = table.xs("std", axis=1, level="stat")
    datasets = mean.drop(index=AVERAGE, errors="ignore")
    covered = datasets.notna().sum(axis=0)
    rows = []
    for name in mean.index:
        partial = {c for c in mean.columns if name == AVERAGE and covered[c] < len(datasets)}
        shown = {c: float(f"{mean.at[name, c]:.1f}") for c in mean.columns if c not in partial}
        finite = [v for v in shown.values() if math.isfinite(v)]
        best = max(finite) if finite else math.nan
        cells = []
        for column in mean.columns:
            m, s = mean.at[name, column], std.at[name, column]
            if not math.isfinite(m):
                cells.append((missing, False))
                continue
            text = f"{m:.1f}" + (f" {pm} {s:.1f}" if math.isfinite(s) else "")
            if column in partial:
                cells.append((f"{text} ({covered[column]}/{len(datasets)})", False))
                continue
            cells.append((text, shown[column] == best))
        rows.append((str(name), cells))
    return rows


def _columns(table: pd.DataFrame) -> list[str]:
    return [str(c) for c in table.columns.get_level_values("label").unique()]


def to_markdown(table: pd.DataFrame) -> str:
    """A Markdown table of ``mean ± std`` (one decimal), the best mean of each row in bold."""
    escape = lambda text: text.replace("|", "\\|")
    lines = [
        "| " + " | ".join(["Dataset", *(escape(display_name(c)) for c in _columns(table))]) + " |",
        "|" + "---|" + ":---:|" * len(_columns(table)),
    ]
    for name, cells in _cells(table, "±", MISSING):
        texts = [f"**{t}**" if best else t for t, best in cells]
        lines.append("| " + " | ".join([escape(name), *texts]) + " |")
    return "\n".join(lines) + "\n"


def to_html(table: pd.DataFrame) -> str:
    """An HTML ``<table>`` of ``mean ± std``, the best mean of each row in ``<b>``."""
    names = ["Dataset", *map(display_name, _columns(table))]
    head = "".join(f"<th>{html.escape(c)}</th>" for c in names)
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
        " & ".join(["Dataset", *(_latex_escape(display_name(c)) for c in columns)]) + " \\\\",
        "\\midrule",
    ]
    for name, cells in _cells(table, "$\\pm$", "--"):
        if name == AVERAGE:
            lines.append("\\midrule")
        texts = [f"\\textbf{{{t}}}" if best else t for t, best in cells]
        lines.append(" & ".join([_latex_escape(name), *texts]) + " \\\\")
    return "\n".join([*lines, "\\bottomrule", "\\end{tabular}"]) + "\n"


# ----------------------------------------------------------------------------------------------
# Runtime and aggregate tables


def runtime_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Hours of wall-clock time per 1M gradient steps (``1e6 / steps_per_s``) per label.

    Columns ``mean``, ``std`` (over runs, all datasets pooled; ddof 1) and ``runs``; runs without a
    positive ``steps_per_s`` are left out.
    """
    require_columns(runs, ("steps_per_s",), "runs")
    runs = labelled(runs)
    rate = runs["steps_per_s"].astype(float)
    runs = runs[np.isfinite(rate) & (rate > 0)]
    hours = timing.hours_per_million(runs["steps_per_s"].astype(float))  # as dry runs state it
    table = hours.groupby(runs["label"]).agg(["mean", "std", "count"])
    table = table.rename(columns={"count": "runs"})
    return table.reindex([label for label in ordered_labels(runs) if label in table.index])


def runtime_to_markdown(table: pd.DataFrame) -> str:
    lines = ["| Algorithm | Runs | Hours per 1M steps |", "|---|---:|:---:|"]
    for label, row in table.iterrows():
        std = MISSING if math.isnan(row["std"]) else f"{row['std']:.2f}"  # one run: no spread
        lines.append(f"| {display_name(label)} | {int(row['runs'])} | {row['mean']:.2f} ± {std} |")
    return "\n".join(lines) + "\n"


def task_scores(runs: pd.DataFrame, metric: str = "final_score") -> dict[str, list[np.ndarray]]:
    """Per algorithm label, the finite ``metric`` values of its runs, one array per dataset."""
    runs = labelled(runs)
    runs = runs[np.isfinite(runs[metric].astype(float))]
    out = {}
    for label in ordered_labels(runs):
        mine = runs[runs["label"] == label]
        out[label] = [
            mine.loc[mine["dataset"] == d, metric].to_numpy(dtype=float)
            for d in dataset_names(mine)
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
            f"| {display_name(label)} | {int(row['tasks'])} | {int(row['runs'])} | "
            + " | ".join(cells)
            + " |"
        )
    note = (
        f"\nPoint estimates with {100 * (1 - alpha):g}% stratified-bootstrap confidence intervals "
        "(Agarwal et al., 2021). Median and mean are over the per-dataset mean scores, IQM over all "
        "runs pooled; a lower optimality gap (mean of max(0, 100 - score)) is better.\n"
    )
    return "\n".join(lines) + "\n" + note


def stability_table(runs: pd.DataFrame, metric: str = "final_score") -> pd.DataFrame:
    """Where each algorithm's critics fail, dataset by dataset (the study's diagnostics).

    One row per dataset and label: ``runs``; ``score`` (mean of the runs' ``metric``: final
    scores, or final returns) and ``score_std``; ``out_of_range`` (runs whose mean Q left the value range the rewards allow);
    ``first_out_of_range_step`` (the earliest over its runs); ``q_mean_max`` (median over runs of
    the largest logged mean Q); ``policy_spread`` (median of ``policy_q_std / |q_mean|`` at the
    last log row: how much of the value ``mean - std`` subtracts at the policy's actions);
    ``spread_ratio`` (median of ``policy_q_std / q_ensemble_std`` at the last row: above 1 the
    policy acts where the ensemble is less sure than at the data's own actions); ``bc_fraction``
    (median at the last row: the share of samples whose BC term was on).
    """
    runs = labelled(runs)
    rows = []
    for (dataset, label), group in runs.groupby(["dataset", "label"], sort=False):
        numeric = lambda c, g=group: pd.to_numeric(g[c], errors="coerce") if c in g else None  # noqa: E731
        out = numeric("q_out_of_range_step")
        q_last = numeric("q_mean_last")
        spread = numeric("policy_q_std_last")
        data_spread = numeric("q_ensemble_std_last")
        scores = numeric(metric).dropna()
        rows.append(
            {
                "dataset": dataset,
                "label": label,
                "runs": len(group),
                "score": scores.mean() if len(scores) else math.nan,
                "score_std": scores.std(ddof=1) if len(scores) > 1 else math.nan,
                "out_of_range": int(out.notna().sum()) if out is not None else 0,
                "first_out_of_range_step": out.min() if out is not None else math.nan,
                "q_mean_max": numeric("q_mean_max").median() if "q_mean_max" in group else math.nan,
                "policy_spread": (spread / q_last.abs()).median()
                if spread is not None
                else math.nan,
                "spread_ratio": (spread / data_spread).median()
                if spread is not None and data_spread is not None
                else math.nan,
                "bc_fraction": numeric("bc_fraction_last").median()
                if "bc_fraction_last" in group
                else math.nan,
            }
        )
    table = pd.DataFrame(rows)
    order = {label: i for i, label in enumerate(ordered_labels(runs))}
    table["_d"] = [dataset_sort_key(d) for d in table["dataset"]]
    table["_l"] = [order[label] for label in table["label"]]
    return table.sort_values(["_d", "_l"]).drop(columns=["_d", "_l"]).reset_index(drop=True)


def stability_to_markdown(table: pd.DataFrame, name: str = "score") -> str:
    def fmt(value, pattern):
        return MISSING if is_missing(value) or not np.isfinite(value) else pattern.format(value)

    lines = [
        f"| Dataset | Algorithm | runs | {name} | out of range | first step out | max mean Q | "
        "spread at pi | spread ratio | BC fraction |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in table.itertuples(index=False):
        score = fmt(r.score, "{:.1f}") + (
            f" ± {r.score_std:.1f}" if np.isfinite(r.score_std) else ""
        )
        lines.append(
            f"| {r.dataset} | {display_name(r.label)} | {r.runs} | {score} | "
            f"{r.out_of_range}/{r.runs} | "
            f"{fmt(r.first_out_of_range_step, '{:,.0f}')} | {fmt(r.q_mean_max, '{:,.0f}')} | "
            f"{fmt(r.policy_spread, '{:.2%}')} | {fmt(r.spread_ratio, '{:.2f}')} | "
            f"{fmt(r.bc_fraction, '{:.2f}')} |"
        )
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------------
# A published rule beside its fix (the study's failures.md)


def _at_onset(group: pd.DataFrame) -> tuple[pd.Series, pd.Series]:
    """Per run: the ensemble's spread at the policy's actions relative to |mean Q|, and that
    spread over the spread at the data's actions, at the last log row before the critics left the
    value range (runs that ran away), else at the last row (runs that stayed in range)."""

    def column(name: str) -> pd.Series:
        values = group[name] if name in group else pd.Series(math.nan, index=group.index)
        return pd.to_numeric(values, errors="coerce")

    ran_away = column("q_out_of_range_step").notna()
    state = {
        k: column(f"{k}_onset").where(ran_away, column(f"{k}_last"))
        for k in ("q_mean", "q_ensemble_std", "policy_q_std")
    }
    return (
        state["policy_q_std"] / state["q_mean"].abs(),
        state["policy_q_std"] / state["q_ensemble_std"],
    )


def failure_table(
    runs: pd.DataFrame,
    published: str,
    fix: str,
    baseline: str | None = None,
    metric: str = "final_score",
) -> pd.DataFrame:
    """The published rule (label ``published``) beside its fix (label ``fix``), one row per dataset
    that has runs of both: for each, ``{side}_runs``, ``{side}_score`` (mean final score),
    ``{side}_out_of_range`` (runs whose mean Q left the value range the rewards allow),
    ``{side}_first_out`` (the earliest such step), ``{side}_q_max`` (median over runs of the
    largest mean Q), ``{side}_spread`` and ``{side}_ratio`` (medians of :func:`_at_onset`: the
    spread at the policy's actions as the runaway began, or at the end of a run in range),
    ``{side}_bc`` (median BC fraction at the last row); and
    ``baseline_score`` (the mean final score of label ``baseline``, when given and run); the
    scores are the runs' ``metric`` (final scores, or final returns)."""
    runs = labelled(runs)
    labels = set(runs["label"])
    for name, label in (("published", published), ("fix", fix)):
        if label not in labels:
            raise ValueError(
                f"no runs labelled {label!r} (the {name} side); labels: {', '.join(sorted(labels))}"
            )
    rows = []
    for dataset in sorted(set(runs["dataset"]), key=dataset_sort_key):
        here = runs[runs["dataset"] == dataset]
        sides = {"published": here[here["label"] == published], "fix": here[here["label"] == fix]}
        if any(group.empty for group in sides.values()):
            continue
        row = {"dataset": dataset}
        if baseline is not None:
            scores = pd.to_numeric(here.loc[here["label"] == baseline, metric], "coerce")
            row["baseline_score"] = scores.mean()
        for side, group in sides.items():
            out = pd.to_numeric(group["q_out_of_range_step"], errors="coerce")
            spread, ratio = _at_onset(group)
            row |= {
                f"{side}_runs": len(group),
                f"{side}_score": pd.to_numeric(group[metric], errors="coerce").mean(),
                f"{side}_out_of_range": int(out.notna().sum()),
                f"{side}_first_out": out.min(),
                f"{side}_q_max": pd.to_numeric(group["q_mean_max"], errors="coerce").median(),
                f"{side}_spread": spread.median(),
                f"{side}_ratio": ratio.median(),
                f"{side}_bc": pd.to_numeric(group.get("bc_fraction_last"), "coerce").median()
                if "bc_fraction_last" in group
                else math.nan,
            }
        rows.append(row)
    return pd.DataFrame(rows)


def failure_to_markdown(
    table: pd.DataFrame, published: str, fix: str, baseline: str | None, name: str = "score"
) -> str:
    def fmt(value, pattern):
        return MISSING if is_missing(value) or not np.isfinite(value) else pattern.format(value)

    side_columns = [name, "out of range", "first step out", "max mean Q", "spread at pi",
                    "spread ratio", "BC fraction"]  # fmt: skip
    head = ["Dataset", *([f"{display_name(baseline)} {name}"] if baseline else [])]
    for label in (published, fix):
        head += [f"{display_name(label)}: {c}" if i == 0 else c for i, c in enumerate(side_columns)]
    lines = ["| " + " | ".join(head) + " |", "|---" + "|---:" * (len(head) - 1) + "|"]
    for r in table.to_dict("records"):
        cells = [r["dataset"], *([fmt(r.get("baseline_score"), "{:.1f}")] if baseline else [])]
        for side in ("published", "fix"):
            cells += [
                fmt(r[f"{side}_score"], "{:.1f}"),
                f"{r[f'{side}_out_of_range']}/{r[f'{side}_runs']}",
                fmt(r[f"{side}_first_out"], "{:,.0f}"),
                fmt(r[f"{side}_q_max"], "{:,.0f}"),
                fmt(r[f"{side}_spread"], "{:.2%}"),
                fmt(r[f"{side}_ratio"], "{:.2f}"),
                fmt(r[f"{side}_bc"], "{:.2f}"),
            ]
        lines.append("| " + " | ".join(cells) + " |")
    note = (
        f"\n{display_name(published)} beside {display_name(fix)}, dataset by dataset: mean final "
        f"{name}; runs whose mean Q left the value range the rewards allow, and the earliest step "
        "it did; the largest mean Q (median over runs); the ensemble's spread at the policy's "
        "actions relative to |mean Q| and over its spread at the data's actions (the spread "
        "ratio: above 1 the policy acts where the ensemble is less sure than on the data), both "
        "at the last log row before the runaway (at the end for a run that stayed in range), "
        "median over runs; the share of samples with the BC term on (Table 3's p for published "
        f"{display_name(published)}), at the last row.\n"
    )
    return "\n".join(lines) + "\n" + note
