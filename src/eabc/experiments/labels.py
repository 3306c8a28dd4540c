"""Labels and order of a sweep's results: a run's label is its algorithm plus its variant
(``ALGO``, ``ALGO K=5``); datasets sort as the paper's tables (Hopper, HalfCheetah, Walker2d;
random ... expert), labels by the algorithm's column in Table 1/6, then by their settings.
Shared by the tables (:mod:`eabc.experiments.tables`) and the figures."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

import pandas as pd

from eabc.agents import ALGORITHMS
from eabc.data import tasks

ENV_ORDER = ("hopper", "halfcheetah", "walker2d")
KIND_ORDER = ("random", "medium", "medium-replay", "medium-expert", "expert")
ABLATION_PARAMETERS = tuple(
    dict.fromkeys(k for a in ALGORITHMS.values() for k in a.report_settings)
)
"""The settings some algorithm's contract lets reports compare (``Algorithm.report_settings``)."""
UNKNOWN_COLUMN = 12.5
"""Where an algorithm the registry does not know goes among the columns (``Algorithm.column``)."""


def algo_label(algo: str, variant: str | None = "") -> str:
    """``algo`` plus its variant when it has one, e.g. ``ALGO K=5``."""
    variant = "" if is_missing(variant) else str(variant).strip()
    return f"{algo} {variant}" if variant else str(algo)


def display_name(label: str) -> str:
    """A label as a reader of the paper knows it: the algorithm's ``display_name``, a variant
    keeping its settings (``ALGO K=5`` -> ``NAME K=5``); unknown algorithms keep their id."""
    algo, _, variant = str(label).partition(" ")
    name = ALGORITHMS[algo].display_name if algo in ALGORITHMS else algo
    return f"{name} {variant}" if variant else name


def dataset_sort_key(name: str) -> tuple:
    """Hopper, HalfCheetah, Walker2d, then other environments; random ... expert within each;
    AntMaze's in Table 5's order (umaze, umaze-diverse, medium-play, ...)."""
    task = tasks.parse_task(name)
    env, _, kind = name.partition("-") if task is None else (task[0], "", task[1])
    env_rank = ENV_ORDER.index(env) if env in ENV_ORDER else len(ENV_ORDER)
    order = tasks.ANTMAZE_KINDS if env == "antmaze" else KIND_ORDER
    kind_rank = order.index(kind) if kind in order else len(order)
    return (env_rank, env, kind_rank, kind, name)


def paper_table(datasets: Sequence[str]) -> str:
    """The paper's table a score table of these datasets lays out: Table 5 for AntMaze only (its
    scores are 100 x the success rate), else Table 1."""
    envs = {(tasks.parse_task(d) or ("",))[0] for d in datasets}
    return "Table 5; 100 x success rate" if envs == {"antmaze"} else "Table 1"


def _natural_key(text: str) -> tuple:
    """Numbers compare as numbers, so ``K=5`` comes before ``K=10``."""
    parts = re.split(r"(-?\d+(?:\.\d+)?)", text)
    return tuple((0, float(p), "") if i % 2 else (1, 0.0, p) for i, p in enumerate(parts) if p)


def _label_key(algo: str, variant: str) -> tuple:
    rank = ALGORITHMS[algo].column if algo in ALGORITHMS else UNKNOWN_COLUMN
    return (rank, algo, variant != "", _natural_key(variant))


def is_missing(value) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def labelled(runs: pd.DataFrame) -> pd.DataFrame:
    require_columns(runs, ("run_id", "dataset", "algo", "seed"), "runs")
    if runs.empty:
        raise ValueError("there are no runs to report on")
    runs = runs.copy()
    variant = runs["variant"] if "variant" in runs else pd.Series("", index=runs.index)
    runs["variant"] = ["" if is_missing(v) else str(v).strip() for v in variant]
    runs["label"] = [algo_label(a, v) for a, v in zip(runs["algo"], runs["variant"])]
    return runs


def ordered_labels(runs: pd.DataFrame) -> list[str]:
    pairs = runs[["algo", "variant", "label"]].drop_duplicates("label")
    ordered = sorted(pairs.itertuples(index=False), key=lambda r: _label_key(r.algo, r.variant))
    return [r.label for r in ordered]


def dataset_names(runs: pd.DataFrame) -> list[str]:
    return sorted(runs["dataset"].unique(), key=dataset_sort_key)


def require_columns(frame: pd.DataFrame, columns: Sequence[str], name: str) -> None:
    missing = [c for c in columns if c not in frame.columns]
    if missing:
        raise ValueError(f"{name} lacks column(s) {missing}; it has {list(frame.columns)}")
