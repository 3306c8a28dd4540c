"""Experiments at scale: seed-vectorised training, sweeps (local and Ray), the results store."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pandas as pd
import pytest
import yaml

from eabc.cli import main
from eabc.data.loaders import save_npz
from eabc.experiments import planning, ray_pool, results, run_status
from eabc.experiments.presets import PRESETS
from eabc.experiments.spec import expand, groups
from eabc.training import lifecycle, trainer
from eabc.training.config import TrainConfig

SMALL = dict(
    steps=300,
    log_interval=100,
    eval_interval=100,
    checkpoint_interval=100,
    eval_episodes=1,
    env="Pendulum-v1",
)
AGENT = dict(num_critics=3, confidence_level=0.5, hidden_dims=(32, 32))


def test_seed_vmapped_training_equals_training_the_seeds_one_by_one(tmp_path, pendulum_dataset):
    # The default build: in the quickly compiled one the vmapped and the one-by-one programs
    # round differently enough that one weight in a thousand drifts past the tolerance.
    def start(name, seed):
        config = TrainConfig(dataset="pendulum", seed=seed, **SMALL)
        return lifecycle.start(config, tmp_path / name, AGENT, dataset=pendulum_dataset)

    together = [start(f"vmap{s}", s) for s in (0, 1, 2)]
    summaries = trainer.train_runs(together, progress=False)
    for seed, run, summary in zip((0, 1, 2), together, summaries):
        alone = start(f"alone{seed}", seed)
        expected = trainer.train(alone, progress=False)
        for a, b in zip(
            jax.tree.leaves(jax.device_get(run.state["agent"])),
            jax.tree.leaves(jax.device_get(alone.state["agent"])),
            strict=True,
        ):
            np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-5)
        assert summary["steps"] == expected["steps"] == 300
        np.testing.assert_allclose(summary["final_score"], expected["final_score"], atol=0.5)
        assert (tmp_path / f"vmap{seed}" / "summary.json").exists()
    first, second = (jax.device_get(r.state["agent"].actor["w0"]) for r in together[:2])
    assert not np.allclose(first, second), "different seeds must give different runs"


def test_sweep_expansion_ids_and_validation():
    runs = expand(
        {
            "datasets": ["hopper-medium", "walker2d-random"],
            "algos": ["eabc", "bc"],
            "seeds": [0, 1],
            "steps": 1000,
            "grid": {"num_critics": [5, 10]},
        }
    )
    # eabc has num_critics (2 values), bc does not (1 arm): (2 + 1) x 2 datasets x 2 seeds.
    assert len(runs) == 12
    ids = [r.run_id for r in runs]
    assert len(set(ids)) == 12 and "hopper-medium__eabc__K5__seed1" in ids
    assert {r.variant for r in runs if r.algo == "eabc"} == {"K=5", "K=10"}
    assert all(r.train_config().steps == 1000 for r in runs)
    assert len(groups(runs)) == 6
    with pytest.raises(ValueError, match="no algorithm of the sweep has"):
        expand({"datasets": ["hopper-medium"], "algos": ["bc"], "grid": {"pessimism": ["min"]}})
    with pytest.raises(ValueError, match="unknown sweep key"):
        expand({"datasets": ["x"], "algos": ["bc"], "seedz": [1]})
    for name, preset in PRESETS.items():
        if name == "table5":  # the six AntMaze datasets x TD3+BC, EABC x 5 seeds
            assert len(expand(preset)) == 6 * 2 * 5, name
        elif not name.startswith("study"):  # the paper's grids: 15 datasets x 5 seeds at least
            assert len(expand(preset)) >= 15 * 5, name
        else:  # the study's presets (tests/experiments/test_study.py): 5 or 2 datasets, 2-3 seeds
            assert len(expand(preset)) >= 3 * 3, name


@pytest.fixture
def two_datasets(tmp_path, pendulum_dataset, quick_chunks):
    """Two dataset files of the same size, so that every program compiles once for both; the
    sweeps' workers train quickly compiled chunks (quick_chunks reaches them through the
    environment)."""
    paths = []
    for i, name in enumerate(("pendA", "pendB")):
        data = dataclasses.replace(pendulum_dataset, name=name)
        if i:  # the second dataset: its 200-step episodes in another order, a different dataset
            data = dataclasses.replace(
                data, **{k: np.roll(getattr(data, k), 1000, axis=0) for k in
                         ("observations", "actions", "rewards", "next_observations",
                          "terminals", "timeouts")}
            )  # fmt: skip
        paths.append(tmp_path / f"{name}.npz")
        save_npz(data, paths[-1])
    return [str(p) for p in paths]


def test_local_sweep_is_interrupted_resumed_and_stored(tmp_path, two_datasets):
    root = tmp_path / "sweep"
    spec = _spec(two_datasets, steps=400, seeds=[0])
    runs = expand(spec)
    assert len(runs) == 4
    root.mkdir()
    (root / "spec.yaml").write_text(yaml.safe_dump(spec))
    # Start the sweep, kill it as soon as some run has a checkpoint but not all are done.
    proc = subprocess.Popen(_cli(two_datasets, root, "--workers", "2"), start_new_session=True)
    try:
        deadline = time.time() + 300
        while time.time() < deadline:
            states = [run_status.status(r, root)[0] for r in runs]
            if "partial" in states:
                break
            assert proc.poll() is None, "the sweep ended before it could be interrupted"
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    interrupted = [r for r, s in zip(runs, states) if s == "partial"]
    assert interrupted and states.count("done") < len(runs)

    main(_cli(two_datasets, root)[3:])  # the sweep again, from this process (its workers are not)
    assert [run_status.status(r, root)[0] for r in runs] == ["done"] * len(runs)
    for run in runs:  # each job's log says what it trains, how long that takes, when it ended
        log = (root / "logs" / f"{run.run_id}.log").read_text()
        assert f"eabc: training {run.algo} " in log and "/400 steps in " in log, log
        assert "\r" not in log  # lines, not a progress bar
    table, evaluations = results.collect(root)
    assert len(table) == 4 and set(table["status"]) == {"done"}
    for run in interrupted:  # resumed, not restarted: one log row per step
        steps = evaluations[evaluations.run_id == f"runs/{run.run_id}"]["step"].tolist()
        assert steps == [100, 200, 300, 400], steps
    # The stored scores are the run directories' own numbers.
    for run in runs:
        row = table[table.run_id == f"runs/{run.run_id}"].iloc[0]
        summary = json.loads((root / "runs" / run.run_id / "summary.json").read_text())
        assert row["final_score"] == pytest.approx(summary["final_score"], abs=1e-9)
        assert row["variant"] == run.variant
        diverged = summary.get("q_out_of_range_step")
        stored = row["q_out_of_range_step"]
        assert pd.isna(stored) if diverged is None else stored == diverged
    again, _ = results.load(root)
    assert len(again) == 4
    (root / results.DATABASE).unlink()
    rebuilt, _ = results.load(root)
    assert sorted(rebuilt.run_id) == sorted(table.run_id)
    assert set(results.query(table, ["algo=bc"]).algo) == {"bc"}

    # The report: every table and figure, with the stored numbers in the table (the HTML and
    # LaTeX tables asked for beside the Markdown; the figures PNG only, the default).
    main(["report", str(root), "--formats", "html", "tex"])
    out = root / "report"
    assert not list(out.glob("*.svg")) and not list(out.glob("*.pdf"))
    for name in ("table.md", "table.html", "table.tex", "aggregate.md", "report.md"):
        assert (out / name).stat().st_size > 0, name
    for name in ("curves.png", "runtime.png", "profiles.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG", name
    markdown = (out / "table.md").read_text()
    bc_scores = table[(table.algo == "bc") & table.dataset.str.startswith("pendA")]["final_score"]
    assert f"{bc_scores.mean():.1f}" in markdown


def _spec(datasets, steps, seeds=(0, 1)):
    return {
        "datasets": datasets,
        "algos": ["eabc", "bc"],
        "seeds": list(seeds),
        "steps": steps,
        "grid": {"confidence_level": [0.5], "hidden_dims": [[32, 32]]},
        "train": {k: v for k, v in SMALL.items() if k != "steps"},
    }


def _cli(datasets, root, *extra):
    return [
        sys.executable, "-m", "eabc.cli", "sweep", str(root / "spec.yaml"), "--root", str(root),
        *extra,
    ]  # fmt: skip


def test_ray_backend_runs_a_sweep_on_a_local_ray_instance(tmp_path, two_datasets, monkeypatch):
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    # The driver then works elsewhere, with a relative root and relative dataset paths (the
    # README's way); the workers kept the directory they started in.
    (tmp_path / "driver").mkdir()
    monkeypatch.chdir(tmp_path / "driver")
    root = Path("ray-sweep")
    # One dataset: two jobs (one per algorithm, its two seeds vmapped) run side by side on the
    # two CPUs Ray is given.
    spec = _spec([os.path.relpath(two_datasets[0])], steps=200)
    runs = expand(spec)
    jobs = planning.jobs(runs, root, "vmap")
    assert len(jobs) == 2
    try:
        ray_pool.run_ray(jobs, root)
    finally:
        ray.shutdown()
    assert [run_status.status(r, root)[0] for r in runs] == ["done"] * 4
    assert len(list((tmp_path / "driver" / "ray-sweep" / run_status.RUNS).iterdir())) == 4
    table, _ = results.collect(root)
    assert len(table) == 4 and table["final_score"].notna().all()
