"""The paper's grids and the study's as sweep presets (``eabc sweep --preset NAME``)."""

from __future__ import annotations

from typing import Any

from eabc.data import generate

# The study: where published EABC fails on our data and what fixes it, at lengths a 2-core CPU
# affords (final = mean of the last 10 of the evaluations every 5,000 steps x 10 episodes).
STUDY_DATASETS = [
    "hopper-medium",
    "halfcheetah-medium",
    "hopper-medium-replay",
    "walker2d-medium",
    "hopper-random",
]
STUDY_TRAIN = {"eval_interval": 5000, "eval_episodes": 10}
SCREEN_VARIANTS = [  # in order of priority: a screen stopped early has run the first ones
    {"algo": "td3bc"},
    {"algo": "eabc"},  # published: Table 3's p
    # Full cloning on LayerNorm critics: on hopper-medium every LayerNorm run scored best while its
    # p was still near 1 (94 at 10K steps, 79 at 20K) and lost it as p fell.
    {"algo": "eabc", "confidence_level": 1.0, "critic_layer_norm": True},
    # Auto p as a trust region: the policy's distance from the data's actions within twice what
    # cloning leaves (the spread ratio kept critics sound but let hopper-medium's policy drift).
    {"algo": "eabc-trust"},
    {"algo": "eabc-robust"},  # auto p with a calibrated target, on LayerNorm critics
    {"algo": "eabc", "confidence_level": 1.0},
    {"algo": "eabc", "critic_layer_norm": True},
    {"algo": "eabc-auto", "critic_layer_norm": True},
    {"algo": "eabc-quantile"},
    {"algo": "eabc-auto", "critic_layer_norm": True, "independent_targets": True},
    {"algo": "eabc-auto"},
    {"algo": "eabc", "independent_targets": True, "pessimism_beta": 2.0},
    {"algo": "eabc", "pessimism_beta": 2.0},
    # No p: clone where the ensemble rates the data's action at least as high as the policy's
    # (last: the actor maximises the same critics, so its action nearly always wins; on
    # hopper-medium the BC term was on for 5% of samples after 1K steps).
    {"algo": "eabc", "bc_weight": "advantage", "critic_layer_norm": True},
]


PRESETS: dict[str, dict[str, Any]] = {
    # Table 1: EABC against BC, TD3, TD3+BC, CQL, IQL and wPC on the 15 datasets, 5 seeds, 1M steps.
    "table1": {
        "datasets": generate.mujoco_names(),
        "algos": ["bc", "td3", "td3bc", "cql", "iql", "wpc", "eabc"],
        "seeds": [0, 1, 2, 3, 4],
    },
    # Table 6: BEAR, MOReL, MOPO, UWAC (its column order), EDAC (50 critics), EDAC-10 and EABC.
    "table6": {
        "datasets": generate.mujoco_names(),
        "algos": ["bear", "morel", "mopo", "uwac", "edac", "edac-10", "eabc"],
        "seeds": [0, 1, 2, 3, 4],
    },
    # Table 5: TD3+BC and EABC (Table 5's p) on the six AntMaze datasets, 5 seeds, 1M steps;
    # scores are 100 x the success rate over the evaluation episodes.
    "table5": {
        "datasets": generate.antmaze_names(),
        "algos": ["td3bc", "eabc"],
        "seeds": [0, 1, 2, 3, 4],
    },
    # Figure 2: K in {3, 5, 7, 10, 20, 30} with Table 3's p.
    "ablation-k": {
        "datasets": generate.mujoco_names(),
        "algos": ["eabc"],
        "seeds": [0, 1, 2, 3, 4],
        "grid": {"num_critics": [3, 5, 7, 10, 20, 30]},
    },
    # Figure 3: p in {0, 0.05, 0.25, 0.5, 0.75, 0.95, 1} at K = 10.
    "ablation-p": {
        "datasets": generate.mujoco_names(),
        "algos": ["eabc"],
        "seeds": [0, 1, 2, 3, 4],
        "grid": {"confidence_level": [0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0]},
    },
    # The study's screen: every variant against published EABC and TD3+BC, 2 seeds, 50K steps
    # (what ran of it: docs/results/screen/README.md).
    "study-screen": {
        "datasets": STUDY_DATASETS,
        "variants": SCREEN_VARIANTS,
        "seeds": [0, 1],
        "steps": 50_000,
        "train": STUDY_TRAIN,
    },
    # The study's confirmation: TD3+BC, published EABC, EABC at p = 1 and the recommended variant
    # (eabc-ln: p = 1 on LayerNorm critics, chosen by the screen); docs/results/study/README.md.
    "study": {
        "datasets": STUDY_DATASETS,
        "variants": [
            {"algo": "td3bc"},
            {"algo": "eabc"},
            {"algo": "eabc", "confidence_level": 1.0},
            {"algo": "eabc-ln"},
        ],
        "seeds": [0, 1, 2],
        "steps": 100_000,
        "train": STUDY_TRAIN,
    },
    # The study at the paper's length: does the short protocol's ranking hold at 1M steps, and
    # where does LayerNorm with weaker cloning stand against ReBRAC? Breadth first in the order the
    # evidence is needed: hopper-medium (where published EABC's critics run away at 100K) and
    # halfcheetah-medium seed 0 first, more seeds after. The clone-less variant's alpha = 20 is
    # ReBRAC's median tuned actor beta over the 15 datasets (its Table 11) as TD3+BC's alpha
    # (alpha = 1 / (beta * action dims)), fixed beforehand: a short screen favours strong cloning.
    "study-1m": {
        "datasets": ["hopper-medium", "halfcheetah-medium"],
        "variants": [
            {"algo": "td3bc"},
            {"algo": "eabc"},
            {"algo": "eabc-ln"},
            {"algo": "eabc", "critic_layer_norm": True},
            {"algo": "rebrac"},
            {"algo": "eabc-ln", "alpha": 20.0},
        ],
        "seeds": [0, 1],
        "steps": 1_000_000,
        "train": STUDY_TRAIN,
    },
    # Figure 4: the pessimism operator at K = 10 with Table 3's p.
    "ablation-pess": {
        "datasets": generate.mujoco_names(),
        "algos": ["eabc"],
        "seeds": [0, 1, 2, 3, 4],
        "grid": {"pessimism": ["mean-std", "min", "min2"]},
    },
}
