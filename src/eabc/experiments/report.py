"""The paper's tables from experiment results, and ``write_report``, which writes every table and
figure of a sweep.

Inputs are the two frames of the results store (:mod:`eabc.experiments.results`): ``runs``, one row
per training run (``run_id, dataset, algo, variant, seed, num_critics, confidence_level, pessimism,
status, steps, wall_time_s, steps_per_s, final_score``), and ``evaluations``, one row per evaluation
(``run_id, step, score``). A run's *label* is its algorithm plus its variant (``eabc``, ``eabc K=5``).

- Table 1 / 6: :func:`score_table` and its renderers :func:`to_markdown`, :func:`to_html`,
  :func:`to_latex` (mean +- std over seeds of each run's final score; best mean per row in bold).
- :func:`runtime_table` (Figure 5's numbers) and :func:`aggregate_table` (median, IQM, mean and
  optimality gap with stratified-bootstrap CIs, from :mod:`eabc.experiments.stats`).
- Figures 1-5 and the performance profiles are drawn by :mod:`eabc.experiments.figures`.
- :func:`write_report` writes all of it, plus a ``report.md`` that shows everything in one file.
"""

from __future__ import annotations

import html
import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from eabc.agents import ALGORITHMS
from eabc.data import tasks
from eabc.experiments.stats import STATISTICS, _aggregates_batched, stratified_bootstrap_ci

ENV_ORDER = ("hopper", "halfcheetah", "walker2d")
KIND_ORDER = ("random", "medium", "medium-replay", "medium-expert", "expert")
ABLATION_PARAMETERS = tuple(
    dict.fromkeys(k for a in ALGORITHMS.values() for k in a.report_settings)
)
"""The settings some algorithm's contract lets reports compare (EABC's K, p and pessimism)."""
AVERAGE = "Average"
UNKNOWN_COLUMN = 12.5
"""Where an algorithm the registry does not know goes among the columns (just before EABC's)."""
MIN_RUNS = 3
"""Fewer runs per dataset than this and a bootstrap interval or a std says little: flagged."""


# ----------------------------------------------------------------------------------------------
# Labels and ordering


def algo_label(algo: str, variant: str | None = "") -> str:
    """``algo`` plus its variant when it has one, e.g. ``eabc K=5``."""
    variant = "" if _missing(variant) else str(variant).strip()
    return f"{algo} {variant}" if variant else str(algo)


def display_name(label: str) -> str:
    """A label as a reader of the paper knows it: ``td3bc`` -> ``TD3+BC``, ``eabc K=5`` ->
    ``EABC K=5`` (a variant keeps its settings); unknown algorithms keep their id."""
    algo, _, variant = str(label).partition(" ")
    name = ALGORITHMS[algo].display_name if algo in ALGORITHMS else algo
    return f"{name} {variant}" if variant else name


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
    rank = ALGORITHMS[algo].column if algo in ALGORITHMS else UNKNOWN_COLUMN
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
        "| " + " | ".join(["Dataset", *(escape(display_name(c)) for c in _columns(table))]) + " |",
        "|" + "---|" + ":---:|" * len(_columns(table)),
    ]
    for name, cells in _cells(table, "±", "–"):
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
        lines.append(
            f"| {display_name(label)} | {int(row['runs'])} | {row['mean']:.2f} ± {std:.2f} |"
        )
    return "\n".join(lines) + "\n"


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


# ----------------------------------------------------------------------------------------------
# The report


def stability_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Where each algorithm's critics fail, dataset by dataset (issue 14's diagnostics).

    One row per dataset and label: ``runs``; ``score`` (mean of the final scores) and
    ``score_std``; ``out_of_range`` (runs whose mean Q left the value range the rewards allow);
    ``first_out_of_range_step`` (the earliest over its runs); ``q_mean_max`` (median over runs of
    the largest logged mean Q); ``policy_spread`` (median of ``policy_q_std / |q_mean|`` at the
    last log row: how much of the value ``mean - std`` subtracts at the policy's actions);
    ``spread_ratio`` (median of ``policy_q_std / q_ensemble_std`` at the last row: above 1 the
    policy acts where the ensemble is less sure than at the data's own actions); ``bc_fraction``
    (median at the last row: the share of samples whose BC term was on).
    """
    runs = _labelled(runs)
    rows = []
    for (dataset, label), group in runs.groupby(["dataset", "label"], sort=False):
        numeric = lambda c, g=group: pd.to_numeric(g[c], errors="coerce") if c in g else None  # noqa: E731
        out = numeric("q_out_of_range_step")
        q_last = numeric("q_mean_last")
        spread = numeric("policy_q_std_last")
        data_spread = numeric("q_ensemble_std_last")
        scores = numeric("final_score").dropna()
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
    order = {label: i for i, label in enumerate(_labels(runs))}
    table["_d"] = [dataset_sort_key(d) for d in table["dataset"]]
    table["_l"] = [order[label] for label in table["label"]]
    return table.sort_values(["_d", "_l"]).drop(columns=["_d", "_l"]).reset_index(drop=True)


def stability_to_markdown(table: pd.DataFrame) -> str:
    def fmt(value, pattern):
        return "" if _missing(value) or not np.isfinite(value) else pattern.format(value)

    lines = [
        "| Dataset | Algorithm | runs | score | out of range | first step out | max mean Q | "
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


def _diverged_runs(runs: pd.DataFrame) -> list[str]:
    """``run (step N)`` for each run with a ``q_out_of_range_step``."""
    if "q_out_of_range_step" not in runs:
        return []
    hit = runs[pd.to_numeric(runs["q_out_of_range_step"], errors="coerce").notna()]
    return [f"`{r}` (step {int(s):,})" for r, s in zip(hit["run_id"], hit["q_out_of_range_step"])]


def _span(values, unit: str) -> str:
    """``5 evaluations`` or ``2-5 evaluations``."""
    low, high = min(values), max(values)
    plural = unit if high == 1 else unit + "s"
    return f"{low} {plural}" if low == high else f"{low}-{high} {plural}"


def evidence(runs: pd.DataFrame, evaluations: pd.DataFrame, table: pd.DataFrame) -> str:
    """What Table 1's cells rest on: evaluations per run score and runs (seeds) per cell."""
    from eabc.training.trainer import FINAL_EVALUATIONS  # noqa: PLC0415

    scored = evaluations[np.isfinite(evaluations["score"].astype(float))]
    counts = scored.groupby("run_id").size().reindex(runs["run_id"], fill_value=0)
    used = [min(int(n), FINAL_EVALUATIONS) for n in counts if n > 0] or [0]
    cells = table.xs("runs", axis=1, level="stat").drop(index=AVERAGE)
    per_cell = [int(n) for n in cells.to_numpy().ravel() if n > 0] or [0]
    return (
        f"each run's score is the mean of its last {_span(used, 'evaluation')} (at most "
        f"{FINAL_EVALUATIONS}); each cell's mean ± std is over {_span(per_cell, 'run')} (seeds)"
    )


def thin_evidence(table: pd.DataFrame) -> list[str]:
    """The labels with a dataset of fewer than :data:`MIN_RUNS` runs (as display names)."""
    cells = table.xs("runs", axis=1, level="stat").drop(index=AVERAGE)
    thin = [c for c in cells.columns if ((cells[c] > 0) & (cells[c] < MIN_RUNS)).any()]
    return [display_name(c) for c in thin]


def _warning(thin: list[str]) -> str:
    return (
        f"**Warning:** {', '.join(thin)} rest on fewer than {MIN_RUNS} runs on some dataset: "
        "their std and the bootstrap intervals below say little there; run more seeds.\n"
    )


RUNTIME_NOTE = (
    "Hours per 1M gradient steps = 10^6 / each run's median steps/s over its training chunks "
    "(log.csv's `steps_per_s`: the compiled update steps only, without evaluation, checkpoints "
    "or logging; the median leaves out the chunks that compiled the program), mean ± std over "
    "runs, on the machine and under the load each run had. `benchmarks/algorithms.py` measures "
    "the same on a quiet machine."
)


def write_report(
    runs: pd.DataFrame, evaluations: pd.DataFrame, out_dir: str | Path
) -> dict[str, Path]:
    """Every table and figure into ``out_dir``, and ``report.md`` that shows them all.

    Writes ``table.{md,html,tex}``, ``aggregate.md``, ``curves.png``, ``profiles.png``,
    ``runtime.png``, ``ablation_PARAMETER.png`` for each parameter that some algorithm's runs vary
    (EABC's first; every figure also as ``.pdf`` and ``.svg``), ``report.md`` and ``report.html``
    (a standalone page). Returns the paths by file name.
    """
    from eabc.experiments import figures  # noqa: PLC0415 (figures imports this module)

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}

    def write(name: str, text: str) -> None:
        paths[name] = out / name
        paths[name].write_text(text, encoding="utf-8")

    table = score_table(runs)
    write("table.md", to_markdown(table))
    stability = stability_to_markdown(stability_table(runs))
    write("stability.md", stability)
    write("runs.csv", runs.drop(columns=["config"], errors="ignore").to_csv(index=False))
    write("evaluations.csv", evaluations.to_csv(index=False))
    write("table.html", html_page("Scores (Table 1)", to_html(table)))
    write("table.tex", to_latex(table))
    aggregate = aggregate_to_markdown(aggregate_table(runs))
    write("aggregate.md", aggregate)
    paths["curves.png"] = figures.plot_learning_curves(runs, evaluations, out / "curves.png")
    paths["profiles.png"] = figures.plot_performance_profiles(runs, out / "profiles.png")
    ablations = []
    for parameter in ABLATION_PARAMETERS:
        algo = figures._ablation_algo(runs, parameter)
        if algo is not None:
            name = f"ablation_{parameter}.png"
            paths[name] = figures.plot_ablation(runs, evaluations, parameter, out / name, algo)
            ablations.append(f"### {parameter} ({display_name(algo)})\n\n![{parameter}]({name})\n")
    paths["runtime.png"] = figures.plot_runtime(runs, out / "runtime.png")
    for name in [n for n in paths if n.endswith(".png")]:
        for suffix in figures.VECTOR_FORMATS:
            paths[name.removesuffix(".png") + suffix] = out / (name.removesuffix(".png") + suffix)
    basis = evidence(runs, evaluations, table)
    thin = thin_evidence(table)

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
    diverged = _diverged_runs(runs)
    if diverged:
        sections.append(
            f"Runs whose critics left the value range the rewards allow ({len(diverged)} of "
            f"{len(runs)}; their later scores rest on a diverging critic): {', '.join(diverged)}.\n"
        )
    sections += [
        "## Scores (Table 1)\n",
        f"D4RL-normalised score: {basis}; best mean per row in bold; the Average row averages "
        "the per-dataset means and stds. Also as [HTML](table.html) and [LaTeX](table.tex); "
        "the whole report as a page: [report.html](report.html). Figures as PNG (300 dpi), "
        "PDF and SVG.\n",
        *([_warning(thin)] if thin else []),
        to_markdown(table),
        "## Stability: where the critics fail\n",
        "Per dataset and algorithm: runs whose mean Q left the range the rewards allow, the "
        "first such step, the largest mean Q (median over runs), the ensemble's spread at the "
        "policy's actions relative to |mean Q|, the spread ratio (that spread over the spread at "
        "the data's actions: above 1 the policy acts where the ensemble is less sure than on "
        "the data) and the share of samples with the BC term on (all at the last log row). [stability.md](stability.md); the results as CSV: "
        "[runs.csv](runs.csv), "
        "[evaluations.csv](evaluations.csv).\n",
        stability,
        "## Aggregate statistics\n",
        *([_warning(thin)] if thin else []),
        aggregate,
        "![Performance profiles](profiles.png)\n",
        "## Learning curves (Figure 1)\n",
        "![Learning curves](curves.png)\n",
        *(["## Ablations (Figures 2-4)\n", *ablations] if ablations else []),
        "## Runtime (Figure 5)\n",
        RUNTIME_NOTE + "\n",
        _runtime_markdown(runtime_table(runs)),
        "![Runtime](runtime.png)\n",
    ]
    write("report.md", "\n".join(sections))
    write("report.html", report_page(sections, table))
    return paths


STYLE = """
body { font: 15px/1.5 -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; color: #222;
       max-width: 72rem; margin: 2rem auto; padding: 0 1.5rem; }
h1 { font-size: 1.7rem; border-bottom: 2px solid #333; padding-bottom: .3rem; }
h2 { font-size: 1.25rem; margin-top: 2.2rem; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 1rem 0; font-variant-numeric: tabular-nums; }
th, td { padding: .3rem .7rem; text-align: center; }
thead th { border-top: 2px solid #333; border-bottom: 1px solid #333; }
tbody tr:last-child th, tbody tr:last-child td { border-bottom: 2px solid #333; }
tbody th { text-align: left; font-weight: normal; }
tbody tr:nth-child(even) { background: #f6f6f6; }
td b { color: #0b4f9c; }
.note { color: #555; font-size: .92rem; }
.warning { background: #fff4e0; border-left: 4px solid #e69500; padding: .5rem .8rem; }
figure { margin: 1.2rem 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { color: #555; font-size: .9rem; }
"""


def html_page(title: str, body: str) -> str:
    """A standalone HTML page (its own style sheet, no external resources) around ``body``."""
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n"
        f"<h1>{html.escape(title)}</h1>\n{body}\n</body>\n</html>\n"
    )


def _markdown_table_html(text: str) -> str:
    """A Markdown table (as this module writes them) as an HTML table."""
    rows = [line.strip().strip("|").split(" | ") for line in text.strip().splitlines()]
    rows = [r for i, r in enumerate(rows) if i != 1]  # the |---| line
    cell = lambda t: re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", html.escape(t.strip()))
    head = "".join(f"<th>{cell(t)}</th>" for t in rows[0])
    body = "".join(
        "<tr>" + f"<th>{cell(r[0])}</th>" + "".join(f"<td>{cell(t)}</td>" for t in r[1:]) + "</tr>"
        for r in rows[1:]
    )
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def report_page(sections: list[str], table: pd.DataFrame) -> str:
    """``report.md``'s content as one styled page: tables as tables, figures as SVG."""
    parts = []
    blocks = [b.strip() for section in sections[1:] for b in re.split(r"\n\s*\n", section)]
    for text in filter(None, blocks):  # sections[0] is report.md's title
        if text.startswith("#"):
            level = len(text) - len(text.lstrip("#"))
            parts.append(f"<h{level}>{html.escape(text[level:].strip())}</h{level}>")
        elif text.startswith("!["):
            parts.extend(_figures_html(text))
        elif text.startswith("|"):
            header = text.splitlines()[0]
            table1 = header.startswith("| Dataset |") and "| Algorithm |" not in header
            parts.append(to_html(table) if table1 else _markdown_table_html(text))
        elif text.startswith("**Warning:**"):
            parts.append(f'<p class="warning">{_inline(text)}</p>')
        else:
            parts.append(f'<p class="note">{_inline(text)}</p>')
    return html_page("Experiment report", "\n".join(parts))


def _figures_html(text: str) -> list[str]:
    out = []
    for alt, target in re.findall(r"!\[([^\]]*)\]\(([^)]+)\)", text):
        vector = target.removesuffix(".png") + ".svg"
        out.append(
            f'<figure><a href="{html.escape(target)}"><img src="{html.escape(vector)}" '
            f'alt="{html.escape(alt)}"></a><figcaption>{html.escape(alt)} (<a '
            f'href="{html.escape(target.removesuffix(".png"))}.pdf">PDF</a>)</figcaption></figure>'
        )
    return out


def _inline(text: str) -> str:
    """Markdown's bold, code and links in one paragraph, as HTML."""
    text = html.escape(text)
    text = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", text)
    text = re.sub(r"`([^`]+)`", r"<code>\1</code>", text)
    return re.sub(r"\[([^\]]+)\]\(([^)]+)\)", r'<a href="\2">\1</a>', text)
