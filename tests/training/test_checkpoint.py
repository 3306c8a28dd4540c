"""Checkpoints' state layout: recorded in every training checkpoint, a missing one read as 1;
a checkpoint of another layout than its algorithm's is refused by resume, evaluate,
``load_policy`` and the ONNX export with a message that says why and what to do."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from eabc import load_policy, pytree
from eabc.agents import get_algorithm
from eabc.cli import main
from eabc.data.loaders import save_npz
from eabc.deploy import export_onnx
from eabc.training import checkpoint, lifecycle
from eabc.training.checkpoint import CheckpointError
from eabc.training.config import TrainConfig

SMALL = dict(
    dataset="pendulum-swingup",
    steps=10,
    log_interval=10,
    eval_interval=10,
    checkpoint_interval=10,
    eval_episodes=1,
    env="Pendulum-v1",
)


def started(tmp_path, pendulum_dataset, algo: str, agent: dict, **options):
    """A run that has saved its initial state as the trainer saves a checkpoint (no training:
    the layout is all these tests need)."""
    config = TrainConfig(**{**SMALL, **options}, algo=algo)
    run = lifecycle.start(config, tmp_path / algo, agent, dataset=pendulum_dataset)
    run.lock.release()
    checkpoint.save(run.run_dir, run.state, run.algorithm.state_layout)
    return run


def test_a_checkpoint_records_its_layout_and_a_nested_state_round_trips(tmp_path, pendulum_dataset):
    run = started(tmp_path, pendulum_dataset, "wpc", {"hidden_dims": (16, 16)})
    raw = checkpoint.load_raw(run.run_dir)
    assert raw[checkpoint.LAYOUT] == get_algorithm("wpc").state_layout == 2
    assert set(raw["agent"]) == {"td3bc", "value", "value_opt"}
    resumed = lifecycle.resume(run.run_dir, pendulum_dataset, lock=False)
    assert checkpoint.LAYOUT not in resumed.state
    assert jax.tree.structure(resumed.state["agent"]) == jax.tree.structure(run.state["agent"])
    assert load_policy(run.run_dir)(pendulum_dataset.observations[0]).shape == (1,)


def test_an_old_layout_checkpoint_is_refused_with_what_to_do(tmp_path, pendulum_dataset):
    """wPC's checkpoints from before its state held TD3+BC's (layout 1: TD3+BC's entries and
    V's side by side, no recorded layout) are refused everywhere they are read."""
    run = started(tmp_path, pendulum_dataset, "wpc", {"hidden_dims": (16, 16)})
    raw = checkpoint.load_raw(run.run_dir)
    agent = raw["agent"]
    old = {k: v for k, v in raw.items() if k != checkpoint.LAYOUT}
    old["agent"] = {**agent["td3bc"], "value": agent["value"], "value_opt": agent["value_opt"]}
    checkpoint.save(run.run_dir, old)  # as the previous version wrote it
    message = (
        r"written by an older version of eabc, with an older state layout for wpc \(layout 1; "
        r"this version reads layout 2\).*train the run again.*use the older package version "
        "to finish it"
    )
    with pytest.raises(CheckpointError, match=message):
        lifecycle.resume(run.run_dir, pendulum_dataset)  # eabc train --resume
    with pytest.raises(CheckpointError, match=message):
        lifecycle.resume(run.run_dir, pendulum_dataset, lock=False)  # eabc evaluate
    with pytest.raises(CheckpointError, match=message):
        load_policy(run.run_dir)
    with pytest.raises(CheckpointError, match=message):
        export_onnx(run.run_dir, tmp_path / "policy.onnx")

    newer = {**raw, checkpoint.LAYOUT: 3}  # a payload edited to a layout from the future
    checkpoint.save(run.run_dir, newer)
    with pytest.raises(CheckpointError, match="newer version of eabc.*layout 3"):
        lifecycle.resume(run.run_dir, pendulum_dataset)


def test_the_cli_refuses_an_old_layout_in_one_line(tmp_path, pendulum_dataset):
    save_npz(pendulum_dataset, tmp_path / "pendulum.npz")  # a file `eabc evaluate` can load
    options = {"dataset": str(tmp_path / "pendulum.npz")}
    run = started(tmp_path, pendulum_dataset, "cql", {"hidden_dims": (16, 16)}, **options)
    raw = checkpoint.load_raw(run.run_dir)
    checkpoint.save(run.run_dir, {**raw, checkpoint.LAYOUT: 1})  # an edited payload's version
    with pytest.raises(SystemExit) as exit:
        main(["evaluate", str(run.run_dir)])
    assert str(exit.value.code).startswith("error: ")
    assert "older state layout for cql (layout 1; this version reads layout 2)" in exit.value.code


def test_eabc_checkpoints_without_a_layout_still_resume(tmp_path, pendulum_dataset):
    """EABC's checkpoints from before the layout was recorded (layout 1, the same entries) resume
    exactly: what they hold is what comes back."""
    agent = {"num_critics": 2, "confidence_level": 0.5, "hidden_dims": (16, 16)}
    run = started(tmp_path, pendulum_dataset, "eabc", agent)
    raw = checkpoint.load_raw(run.run_dir)
    assert raw[checkpoint.LAYOUT] == get_algorithm("eabc").state_layout == 1
    old = {k: v for k, v in raw.items() if k != checkpoint.LAYOUT}
    old["agent"] = {**old["agent"], "step": np.asarray(7, np.int32)}
    old["agent"]["actor"] = {k: v + 1.0 for k, v in old["agent"]["actor"].items()}
    checkpoint.save(run.run_dir, old)  # no layout recorded: the previous version's file
    data = (run.run_dir / checkpoint.CHECKPOINT).read_bytes()
    assert data[:-40] == pytree.dumps(old), "the previous version's bytes, unchanged"

    resumed = lifecycle.resume(run.run_dir, pendulum_dataset, lock=False)
    assert resumed.step == 7 and checkpoint.LAYOUT not in resumed.state
    for name, value in old["agent"]["actor"].items():
        np.testing.assert_array_equal(np.asarray(resumed.state["agent"].actor[name]), value)
    policy = load_policy(run.run_dir)
    assert policy(pendulum_dataset.observations[0]).shape == (1,)


def test_an_algorithms_declared_infinite_entries_load_and_no_others(tmp_path, pendulum_dataset):
    """eabc-auto's controller starts with an infinite reward range: its step-0 checkpoint resumes
    and serves a policy, because the algorithm declares those entries; read without that
    declaration, the same file is refused as corrupt."""
    run = started(
        tmp_path, pendulum_dataset, "eabc-auto", {"hidden_dims": (16, 16), "num_critics": 2}
    )
    assert np.isinf(np.asarray(run.state["agent"].controller["reward_min"]))
    declared = get_algorithm("eabc-auto").infinite_state
    assert checkpoint.load_raw(run.run_dir, infinite=declared)["agent"]["controller"]
    resumed = lifecycle.resume(run.run_dir, pendulum_dataset, lock=False)
    assert np.isinf(np.asarray(resumed.state["agent"].controller["reward_max"]))
    assert load_policy(run.run_dir)(pendulum_dataset.observations[0]).shape == (1,)
    with pytest.raises(CheckpointError, match="NaN/inf in agent/controller/reward_"):
        checkpoint.load_raw(run.run_dir)
