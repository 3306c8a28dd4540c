"""Reports: tables against the inputs, bold on the best cell, rliable statistics, figures on disk."""

from __future__ import annotations

import json
import re
import typing

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from synthetic_results import DATASETS, LEVELS, SEEDS, make_results

from eabc.cli import main
from eabc.experiments import compare, figures, report, tables
from eabc.experiments import stats as aggregate

PNG = b"\x89PNG\r\n\x1a\n"


def labelled(runs: pd.DataFrame) -> pd.Series:
    return runs["algo"] + runs["variant"].map(lambda v: f" {v}" if v else "")


def grouped(runs: pd.DataFrame) -> pd.DataFrame:
    return runs.groupby(["dataset", labelled(runs).rename("label")])["final_score"].agg(
        ["mean", "std", "count"]
    )


@pytest.fixture(scope="module")
def results():
    return make_results()


@pytest.fixture(scope="module")
def written(results, tmp_path_factory):
    runs, evaluations = results
    out = tmp_path_factory.mktemp("report")
    return out, report.write_report(runs, evaluations, out, formats=report.FORMATS)


# Table 1


def test_score_table_cells_equal_the_groupby_of_the_input(results):
    runs, _ = results
    table = tables.score_table(runs)
    expected = grouped(runs)
    assert list(table.index) == ["hopper-random", "walker2d-medium", "Average"]
    assert tables._columns(table) == ["td3bc", "iql", "eabc", "eabc K=5"]
    means = table.xs("mean", axis=1, level="stat")
    stds = table.xs("std", axis=1, level="stat")
    count = table.xs("runs", axis=1, level="stat")
    for (dataset, label), row in expected.iterrows():
        assert means.at[dataset, label] == pytest.approx(row["mean"], abs=1e-12)
        assert stds.at[dataset, label] == pytest.approx(row["std"], abs=1e-12)
        assert count.at[dataset, label] == row["count"] == len(SEEDS)


def test_average_row_is_over_the_datasets_where_a_column_has_values(results):
    runs, _ = results
    extra = runs[(runs["algo"] == "iql") & (runs["dataset"] == "hopper-random")].copy()
    extra["algo"], extra["run_id"] = "cql", extra["run_id"] + "_cql"
    extra["final_score"] = [10.0, 20.0, 60.0]
    table = tables.score_table(pd.concat([runs, extra]))
    means = table.xs("mean", axis=1, level="stat")
    stds = table.xs("std", axis=1, level="stat")
    expected = grouped(runs)
    for label in LEVELS:
        per_dataset = expected.xs(label, level="label")
        assert means.at["Average", label] == pytest.approx(per_dataset["mean"].mean())
        assert stds.at["Average", label] == pytest.approx(per_dataset["std"].mean())
    assert np.isnan(means.at["walker2d-medium", "cql"])
    assert means.at["Average", "cql"] == pytest.approx(30.0)
    assert stds.at["Average", "cql"] == pytest.approx(np.std([10.0, 20.0, 60.0], ddof=1))
    assert "–" in tables.to_markdown(table)  # the missing cell


def test_datasets_are_ordered_by_environment_then_kind():
    names = [
        "walker2d-expert",
        "antmaze-umaze",
        "halfcheetah-random",
        "hopper-medium-expert",
        "ant-medium",
        "hopper-medium-replay",
        "hopper-medium",
        "hopper-random",
    ]
    assert sorted(names, key=tables.dataset_sort_key) == [
        "hopper-random",
        "hopper-medium",
        "hopper-medium-replay",
        "hopper-medium-expert",
        "halfcheetah-random",
        "walker2d-expert",
        "ant-medium",
        "antmaze-umaze",
    ]


def markdown_rows(text: str) -> dict[str, list[str]]:
    lines = [line for line in text.splitlines() if line.startswith("| ")]
    return {
        cells[0]: cells[1:]
        for cells in ([c.strip() for c in ln.strip("| ").split(" | ")] for ln in lines[1:])
    }


def best_columns(runs: pd.DataFrame) -> dict[str, int]:
    """Row -> position of the highest mean, computed from the input without the report code."""
    order = ["td3bc", "iql", "eabc", "eabc K=5"]
    means = grouped(runs)["mean"].unstack("label")[order]
    best = {d: int(np.argmax(means.loc[d].to_numpy())) for d in means.index}
    best["Average"] = int(np.argmax(means.mean(axis=0).to_numpy()))
    return best


def test_the_best_mean_of_each_row_is_bold_in_every_format(results):
    runs, _ = results
    runs = runs.copy()  # make the row winners differ: td3bc best on hopper-random
    runs.loc[(runs["dataset"] == "hopper-random") & (runs["algo"] == "td3bc"), "final_score"] += 40
    table = tables.score_table(runs)
    best = best_columns(runs)
    assert best["hopper-random"] != best["walker2d-medium"]

    md = markdown_rows(tables.to_markdown(table))
    html = {
        re.search(r"<th>(.*?)</th>", row)[1]: re.findall(r"<td>(.*?)</td>", row)
        for row in re.findall(r"<tr><th>.*?</tr>", tables.to_html(table))
    }
    tex_lines = [ln for ln in tables.to_latex(table).splitlines() if ln.endswith("\\\\")]
    tex = {cells[0]: cells[1:] for cells in (ln[:-2].strip().split(" & ") for ln in tex_lines)}
    for rendered, bold in (
        (md, r"^\*\*.*\*\*$"),
        (html, r"^<b>.*</b>$"),
        (tex, r"^\\textbf\{.*\}$"),
    ):
        assert set(best) <= set(rendered)
        for row, position in best.items():
            marked = [i for i, cell in enumerate(rendered[row]) if re.match(bold, cell)]
            assert marked == [position], (row, rendered[row])
    assert "$\\pm$" in tex["hopper-random"][0] and "&plusmn;" in html["hopper-random"][0]


# Aggregate table


def test_aggregate_table_matches_the_statistics_and_the_unbatched_bootstrap(results):
    runs, _ = results
    table = tables.aggregate_table(runs, reps=300, seed=3)
    assert list(table.index) == ["td3bc", "iql", "eabc", "eabc K=5"]
    eabc = runs[(runs["algo"] == "eabc") & (runs["variant"] == "")]
    per_task = [g["final_score"].to_numpy() for _, g in eabc.groupby("dataset")]
    row = table.loc["eabc"]
    assert (row["tasks"], row["runs"]) == (2, 6)
    assert row["iqm"] == pytest.approx(stats.trim_mean(eabc["final_score"], 0.25))
    assert row["mean"] == pytest.approx(eabc.groupby("dataset")["final_score"].mean().mean())
    assert row["median"] == pytest.approx(row["mean"])  # the median of two task means
    gap = eabc.groupby("dataset")["final_score"].agg(lambda x: np.maximum(0, 100 - x).mean())
    assert row["optimality_gap"] == pytest.approx(gap.mean())
    everything = lambda s: [f(s) for f in aggregate.STATISTICS.values()]
    low, high = aggregate.stratified_bootstrap_ci(per_task, everything, reps=300, seed=3)
    for i, name in enumerate(aggregate.STATISTICS):
        assert row[f"{name}_low"] == pytest.approx(low[i])
        assert row[f"{name}_high"] == pytest.approx(high[i])
        assert row[f"{name}_low"] <= row[name] <= row[f"{name}_high"]


# Figures and the report


def test_ablation_holds_the_other_settings_fixed(results):
    runs, _ = results
    assert figures.ablation_values(runs, "num_critics") == [5.0, 10.0]
    assert figures.ablation_values(runs, "confidence_level") == [0.25]
    assert figures.ablation_values(runs, "pessimism") == ["mean-std"]
    p_arm = runs[(runs["algo"] == "eabc") & (runs["variant"] == "")].copy()
    p_arm["variant"], p_arm["confidence_level"] = "p=0.5", 0.5
    p_arm["run_id"] += "_p"
    both = pd.concat([runs, p_arm])
    assert figures.ablation_values(both, "num_critics") == [5.0, 10.0]  # p=0.5 runs left out
    assert figures.ablation_values(both, "confidence_level") == [0.25, 0.5]  # K=5 runs left out
    assert figures.ablation_values(both, "num_critics", algo="td3bc") == [2.0]


def test_runtime_table_is_time_per_million_steps(results):
    runs, _ = results
    table = tables.runtime_table(runs)
    hours = (1e6 / runs["steps_per_s"] / 3600).groupby(labelled(runs)).agg(["mean", "std"])
    for label in LEVELS:
        assert table.at[label, "mean"] == pytest.approx(hours.at[label, "mean"])
        assert table.at[label, "std"] == pytest.approx(hours.at[label, "std"])
    assert table.at["eabc", "mean"] > table.at["td3bc", "mean"]


def test_write_report_writes_every_file_and_the_table_matches_the_input(results, written):
    runs, _ = results
    out, paths = written
    expected = {
        "table.md",
        "table.html",
        "table.tex",
        "aggregate.md",
        "curves.png",
        "runtime.png",
        "profiles.png",
        "ablation_num_critics.png",
        "stability.md",
        "comparison.md",
        "runs.csv",
        "evaluations.csv",
        "report.md",
        "report.html",
    }
    figures_ = {name.removesuffix(".png") for name in expected if name.endswith(".png")}
    expected |= {f"{name}{suffix}" for name in figures_ for suffix in (".pdf", ".svg")}
    assert set(paths) == expected == {p.name for p in out.iterdir()}
    for name, path in paths.items():
        assert path == out / name and path.stat().st_size > 0
        if name.endswith(".png"):
            assert path.read_bytes()[:8] == PNG and path.stat().st_size > 5000
    rows = markdown_rows(paths["table.md"].read_text())
    for (dataset, label), row in grouped(runs).iterrows():
        cell = rows[dataset][["td3bc", "iql", "eabc", "eabc K=5"].index(label)]
        mean, std = (float(x) for x in cell.strip("*").split(" ± "))
        assert abs(mean - row["mean"]) <= 0.05 + 1e-9 and abs(std - row["std"]) <= 0.05 + 1e-9
    text = paths["report.md"].read_text()
    for name in {n for n in expected if not n.endswith((".pdf", ".svg"))} - {
        "report.md",
        "aggregate.md",
        "table.md",
    }:
        assert f"({name})" in text
    assert paths["table.md"].read_text() in text and "IQM" in text


def test_a_report_is_png_and_markdown_unless_asked_for_more(results, tmp_path, quick_figures):
    """One format per figure and table by default: no PDF, SVG, HTML or LaTeX, and no link in
    report.md to a file that was not written; each asked-for format adds its files alone."""
    runs, evaluations = results
    paths = report.write_report(runs, evaluations, tmp_path / "default")
    assert {p.suffix for p in (tmp_path / "default").iterdir()} == {".png", ".md", ".csv"}
    assert set(paths) == {p.name for p in (tmp_path / "default").iterdir()}
    text = paths["report.md"].read_text()
    for target in re.findall(r"\]\(([^)#]+)\)", text):
        assert (tmp_path / "default" / target).is_file(), target
    assert "Figures as PNG (300 dpi)." in text and "table.html" not in text

    some = report.write_report(runs, evaluations, tmp_path / "some", formats=("svg", "tex"))
    extra = {n for n in some if not n.endswith((".png", ".md", ".csv"))}
    figures_ = {n.removesuffix(".png") for n in paths if n.endswith(".png")}
    assert extra == {"table.tex"} | {f"{name}.svg" for name in figures_}
    assert (
        "Also as [LaTeX](table.tex). Figures as PNG (300 dpi) and SVG."
        in some["report.md"].read_text()
    )
    with pytest.raises(ValueError, match=r"no report format \[.docx.\]; there are"):
        report.write_report(runs, evaluations, tmp_path / "bad", formats=("docx",))


def test_eabc_report_formats_flag_offers_the_reports_formats(tmp_path):
    from eabc.cli.experiments import Report, ReportFormat  # noqa: PLC0415

    assert typing.get_args(ReportFormat) == report.FORMATS
    assert Report(root="r").formats == report.DEFAULT_FORMATS
    with pytest.raises(SystemExit):
        main(["report", str(tmp_path), "--formats", "docx"])


def test_the_html_page_shows_png_figures_when_no_svg_was_written(results, tmp_path, quick_figures):
    runs, evaluations = results
    paths = report.write_report(runs, evaluations, tmp_path, formats=("html",))
    page = paths["report.html"].read_text()
    assert '<img src="curves.png"' in page and ".svg" not in page and ".pdf" not in page
    assert "table.html" in paths and "table.tex" not in paths


def test_bad_input_gives_clear_errors(results):
    runs, evaluations = results
    with pytest.raises(ValueError, match="final_score"):
        tables.score_table(runs.drop(columns="final_score"))
    with pytest.raises(ValueError, match="unknown ablation parameter"):
        figures.plot_ablation(runs, evaluations, "alpha", "unused.png")
    with pytest.raises(ValueError, match="no runs of 'cql'"):
        figures.plot_ablation(runs, evaluations, "num_critics", "unused.png", algo="cql")


def test_report_lists_runs_whose_critics_diverged(results, tmp_path, quick_figures):
    runs, evaluations = results
    runs = runs.assign(q_out_of_range_step=np.nan)
    runs.loc[3, "q_out_of_range_step"] = 12000
    text = report.write_report(runs, evaluations, tmp_path)["report.md"].read_text()
    assert f"`{runs.loc[3, 'run_id']}` (step 12,000)" in text
    assert f"(1 of {len(runs)};" in text
    clean = report.write_report(runs.assign(q_out_of_range_step=np.nan), evaluations, tmp_path)
    assert "left the value range" not in clean["report.md"].read_text()


def test_figures_are_print_ready_and_name_the_algorithms_as_the_paper_does(written):
    from PIL import Image  # noqa: PLC0415

    out, paths = written
    for name in ("curves", "runtime", "profiles", "ablation_num_critics"):
        with Image.open(paths[f"{name}.png"]) as image:
            assert [round(d) for d in image.info["dpi"]] == [300, 300], name
        assert paths[f"{name}.pdf"].read_bytes()[:5] == b"%PDF-"
        assert "<svg" in paths[f"{name}.svg"].read_text()[:1000]
    curves = paths["curves.svg"].read_text()
    assert "TD3+BC" in curves and "EABC K=5" in curves and ">td3bc<" not in curves
    header = paths["table.md"].read_text().splitlines()[0]
    assert header == "| Dataset | TD3+BC | IQL | EABC | EABC K=5 |"
    assert "TD3+BC" in paths["table.tex"].read_text()
    assert "<th>TD3+BC</th>" in paths["table.html"].read_text()


def test_every_summary_says_what_it_rests_on_and_warns_when_that_is_thin(
    results, written, tmp_path, quick_figures
):
    runs, evaluations = results
    text = written[1]["report.md"].read_text()
    per_run = evaluations.groupby("run_id").size().iloc[0]  # 6: fewer than 10, said so
    assert (
        f"mean of its last 10 evaluations ({len(runs)} runs have fewer, {per_run} evaluations: "
        "the mean of all of them)" in text
    )
    assert f"over {len(SEEDS)} runs (seeds)" in text and "Warning" not in text
    assert "median steps/s over its training chunks" in text

    # Two seeds of TD3+BC on one dataset, five evaluations each: said, and warned about.
    few = runs[
        ~(
            (runs["algo"] == "td3bc")
            & (runs["seed"] >= 2)
            & (runs["dataset"] == runs["dataset"].iloc[0])
        )
    ]
    last5 = evaluations[evaluations["step"] >= sorted(evaluations["step"].unique())[-5]]
    text = report.write_report(few, last5, tmp_path / "few")["report.md"].read_text()
    assert "have fewer, 5 evaluations: the mean of all of them" in text
    assert "over 2-3 runs (seeds)" in text
    assert "**Warning:** TD3+BC rest on fewer than 3 runs" in text


def test_the_html_report_is_a_standalone_styled_page(written):
    out, paths = written
    page = paths["report.html"].read_text()
    assert page.startswith("<!DOCTYPE html>") and "<style>" in page and "</html>" in page
    assert '<img src="curves.svg"' in page and '<table class="scores">' in page
    assert "<th>TD3+BC</th>" in page and "http" not in page  # no external resources
    assert paths["table.html"].read_text().startswith("<!DOCTYPE html>")


def test_a_runs_speed_is_the_median_of_its_training_chunks(tmp_path):
    """The first chunk after a start or resume compiles; whole-run steps/s would count it."""
    import json  # noqa: PLC0415

    from eabc.experiments import results as store  # noqa: PLC0415

    run = tmp_path / "run"
    run.mkdir()
    train = {"dataset": "hopper-medium", "algo": "td3bc", "seed": 0, "steps": 4000}
    (run / "config.json").write_text(json.dumps({"train": train, "agent": {}, "dataset": {}}))
    rates = [4.0, 290.0, 300.0, 3.0, 280.0]  # two compiling chunks (start, resume)
    rows = [f"{1000 * (i + 1)},{1000 / r:.6f},{r}" for i, r in enumerate(rates)]
    (run / "log.csv").write_text("step,wall_time,steps_per_s\n" + "\n".join(rows) + "\n")
    row, _ = store.read_run(run)
    assert row["steps_per_s"] == 280.0
    table = tables.runtime_table(pd.DataFrame([row]))
    assert table.at["td3bc", "mean"] == pytest.approx(1e6 / 280.0 / 3600)


def test_a_wide_legend_wraps_and_stays_inside_the_saved_image(tmp_path):
    """Long variant labels used to run off both sides of the curves figure (one legend row)."""
    from matplotlib.figure import Figure  # noqa: PLC0415

    from eabc.experiments import figures  # noqa: PLC0415

    labels = [f"EABC-auto critic_layer_norm=True independent_targets=True #{i}" for i in range(5)]
    columns = figures.legend_columns(labels, 12.0)
    assert 1 <= columns < len(labels)
    assert figures.legend_columns(["BC", "TD3+BC"], 12.0) == 2
    fig = Figure(figsize=(12.0, 4.0))
    ax = fig.add_subplot()
    lines = [ax.plot([0, 1], [i, i])[0] for i in range(len(labels))]
    legend = fig.legend(lines, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=columns)
    path = figures._save(fig, tmp_path / "wide.png")
    renderer = fig.canvas.get_renderer() if hasattr(fig.canvas, "get_renderer") else None
    box = legend.get_window_extent(renderer)
    assert box.width <= fig.get_figwidth() * fig.dpi  # one figure's width, not wider
    from PIL import Image  # noqa: PLC0415

    with Image.open(path) as image:  # the saved canvas grew to hold the legend below the panels
        assert image.height > 4.0 * figures.PRINT_DPI


def test_an_average_over_fewer_datasets_says_so_and_is_never_bold(results):
    runs, _ = results
    # IQL only on walker2d-medium, where it now scores best of all: its average is over 1 of 2.
    runs = runs[(runs.algo != "iql") | (runs.dataset == "walker2d-medium")].copy()
    runs.loc[runs.algo == "iql", "final_score"] = 99.0
    rows = markdown_rows(tables.to_markdown(tables.score_table(runs)))
    average = rows["Average"]
    assert average[1].endswith("(1/2)") and "**" not in average[1]  # IQL's column
    assert sum("**" in cell for cell in average) == 1  # the best complete column keeps its bold
    assert rows["walker2d-medium"][1] == "**99.0 ± 0.0**"


# Runs on data without reference scores (a user's own file)


def without_scores(runs: pd.DataFrame, evaluations: pd.DataFrame, datasets=DATASETS):
    """The results as runs on ``datasets`` would have them without reference returns: no
    score, a final return (here 30 x what the score was)."""
    raw = runs["dataset"].isin(datasets)
    runs = runs.assign(final_return=30 * runs["final_score"])
    runs.loc[raw, "final_score"] = np.nan
    raw_ids = runs.loc[raw, "run_id"]
    evaluations = evaluations.copy()
    evaluations.loc[evaluations["run_id"].isin(raw_ids), "score"] = np.nan
    return runs, evaluations


def test_runs_without_reference_scores_are_reported_in_raw_return(results, tmp_path, quick_figures):
    runs, evaluations = without_scores(*results)
    published = runs[(runs["algo"] == "eabc") & (runs["variant"] == "")]
    recommended = published.assign(algo="eabc-ln", run_id=published["run_id"] + "-ln")
    runs = pd.concat([runs, recommended], ignore_index=True)
    runs = runs.assign(q_out_of_range_step=np.nan, q_mean_max=np.nan)  # for failures.md
    paths = report.write_report(runs, evaluations, tmp_path, formats=("html",))
    table = paths["table.md"].read_text()
    assert table.startswith("Raw return: these runs have no reference scores")
    rows = markdown_rows(table)
    expected = runs[runs["algo"] == "td3bc"].groupby("dataset")["final_return"].mean()
    for dataset, mean in expected.items():
        assert abs(float(rows[dataset][0].strip("*").split(" ± ")[0]) - mean) <= 0.05
    text = paths["report.md"].read_text()
    assert "## Returns (Table 1)" in text and "Raw return: these runs have no reference" in text
    assert "mean final return" in paths["comparison.md"].read_text()
    assert "| TD3+BC return | EABC: return |" in paths["failures.md"].read_text()
    assert "Not computed for raw returns" in text and "aggregate.md" not in paths
    assert "profiles.png" not in paths and "Raw return" in paths["table.html"].read_text()


def test_a_dataset_without_reference_scores_gets_a_section_of_returns(
    results, tmp_path, quick_figures
):
    runs, evaluations = without_scores(*results, datasets=["hopper-random"])
    paths = report.write_report(runs, evaluations, tmp_path, formats=("html",))
    assert set(markdown_rows(paths["table.md"].read_text())) == {"walker2d-medium", "Average"}
    returns = paths["returns_table.md"].read_text()
    assert returns.startswith("Raw return") and "hopper-random" in returns
    text = paths["report.md"].read_text()
    assert "## Returns of the runs without reference scores" in text
    assert "Also as [returns_comparison.md](returns_comparison.md)" in text
    assert "returns_curves.png" in paths and "IQM" in text  # the scores keep their statistics
    page = paths["report.html"].read_text()  # each score table rendered as itself
    assert page.count('<table class="scores">') == 2


def test_a_missing_baseline_lists_the_labels_there_are(results):
    runs, _ = results
    with pytest.raises(ValueError, match=r"no run is labelled 'cql'; the labels are: td3bc, iql"):
        compare.comparison_table(runs, "cql")
    unscored = runs.assign(final_score=np.nan)
    with pytest.raises(ValueError, match=r"the runs labelled 'td3bc' have no final_score yet"):
        compare.comparison_table(unscored, "td3bc")


def _run_directory(root, algo: str, returns: list[float], dataset="my_data", name=None, **train):
    """A finished run of ``algo`` on a user's file without reference scores, as training
    leaves it: config.json, log.csv (evaluations with a return and no score), summary.json."""
    run_dir = root / (name or algo)
    run_dir.mkdir(parents=True)
    steps = 100 * len(returns)
    train = {"dataset": str(root / f"{dataset}.npz"), "algo": algo, "seed": 0, "steps": steps,
             "env": "Hopper-v4", **train}  # fmt: skip
    config = {"train": train, "agent": {}, "dataset": {"name": dataset, "ref_min_score": None}}
    (run_dir / "config.json").write_text(json.dumps(config))
    rows = ["step,return_mean,return_std,score,wall_time,steps_per_s"]
    rows += [f"{100 * (i + 1)},{r},1.0,,{i + 1},100.0" for i, r in enumerate(returns)]
    (run_dir / "log.csv").write_text("\n".join(rows) + "\n")
    summary = {"steps": steps, "evaluations": len(returns), "final_return": float(np.mean(returns))}
    (run_dir / "summary.json").write_text(json.dumps(summary))


def test_eabc_report_on_runs_of_a_users_own_data_reports_returns(tmp_path, capsys, quick_figures):
    """Before: nothing written, and 'no finished run is labelled td3bc; the labels are: '."""
    root = tmp_path / "root"
    _run_directory(root, "td3bc", [500.0, 700.0])
    _run_directory(root, "bc", [400.0, 450.0])
    main(["report", str(root)])
    text = (root / "report" / "report.md").read_text()
    assert "## Returns (Table 1)" in text and "Raw return: these runs have no reference" in text
    rows = markdown_rows((root / "report" / "table.md").read_text())
    assert rows["my_data"] == ["425.0", "**600.0**"]  # BC, TD3+BC: the mean final returns
    assert "mean final return" in (root / "report" / "comparison.md").read_text()
    with pytest.raises(
        SystemExit, match=r"--baseline iql: no runs with that label; labels: bc, td3bc"
    ):
        main(["report", str(root), "--baseline", "iql"])


def test_a_refused_report_or_results_command_writes_nothing(tmp_path):
    """Before: results.sqlite was written before --baseline, --fix, --out, --include, --columns
    and --filter were checked (and an --out that is a file named no flag)."""
    root = tmp_path / "root"
    _run_directory(root, "td3bc", [500.0, 700.0])
    (tmp_path / "afile").write_text("")
    refusals = [
        (["report", str(root), "--baseline", "nope"], "--baseline nope: no runs"),
        (["report", str(root), "--fix", "nope"], "--fix nope: no runs"),
        (["report", str(root), "--out", str(tmp_path / "afile")], "--out .*afile is not a dir"),
        (["report", str(root), "--include", str(tmp_path / "missing")], "missing has no runs"),
        (["results", str(root), "--columns", "bogus"], "--columns: unknown column"),
        (["results", str(root), "--filter", "x=1"], "bad filter 'x=1'"),
    ]
    for argv, message in refusals:
        with pytest.raises(SystemExit, match=message):
            main(argv)
        assert sorted(p.name for p in root.iterdir()) == ["td3bc"], argv
    main(["results", str(root)])
    assert (root / "results.sqlite").exists()


def test_eabc_results_shows_a_missing_value_as_a_dash(tmp_path, capsys):
    """Before: ``NaN`` for a run without a score or a steps/s."""
    root = tmp_path / "root"
    _run_directory(root, "td3bc", [500.0, 700.0])
    capsys.readouterr()
    main(["results", str(root), "--columns", "run_id", "final_score", "final_return",
          "q_out_of_range_step"])  # fmt: skip
    out = capsys.readouterr().out
    assert "NaN" not in out and "None" not in out and "nan" not in out
    row = out.splitlines()[1].split()
    assert row[1:] == ["–", "600.0", "–"]
    main(["results", str(root), "--columns", "run_id", "final_score", "--csv"])
    assert capsys.readouterr().out.splitlines()[1].endswith(",")  # CSV: empty, machine-readable


def test_eabc_results_says_what_final_score_averages(tmp_path, capsys):
    """Before: a run of 5 evaluations showed the mean of all 5 as its final score, beside runs
    of the last 10, without a word (the report says it; `eabc results` did not)."""
    root = tmp_path / "root"
    _run_directory(root, "td3bc", [500.0, 700.0])
    capsys.readouterr()
    main(["results", str(root)])
    note = capsys.readouterr().out.splitlines()[-1]
    assert note == (
        "final_score: the mean of a run's last 10 evaluations; of all of them where it has "
        "fewer (td3bc: 2)"
    ), note


def test_report_tables_show_a_missing_value_as_a_dash(results):
    runs, _ = results
    table = tables.stability_table(runs.assign(q_mean_max=np.nan))
    text = tables.stability_to_markdown(table)
    body = [line for line in text.splitlines()[2:]]
    assert body and all("|  |" not in line and "nan" not in line.lower() for line in body)
    assert all(line.split(" | ")[6] == "–" for line in body)  # max mean Q: none recorded
    one = runs[(runs["seed"] == 0) & (runs["dataset"] == DATASETS[0])]
    runtime = tables.runtime_to_markdown(tables.runtime_table(one))
    assert "± 0.00" not in runtime and "± –" in runtime  # one run: no spread, not a zero one


def test_curve_titles_say_over_how_many_seeds(results, tmp_path, monkeypatch):
    """Before: "mean ± 1 std over seeds" above curves of one seed, which have no band."""
    runs, evaluations = results
    titles = []
    monkeypatch.setattr(
        figures, "_plot_curves", lambda stats, by, keys, path, title, **kw: titles.append(title)
    )
    figures.plot_learning_curves(runs, evaluations, tmp_path / "a.png")
    figures.plot_learning_curves(runs[runs["seed"] == 0], evaluations, tmp_path / "b.png")
    mixed = runs[(runs["seed"] == 0) | (runs["algo"] == "td3bc")]
    figures.plot_learning_curves(mixed, evaluations, tmp_path / "c.png")
    figures.plot_ablation(runs[runs["seed"] < 2], evaluations, "num_critics", tmp_path / "d.png")
    assert titles == [
        f"Learning curves: mean ± 1 std over {len(SEEDS)} seeds",
        "Learning curves: one seed each (no band)",
        f"Learning curves: mean ± 1 std over 1-{len(SEEDS)} seeds (one seed: no band)",
        "Ablation of num_critics (EABC)\nmean ± 1 std over 2 seeds",
    ]


def test_writing_a_report_says_its_stages(results, tmp_path, capfd, quick_figures):
    """Before: a report of many runs wrote its tables and figures in silence."""
    runs, evaluations = results
    report.write_report(runs, evaluations, tmp_path / "report")
    err = capfd.readouterr().err
    assert f"eabc: report: {len(runs)} runs into {tmp_path / 'report'}: tables\n" in err
    assert "eabc: report: figures (learning curves, ablations, runtime)\n" in err
    assert re.search(r"eabc: report: done in ([\d.]+ (s|minutes)|less than a second)\n", err)
    assert err.index(": tables") < err.index(": figures") < err.index(": done in")


def test_the_report_says_which_reward_convention_each_run_trained_on(tmp_path, quick_figures):
    """runs.csv records each run's reward convention where its data has sparse goal rewards (a
    run from before the setting: r - 1, what it trained on), and report.md counts them."""
    root = tmp_path / "root"
    _run_directory(root, "td3bc", [0.5, 0.7], "antmaze-umaze", reward_convention="raw")
    _run_directory(root, "iql", [0.6, 0.8], "antmaze-umaze", reward_convention="iql-scale")
    _run_directory(root, "bc", [0.6, 0.6], "antmaze-umaze")  # config.json without the setting
    _run_directory(
        root, "td3bc", [500.0, 700.0], "hopper-medium", name="hopper", reward_convention="raw"
    )
    main(["report", str(root)])
    runs = pd.read_csv(root / "report" / "runs.csv", keep_default_na=False).set_index("run_id")
    assert runs["reward_convention"].to_dict() == {
        "bc": "minus-one", "hopper": "", "iql": "iql-scale", "td3bc": "raw"
    }  # fmt: skip
    text = (root / "report" / "report.md").read_text()
    assert "`iql-scale` 1 (IQL); `minus-one` 1 (BC); `raw` 1 (TD3+BC)." in text
    _run_directory(tmp_path / "mujoco", "td3bc", [500.0, 700.0], "hopper-medium")
    main(["report", str(tmp_path / "mujoco")])
    assert "Sparse goal rewards" not in (tmp_path / "mujoco" / "report" / "report.md").read_text()
    # A report from before the column, read back: runs.csv keeps no config, so it cannot say.
    runs.drop(columns="reward_convention").to_csv(root / "report" / "runs.csv")
    main(
        [
            "report",
            str(tmp_path / "none"),
            "--include",
            str(root / "report"),
            "--out",
            str(tmp_path / "again"),
        ]
    )
    assert "`not recorded` 3 (BC, IQL, TD3+BC)." in (tmp_path / "again" / "report.md").read_text()
