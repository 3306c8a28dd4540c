"""Many runs in one compiled program: seeds x datasets of one shape x values of the algorithm's
traced settings (``trainer.train_runs``, ``chunks.train_chunk_runs``, ``spec.groups``)."""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from eabc import ranges
from eabc.agents import get_algorithm
from eabc.data.dataset import Normalizer
from eabc.data.loaders import save_npz
from eabc.experiments import job_process
from eabc.experiments.spec import RunSpec, expand, groups, job_name
from eabc.training import chunks, eval_pool, lifecycle, trainer
from eabc.training.config import TrainConfig, resolve_agent_config

TRAIN = dict(
    steps=300,
    log_interval=100,
    eval_interval=300,
    checkpoint_interval=300,
    eval_episodes=1,
    env="Pendulum-v1",
    batch_size=64,
)
AGENT = dict(num_critics=3, hidden_dims=(32, 32))


def _cut(dataset, rows: int, name: str):
    arrays = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")
    return dataclasses.replace(
        dataset, name=name, **{f: getattr(dataset, f)[:rows] for f in arrays}
    )


def _leaves(tree) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree.leaves(jax.device_get(tree))]


def test_three_different_runs_in_one_program_equal_each_trained_alone(tmp_path, pendulum_dataset):
    # Two datasets of one shape (one of them shorter) and three settings of EABC's traced p,
    # alpha and pessimism beta, through the sweep's job runner as one group, then one by one.
    files = []
    for rows, name in ((10_000, "swing-long"), (6_000, "swing-short")):
        files.append(str(tmp_path / f"{name}.npz"))
        save_npz(_cut(pendulum_dataset, rows, name), files[-1])
    train = tuple(sorted(TRAIN.items()))
    runs = [
        RunSpec(files[0], "eabc", 0, tuple(sorted({**AGENT, "confidence_level": 0.5}.items())), train),
        RunSpec(files[1], "eabc", 1, tuple(sorted({**AGENT, "confidence_level": 0.25, "alpha": 1.0}.items())), train),
        RunSpec(files[0], "eabc", 2, tuple(sorted({**AGENT, "confidence_level": 1.0, "pessimism_beta": 2.0}.items())), train),
    ]  # fmt: skip
    together = job_process.execute([r.to_json() for r in runs], str(tmp_path / "together"))
    for run, summary in zip(runs, together):
        (alone,) = job_process.execute([run.to_json()], str(tmp_path / "alone"))
        got, expected = (
            lifecycle.resume(root / "runs" / run.run_id, lock=False)
            for root in (tmp_path / "together", tmp_path / "alone")
        )
        assert got.step == expected.step == 300
        for a, b in zip(_leaves(got.state["agent"]), _leaves(expected.state["agent"]), strict=True):
            np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-5)
        assert summary["dataset"] == alone["dataset"] == Path(run.dataset).stem
        np.testing.assert_allclose(summary["final_score"], alone["final_score"], atol=0.5)
        assert summary["q_range"] == alone["q_range"]  # each run's own data's value range
    short = lifecycle.resume(tmp_path / "together" / "runs" / runs[1].run_id, lock=False)
    assert short.agent_config.confidence_level == 0.25 and short.agent_config.alpha == 1.0
    assert short.dataset.size == 6_000


def _runs_program(alg, cfgs, datas, which, states, keys, names, period, steps=40):
    stack = lambda xs: jax.tree.map(lambda *x: jnp.stack(x), *xs)  # noqa: E731
    values = {n: [getattr(c, n) for c in cfgs] for n in names}
    sizes = [int(datas[i].rewards.shape[0]) for i in which]
    update = functools.partial(alg.update, config=cfgs[0], max_action=2.0)
    return chunks.train_chunk_runs(
        stack(states), jnp.stack(keys), chunks.stack_data(datas), which, sizes, values, update,
        32, steps, period, 0,
    )  # fmt: skip


def test_rebrac_betas_traced_per_run_equal_the_runs_alone(pendulum_dataset):
    alg = get_algorithm("rebrac")
    base = dataclasses.replace(alg.preset, hidden_dims=(16, 16), actor_bc_weight=0.1,
                               critic_bc_weight=0.01)  # fmt: skip
    cfgs = [base, dataclasses.replace(base, actor_bc_weight=0.01, critic_bc_weight=0.5)]
    short = _cut(pendulum_dataset, 3_000, "short")
    datas = [
        chunks.device_data(d, Normalizer.fit(d.observations), next_actions=True)
        for d in (pendulum_dataset, short)
    ]
    states = [alg.init(jax.random.PRNGKey(s), 3, 1, base) for s in (0, 1)]
    keys = [jax.random.PRNGKey(7 + s) for s in (0, 1)]
    period = alg.delayed_period(base)
    names = alg.traced_settings
    together = _runs_program(alg, cfgs, datas, [1, 0], states, keys, names, period)
    for i, data in enumerate((datas[1], datas[0])):
        update = functools.partial(alg.update, config=cfgs[i], max_action=2.0)
        alone = chunks.train_chunk(states[i], keys[i], data, update, 32, 40, period, 0)
        for a, b in zip([x[i] for x in _leaves(together[:2])], _leaves(alone[:2]), strict=True):
            np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-5)
    actor = _leaves(together[0].actor)
    assert not np.allclose(actor[0][0], actor[0][1]), "the runs must differ"


def test_one_dataset_one_setting_is_the_seed_program_bit_for_bit(pendulum_dataset):
    alg = get_algorithm("eabc")
    cfg = dataclasses.replace(alg.preset, num_critics=2, confidence_level=0.5, hidden_dims=(16,))
    data = chunks.device_data(pendulum_dataset, Normalizer.fit(pendulum_dataset.observations))
    states = [alg.init(jax.random.PRNGKey(s), 3, 1, cfg) for s in (0, 1)]
    keys = [jax.random.PRNGKey(3 + s) for s in (0, 1)]
    period = alg.delayed_period(cfg)
    runs = _runs_program(alg, [cfg, cfg], [data], [0, 0], states, keys, (), period)
    stack = lambda xs: jax.tree.map(lambda *x: jnp.stack(x), *xs)  # noqa: E731
    update = functools.partial(alg.update, config=cfg, max_action=2.0)
    seeds = chunks.train_chunk_seeds(stack(states), jnp.stack(keys), data, update, 32, 40, period)
    for a, b in zip(_leaves(runs), _leaves(seeds), strict=True):
        np.testing.assert_array_equal(a, b)


def _fake_run(name="a", algo="eabc", obs_dim=3, max_action=2.0, **settings):
    algorithm = get_algorithm(algo)
    return SimpleNamespace(
        algorithm=algorithm,
        agent_config=ranges.validated(algorithm.preset, settings),
        config=TrainConfig(dataset=f"{name}.npz", algo=algo, seed=len(name)),
        dataset=SimpleNamespace(obs_dim=obs_dim, act_dim=1),
        max_action=max_action,
        run_dir=Path(name),
    )


def test_one_program_values_names_what_differs():
    runs = [_fake_run("a", confidence_level=0.5), _fake_run("bb", confidence_level=0.25)]
    assert trainer.one_program_values(runs) == {"confidence_level": [0.5, 0.25]}
    same = [_fake_run("a", alpha=2.5), _fake_run("bb", alpha=2.5)]
    assert trainer.one_program_values(same) == {}
    for other, why in (
        (_fake_run("bb", num_critics=5), "algorithm settings"),
        (_fake_run("bb", obs_dim=4), "observation or action size"),
        (_fake_run("bb", max_action=1.0), "max_action"),
    ):
        with pytest.raises(ValueError, match=why):
            trainer.one_program_values([_fake_run("a"), other])
    quantile = dict(bc_weight="quantile", quantile_level=0.5)
    with pytest.raises(ValueError, match="not a number"):
        trainer.one_program_values(
            [_fake_run("a", confidence_level=None, **quantile),
             _fake_run("bb", confidence_level=0.5, **quantile)]
        )  # fmt: skip


def test_sweep_groups_put_one_environment_and_traced_values_in_one_program():
    runs = expand(
        {
            "datasets": ["hopper-medium", "hopper-random", "walker2d-medium", "mine.npz"],
            "algos": ["eabc", "rebrac", "bc"],
            "seeds": [0, 1],
            "steps": 1000,
            "grid": {"confidence_level": [0.25, 0.5], "num_critics": [5, 10]},
        }
    )
    found = {
        (g[0].algo, tuple(sorted({Path(r.dataset).name for r in g})), len(g)): g
        for g in groups(runs)
    }
    # eabc: K is a shape (two programs per environment); p is traced (one program for both).
    assert ("eabc", ("hopper-medium", "hopper-random"), 8) in found
    assert ("eabc", ("walker2d-medium",), 4) in found
    assert ("eabc", ("mine.npz",), 4) in found  # a file's shape is unknown before it is read
    assert ("rebrac", ("hopper-medium", "hopper-random"), 4) in found
    assert ("bc", ("hopper-medium", "hopper-random"), 4) in found
    assert sum(len(g) for g in groups(runs)) == len(runs)
    assert len(groups(runs)) == 2 * 3 + 2 * 3 + 3  # eabc, rebrac: 2 K x 3 shapes; bc: 3 shapes
    job = found[("eabc", ("hopper-medium", "hopper-random"), 8)]
    assert job_name(job) == f"{job[0].group_id}+3" and job_name(job[:1]) == job[0].run_id


def test_a_group_past_its_deadline_stops_after_its_first_chunks_and_resumes_as_if_killed(
    tmp_path, pendulum_dataset, monkeypatch
):
    """With a deadline the first chunks time the program; where the rest would end after it,
    training stops there (:class:`trainer.PastDeadline`: the width, the step, the speed), the
    runs' locks are free, and resumed without a deadline the runs end with the same parameters
    and log as the same group never stopped; evaluated by a pool, as a study does, whose
    evaluations were still out when it stopped."""
    monkeypatch.setattr(trainer, "PROBE_CHUNKS", 2)
    monkeypatch.setattr(trainer, "PROBE_SECONDS", 0.0)
    path = str(tmp_path / "swing.npz")
    save_npz(_cut(pendulum_dataset, 5_000, "swing"), path)
    train = {**TRAIN, "steps": 600, "checkpoint_interval": 200, "eval_interval": 100}
    train = tuple(sorted(train.items()))
    agent = tuple(sorted({"hidden_dims": (32, 32)}.items()))
    job = [RunSpec(path, "td3bc", seed, agent, train).to_json() for seed in (0, 1)]
    pool = eval_pool.EvaluationPool(1)
    try:
        with pytest.raises(trainer.PastDeadline) as stopped:
            job_process.execute(job, str(tmp_path / "stopped"), pool, time.time() + 1e-3)
        resumed = job_process.execute(job, str(tmp_path / "stopped"), pool)  # locks released
        never = job_process.execute(job, str(tmp_path / "never"), pool, time.time() + 3600)
    finally:
        pool.close(finished=True)
    error = stopped.value
    assert (error.width, error.step, error.steps) == (2, 300, 600)  # timed: steps 100-300
    assert error.steps_per_s > 0 and error.compile_s >= 0 and error.late_s > 0
    assert "2 runs at" in str(error) and "after the deadline (step 300 of 600)" in str(error)
    assert [s["final_score"] for s in resumed] == [s["final_score"] for s in never]
    for spec in job:
        run_id = RunSpec.from_json(spec).run_id
        got, expected = (
            lifecycle.resume(tmp_path / root / "runs" / run_id, lock=False)
            for root in ("stopped", "never")
        )
        assert got.step == expected.step == 600
        for a, b in zip(_leaves(got.state["agent"]), _leaves(expected.state["agent"]), strict=True):
            np.testing.assert_array_equal(a, b)
        logs = [pd.read_csv(got.run_dir / "log.csv"), pd.read_csv(expected.run_dir / "log.csv")]
        assert [len(log) for log in logs] == [6, 6]  # a row every 100 steps, none twice
        pd.testing.assert_series_equal(logs[0]["score"], logs[1]["score"])


def test_a_group_compiled_before_its_runs_exist_finds_its_program_in_the_cache(
    tmp_path, pendulum_dataset, caplog, quick_chunks
):
    """``chunks.compile_first_chunk`` compiles, from settings and sizes alone, the very program
    the group's first chunk runs: three EABC runs (two values of the traced p) on two datasets
    of different lengths, and one TD3+BC run alone; their training then loads it from XLA's
    persistent cache (the suite's own) rather than compiling it."""
    caplog.set_level(logging.DEBUG, logger="jax._src.compiler")
    files = []
    for rows, name in ((4_321, "swing-long"), (3_000, "swing-short")):
        files.append(str(tmp_path / f"{name}.npz"))
        save_npz(_cut(pendulum_dataset, rows, name), files[-1])
    train = tuple(sorted({**TRAIN, "steps": 100, "eval_interval": 100}.items()))
    agent = {"num_critics": 2, "hidden_dims": (24, 24)}
    groups_ = {
        "_chunk_runs": [
            RunSpec(files[s % 2], "eabc", s, tuple(sorted({**agent, "confidence_level": p}.items())), train)
            for s, p in enumerate((0.5, 0.25, 0.5))
        ],
        "_chunk": [RunSpec(files[1], "td3bc", 0, (("hidden_dims", (24, 24)),), train)],
    }  # fmt: skip
    for program, job in groups_.items():
        configs = [run.train_config() for run in job]
        agent_configs = [
            resolve_agent_config(c.algo, run.dataset, dict(run.overrides), c.steps)
            for run, c in zip(job, configs)
        ]
        rows = [4_321, 3_000] if len(job) > 1 else [3_000]
        caplog.clear()
        chunks.compile_first_chunk(configs[0], agent_configs, 3, 1, 2.0, rows)
        miss = f"PERSISTENT COMPILATION CACHE MISS for 'jit_{program}'"
        assert any(miss in m for m in caplog.messages), "a new program: compiled here"
        caplog.clear()
        job_process.execute([r.to_json() for r in job], str(tmp_path / program))
        hit = f"Persistent compilation cache hit for 'jit_{program}'"
        assert any(hit in m for m in caplog.messages), caplog.messages
        assert not any(miss in m for m in caplog.messages)
