"""The algorithm contract's generic check (tests/test_contract*.py run it over every registered
algorithm): a new algorithm gets it by being registered. Per-algorithm files keep only their
hand-computed loss tests and their learning checks.

For each algorithm, at tiny sizes on the Pendulum data: two seeds trained together (the vmapped,
scanned chunk), finite metrics in every log row, the seeds differing, a checkpoint that restores
exactly and records the algorithm's state layout (its actor and step found by name, wherever the
state keeps them), the contract's settings resolved and validated, and ``load_policy`` giving
actions of the right shape inside the action bounds.
"""

from __future__ import annotations

import dataclasses
import math
import os

import jax
import numpy as np

from eabc import load_policy, pytree, ranges
from eabc.agents import ALGORITHMS, get_algorithm
from eabc.agents.contract import Algorithm
from eabc.training import checkpoint, chunks, lifecycle, trainer
from eabc.training.config import TrainConfig

NAMES = list(ALGORITHMS)
FIRST_HALF = NAMES[: len(NAMES) // 2]
"""test_contract.py checks these, test_contract_more.py the rest, so that the halves run side by side."""

TINY_INTS = {"buffer_capacity": 4096, "model_max_epochs": 1, "model_members": 2, "model_elites": 1,
             "num_dropout_samples": 4, "num_target_actions": 4}  # fmt: skip


def tiny_settings(algorithm: Algorithm) -> dict:
    """Small networks and short inner loops, found by the settings' names (no per-algorithm list)."""
    out = {}
    for field in dataclasses.fields(algorithm.preset):
        value = getattr(algorithm.preset, field.name)
        if field.name.endswith("hidden_dims") and isinstance(value, tuple):
            out[field.name] = (16,) * len(value)
        elif field.name == "num_critics":
            out[field.name] = min(value, 3)
        elif field.name in TINY_INTS:
            out[field.name] = TINY_INTS[field.name]
    return out


def check_contract(tmp_path, pendulum_dataset, algo: str) -> None:
    """Every check of the module docstring, for one registered algorithm. Its 10 steps run in
    quickly compiled chunks ($EABC_FAST_COMPILE): about half the compile time, same checks."""
    os.environ[chunks.FAST_COMPILE_ENV] = "1"
    try:
        _check_contract(tmp_path, pendulum_dataset, algo)
    finally:
        os.environ.pop(chunks.FAST_COMPILE_ENV, None)


def _check_contract(tmp_path, pendulum_dataset, algo: str) -> None:
    algorithm = get_algorithm(algo)
    overrides = tiny_settings(algorithm)
    # Pendulum is in none of the per-dataset tables (EABC's p and q, ReBRAC's betas).
    for name in ("confidence_level", "quantile_level", "actor_bc_weight", "critic_bc_weight"):
        if name in algorithm.settings() and ranges.value_of(algorithm.preset, name) is None:
            overrides[name] = 0.5
    config = TrainConfig(
        dataset="pendulum-swingup",
        algo=algo,
        steps=10,
        log_interval=10,
        eval_interval=10,
        checkpoint_interval=10,
        eval_episodes=1,
        env="Pendulum-v1",
    )
    runs = [
        lifecycle.start(dataclasses.replace(config, seed=seed), tmp_path / f"s{seed}", overrides,
                      pendulum_dataset)
        for seed in (0, 1)
    ]  # fmt: skip
    assert runs[0].agent_config == algorithm.resolved(
        runs[0].agent_config, pendulum_dataset.name, config.steps, set(overrides)
    ), "resolving twice changes nothing"
    summaries = trainer.train_runs(runs, progress=False)  # one vmapped, scanned program
    for run, summary in zip(runs, summaries):
        assert int(run.state["agent"].step) == 10 and summary["steps"] == 10
        assert summary.get("diverged_step") is None
        for row in (run.run_dir / "log.csv").read_text().splitlines()[1:]:
            cells = [float(c) for c in row.split(",") if c not in ("", "nan")]
            assert all(math.isfinite(c) for c in cells), (algo, row)
    actors = [jax.tree.leaves(run.state["agent"].actor) for run in runs]
    assert any(not np.array_equal(a, b) for a, b in zip(*actors)), "seeds must differ"

    resumed = lifecycle.resume(runs[0].run_dir, pendulum_dataset, lock=False)
    saved, restored = (
        jax.tree.leaves(runs[0].state["agent"]),
        jax.tree.leaves(resumed.state["agent"]),
    )
    assert len(saved) == len(restored)
    for a, b in zip(saved, restored):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    raw = checkpoint.load_raw(runs[0].run_dir, infinite=algorithm.infinite_state)  # as sweeps read
    assert raw[checkpoint.LAYOUT] == algorithm.state_layout
    assert int(pytree.find(raw["agent"], "step")) == 10
    saved_actor = pytree.find(raw["agent"], "actor")
    for name, value in jax.device_get(runs[0].state["agent"].actor).items():
        np.testing.assert_array_equal(saved_actor[name], value)

    policy = load_policy(runs[0].run_dir)
    observations = pendulum_dataset.observations[:4]
    actions = np.stack([policy(o) for o in observations])
    assert actions.shape == (4, pendulum_dataset.act_dim) and actions.dtype == np.float32
    assert np.all(np.abs(actions) <= runs[0].max_action + 1e-6)
    np.testing.assert_allclose(actions, trainer.policy_fn(runs[0])(observations), rtol=1e-5)
