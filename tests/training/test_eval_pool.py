"""Evaluation in a pool of processes while training goes on: the same files as evaluation in the
training process (log.csv, summary.json, the checkpoints' evaluation histories), the same after a
kill and a resume, for one run and for seeds trained together, and the thinned schedule."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from eabc.training import checkpoint, eval_pool, lifecycle, trainer
from eabc.training.config import TrainConfig
from eabc.training.logger import read_log

SMALL = dict(
    dataset="pendulum-swingup",
    steps=600,
    log_interval=100,
    eval_interval=100,
    checkpoint_interval=200,
    eval_episodes=2,
    env="Pendulum-v1",
)
AGENT = dict(num_critics=3, confidence_level=1.0, hidden_dims=(64, 64))
TIMES = {"wall_time", "steps_per_s", "wall_time_s"}
"""What differs between two runs of the same program: how long they took."""


def start(tmp_path, name, dataset, **overrides):
    config = TrainConfig(**{**SMALL, **overrides})
    return lifecycle.start(config, tmp_path / name, AGENT, dataset=dataset)


def results(run_dir, summary):
    """A run's files but for their times: log rows, summary, the checkpoint's evaluations."""
    rows = [
        {k: v for k, v in row.items() if k not in TIMES} for row in read_log(run_dir / "log.csv")
    ]
    raw = checkpoint.load_raw(run_dir)
    return rows, {k: v for k, v in summary.items() if k not in TIMES}, raw["evaluations"]


@pytest.fixture(scope="module")
def pool():
    with eval_pool.EvaluationPool(2) as shared:
        yield shared


def test_a_pool_writes_what_evaluation_in_the_training_process_writes(
    tmp_path, pendulum_dataset, pool
):
    here = start(tmp_path, "here", pendulum_dataset)
    there = start(tmp_path, "there", pendulum_dataset)
    expected = results(here.run_dir, trainer.train(here, progress=False))
    got = results(there.run_dir, trainer.train(there, progress=False, eval_workers=pool))
    assert got == expected
    rows, summary, evaluations = got
    assert [int(s) for s in evaluations] == list(range(100, 601, 100))
    assert all("return_mean" in row for row in rows)
    assert summary["evaluations"] == 6


class Killed(Exception):
    pass


def test_a_run_killed_while_its_evaluations_are_out_resumes_to_the_same_end(
    tmp_path, pendulum_dataset, monkeypatch, pool
):
    straight = start(tmp_path, "straight", pendulum_dataset)
    expected = results(straight.run_dir, trainer.train(straight, progress=False))

    killed = start(tmp_path, "killed", pendulum_dataset)
    log = trainer.RunLogger.log

    def log_then_die(self, row):
        log(self, row)
        if row["step"] == 500:
            raise Killed

    monkeypatch.setattr(trainer.RunLogger, "log", log_then_die)
    with pytest.raises(Killed):
        trainer.train(killed, progress=False, eval_workers=2)  # a pool of its own, cancelled
    monkeypatch.undo()
    resumed = lifecycle.resume(tmp_path / "killed", dataset=pendulum_dataset)
    assert resumed.step == 400
    assert sorted(map(int, resumed.state["evaluations"])) == [100, 200, 300, 400]
    summary = trainer.train(resumed, progress=False, eval_workers=pool)
    assert results(resumed.run_dir, summary) == expected


def test_seeds_trained_together_share_one_pool(tmp_path, pendulum_dataset, pool):
    here = [start(tmp_path, f"here{s}", pendulum_dataset, seed=s, steps=300) for s in (0, 1)]
    there = [start(tmp_path, f"there{s}", pendulum_dataset, seed=s, steps=300) for s in (0, 1)]
    expected = trainer.train_runs(here, progress=False)
    got = trainer.train_runs(there, progress=False, eval_workers=pool)
    for a, b, x, y in zip(here, there, expected, got, strict=True):
        assert results(b.run_dir, y) == results(a.run_dir, x)
    assert expected[0]["final_return"] != expected[1]["final_return"]


def test_the_thin_schedule_evaluates_where_it_says(tmp_path, pendulum_dataset, pool):
    """Every 500 steps (10 x the interval), and every 50 in the last 500."""
    config = dict(steps=1100, log_interval=50, eval_interval=50, checkpoint_interval=550)
    run = start(tmp_path, "thin", pendulum_dataset, eval_schedule="thin", eval_episodes=1, **config)
    summary = trainer.train(run, progress=False, eval_workers=pool)
    steps = sorted(int(s) for s in checkpoint.load_raw(run.run_dir)["evaluations"])
    assert steps == run.config.evaluation_steps() == [500, *range(650, 1101, 50)]
    logged = [int(r["step"]) for r in read_log(run.run_dir / "log.csv") if "return_mean" in r]
    assert logged == steps
    assert summary["evaluations"] == 11
    assert summary["final_score_window"] == "last 10 evaluations (steps 650-1,100)"


def test_a_task_carries_the_run_s_policy(tmp_path, pendulum_dataset):
    run = start(tmp_path, "run", pendulum_dataset, steps=100)
    task = trainer.evaluation_task(run)
    assert task.step == 0 and task.seed == 100 and task.episodes == 2
    actor = jax.device_get(run.state["agent"].actor)
    assert all(np.array_equal(task.actor[k], actor[k]) for k in actor)
    assert eval_pool.evaluate(task) == trainer.evaluate(run)
    run.lock.release()


def test_a_critic_out_of_range_is_reported_once_when_its_row_is_written(
    tmp_path, pendulum_dataset, pool, capsys
):
    """The warning comes with the row (held back until its evaluation is in), once."""
    import dataclasses

    silent = dataclasses.replace(pendulum_dataset, rewards=np.zeros_like(pendulum_dataset.rewards))
    here = start(tmp_path, "here", silent, steps=200)
    expected = results(here.run_dir, trainer.train(here, progress=False))
    assert capsys.readouterr().err.count("the critics are diverging") == 1
    there = start(tmp_path, "there", silent, steps=200)
    summary = trainer.train(there, progress=False, eval_workers=pool)
    assert capsys.readouterr().err.count("the critics are diverging") == 1
    assert summary["q_out_of_range_step"] == 100
    assert results(there.run_dir, summary) == expected
