"""``write_report``: every table and figure of a sweep into one folder, and a ``report.md`` that
shows them all: PNG figures and Markdown tables, and on request (``formats``) PDF and SVG
figures, HTML and LaTeX tables and ``report.html``.

The tables come from :mod:`eabc.experiments.tables`, Figures 1-5 and the performance profiles from
:mod:`eabc.experiments.figures`; this module adds what the cells rest on (evaluations per score,
runs per cell) and the pages.
"""

from __future__ import annotations

import html
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from eabc import progress, timing
from eabc.data import tasks
from eabc.experiments import compare, figures
from eabc.experiments.compare import PUBLISHED, RECOMMENDED
from eabc.experiments.labels import ABLATION_PARAMETERS, display_name, labelled, paper_table
from eabc.experiments.report_html import html_page, report_page
from eabc.experiments.tables import (
    AVERAGE,
    MIN_RUNS,
    RETURN,
    SCORE,
    Metric,
    aggregate_table,
    aggregate_to_markdown,
    failure_table,
    failure_to_markdown,
    runtime_table,
    runtime_to_markdown,
    score_table,
    stability_table,
    stability_to_markdown,
    to_html,
    to_latex,
    to_markdown,
)
from eabc.training.config import FINAL_EVALUATIONS

# ----------------------------------------------------------------------------------------------
# The report

FORMATS = ("png", "md", "pdf", "svg", "html", "tex")
"""What a report can be written in: PNG figures and Markdown tables always (``report.md`` links
them); on request, PDF and SVG beside every figure, HTML and LaTeX beside the score table, and
``report.html``, the whole report as one page (``eabc report --formats``)."""
DEFAULT_FORMATS = ("png", "md")
"""One format per figure (PNG) and per table (Markdown); the others are made on demand."""


def check_formats(formats: Sequence[str]) -> tuple[str, ...]:
    """``formats`` with PNG and Markdown added, each once; an unknown one is refused, naming
    those there are."""
    unknown = [f for f in formats if f not in FORMATS]
    if unknown:
        raise ValueError(f"no report format {unknown}; there are {list(FORMATS)}")
    return tuple(f for f in FORMATS if f in {*DEFAULT_FORMATS, *formats})


def _other_formats(formats: Sequence[str]) -> str:
    """The score table's caption: where the same table, the report and the figures are in the
    other ``formats`` written."""
    tables = [f"[{n}](table.{e})" for e, n in (("html", "HTML"), ("tex", "LaTeX")) if e in formats]
    text = f" Also as {' and '.join(tables)}" if tables else ""
    if "html" in formats:
        text += "; the whole report as a page: [report.html](report.html)"
    kinds = ["PNG (300 dpi)", *(e.upper() for e in ("pdf", "svg") if e in formats)]
    listed = ", ".join(kinds[:-1]) + " and " + kinds[-1] if len(kinds) > 1 else kinds[0]
    return f"{text}{'.' if text else ''} Figures as {listed}."


def vector_extensions(machines: pd.Series) -> list[str]:
    """The vector extensions (AVX-512, AVX2, ...) of the hosts named in runs' ``machine`` texts
    (``CPU, ISA [+ CPU, ISA]``), each once, in order of appearance."""
    found = []
    for text in machines:
        for host in str(text).split(" + "):
            isa = host.rpartition(", ")[2].split(" (")[0].strip()  # "AVX-512 (+BF16)": AVX-512
            if isa and isa not in found:
                found.append(isa)
    return found


def reward_conventions(runs: pd.DataFrame) -> str:
    """Which reward convention the runs on sparse goal rewards trained on, by algorithm (each
    run's is runs.csv's ``reward_convention``); "" when no run's data has such rewards."""
    if "reward_convention" not in runs:
        return ""
    goal = runs[
        runs["dataset"].map(lambda d: tasks.reward_offset(tasks.parse_task(str(d))) is not None)
    ]
    if goal.empty:
        return ""
    convention = goal["reward_convention"].astype(object).fillna("").astype(str)
    convention = convention.replace("", "not recorded")
    parts = []
    for name, group in goal.groupby(convention, sort=True):
        algos = ", ".join(display_name(a) for a in dict.fromkeys(group["algo"]))
        parts.append(f"`{name}` {len(group)} ({algos})")
    return (
        "Sparse goal rewards trained on (runs.csv's `reward_convention`: `raw` the stored 0/1, "
        "`minus-one` r - 1, others as the algorithm's file defines them; `not recorded` in "
        "reports from before the column): " + "; ".join(parts) + ".\n"
    )


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


def evidence(
    runs: pd.DataFrame, evaluations: pd.DataFrame, table: pd.DataFrame, metric: Metric = SCORE
) -> str:
    """What Table 1's cells rest on: evaluations per run score and runs (seeds) per cell."""
    scored = evaluations[np.isfinite(pd.to_numeric(evaluations[metric.curve], errors="coerce"))]
    counts = scored.groupby("run_id").size().reindex(runs["run_id"], fill_value=0)
    short = [int(n) for n in counts if 0 < n < FINAL_EVALUATIONS]
    cells = table.xs("runs", axis=1, level="stat").drop(index=AVERAGE)
    per_cell = [int(n) for n in cells.to_numpy().ravel() if n > 0] or [0]
    window = f"each run's {metric.name} is the mean of its last {FINAL_EVALUATIONS} evaluations"
    if short:
        many = "run has" if len(short) == 1 else "runs have"
        window += (
            f" ({len(short)} {many} fewer, {_span(short, 'evaluation')}: the mean of all of them)"
        )
    return f"{window}; each cell's mean ± std is over {_span(per_cell, 'run')} (seeds)"


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


def reference_groups(runs: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``(scored, raw)``: the runs on data with reference scores (or with no evaluation yet), and
    the runs on datasets no run has a score for (no reference returns: a user's own file) that
    have a final return, which reports show in raw return."""
    if "final_return" not in runs:  # an archive or a frame from before returns were kept
        return runs, runs.iloc[:0]
    scores = pd.to_numeric(runs["final_score"], errors="coerce")
    returns = pd.to_numeric(runs["final_return"], errors="coerce")
    scored_datasets = set(runs.loc[np.isfinite(scores), "dataset"])
    raw = ~runs["dataset"].isin(scored_datasets) & np.isfinite(returns)
    return runs[~raw], runs[raw]


def _has(runs: pd.DataFrame, metric: Metric) -> bool:
    return bool(np.isfinite(pd.to_numeric(runs[metric.column], errors="coerce")).any())


def _axis(metric: Metric) -> str:
    return "normalised score" if metric is SCORE else "return"


def _metric_sections(
    runs: pd.DataFrame,
    evaluations: pd.DataFrame,
    metric: Metric,
    baseline: str | None,
    fix: str,
    write,
    prefix: str = "",
    formats: Sequence[str] = DEFAULT_FORMATS,
) -> tuple[pd.DataFrame, dict]:
    """Table 1, the comparison with ``baseline``, the published rule beside ``fix`` and the
    stability table of ``runs`` in ``metric``, each written to its file (``PREFIXtable.md``,
    and ``.html`` / ``.tex`` where ``formats`` asks); returns the table and the report's text of
    each, by name. A comparison that cannot be made says why in its place."""
    table = score_table(runs, metric.column)
    heading = "Scores" if metric is SCORE else "Returns"
    # A table of returns says so wherever it is read, not only in report.md.
    note = "" if metric is SCORE else f"{metric.title}.\n"
    write(f"{prefix}table.md", (note and note + "\n") + to_markdown(table))
    if "html" in formats:
        body = (note and f'<p class="note">{html.escape(note.strip())}</p>\n') + to_html(table)
        title = f"{heading} ({paper_table(runs['dataset'].unique())})"
        write(f"{prefix}table.html", html_page(title, body))
    if "tex" in formats:
        write(f"{prefix}table.tex", (note and f"% {note}") + to_latex(table))
    stability = stability_to_markdown(stability_table(runs, metric.column), metric.name)
    write(f"{prefix}stability.md", stability)
    thin = thin_evidence(table)
    links = _other_formats(formats)
    caption = (
        f"{metric.title}: {evidence(runs, evaluations, table, metric)}; best mean per row in "
        f"bold; the Average row averages the per-dataset means and stds.{'' if prefix else links}\n"
    )
    level = "###" if prefix else "##"  # a section of its own, or inside the returns' section
    sections = {"table": [caption, *([_warning(thin)] if thin else []), to_markdown(table)]}
    sections["comparison"] = []
    if baseline is not None:
        name = display_name(baseline)
        try:
            compared = compare.comparison_table(runs, baseline, metric.column)
        except ValueError as error:
            sections["comparison"] = [f"Not compared with {name} here: {error}.\n"]
        else:
            text = compare.comparison_to_markdown(compared, baseline, what=metric.name)
            write(f"{prefix}comparison.md", text)
            sections["comparison"] = [
                f"{level} Against {name}, dataset by dataset\n",
                f"Also as [{prefix}comparison.md]({prefix}comparison.md).\n",
                text,
            ]
    sections["failures"] = []
    if {PUBLISHED, fix} <= set(labelled(runs)["label"]):
        failures = failure_table(runs, PUBLISHED, fix, baseline, metric.column)
        text = failure_to_markdown(failures, PUBLISHED, fix, baseline, metric.name)
        write(f"{prefix}failures.md", text)
        sections["failures"] = [
            f"{level} Where published {display_name(PUBLISHED)} fails, beside {display_name(fix)}\n",
            f"Also as [{prefix}failures.md]({prefix}failures.md).\n",
            text,
        ]
    sections["stability"] = stability
    return table, sections


RUNTIME_NOTE = (
    "Hours per 1M gradient steps = 10^6 / each run's median steps/s over its training chunks "
    "(log.csv's `steps_per_s`: the compiled update steps only, without evaluation, checkpoints "
    "or logging; the median leaves out the chunks that compiled the program), mean ± std over "
    "runs, on the machine and under the load each run had. `benchmarks/algorithms.py` measures "
    "the same on a quiet machine."
)


def write_report(
    runs: pd.DataFrame,
    evaluations: pd.DataFrame,
    out_dir: str | Path,
    baseline: str | None = None,
    fix: str = RECOMMENDED,
    repeats: pd.DataFrame | None = None,
    formats: Sequence[str] = DEFAULT_FORMATS,
) -> dict[str, Path]:
    """Every table and figure into ``out_dir``, and ``report.md`` that shows them all.

    Writes ``table.md``, ``aggregate.md``, ``curves.png``, ``profiles.png``, ``runtime.png``,
    ``ablation_PARAMETER.png`` for each parameter that some algorithm's runs vary (the registry's
    first), ``report.md``, and ``comparison.md``: every label against ``baseline`` (default
    :func:`~eabc.experiments.compare.default_baseline`), dataset by dataset; ``failures.md`` when
    the published rule (label :data:`PUBLISHED`) and ``fix`` both ran: the one beside the other, where the published rule
    fails and the ensemble's spread at the policy's actions as it did. Returns the paths by file
    name. ``repeats`` (:func:`eabc.experiments.archive_merge.repeats`): runs trained more than once,
    kept as ``repeats.csv`` and shown with whether their copies agree. ``formats``
    (:data:`FORMATS`) adds ``pdf`` and ``svg`` beside every figure, ``html`` (``table.html`` and
    ``report.html``, a standalone page) and ``tex`` (``table.tex``) to the PNG and Markdown.
    """

    formats = check_formats(formats)
    vector = tuple(f".{f}" for f in formats if f".{f}" in figures.VECTOR_FORMATS)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}

    def write(name: str, text: str) -> None:
        paths[name] = out / name
        paths[name].write_text(text, encoding="utf-8")

    started = time.perf_counter()
    progress.say(f"report: {len(runs)} runs into {out}: tables")
    write("runs.csv", runs.drop(columns=["config"], errors="ignore").to_csv(index=False))
    write("evaluations.csv", evaluations.to_csv(index=False))
    scored, raw = reference_groups(runs)
    # Scores where any run has one; raw returns for the runs on data without reference returns
    # (a section of their own beside the scores, or the whole report when no run has a score).
    metric, main = (SCORE, scored) if raw.empty or _has(scored, SCORE) else (RETURN, runs)
    baseline = baseline or compare.default_baseline(runs)
    table, results = _metric_sections(
        main, evaluations, metric, baseline, fix, write, formats=formats
    )
    tables = [table]
    returns = []
    if main is scored and not raw.empty:
        raw_table, raw_results = _metric_sections(
            raw, evaluations, RETURN, baseline, fix, write, "returns_", formats
        )
        tables.append(raw_table)
        paths["returns_curves.png"] = figures.plot_learning_curves(
            raw, evaluations, out / "returns_curves.png", RETURN.curve, RETURN.name, vector
        )
        returns = [
            "## Returns of the runs without reference scores\n",
            f"On {', '.join(sorted(set(raw['dataset'])))}, which have no reference returns: "
            "these runs are left out of the scores above. Also as "
            "[returns_table.md](returns_table.md).\n",
            *raw_results["table"],
            *raw_results["comparison"],
            *raw_results["failures"],
            "### Stability\n",
            raw_results["stability"],
            "![Learning curves (raw return)](returns_curves.png)\n",
        ]
    if metric is SCORE:
        aggregate = aggregate_to_markdown(aggregate_table(main))
        write("aggregate.md", aggregate)
        paths["profiles.png"] = figures.plot_performance_profiles(
            main, out / "profiles.png", vector=vector
        )
        aggregate = [aggregate, "![Performance profiles](profiles.png)\n"]
    else:
        aggregate = [
            "Not computed for raw returns: these statistics and the performance profiles pool "
            "D4RL-normalised scores over datasets (the optimality gap is 100 minus a score), and "
            "the returns of different environments are on different scales.\n"
        ]
    progress.say("report: figures (learning curves, ablations, runtime)")
    paths["curves.png"] = figures.plot_learning_curves(
        main, evaluations, out / "curves.png", metric.curve, _axis(metric), vector
    )
    ablations = []
    for parameter in ABLATION_PARAMETERS:
        algo = figures._ablation_algo(main, parameter)
        if algo is not None:
            name = f"ablation_{parameter}.png"
            paths[name] = figures.plot_ablation(
                main, evaluations, parameter, out / name, algo, metric.curve, _axis(metric), vector
            )
            ablations.append(f"### {parameter} ({display_name(algo)})\n\n![{parameter}]({name})\n")
    paths["runtime.png"] = figures.plot_runtime(runs, out / "runtime.png", vector)
    for name in [n for n in paths if n.endswith(".png")]:
        for suffix in vector:
            paths[name.removesuffix(".png") + suffix] = out / (name.removesuffix(".png") + suffix)
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
    if "source" in runs and runs["source"].nunique() > 1:
        counts = runs["source"].value_counts(sort=False)
        archived = set(runs.loc[runs["archived"].fillna(False).astype(bool), "source"])
        kinds = {True: "an earlier report, read back with `--include`", False: "run directories"}
        sections.append(
            "Runs by where they were read: "
            + ", ".join(f"{n} from `{w}` ({kinds[w in archived]})" for w, n in counts.items())
            + "; a run in several places counts once, from the copy that trained the most "
            "steps.\n"
        )
    if repeats is not None and not repeats.empty:
        write("repeats.csv", repeats.to_csv(index=False))
        sections.append(repeats_to_markdown(repeats))
    trained_on = runs["machine"].dropna().astype(str) if "machine" in runs else pd.Series([])
    trained_on = trained_on[trained_on != ""]
    if len(trained_on):
        counts = trained_on.value_counts(sort=False)
        sections.append(
            "Trained on (from the runs' `provenance.json`; "
            f"{len(runs) - len(trained_on)} runs predate that record): "
            + ", ".join(f"{n} on {m}" for m, n in counts.items())
            + "; the code of each run is in runs.csv (`code`).\n"
        )
        extensions = vector_extensions(trained_on)
        if len(extensions) > 1:
            sections.append(
                f"**These tables merge runs from hosts of different vector extensions "
                f"({', '.join(extensions)}).** Runs reproduce each other to the bit only on "
                "hosts of the same extension: the same seed on another one computes in other "
                "vector kernels and its numbers drift apart within a few thousand steps, as "
                "another seed's would. Compare like with like through runs.csv's `machine`.\n"
            )
        code = runs.get("code", pd.Series("", index=runs.index)).fillna("").astype(str)
        uncommitted = runs.loc[code.str.contains("uncommitted changes", regex=False), "run_id"]
        if len(uncommitted):
            sections.append(
                f"**{len(uncommitted)} run(s) ran code with uncommitted changes**, which no commit "
                "reproduces: " + ", ".join(f"`{r}`" for r in uncommitted) + ".\n"
            )
    conventions = reward_conventions(runs)
    if conventions:
        sections.append(conventions)
    diverged = _diverged_runs(runs)
    if diverged:
        sections.append(
            f"Runs whose critics left the value range the rewards allow ({len(diverged)} of "
            f"{len(runs)}; their later scores rest on a diverging critic): {', '.join(diverged)}.\n"
        )
    heading = "Scores" if metric is SCORE else "Returns"
    sections += [
        f"## {heading} ({paper_table(runs['dataset'].unique())})\n",
        *results["table"],
        *results["comparison"],
        *results["failures"],
        *returns,
        "## Stability: where the critics fail\n",
        "Per dataset and algorithm: runs whose mean Q left the range the rewards allow, the "
        "first such step, the largest mean Q (median over runs), the ensemble's spread at the "
        "policy's actions relative to |mean Q|, the spread ratio (that spread over the spread at "
        "the data's actions: above 1 the policy acts where the ensemble is less sure than on "
        "the data) and the share of samples with the BC term on (all at the last log row). [stability.md](stability.md); the results as CSV: "
        "[runs.csv](runs.csv), "
        "[evaluations.csv](evaluations.csv).\n",
        results["stability"],
        "## Aggregate statistics\n",
        *([_warning(thin)] if thin and metric is SCORE else []),
        *aggregate,
        "## Learning curves (Figure 1)\n",
        "![Learning curves](curves.png)\n",
        *(["## Ablations (Figures 2-4)\n", *ablations] if ablations else []),
        "## Runtime (Figure 5)\n",
        RUNTIME_NOTE + "\n",
        runtime_to_markdown(runtime_table(runs)),
        "![Runtime](runtime.png)\n",
    ]
    write("report.md", "\n".join(sections))
    if "html" in formats:
        write("report.html", report_page(sections, tables, formats))
    progress.say(f"report: done in {timing.duration(time.perf_counter() - started)}")
    return paths


def repeats_to_markdown(repeats: pd.DataFrame) -> str:
    """The runs trained more than once, and whether their copies agree to the last bit."""
    same = int(repeats["identical"].astype(bool).sum())
    lines = [
        f"Runs trained more than once, to the same step ({len(repeats)}; the report counts each "
        f"once): {same} of {len(repeats)} agree in every evaluation to the last bit"
        + ("." if same == len(repeats) else "; the others mix two computations (a host or code "
           "that changes the numerics): compare their machines and code in runs.csv.")
        + " [repeats.csv](repeats.csv).\n",
        "| Run | Steps | Trained in | Evaluations | Largest score difference | Identical |",
        "|---|---:|---|---:|---:|:---:|",
    ]  # fmt: skip
    for row in repeats.itertuples():
        difference = "" if pd.isna(row.max_score_difference) else f"{row.max_score_difference:.3g}"
        lines.append(
            f"| {row.run_id} | {int(row.steps):,} | {row.sources} | {int(row.evaluations)} | "
            f"{difference} | {'yes' if row.identical else '**no**'} |"
        )
    return "\n".join(lines) + "\n"
