"""The training loop: determinism, exact resume after a kill, learning, checkpoints and the policy API."""

from __future__ import annotations

import dataclasses
import functools
import json

import jax
import numpy as np
import pytest

from eabc import load_policy
from eabc.agents import eabc, get_algorithm
from eabc.experiments import results
from eabc.training import checkpoint, chunks, health, lifecycle, provenance, trainer
from eabc.training.config import FINAL_EVALUATIONS, TrainConfig

SMALL = dict(
    dataset="pendulum-swingup",
    steps=600,
    log_interval=100,
    eval_interval=300,
    checkpoint_interval=200,
    eval_episodes=1,
    env="Pendulum-v1",
)
# p = 1 (TD3+BC's cloning everywhere), which the learning check needs; the other runs here do not
# depend on p, and with the same settings all of them train one compiled program.
AGENT = dict(num_critics=3, confidence_level=1.0, hidden_dims=(64, 64))


def params(run):
    return jax.device_get((run.state["agent"].actor, run.state["agent"].critic))


def assert_same(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


def start(tmp_path, name, dataset, **overrides):
    config = TrainConfig(**{**SMALL, **overrides})
    return lifecycle.start(config, tmp_path / name, AGENT, dataset=dataset)


def test_same_seed_same_result_and_other_seed_differs(tmp_path, pendulum_dataset):
    runs = []
    for name, seed in [("a", 0), ("b", 0), ("c", 1)]:
        run = start(tmp_path, name, pendulum_dataset, seed=seed, steps=200)
        trainer.train(run, progress=False)
        runs.append(params(run))
    assert_same(runs[0], runs[1])
    assert not np.array_equal(runs[0][0]["w0"], runs[2][0]["w0"])


class Killed(Exception):
    pass


def test_killed_and_resumed_run_ends_exactly_like_an_uninterrupted_one(
    tmp_path, pendulum_dataset, monkeypatch
):
    straight = start(tmp_path, "straight", pendulum_dataset)
    summary = trainer.train(straight, progress=False)

    # Kill the second run after step 500 has been logged: its last checkpoint is at step 400.
    killed = start(tmp_path, "killed", pendulum_dataset)
    log = trainer.RunLogger.log

    def log_then_die(self, row):
        log(self, row)
        if row["step"] == 500:
            raise Killed

    monkeypatch.setattr(trainer.RunLogger, "log", log_then_die)
    with pytest.raises(Killed):
        trainer.train(killed, progress=False)
    monkeypatch.undo()

    resumed = lifecycle.resume(tmp_path / "killed", dataset=pendulum_dataset)
    assert resumed.step == 400
    resumed_summary = trainer.train(resumed, progress=False)
    assert_same(params(straight), params(resumed))
    assert_same(
        jax.device_get(straight.state["agent"].critic_opt),
        jax.device_get(resumed.state["agent"].critic_opt),
    )
    assert resumed_summary["final_score"] == summary["final_score"]
    # Fewer than 10 evaluations: the final score is the mean of all of them, and says so.
    evaluations = sorted(int(s) for s in straight.state["evaluations"])
    assert 0 < len(evaluations) < FINAL_EVALUATIONS
    assert summary["final_score_window"] == (
        f"all {len(evaluations)} evaluations (fewer than 10; steps {evaluations[0]:,}-"
        f"{evaluations[-1]:,})"
    )
    assert summary["final_score"] == pytest.approx(
        np.mean([straight.state["evaluations"][str(s)]["score"] for s in evaluations])
    )
    assert resumed_summary["final_score_window"] == summary["final_score_window"]
    steps = [
        int(line.split(",")[0])
        for line in (tmp_path / "killed/log.csv").read_text().split("\n")[1:]
        if line
    ]
    assert steps == list(range(100, 601, 100)), "log rows after the checkpoint must not repeat"
    # Each start of training left its segment: from 0 (killed at 500), then from the checkpoint.
    segments = provenance.read(tmp_path / "killed")
    assert [s["from_step"] for s in segments] == [0, 400]
    assert all(s["cpu"] and s["code"] and s["libraries"]["jax"] for s in segments)


def test_checkpoint_is_msgpack_and_policy_api_matches_training(tmp_path, pendulum_dataset):
    run = start(tmp_path, "run", pendulum_dataset, steps=200)
    trainer.train(run, progress=False)
    raw = (tmp_path / "run" / checkpoint.CHECKPOINT).read_bytes()
    assert raw[0] & 0xF0 == 0x80 or raw[0] in (0xDE, 0xDF), "a msgpack map, not a pickle"
    policy = load_policy(tmp_path / "run")
    obs = pendulum_dataset.observations[:5]
    expected = trainer.policy_fn(run)(obs)
    np.testing.assert_allclose(np.stack([policy(o) for o in obs]), expected, rtol=1e-6)
    for name in ("config.json", "log.csv", "curve.png", "summary.json"):
        assert (tmp_path / "run" / name).exists()
    # Every run file has the mode open() gives under the umask (mkstemp's 0600 hid them from the
    # group a team shares run directories with).
    expected_mode = checkpoint.file_mode()
    for name in ("config.json", "log.csv", "summary.json", checkpoint.CHECKPOINT):
        assert (tmp_path / "run" / name).stat().st_mode & 0o777 == expected_mode, name


def test_existing_run_dir_is_not_overwritten(tmp_path, pendulum_dataset):
    start(tmp_path, "run", pendulum_dataset)
    with pytest.raises(FileExistsError, match="--resume"):
        start(tmp_path, "run", pendulum_dataset)


def test_learning_lifts_the_score_well_above_the_untrained_policy(tmp_path, pendulum_dataset):
    config = TrainConfig(
        **{
            **SMALL,
            "steps": 3000,
            "eval_interval": 1000,
            "checkpoint_interval": 1000,
            "eval_episodes": 5,
        }
    )
    run = lifecycle.start(config, tmp_path / "learn", AGENT, dataset=pendulum_dataset)
    untrained = trainer.evaluate(run)["score"]
    summary = trainer.train(run, progress=False)
    last = run.state["evaluations"]["3000"]["score"]
    assert untrained < 30
    assert last > untrained + 40, (untrained, last, summary)


def test_value_range_is_what_the_rewards_allow():
    low, high = health.value_range(np.array([-1.0, 0.5, 2.0]), discount=0.9)
    np.testing.assert_allclose((low, high), (-10 - 3, 20 + 3), rtol=1e-6)
    assert health.value_range(np.ones(3), discount=None) is None
    # Positive rewards: critics starting near 0 are not out of range.
    np.testing.assert_allclose(health.value_range(np.array([1.0, 3.0]), 0.9), (-3, 33), rtol=1e-6)
    rows = [{"step": 100, "q_mean": 5.0}, {"step": 200, "q_mean": 30.0}, {"step": 300}]
    assert health.first_divergence(rows, (low, high)) == 200
    assert health.first_divergence(rows[:1], (low, high)) is None


def test_diverging_critics_are_reported(tmp_path, pendulum_dataset, capsys):
    healthy = start(tmp_path, "healthy", pendulum_dataset, steps=200)
    trainer.train(healthy, progress=False)
    summary = json.loads((tmp_path / "healthy" / "summary.json").read_text())
    assert summary["q_out_of_range_step"] is None
    assert summary["q_range"][0] < -1000 < 0 < summary["q_range"][1]
    assert "diverging" not in capsys.readouterr().err

    # All-zero rewards allow only Q = 0, so the critics' nonzero initial values are out of range.
    silent = dataclasses.replace(pendulum_dataset, rewards=np.zeros_like(pendulum_dataset.rewards))
    run = start(tmp_path, "zero", silent, steps=200)
    trainer.train(run, progress=False)
    summary = json.loads((tmp_path / "zero" / "summary.json").read_text())
    assert summary["q_out_of_range_step"] == 100
    err = capsys.readouterr().err
    assert err.count("the critics are diverging") == 1, "warn once, at the first step out of range"
    # The results store reads the same step from the log (also for unfinished runs).
    assert results.read_run(tmp_path / "zero")[0]["q_out_of_range_step"] == 100
    assert np.isnan(results.read_run(tmp_path / "healthy")[0]["q_out_of_range_step"])


def _tensorboard_points(run_dir):
    from tensorboard.backend.event_processing.event_accumulator import (  # noqa: PLC0415
        EventAccumulator,
    )

    events = EventAccumulator(str(run_dir / "tb"), size_guidance={"scalars": 0})
    events.Reload()
    points = {t: [(e.step, e.value) for e in events.Scalars(t)] for t in events.Tags()["scalars"]}
    return points, events


def _log_points(run_dir):
    from eabc.training.logger import read_log  # noqa: PLC0415

    points = {}
    for row in read_log(run_dir / "log.csv"):
        for key, text in row.items():
            if key != "step" and text != "nan":
                points.setdefault(key, []).append((int(row["step"]), float(text)))
    return points


def assert_tensorboard_equals_log(run_dir):
    tensorboard, _ = _tensorboard_points(run_dir)
    log = _log_points(run_dir)
    assert sorted(tensorboard) == sorted(log)
    for tag, points in log.items():
        assert [s for s, _ in tensorboard[tag]] == [s for s, _ in points], tag
        np.testing.assert_allclose([v for _, v in tensorboard[tag]], [v for _, v in points], 1e-6)


def test_tensorboard_keeps_every_point_of_log_csv_through_resumes(
    tmp_path, pendulum_dataset, monkeypatch
):
    """Read back with TensorBoard's own reader: a resume keeps the checkpoint step's point, and
    resuming a finished run keeps its last one; the run's settings are in the HParams tab."""
    from tensorboard.plugins.hparams import plugin_data_pb2  # noqa: PLC0415

    run = lifecycle.start(
        TrainConfig(**{**SMALL, "algo": "bc", "steps": 400, "eval_interval": 100}),
        tmp_path / "run",
        {"hidden_dims": (32, 32)},
        dataset=pendulum_dataset,
    )
    evaluate = trainer.evaluate

    def killed_at_400(run):
        if run.step == 400:
            raise KeyboardInterrupt  # after step 300's row, whose checkpoint never came
        return evaluate(run)

    monkeypatch.setattr(trainer, "evaluate", killed_at_400)
    with pytest.raises(KeyboardInterrupt):
        trainer.train(run, progress=False)
    monkeypatch.undo()
    assert [p[0] for p in _log_points(tmp_path / "run")["score"]] == [100, 200, 300]
    trainer.train(lifecycle.resume(tmp_path / "run", dataset=pendulum_dataset), progress=False)
    assert_tensorboard_equals_log(tmp_path / "run")  # step 200, the checkpoint, included
    trainer.train(lifecycle.resume(tmp_path / "run", dataset=pendulum_dataset), progress=False)
    assert_tensorboard_equals_log(tmp_path / "run")  # step 400, the final point, kept

    _, events = _tensorboard_points(tmp_path / "run")
    content = events.PluginTagToContent("hparams")["_hparams_/session_start_info"]
    hparams = plugin_data_pb2.HParamsPluginData.FromString(content).session_start_info.hparams
    assert hparams["algo"].string_value == "bc" and hparams["steps"].number_value == 400


@pytest.mark.parametrize("algo", ["eabc", "sac-n"])
def test_the_fast_compiled_init_gives_the_default_compiled_parameters_bit_for_bit(algo):
    """The trainer's init program and an eager call (each network's own quickly compiled
    program) give what XLA's default build of the whole init gives."""
    algorithm = get_algorithm(algo)
    key = jax.random.PRNGKey(7)
    fast = lifecycle.init_agent(algorithm.init, key, 11, 3, algorithm.preset)
    eager = algorithm.init(key, 11, 3, algorithm.preset)
    default = jax.jit(lambda k: algorithm.init(k, 11, 3, algorithm.preset))(key)
    for a, b, c in zip(*map(jax.tree.leaves, (fast, eager, default)), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
        np.testing.assert_array_equal(np.asarray(b), np.asarray(c))


def test_fast_compiled_chunks_are_another_program_with_the_same_results(monkeypatch, batch):
    """$EABC_FAST_COMPILE picks chunk programs compiled at XLA O0: another build of the same
    steps, equal to the default build up to float rounding."""
    config = dataclasses.replace(
        get_algorithm("eabc").preset, hidden_dims=(8, 8), num_critics=3, confidence_level=0.5
    )
    state = get_algorithm("eabc").init(jax.random.PRNGKey(0), 3, 2, config)
    update = functools.partial(eabc.update, config=config, max_action=1.0)
    results = {}
    for fast in (False, True):
        monkeypatch.setenv(chunks.FAST_COMPILE_ENV, "1" if fast else "0")
        assert chunks.fast_compile() is fast
        before = chunks._PROGRAMS[fast][0]._cache_size()
        results[fast] = chunks.train_chunk(state, jax.random.PRNGKey(1), batch, update, 4, 6)
        assert chunks._PROGRAMS[fast][0]._cache_size() == before + 1  # compiled in this build
    for a, b in zip(jax.tree.leaves(results[False]), jax.tree.leaves(results[True]), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)


def test_two_resumes_within_one_second_keep_both_event_files(tmp_path, monkeypatch):
    """Event files are named by the second they open in: a resume in the same second as the
    previous writer must not truncate that writer's points (and its purge marker)."""
    import tensorboardX.event_file_writer as event_file_writer  # noqa: PLC0415

    from eabc.training.logger import RunLogger as Logger  # noqa: PLC0415

    class Frozen:  # the module's clock stands still: every writer opens in the same second
        @staticmethod
        def time():
            return 1_764_662_400.0

    monkeypatch.setattr(event_file_writer, "time", Frozen)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    first = Logger(run_dir, tensorboard=True)
    for step in (100, 200, 300):
        first.log({"step": step, "score": float(step)})
    first.close()
    resumed = Logger(run_dir, resume_step=200, tensorboard=True)  # 300 goes, 200 stays
    resumed.log({"step": 300, "score": 301.0})
    resumed.log({"step": 400, "score": 400.0})
    resumed.close()
    Logger(run_dir, resume_step=400, tensorboard=True).close()  # resuming the finished run
    assert len(list((run_dir / "tb").glob("events.out.tfevents.*"))) == 3
    assert_tensorboard_equals_log(run_dir)
    points, _ = _tensorboard_points(run_dir)
    assert points["score"] == [(100, 100.0), (200, 200.0), (300, 301.0), (400, 400.0)]


def test_file_mode_follows_the_umask(tmp_path):
    import os  # noqa: PLC0415

    old = os.umask(0o027)
    try:
        assert checkpoint.file_mode() == 0o640
        checkpoint.atomic_write(tmp_path / "f", b"x")
        assert (tmp_path / "f").stat().st_mode & 0o777 == 0o640
        os.umask(0o022)
        assert checkpoint.file_mode() == 0o644
    finally:
        os.umask(old)


def test_the_final_window_names_the_evaluations_a_final_score_averages():
    assert trainer.final_window([]) == "no evaluations"
    assert trainer.final_window([5000]) == "the only evaluation (fewer than 10; step 5,000)"
    steps = [5000 * i for i in range(1, 13)]
    assert trainer.final_window(steps) == "last 10 evaluations (steps 15,000-60,000)"
