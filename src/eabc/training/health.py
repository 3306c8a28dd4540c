"""Whether a run is still sound: NaN/inf in its losses, and critics whose mean Q leaves the range
of discounted returns the data's rewards allow (extrapolation error running away)."""

from __future__ import annotations

import math

import numpy as np


def non_finite(row: dict[str, float]) -> list[str]:
    """The losses and Q statistics of a log row that are NaN or inf."""
    watched = [k for k in row if k.endswith("_loss") or k in ("q_mean", "target_mean")]
    return [k for k in watched if not math.isfinite(row[k])]


def value_range(rewards: np.ndarray, discount: float | None) -> tuple[float, float] | None:
    """The Q values a critic can honestly reach on these rewards, with a 10% margin.

    No policy collects more than ``max(0, max r) / (1 - gamma)`` or less than
    ``min(0, min r) / (1 - gamma)`` in discounted return (0 is inside: an episode can end, and
    critics start near 0), so a mean Q outside this range (widened by 10% of its width, room for
    entropy bonuses) is extrapolation error running away, not learning. None without a discount.
    """
    if discount is None or not 0.0 <= discount < 1.0:
        return None
    low = min(0.0, float(np.min(rewards))) / (1 - discount)
    high = max(0.0, float(np.max(rewards))) / (1 - discount)
    margin = 0.1 * (high - low)
    return low - margin, high + margin


def first_divergence(rows: list[dict[str, float]], q_range: tuple[float, float]) -> int | None:
    """The first logged step whose mean Q lies outside ``q_range`` (None if none does)."""
    for row in rows:
        q = row.get("q_mean", math.nan)
        if not math.isnan(q) and not in_range(q, q_range):
            return int(row["step"])
    return None


def in_range(q: float, q_range: tuple[float, float]) -> bool:
    return q_range[0] <= q <= q_range[1]


def divergence_warning(
    name: str, step: int, q_mean: float, q_range: tuple[float, float], advice: str = ""
) -> str:
    """What the trainer prints at a run's first out-of-range step, with what to try (``advice``:
    the algorithm's ``divergence_advice``)."""
    return (
        f"warning: {name} at step {step}: mean Q {q_mean:,.0f} lies outside "
        f"[{q_range[0]:,.0f}, {q_range[1]:,.0f}], the discounted returns this data's rewards allow: "
        "the critics are diverging (extrapolation error on out-of-data actions), and scores from "
        f"here on rest on a broken critic. {advice + ' ' if advice else ''}Training goes on; "
        "summary.json records the step as q_out_of_range_step."
    )
