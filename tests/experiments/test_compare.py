"""Every algorithm against a baseline, dataset by dataset (the study's criterion), by hand."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from eabc.experiments import compare, report

pytestmark = pytest.mark.usefixtures("quick_figures")  # tables and text, not figures


def runs_frame(scores: dict[tuple[str, str], list[float]]) -> pd.DataFrame:
    rows = []
    for (label, dataset), values in scores.items():
        algo, _, variant = label.partition(" ")
        for seed, value in enumerate(values):
            rows.append(
                {
                    "run_id": f"{dataset}__{algo}__{variant}__seed{seed}",
                    "dataset": dataset,
                    "algo": algo,
                    "variant": variant,
                    "seed": seed,
                    "status": "done",
                    "steps": 1000,
                    "final_score": value,
                    "steps_per_s": 100.0,
                    "wall_time_s": 10.0,
                }
            )
    return pd.DataFrame(rows)


SCORES = {
    ("td3bc", "hopper-medium"): [50.0, 49.0, 51.0],
    ("td3bc", "walker2d-medium"): [48.0, 47.0, 49.0],
    ("td3bc", "hopper-random"): [30.0, 31.0, 29.0],
    ("eabc-ln", "hopper-medium"): [60.0, 62.0, 64.0],  # every resample above 50: above
    ("eabc-ln", "walker2d-medium"): [40.0, 60.0, 50.0],  # 48 inside [40, 60]: tie
    ("eabc-ln", "hopper-random"): [10.0, 12.0, 11.0],  # every resample below 30: below
    ("eabc-ln", "halfcheetah-medium"): [70.0, 71.0],  # no baseline there
    ("eabc p=1.0", "hopper-medium"): [55.0],  # one run: no interval
}


def hand_interval(values, reps=2000, seed=0):
    """The percentile bootstrap of the mean, written out."""
    values = np.asarray(values)
    rng = np.random.default_rng(seed)
    means = values[rng.integers(0, values.size, size=(reps, values.size))].mean(axis=1)
    return np.percentile(means, [2.5, 97.5])


def test_verdicts_means_and_intervals_per_dataset():
    table = compare.comparison_table(runs_frame(SCORES), "td3bc")
    ln = table.loc["eabc-ln"]
    assert ln.loc["hopper-medium", "verdict"] == "above"
    assert ln.loc["walker2d-medium", "verdict"] == "tie"
    assert ln.loc["hopper-random", "verdict"] == "below"
    assert ln.loc["halfcheetah-medium", "verdict"] == "–"  # no TD3+BC runs to compare with
    assert ln.loc["hopper-medium", "mean"] == pytest.approx(62.0)
    assert ln.loc["hopper-medium", "difference"] == pytest.approx(12.0)
    assert ln.loc["walker2d-medium", "baseline_mean"] == pytest.approx(48.0)
    low, high = hand_interval(SCORES[("eabc-ln", "walker2d-medium")])
    assert ln.loc["walker2d-medium", "low"] == pytest.approx(low)
    assert ln.loc["walker2d-medium", "high"] == pytest.approx(high)
    one = table.loc[("eabc p=1.0", "hopper-medium")]
    assert one["verdict"] == "–" and one["low"] == one["high"] == 55.0
    assert "td3bc" not in table.index.get_level_values("label")


def test_average_is_over_the_datasets_both_ran_with_a_stratified_interval():
    row = compare.comparison_table(runs_frame(SCORES), "td3bc").loc[("eabc-ln", "Average")]
    shared = ["hopper-medium", "walker2d-medium", "hopper-random"]  # not halfcheetah-medium
    assert row["mean"] == pytest.approx(np.mean([np.mean(SCORES[("eabc-ln", d)]) for d in shared]))
    assert row["baseline_mean"] == pytest.approx(
        np.mean([np.mean(SCORES[("td3bc", d)]) for d in shared])
    )
    assert row["runs"] == 9 and row["baseline_runs"] == 9
    # Resampling each dataset's seeds on their own keeps the interval inside the range of the
    # means of per-dataset extremes, and around the estimate.
    lows = np.mean([min(SCORES[("eabc-ln", d)]) for d in shared])
    highs = np.mean([max(SCORES[("eabc-ln", d)]) for d in shared])
    assert lows <= row["low"] < row["mean"] < row["high"] <= highs
    assert row["verdict"] == "tie"  # 41.0 [37.8, 44.1] reaches 42.7


def test_an_unknown_baseline_names_the_labels_there_are():
    with pytest.raises(ValueError, match="labelled 'cql'.*td3bc"):
        compare.comparison_table(runs_frame(SCORES), "cql")


def test_the_report_compares_with_td3bc_when_it_ran_and_not_otherwise(tmp_path):
    runs = runs_frame(SCORES)
    evaluations = pd.DataFrame(
        [{"run_id": r, "step": 1000, "score": s} for r, s in zip(runs.run_id, runs.final_score)]
    )
    paths = report.write_report(runs, evaluations, tmp_path / "with")
    text = paths["comparison.md"].read_text()
    assert "| EABC-LN | hopper-random | 3 | 11.0 [10.0, 12.0] | 30.0 (3) | -19.0 | below |" in text
    assert "## Against TD3+BC, dataset by dataset" in paths["report.md"].read_text()
    chosen = report.write_report(runs, evaluations, tmp_path / "chosen", baseline="eabc-ln")
    assert "| TD3+BC | hopper-random |" in chosen["comparison.md"].read_text()
    no_td3bc = runs[runs.algo != "td3bc"]
    assert "comparison.md" not in report.write_report(no_td3bc, evaluations, tmp_path / "without")


def test_two_runs_get_no_verdict_even_when_both_lie_on_one_side():
    scores = {
        ("td3bc", "walker2d-medium"): [69.9, 68.9, 69.4],
        ("eabc-ln", "walker2d-medium"): [68.7, 68.9],
    }
    row = compare.comparison_table(runs_frame(scores), "td3bc").loc[("eabc-ln", "walker2d-medium")]
    assert row["high"] < row["baseline_mean"]  # both below TD3+BC's mean ...
    assert row["verdict"] == "–"  # ... but two seeds are too few to say "beyond seed noise"
    scores[("eabc-ln", "walker2d-medium")].append(68.8)
    row = compare.comparison_table(runs_frame(scores), "td3bc").loc[("eabc-ln", "walker2d-medium")]
    assert row["verdict"] == "below"
