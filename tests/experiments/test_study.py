"""The study's sweep presets: named variants, breadth-first order, the protocol's numbers."""

from __future__ import annotations

import pytest

from eabc import cli
from eabc.experiments.presets import PRESETS
from eabc.experiments.spec import expand

pytestmark = pytest.mark.usefixtures("quick_figures")  # tables and text, not figures


def test_variants_expand_breadth_first_beside_the_grid():
    spec = {
        "datasets": ["hopper-medium", "walker2d-medium"],
        "algos": ["td3bc"],
        "variants": [{"algo": "eabc"}, {"algo": "eabc-auto", "critic_layer_norm": True}],
        "seeds": [0, 1],
        "steps": 1000,
    }
    runs = expand(spec)
    ids = [r.run_id for r in runs]
    assert ids[:4] == [  # the algos part keeps its order: dataset, algo, seed
        "hopper-medium__td3bc__seed0",
        "hopper-medium__td3bc__seed1",
        "walker2d-medium__td3bc__seed0",
        "walker2d-medium__td3bc__seed1",
    ]
    assert ids[4:8] == [  # variants: seed, then variant, then dataset
        "hopper-medium__eabc__seed0",
        "walker2d-medium__eabc__seed0",
        "hopper-medium__eabc-auto__critic_layer_normTrue__seed0",
        "walker2d-medium__eabc-auto__critic_layer_normTrue__seed0",
    ]
    assert len(runs) == 4 + 2 * 2 * 2 and len(set(ids)) == len(ids)
    variant = runs[6]
    assert variant.overrides == (("critic_layer_norm", True),)
    assert variant.variant == "critic_layer_norm=True"
    assert variant.train_config().steps == 1000


def test_a_variant_can_name_its_own_datasets_to_set_the_priority_order():
    spec = {
        "datasets": ["hopper-medium", "walker2d-medium"],
        "variants": [
            {"algo": "eabc", "critic_layer_norm": True, "datasets": ["hopper-medium"]},
            {"algo": "td3bc"},
            {"algo": "eabc", "critic_layer_norm": True, "datasets": ["walker2d-medium"]},
            {"algo": "td3bc", "datasets": ["hopper-random"]},
            {"algo": "td3bc", "datasets": ["hopper-medium"]},  # already listed: not run twice
        ],
        "seeds": [0],
    }
    ids = [r.run_id for r in expand(spec)]
    assert ids == [
        "hopper-medium__eabc__critic_layer_normTrue__seed0",
        "hopper-medium__td3bc__seed0",
        "walker2d-medium__td3bc__seed0",
        "walker2d-medium__eabc__critic_layer_normTrue__seed0",
        "hopper-random__td3bc__seed0",
    ]
    with pytest.raises(ValueError, match="non-empty list"):
        expand({**spec, "variants": [{"algo": "td3bc", "datasets": "hopper-medium"}]})


def test_bad_variants_are_refused_with_the_settings_named():
    base = {"datasets": ["hopper-medium"], "seeds": [0]}
    with pytest.raises(ValueError, match="has no setting"):
        expand({**base, "variants": [{"algo": "td3bc", "layer_norm": True}]})
    with pytest.raises(ValueError, match="'algo' key"):
        expand({**base, "variants": [{"critic_layer_norm": True}]})
    with pytest.raises(ValueError, match="unknown algorithm"):
        expand({**base, "variants": ["eabc-nope"]})
    with pytest.raises(ValueError, match="'algos' or 'variants'"):
        expand(base)


def test_study_presets_follow_the_study_protocol():
    assert set(cli.SWEEP_PRESETS) == set(PRESETS)
    screen = PRESETS["study-screen"]
    runs = expand(screen)
    datasets = {
        "hopper-medium",
        "hopper-medium-replay",
        "hopper-random",
        "halfcheetah-medium",
        "walker2d-medium",
    }
    assert {r.dataset for r in runs} == datasets
    assert {r.seed for r in runs} == {0, 1}
    config = runs[0].train_config()
    assert (config.steps, config.eval_interval, config.eval_episodes) == (50_000, 5000, 10)
    # Published EABC (Table 3's p) and TD3+BC are in every screen, first.
    assert [r.algo for r in runs[:10]] == ["td3bc"] * 5 + ["eabc"] * 5
    assert all(r.overrides == () for r in runs[:10])
    confirm = expand(PRESETS["study"])
    config = confirm[0].train_config()
    assert (config.steps, {r.seed for r in confirm}) == (100_000, {0, 1, 2})
    labels = {(r.algo, r.overrides) for r in confirm}
    assert labels == {
        ("td3bc", ()),
        ("eabc", ()),
        ("eabc", (("confidence_level", 1.0),)),
        ("eabc-ln", ()),
    }
    long = expand(PRESETS["study-1m"])
    assert {r.dataset for r in long} == {"hopper-medium", "halfcheetah-medium"}
    assert long[0].train_config().steps == 1_000_000
    # breadth first: every algorithm's seed 0 on both datasets before any seed 1
    zero = [r for r in long if r.seed == 0]
    assert {r.seed for r in long[: len(zero)]} == {0} and len(zero) < len(long)


def test_stability_table_says_where_the_critics_fail():
    import math

    import pandas as pd

    from eabc.experiments import tables

    nan = math.nan
    runs = pd.DataFrame(
        {
            "run_id": ["a", "b", "c", "d"],
            "dataset": ["hopper-medium"] * 4,
            "algo": ["eabc", "eabc", "td3bc", "eabc"],
            "variant": ["", "", "", "critic_layer_norm=True"],
            "seed": [0, 1, 0, 0],
            "final_score": [5.0, 9.0, 48.0, 50.0],
            "q_out_of_range_step": [11_000, 17_000, nan, nan],
            "q_mean_max": [2000.0, 4000.0, 150.0, 120.0],
            "q_mean_last": [1000.0, -500.0, 100.0, 100.0],
            "policy_q_std_last": [10.0, 10.0, nan, 5.0],
            "q_ensemble_std_last": [5.0, 2.5, nan, 6.0],
            "bc_fraction_last": [0.25, 0.25, 1.0, 0.5],
        }
    )
    table = tables.stability_table(runs)
    assert list(table["label"]) == ["td3bc", "eabc", "eabc critic_layer_norm=True"]
    eabc = table[table["label"] == "eabc"].iloc[0]
    assert eabc["runs"] == 2 and eabc["out_of_range"] == 2
    assert eabc["first_out_of_range_step"] == 11_000
    assert eabc["q_mean_max"] == 3000.0
    assert math.isclose(eabc["policy_spread"], (0.01 + 0.02) / 2)
    assert math.isclose(eabc["spread_ratio"], (2.0 + 4.0) / 2)  # the policy off the data's support
    assert math.isclose(eabc["score"], 7.0) and math.isclose(eabc["score_std"], 2**0.5 * 2)
    text = tables.stability_to_markdown(table)
    assert (
        "| hopper-medium | EABC | 2 | 7.0 ± 2.8 | 2/2 | 11,000 | 3,000 | 1.50% | 3.00 | 0.25 |"
        in text
    )
    assert "| hopper-medium | TD3+BC | 1 | 48.0 | 0/1 | – | 150 | – | – | 1.00 |" in text


def test_a_run_keeps_the_ensembles_state_from_just_before_its_critics_ran_away(tmp_path):
    """A runaway run's last row is long past the runaway (mean Q 1e9): the failure table needs
    the row before the first out-of-range one; a run that stayed in range has no onset."""
    import json
    import math

    from eabc.experiments import results

    header = "step,wall_time,steps_per_s,q_mean,q_ensemble_std,policy_q_std,q_out_of_range"
    logs = {
        "ran-away": ["1000,1,100,50,2,2,0", "2000,2,100,300,4,9,0", "3000,3,100,900,8,40,1",
                     "4000,4,100,1e9,1e6,5e6,1"],
        "in-range": ["1000,1,100,50,2,2,0", "2000,2,100,60,2,3,0"],
        "out-at-once": ["1000,1,100,900,8,40,1"],
    }  # fmt: skip
    rows = {}
    for name, lines in logs.items():
        run = tmp_path / name
        run.mkdir()
        train = {"dataset": "hopper-medium", "algo": "eabc", "seed": 0, "steps": 4000}
        (run / "config.json").write_text(json.dumps({"train": train, "agent": {}, "dataset": {}}))
        (run / "log.csv").write_text("\n".join([header, *lines]) + "\n")
        rows[name], _ = results.read_run(run)
    away = rows["ran-away"]
    assert away["q_out_of_range_step"] == 3000
    assert (away["q_mean_onset"], away["q_ensemble_std_onset"], away["policy_q_std_onset"]) == (
        300.0,
        4.0,
        9.0,
    )
    assert away["q_mean_last"] == 1e9  # the last row is still the last row
    assert all(math.isnan(rows["in-range"][f"{k}_onset"]) for k in results.ONSET)
    assert rows["out-at-once"]["q_mean_onset"] == 900.0  # no row in range: the first one


def test_the_failure_table_sets_published_eabc_beside_the_fix(tmp_path):
    import math

    import pandas as pd

    from eabc.experiments import report, tables

    nan = math.nan
    runs = pd.DataFrame(
        {
            "run_id": ["p0", "p1", "f0", "f1", "t0", "w"],
            "dataset": ["hopper-medium"] * 5 + ["walker2d-medium"],
            "algo": ["eabc", "eabc", "eabc-ln", "eabc-ln", "td3bc", "eabc"],
            "variant": [""] * 6,
            "seed": [0, 1, 0, 1, 0, 0],
            "final_score": [5.0, 9.0, 50.0, 54.0, 48.0, 70.0],
            "q_out_of_range_step": [11_000, 17_000, nan, nan, nan, nan],
            "q_mean_max": [2e6, 4e6, 200.0, 210.0, 150.0, 220.0],
            # Runaway rows at the end: the table must not read them for the published runs.
            "q_mean_last": [1e9, 1e9, 100.0, 100.0, 100.0, 100.0],
            "q_ensemble_std_last": [1e6, 1e6, 5.0, 5.0, 5.0, 5.0],
            "policy_q_std_last": [9e6, 9e6, 4.0, 6.0, 5.0, 5.0],
            "q_mean_onset": [200.0, 400.0, nan, nan, nan, nan],
            "q_ensemble_std_onset": [2.0, 2.0, nan, nan, nan, nan],
            "policy_q_std_onset": [4.0, 12.0, nan, nan, nan, nan],
            "bc_fraction_last": [0.25, 0.25, 1.0, 1.0, 1.0, 0.25],
            "status": ["done"] * 6,
            "steps": [100_000] * 6,
            "steps_per_s": [80.0, 80.0, 40.0, 40.0, 300.0, 80.0],
        }
    )
    table = tables.failure_table(runs, "eabc", "eabc-ln", "td3bc")
    assert list(table["dataset"]) == ["hopper-medium"]  # walker2d has no eabc-ln run
    row = table.iloc[0]
    assert row["baseline_score"] == 48.0
    assert (row["published_runs"], row["published_out_of_range"]) == (2, 2)
    assert row["published_first_out"] == 11_000 and row["published_score"] == 7.0
    assert math.isclose(row["published_spread"], (0.02 + 0.03) / 2)  # at the onset rows
    assert math.isclose(row["published_ratio"], (2.0 + 6.0) / 2)
    assert row["fix_out_of_range"] == 0 and math.isnan(row["fix_first_out"])
    assert math.isclose(row["fix_ratio"], (0.8 + 1.2) / 2)  # at the last rows: in range
    text = tables.failure_to_markdown(table, "eabc", "eabc-ln", "td3bc")
    assert (
        "| hopper-medium | 48.0 | 7.0 | 2/2 | 11,000 | 3,000,000 | 2.50% | 4.00 | 0.25 | 52.0 | 0/2 |"
        in text
    )
    with pytest.raises(ValueError, match="eabc-lnn"):
        tables.failure_table(runs, "eabc", "eabc-lnn")
    # The report writes it when both ran, and says nothing of it when the fix did not.
    evaluations = pd.DataFrame(
        {"run_id": runs["run_id"], "step": 5000, "score": runs["final_score"]}
    )
    paths = report.write_report(runs, evaluations, tmp_path / "with")
    assert "failures.md" in paths and "Where published EABC fails" in paths["report.md"].read_text()
    paths = report.write_report(runs[runs.algo != "eabc-ln"], evaluations, tmp_path / "without")
    assert "failures.md" not in paths
    # A --fix that names no label is an error that lists the labels, not a report without it.
    with pytest.raises(SystemExit, match=r"--fix eabc-lnn: no runs with that label; labels: eabc,"):
        cli.main(["report", str(tmp_path / "none"), "--include", str(tmp_path / "with"),
                  "--fix", "eabc-lnn", "--out", str(tmp_path / "again")])  # fmt: skip
    cli.main(["report", str(tmp_path / "none"), "--include", str(tmp_path / "with"), "--out",
              str(tmp_path / "again"), "--fix", "eabc-ln"])  # fmt: skip
    again = (tmp_path / "again/failures.md").read_text()  # the onset rows survive runs.csv
    assert "| hopper-medium | 48.0 | 7.0 | 2/2 | 11,000 | 3,000,000 | 2.50% | 4.00 |" in again
