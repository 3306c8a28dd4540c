"""A run's files belong together and are never thrown away unasked.

Every checkpoint records which run wrote it (run id, algorithm, seed, settings hash, dataset and
its fingerprint); resume, evaluate, ``load_policy``, the ONNX export and ``eabc results`` refuse
another run's checkpoint or config.json even when every shape matches. A finished run whose
checkpoint was deleted is refused rather than trained again from step 0 (``--restart`` asks for
that); a log.csv cut short or deleted is reported as damaged and rebuilt from the checkpoint's
evaluation history; inputs that would fail after training (equal reference scores, a cache
directory that is a file) are refused before any work. Runs are tiny: TD3+BC with 32-unit
networks, 300 steps, one evaluation episode.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import re
import shutil

import pytest

from eabc import load_policy
from eabc.cli import main
from eabc.data.dataset import DatasetError
from eabc.data.loaders import save_npz
from eabc.deploy import export_onnx
from eabc.experiments import job_process, results, run_status
from eabc.experiments.spec import expand
from eabc.training import checkpoint, lifecycle, trainer
from eabc.training.checkpoint import CheckpointError
from eabc.training.config import TrainConfig
from eabc.training.directory import ProgressLostError

SMALL = dict(
    dataset="pendulum-swingup",
    algo="td3bc",
    steps=300,
    log_interval=100,
    eval_interval=100,
    checkpoint_interval=100,
    eval_episodes=1,
    env="Pendulum-v1",
)
AGENT = {"hidden_dims": (32, 32)}


@pytest.fixture(scope="module")
def finished(tmp_path_factory, pendulum_dataset):
    """A finished run (seed 0, its data in a file) and two runs of its setting that saved their initial state as a
    checkpoint: seed 1, and seed 0 on other data of the same shapes (rewards + 1)."""
    root = tmp_path_factory.mktemp("finished")
    save_npz(pendulum_dataset, root / "pendulum.npz")  # a file the CLI can load
    config = TrainConfig(**{**SMALL, "dataset": str(root / "pendulum.npz")})
    trainer.train(lifecycle.start(config, root / "seed0", AGENT, pendulum_dataset), progress=False)
    other = dataclasses.replace(pendulum_dataset, rewards=pendulum_dataset.rewards + 1.0)
    for name, seed, data in [("seed1", 1, pendulum_dataset), ("other", 0, other)]:
        run = lifecycle.start(dataclasses.replace(config, seed=seed), root / name, AGENT, data)
        run.lock.release()
        checkpoint.save(run.run_dir, run.state, run.algorithm.state_layout, run.identity)
    return root


def copy(finished, tmp_path, name="seed0"):
    shutil.copytree(finished / name, tmp_path / "run")
    return tmp_path / "run"


def config_of(run_dir) -> dict:
    return json.loads((run_dir / checkpoint.CONFIG).read_text())


def test_another_runs_checkpoint_is_refused_by_every_reader(
    finished, tmp_path, pendulum_dataset, capsys
):
    run_dir = copy(finished, tmp_path)
    mine, theirs = config_of(run_dir)["run_id"], config_of(finished / "seed1")["run_id"]
    assert mine and theirs and mine != theirs
    shutil.copy(finished / "seed1" / checkpoint.CHECKPOINT, run_dir)
    message = (
        rf"run/checkpoint.msgpack belongs to run {theirs} \(td3bc, seed 1, pendulum-swingup.*\) "
        rf"but .*run/config.json is run {mine} \(td3bc, seed 0, .*differ in run_id, seed\)"
    )
    with pytest.raises(CheckpointError, match=message):
        lifecycle.resume(run_dir, pendulum_dataset)  # eabc train --resume
    with pytest.raises(CheckpointError, match=message):
        lifecycle.resume(run_dir, pendulum_dataset, lock=False)  # eabc evaluate
    with pytest.raises(CheckpointError, match=message):
        load_policy(run_dir)
    with pytest.raises(CheckpointError, match=message):
        export_onnx(run_dir, tmp_path / "policy.onnx")
    assert not (tmp_path / "policy.onnx").exists()
    row, _ = results.read_run(run_dir)
    assert row["status"] == "damaged" and f"belongs to run {theirs}" in row["config"]
    with pytest.raises(SystemExit, match=f"error: .*belongs to run {theirs}"):
        main(["export-policy", str(run_dir), "--onnx", str(tmp_path / "policy.onnx")])

    # Data of the same shapes but other content: the fingerprint tells them apart.
    shutil.copy(finished / "other" / checkpoint.CHECKPOINT, run_dir)
    with pytest.raises(CheckpointError, match="differ in run_id, fingerprint\\)"):
        load_policy(run_dir)

    # Another run's config.json beside this checkpoint does not resume as the other seed.
    shutil.copy(finished / "seed0" / checkpoint.CHECKPOINT, run_dir)
    shutil.copy(finished / "seed1" / checkpoint.CONFIG, run_dir)
    with pytest.raises(CheckpointError, match=f"belongs to run {mine} .* is run {theirs}"):
        lifecycle.resume(run_dir, pendulum_dataset)


def test_checkpoints_from_before_the_identity_load_with_a_warning(
    finished, tmp_path, pendulum_dataset, capsys
):
    """A checkpoint without an identity and a config.json without a run id (an older eabc's):
    read with a one-line warning; resumed for training, the run gets an id from then on."""
    run_dir = copy(finished, tmp_path)
    raw = checkpoint.load_raw(run_dir)
    assert raw[checkpoint.IDENTITY]["run_id"] == config_of(run_dir)["run_id"]
    old = {k: v for k, v in raw.items() if k != checkpoint.IDENTITY}
    checkpoint.save(run_dir, old)
    config = config_of(run_dir)
    del config["run_id"]
    checkpoint.save_json(run_dir / checkpoint.CONFIG, config)
    capsys.readouterr()

    assert lifecycle.resume(run_dir, pendulum_dataset, lock=False).step == 300
    load_policy(run_dir)
    warnings = capsys.readouterr().err.strip().splitlines()
    assert len(warnings) == 2 and all("does not record which run wrote it" in w for w in warnings)
    assert results.read_run(run_dir)[0]["status"] == "done"

    run = lifecycle.resume(run_dir, pendulum_dataset)  # for training: the run gets an id
    run.lock.release()
    assert config_of(run_dir)["run_id"] == run.identity["run_id"]


def test_a_finished_run_without_its_checkpoint_is_refused_not_retrained(
    finished, tmp_path, pendulum_dataset
):
    run_dir = copy(finished, tmp_path)
    (run_dir / checkpoint.CHECKPOINT).unlink()  # to save disk
    kept = {name: (run_dir / name).read_bytes() for name in ("log.csv", "summary.json")}
    with pytest.raises(SystemExit) as exit:
        main(["train", "--resume", str(run_dir), "--no-progress"])
    assert "run is finished (300 of 300 steps; summary.json)" in exit.value.code
    assert "--restart" in exit.value.code and "\n" not in exit.value.code
    assert {name: (run_dir / name).read_bytes() for name in kept} == kept
    with pytest.raises(SystemExit, match="run is finished.*nothing to read"):
        main(["evaluate", str(run_dir)])

    # Its log alone shows it finished; a log past the first checkpoint shows progress.
    (run_dir / "summary.json").unlink()
    with pytest.raises(ProgressLostError, match="finished \\(log.csv reaches step 300 of 300\\)"):
        lifecycle.resume(run_dir, pendulum_dataset)
    lines = kept["log.csv"].decode().splitlines(keepends=True)
    (run_dir / "log.csv").write_text("".join(lines[:3]))  # rows at steps 100 and 200
    with pytest.raises(
        ProgressLostError, match="trained to step 200 \\(log.csv\\), past its first"
    ):
        lifecycle.resume(run_dir, pendulum_dataset)
    (run_dir / "log.csv").write_text("".join(lines[:2]))  # killed before its first checkpoint
    lifecycle.resume(run_dir, pendulum_dataset).lock.release()
    assert not (run_dir / "log.csv").exists()  # started again, as before

    # --restart asks for it, and only where the checkpoint is missing.
    shutil.rmtree(run_dir)
    run_dir = copy(finished, tmp_path)
    with pytest.raises(SystemExit, match="--restart trains a run again only when its checkpoint"):
        main(["train", "--resume", str(run_dir), "--restart", "--no-progress"])
    (run_dir / checkpoint.CHECKPOINT).unlink()
    run = lifecycle.resume(run_dir, pendulum_dataset, restart=True)
    assert run.step == 0 and not (run_dir / "summary.json").exists()
    run.lock.release()


def test_a_sweep_does_not_start_again_a_run_whose_checkpoint_is_gone(tmp_path, pendulum_dataset):
    save_npz(pendulum_dataset, tmp_path / "pend.npz")
    train = {k: v for k, v in SMALL.items() if k not in ("dataset", "algo", "steps")}
    spec = {"datasets": [str(tmp_path / "pend.npz")], "algos": ["td3bc"], "steps": 200,
            "grid": {"hidden_dims": [[32, 32]]}, "train": train}  # fmt: skip
    (run,) = expand(spec)
    job_process.execute([run.to_json()], str(tmp_path / "sweep"))
    run_dir = tmp_path / "sweep" / "runs" / run.run_id
    (run_dir / checkpoint.CHECKPOINT).unlink()
    (longer,) = expand({**spec, "steps": 300})  # an extension needs the checkpoint
    state, _, why = run_status.status_with_reason(longer, tmp_path / "sweep")
    assert state == "broken" and "is finished (200 of 300 steps" in why


def test_damaged_logs_are_reported_and_rebuilt_from_the_checkpoint(
    finished, tmp_path, pendulum_dataset, capsys
):
    run_dir = copy(finished, tmp_path)
    good = (run_dir / "log.csv").read_bytes()
    summary = json.loads((run_dir / "summary.json").read_text())
    lines = good.decode().splitlines(keepends=True)
    header = lines[0].rstrip().split(",")
    edited = lines[2].rstrip().split(",")  # step 200, an evaluation
    edited[header.index("return_mean")] = "1.5"
    cases = [
        ("deleted", None, "run/log.csv is missing"),
        ("cut short", "".join(lines[:3]), "ends at step 200, before the checkpoint's step 300"),
        ("cut mid-line", good.decode()[:-20], "cut short \\(its last line is incomplete\\)"),
        (
            "edited",
            "".join([*lines[:2], ",".join(edited) + "\r\n", *lines[3:]]),
            "has an evaluation at step 200 that the checkpoint does not hold",
        ),
    ]
    for name, text, why in cases:
        (run_dir / "log.csv").unlink(missing_ok=True)
        if text is not None:
            (run_dir / "log.csv").write_bytes(text.encode())
        row, _ = results.read_run(run_dir)
        assert row["status"] == "damaged", name
        assert re.search(why, row["config"]), (name, row["config"])
        assert "`eabc train --resume" in row["config"]

    # The last case's resume: the log is rebuilt from the checkpoint, the summary agrees again.
    (run_dir / "log.csv").unlink()
    trainer.train(lifecycle.resume(run_dir, pendulum_dataset), progress=False)
    assert (
        "run/log.csv is missing: rebuilt its evaluations up to step 300" in capsys.readouterr().err
    )
    row, evaluations = results.read_run(run_dir)
    assert row["status"] == "done" and row["final_return"] == summary["final_return"]
    assert [e["step"] for e in evaluations] == [100, 200, 300]

    # summary.json contradicting the log (replaced, or its return edited) is damage too.
    (run_dir / "summary.json").write_text(json.dumps({**summary, "final_return": 1.0}))
    row, _ = results.read_run(run_dir)
    assert row["status"] == "damaged" and "is not summary.json's 1.0" in row["config"]
    (run_dir / "summary.json").write_text("{")
    assert "summary.json cannot be read" in results.read_run(run_dir)[0]["config"]


def test_temporary_files_of_a_killed_writer_are_removed_by_the_next(
    finished, tmp_path, pendulum_dataset
):
    run_dir = copy(finished, tmp_path)
    for name in (".log.csv.x1y2.tmp", ".checkpoint.msgpack.a9b8.tmp"):
        (run_dir / name).write_bytes(b"half")
    lifecycle.resume(run_dir, pendulum_dataset, lock=False)  # a reader leaves them
    assert len(list(run_dir.glob(".*.tmp"))) == 2
    lifecycle.resume(run_dir, pendulum_dataset).lock.release()
    assert not list(run_dir.glob(".*.tmp"))


def test_inputs_that_fail_after_training_are_refused_before_it(
    tmp_path, pendulum_dataset, monkeypatch
):
    for low, high in [(-130.0, -130.0), (float("nan"), -130.0), (-130.0, -1200.0)]:
        with pytest.raises(  # by the data themselves, whatever their source
            DatasetError, match="pendulum-swingup: its reference scores .*(equal|finite|order)"
        ):
            data = dataclasses.replace(pendulum_dataset, ref_min_score=low, ref_max_score=high)
            lifecycle.start(TrainConfig(**SMALL), tmp_path / "same", AGENT, dataset=data)
        assert not (tmp_path / "same").exists(), "nothing made: a fixed file can start afresh"

    (tmp_path / "afile").write_text("")
    for cache in ("afile", "afile/sub"):
        with pytest.raises(ValueError, match=f"cache_dir .*{cache} is not a directory"):
            TrainConfig(**SMALL, cache_dir=str(tmp_path / cache))
    with pytest.raises(SystemExit, match="error: --cache-dir .*afile is not a directory"):
        main(["train", "--cache-dir", str(tmp_path / "afile"), "--run-dir", str(tmp_path / "r")])
    monkeypatch.setenv("EABC_CACHE_DIR", str(tmp_path / "afile"))
    with pytest.raises(ValueError, match=r"\$EABC_CACHE_DIR .*afile is not a directory"):
        lifecycle.start(TrainConfig(**SMALL), tmp_path / "env", AGENT, dataset=pendulum_dataset)


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--dataset", "hopper-medium", "--cache-dir", "~nouser/c", "--dry-run"],
        ["train", "--dataset", "~nouser/d.npz", "--dry-run"],
        ["data", "make", "hopper-medium", "--cache-dir", "~nouser/c"],
        ["sweep", "--preset", "study-1m", "--root", "~nouser/r", "--dry-run"],
        ["results", "~nouser/r"],
    ],
)
def test_a_home_that_does_not_exist_is_refused_in_one_line(argv, tmp_path, monkeypatch):
    """``~nouser`` cannot be expanded (Python raises RuntimeError): every command that takes a
    path names it and asks for the full path, before any work and without a traceback."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit, match=r"error: ~nouser/\S+: cannot expand ~nouser .*full path"):
        main(argv)
    assert not list(tmp_path.iterdir()), "nothing made"


def _released(fifo, action):
    """``action()``'s outcome (its value or the exception it raised), run in a thread; if it
    blocks on opening ``fifo`` (the readers did) it is released and the test fails. A signal
    cannot stop it: it may reach one of JAX's threads instead of the one blocked."""
    import os  # noqa: PLC0415
    import threading  # noqa: PLC0415

    outcome = {}

    def run():
        try:
            outcome["value"] = action()
        except BaseException as error:  # noqa: BLE001 (SystemExit too: compared below)
            outcome["value"] = error

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(30)
    blocked = thread.is_alive()
    while thread.is_alive():  # a writer that closes at once lets a blocked open() return
        with contextlib.suppress(OSError):
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        thread.join(0.5)
    assert not blocked, f"blocked on {fifo}"
    return outcome["value"]


@pytest.mark.parametrize(
    "name", ["checkpoint.msgpack", "config.json", "log.csv", "summary.json", "provenance.json"]
)
def test_a_run_file_that_is_a_fifo_is_refused_not_waited_on(finished, tmp_path, name):
    """Before: every reader blocked forever on a FIFO (and read /dev/zero until memory ran out)."""
    import os  # noqa: PLC0415

    run_dir = copy(finished, tmp_path)
    (run_dir / name).unlink()
    os.mkfifo(run_dir / name)
    row, _ = _released(run_dir / name, lambda: results.read_run(run_dir))
    if name in ("checkpoint.msgpack", "config.json", "log.csv", "summary.json"):
        assert row["status"] in results.UNUSABLE and f"run/{name}" in row["config"], row
    for argv in (["evaluate", str(run_dir)], ["train", "--resume", str(run_dir), "--no-progress"]):
        with contextlib.redirect_stdout(io.StringIO()):
            ended = _released(run_dir / name, lambda argv=argv: main(argv))
        if isinstance(ended, BaseException):
            assert isinstance(ended, SystemExit), ended
            assert f"run/{name}" in str(ended.code) and "\n" not in str(ended.code)


def test_results_lists_a_run_whose_config_json_was_deleted(finished, tmp_path):
    """Before: the run vanished from `eabc results` (only config.json marked a run)."""
    run_dir = copy(finished, tmp_path)
    (run_dir / checkpoint.CONFIG).unlink()
    runs, _ = results.collect(tmp_path, write=False)
    assert list(runs["status"]) == ["broken"] and "run/config.json is missing" in runs["config"][0]


def _log_lines(run_dir):
    return (run_dir / "log.csv").read_text().splitlines(keepends=True)


@pytest.mark.parametrize(
    ("damage", "why"),
    [
        (lambda lines: [*lines, lines[-1]], "has step 300 more than once"),
        (lambda lines: [*lines, lines[-1].replace("300,", "400,", 1)], "goes on to step 400"),
    ],
)
def test_a_log_with_a_repeated_row_or_one_past_the_end_is_damaged_and_rebuilt(
    finished, tmp_path, pendulum_dataset, damage, why
):
    """Before: results counted the repeated evaluation (or listed the run as done), and resume
    left the log as it was."""
    run_dir = copy(finished, tmp_path)
    (run_dir / "log.csv").write_text("".join(damage(_log_lines(run_dir))))
    row, _ = results.read_run(run_dir)
    assert row["status"] == "damaged" and why in row["config"]
    trainer.train(lifecycle.resume(run_dir, pendulum_dataset), progress=False)
    assert results.read_run(run_dir)[0]["status"] == "done"


@pytest.mark.parametrize("text", ["{}", "[300]", '{"steps": "300"}'])
def test_a_summary_that_is_not_one_is_damaged(finished, tmp_path, text):
    """Before: ``{}`` or a list read as no summary at all (the run listed as partial)."""
    run_dir = copy(finished, tmp_path)
    (run_dir / "summary.json").write_text(text)
    row, _ = results.read_run(run_dir)
    assert (
        row["status"] == "damaged"
        and "summary.json cannot be read as a run's summary" in (row["config"])
    )


def test_a_log_whose_scores_are_not_the_checkpoints_is_damaged(finished, tmp_path):
    """The returns the checkpoint holds but other scores (another run's log on data with other
    reference scores): before, the run was listed as done with scores it never had."""
    run_dir = copy(finished, tmp_path)
    lines = _log_lines(run_dir)
    header = lines[0].rstrip("\r\n").split(",")
    cells = lines[2].rstrip("\r\n").split(",")  # step 200, an evaluation
    cells[header.index("score")] = "99.0"
    (run_dir / "log.csv").write_text("".join([*lines[:2], ",".join(cells) + "\n", *lines[3:]]))
    row, _ = results.read_run(run_dir)
    assert row["status"] == "damaged" and "evaluation at step 200" in row["config"]


def test_one_reference_score_without_the_other_is_refused_before_training(
    tmp_path, pendulum_dataset
):
    """Before: the run trained, with a score that could never be computed."""
    for low, high in [(-1200.0, None), (None, -130.0)]:
        data = dataclasses.replace(pendulum_dataset, ref_min_score=low, ref_max_score=high)
        with pytest.raises(DatasetError, match="has ref_m.._score but no ref_m.._score"):
            lifecycle.start(TrainConfig(**SMALL), tmp_path / "one", AGENT, dataset=data)
        assert not (tmp_path / "one").exists()


def test_another_runs_summary_is_damage_even_where_its_numbers_agree(finished, tmp_path):
    """Another seed's (or algorithm's, or dataset's) summary.json with the same numbers: before,
    listed as done."""
    run_dir = copy(finished, tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    for key, value in [("seed", 1), ("algo", "bc"), ("dataset", "other")]:
        (run_dir / "summary.json").write_text(json.dumps({**summary, key: value}))
        row, _ = results.read_run(run_dir)
        assert row["status"] == "damaged" and f"summary.json is of {key}" in row["config"]
