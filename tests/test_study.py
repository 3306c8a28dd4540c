"""Issue 14's study as sweep presets: named variants, breadth-first order, the protocol's numbers."""

from __future__ import annotations

import pytest

from eabc import cli
from eabc.experiments import sweep


def test_variants_expand_breadth_first_beside_the_grid():
    spec = {
        "datasets": ["hopper-medium", "walker2d-medium"],
        "algos": ["td3bc"],
        "variants": [{"algo": "eabc"}, {"algo": "eabc-auto", "critic_layer_norm": True}],
        "seeds": [0, 1],
        "steps": 1000,
    }
    runs = sweep.expand(spec)
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


def test_bad_variants_are_refused_with_the_settings_named():
    base = {"datasets": ["hopper-medium"], "seeds": [0]}
    with pytest.raises(ValueError, match="has no setting"):
        sweep.expand({**base, "variants": [{"algo": "td3bc", "layer_norm": True}]})
    with pytest.raises(ValueError, match="'algo' key"):
        sweep.expand({**base, "variants": [{"critic_layer_norm": True}]})
    with pytest.raises(ValueError, match="unknown algorithm"):
        sweep.expand({**base, "variants": ["eabc-nope"]})
    with pytest.raises(ValueError, match="'algos' or 'variants'"):
        sweep.expand(base)


def test_study_presets_follow_the_issue_protocol():
    assert set(cli.SWEEP_PRESETS) == set(sweep.PRESETS)
    screen = sweep.PRESETS["study-screen"]
    runs = sweep.expand(screen)
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
    confirm = sweep.expand(sweep.PRESETS["study"])
    config = confirm[0].train_config()
    assert (config.steps, {r.seed for r in confirm}) == (100_000, {0, 1, 2})
    labels = {(r.algo, r.overrides) for r in confirm}
    assert labels == {
        ("td3bc", ()),
        ("eabc", ()),
        ("eabc", (("confidence_level", 1.0),)),
        ("eabc-robust", ()),
    }
    long = sweep.expand(sweep.PRESETS["study-1m"])
    assert {r.dataset for r in long} == {"halfcheetah-medium"}
    assert long[0].train_config().steps == 1_000_000
