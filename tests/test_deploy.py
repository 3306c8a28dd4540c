"""Deployable policies: the ONNX export equals load_policy, run with onnxruntime (no JAX)."""

from __future__ import annotations

import numpy as np
import pytest

from eabc import load_policy
from eabc.agents import get_algorithm
from eabc.cli import main
from eabc.data.dataset import Normalizer
from eabc.training import checkpoint

onnxruntime = pytest.importorskip("onnxruntime")


def write_run(run_dir, algo, observations, outputs, seed=0):
    """A run directory with a checkpoint of a random 32-32 actor (what export reads, no more)."""
    rng = np.random.default_rng(seed)
    sizes = [observations.shape[1], 32, 32, outputs]
    actor = {}
    for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        bound = 1 / np.sqrt(fan_in)
        actor[f"w{i}"] = rng.uniform(-bound, bound, (fan_in, fan_out)).astype(np.float32)
        actor[f"b{i}"] = rng.uniform(-bound, bound, fan_out).astype(np.float32)
    normalizer = Normalizer.fit(observations)
    run_dir.mkdir()
    config = {
        "train": {"algo": algo, "dataset": "pendulum.npz", "seed": 0, "steps": 100},
        "agent": {"hidden_dims": [32, 32]},  # what the export checks the actor's shapes against
        "dataset": {"name": "pendulum"},
        "max_action": 2.0,
    }
    checkpoint.save_json(run_dir / checkpoint.CONFIG, config)
    layout = get_algorithm(algo).state_layout
    # CQL's state (layout 2) holds its SAC state, and the actor in it, as the trainer writes it.
    agent = {"actor": actor} if layout == 1 else {"sac": {"actor": actor}}
    state = {"agent": agent, "normalizer": {"mean": normalizer.mean, "std": normalizer.std}}
    checkpoint.save(run_dir, state, layout)


@pytest.mark.parametrize(("algo", "outputs"), [("td3bc", 1), ("cql", 2)])  # Gaussian: mean, log std
def test_onnx_policy_equals_load_policy(tmp_path, pendulum_dataset, algo, outputs, capsys):
    run_dir = tmp_path / "run"
    write_run(run_dir, algo, pendulum_dataset.observations, outputs)
    main(["export-policy", str(run_dir), "--onnx", str(tmp_path / "policy.onnx")])
    assert capsys.readouterr().out.strip() == str(tmp_path / "policy.onnx")

    session = onnxruntime.InferenceSession(str(tmp_path / "policy.onnx"))
    observations = pendulum_dataset.observations[::97]  # raw: the normaliser is inside
    (actions,) = session.run(None, {"observation": observations})
    expected = load_policy(run_dir)(observations)
    assert actions.shape == expected.shape == (len(observations), 1)
    np.testing.assert_allclose(actions, expected, atol=2e-6)
    assert np.abs(actions).max() <= 2.0 and np.std(actions) > 1e-3  # Pendulum's bounds, not flat
