"""Issue 14's study as sweep presets: named variants, breadth-first order, the protocol's numbers."""

from __future__ import annotations

import pytest

from eabc import cli
from eabc.experiments.presets import PRESETS
from eabc.experiments.spec import expand


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


def test_study_presets_follow_the_issue_protocol():
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
    assert {r.dataset for r in long} == {"halfcheetah-medium"}
    assert long[0].train_config().steps == 1_000_000


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
    assert "| hopper-medium | TD3+BC | 1 | 48.0 | 0/1 |  | 150 |  |  | 1.00 |" in text
