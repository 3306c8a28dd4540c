"""Files that were damaged or edited by hand after eabc wrote them, and the names of what a sweep
runs: every one is refused in one line that names the file and says what to do, before any work,
whatever its checksum says. The example tests first (each failed before its fix), then the
generated ones (Hypothesis).

- a run's checkpoint holding NaN/inf weights (its checksum recomputed), its config.json with an
  edited ``max_action`` or without a key every eabc writes (``evaluate``, ``export-policy``,
  ``load_policy``, ``--resume``);
- reference scores in the wrong order (random above expert) in a dataset file, a Minari dataset or
  a run's config.json; a file whose every row is a timeout;
- a sweep naming a dataset whose run directory's name is too long for the file system, or a
  ``minari:`` dataset that is not there; a junk file in the dataset cache (``eabc data list``).

The run is a TD3+BC run's initial checkpoint on 40 transitions: no training.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

from eabc import load_policy, pytree
from eabc.cli import main
from eabc.data.dataset import DatasetError
from eabc.data.loaders import load_file
from eabc.experiments import results
from eabc.training import checkpoint, trainer
from eabc.training.trainer import TrainConfig

SETTINGS = settings(
    deadline=None,
    database=None,  # the same examples on every machine
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


def tiny_arrays(rows: int = 40, **changes) -> dict[str, np.ndarray]:
    """Pendulum-shaped transitions, with ``changes`` (None removes a key)."""
    rng = np.random.default_rng(0)
    arrays = {
        "observations": rng.normal(size=(rows, 3)).astype(np.float32),
        "actions": rng.uniform(-1, 1, (rows, 1)).astype(np.float32),
        "rewards": rng.normal(size=rows).astype(np.float32),
        "terminals": np.zeros(rows, bool),
    }
    return {k: v for k, v in {**arrays, **changes}.items() if v is not None}


@pytest.fixture(scope="module")
def started(tmp_path_factory):
    """A run directory as `eabc train` leaves it after its first checkpoint (the initial state)."""
    root = tmp_path_factory.mktemp("started")
    np.savez(root / "tiny.npz", **tiny_arrays())
    config = TrainConfig(dataset=str(root / "tiny.npz"), algo="td3bc", steps=200,
                         log_interval=100, eval_interval=100, checkpoint_interval=100,
                         eval_episodes=1, env="Pendulum-v1")  # fmt: skip
    run = trainer.start(config, root / "run", {"hidden_dims": (32, 32)})
    run.lock.release()
    checkpoint.save(run.run_dir, run.state, run.algorithm.state_layout, run.identity)
    return root / "run"


def snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != results.DATABASE
    }


def copy_run(started: Path, tmp_path: Path) -> Path:
    run_dir = tmp_path / "root" / "run"
    shutil.copytree(started, run_dir)
    return run_dir


def tamper_checkpoint(run_dir: Path, change) -> None:
    """Rewrite the checkpoint with ``change(payload)`` applied, its checksum recomputed (as a
    careful forger, or a bit flip before the checksum was taken, would leave it)."""
    path = run_dir / checkpoint.CHECKPOINT
    raw = pytree.loads(path.read_bytes()[:-40])
    change(raw)
    checkpoint.write_tree(path, raw)


def edit_config(run_dir: Path, change) -> None:
    path = run_dir / checkpoint.CONFIG
    path.write_text(json.dumps(change(json.loads(path.read_text()))))


READERS = (
    lambda run_dir, out: ["evaluate", str(run_dir), "--episodes", "1"],
    lambda run_dir, out: ["export-policy", str(run_dir), "--onnx", str(out / "policy.onnx")],
    lambda run_dir, out: ["train", "--resume", str(run_dir), "--no-progress"],
)


def refused_by_every_reader(run_dir: Path, tmp_path: Path, names: tuple[str, ...]) -> None:
    """``evaluate``, ``export-policy``, ``--resume`` and ``load_policy`` each refuse the run in
    one line naming one of ``names``; nothing on disk changes."""
    before = snapshot(tmp_path)
    for argv in READERS:
        with pytest.raises(SystemExit) as exit_:
            main(argv(run_dir, tmp_path))
        message = str(exit_.value.code)
        assert message.startswith("error: ") and "\n" not in message, message
        assert any(name in message for name in names), (argv(run_dir, tmp_path)[0], message)
    with pytest.raises(ValueError) as error:
        load_policy(run_dir)
    assert "\n" not in str(error.value) and any(name in str(error.value) for name in names)
    assert snapshot(tmp_path) == before


# ----------------------------------------------------------------------------------------------
# Tampered run files


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("where", ["actor", "critic", "normalizer"])
def test_a_checkpoint_with_non_finite_weights_is_refused_whatever_its_checksum(
    started, tmp_path, value, where
):
    """Before: NaN actor weights with a recomputed checksum were evaluated (printing NaN),
    exported to ONNX and returned by load_policy."""
    run_dir = copy_run(started, tmp_path)

    def poison(raw):
        params, key = (
            (raw["normalizer"], "std") if where == "normalizer" else
            (pytree.find(raw["agent"], where), "w0")
        )  # fmt: skip
        array = np.array(params[key])  # a writable copy
        array.reshape(-1)[0] = value
        params[key] = array

    tamper_checkpoint(run_dir, poison)
    refused_by_every_reader(run_dir, tmp_path, (str(run_dir / checkpoint.CHECKPOINT),))
    with pytest.raises(SystemExit, match="NaN/inf"):
        main(["evaluate", str(run_dir), "--episodes", "1"])
    runs, _ = results.collect(tmp_path / "root", write=False)  # listed as unusable, not dropped
    assert list(runs["status"]) == ["damaged"] and "NaN/inf" in runs["config"][0]


@pytest.mark.parametrize("value", [math.nan, math.inf, 0.0, -2.0, 1.0, 1e30])
def test_an_edited_max_action_is_refused(started, tmp_path, value):
    """Pendulum's actions are bounded by 2. Before: an edited max_action was exported and
    returned by load_policy silently (the policy then acted outside the environment's bounds)."""
    run_dir = copy_run(started, tmp_path)
    edit_config(run_dir, lambda c: {**c, "max_action": value})
    refused_by_every_reader(run_dir, tmp_path, ("max_action",))


@pytest.mark.parametrize("key", ["agent", "dataset", "train"])
def test_a_config_without_a_key_every_eabc_writes_is_refused_naming_it(started, tmp_path, key):
    """Before: ``KeyError: 'agent'`` from --resume, and the preset's settings silently in place
    of the run's for evaluate and load_policy."""
    run_dir = copy_run(started, tmp_path)
    edit_config(run_dir, lambda c: {k: v for k, v in c.items() if k != key})
    refused_by_every_reader(run_dir, tmp_path, (f"config.json: {key} is missing",))
    runs, _ = results.collect(tmp_path / "root", write=False)
    assert list(runs["status"]) == ["broken"] and f"{key} is missing" in runs["config"][0]


def test_the_pretraining_progress_file_is_checked_for_finite_values(tmp_path):
    """The model fit's progress (``pretrain.msgpack``) is read through the same check."""
    checkpoint.write_tree(tmp_path / "p.msgpack", {"model": {"w0": np.array([1.0, np.nan])}})
    with pytest.raises(checkpoint.CheckpointError, match="p.msgpack holds NaN/inf in model/w0"):
        checkpoint.read_tree(tmp_path / "p.msgpack")


# ----------------------------------------------------------------------------------------------
# Dataset metadata


@pytest.mark.parametrize("scores", [(3234.3, -20.3), (5.0, 5.0), (-math.inf, 10.0)])
def test_reference_scores_out_of_order_are_refused_in_a_file(tmp_path, scores):
    """Before: random above expert was accepted, and near-random data then scored 98.8."""
    low, high = scores
    path = tmp_path / "d.npz"
    np.savez(path, **tiny_arrays(), env_id=np.asarray("Pendulum-v1"),
             ref_min_score=np.asarray(low), ref_max_score=np.asarray(high))  # fmt: skip
    with pytest.raises(DatasetError) as error:
        load_file(path)
    message = str(error.value)
    assert str(path) in message and "ref_min_score" in message and "\n" not in message
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--dataset", str(path), "--algo", "td3bc", "--dry-run"])
    assert "ref_min_score" in str(exit_.value.code) and str(path) in str(exit_.value.code)


def test_reference_scores_out_of_order_are_refused_in_a_run_config(started, tmp_path):
    run_dir = copy_run(started, tmp_path)
    edit_config(
        run_dir,
        lambda c: {**c, "dataset": {**c["dataset"], "ref_min_score": 10.0, "ref_max_score": 1.0}},
    )
    refused_by_every_reader(run_dir, tmp_path, ("dataset: its reference scores ref_min_score",))


def test_a_file_of_timeouts_only_is_described_as_such(tmp_path):
    """Before: "the dataset is empty", of a file with 40 rows."""
    path = tmp_path / "d.npz"
    np.savez(path, **tiny_arrays(), timeouts=np.ones(40, bool))
    with pytest.raises(DatasetError) as error:
        load_file(path)
    message = str(error.value)
    assert "empty" not in message and "40 rows" in message and "timeout" in message
    assert str(path) in message and "\n" not in message


# ----------------------------------------------------------------------------------------------
# Sweeps: every name and dataset checked before any job starts


def sweep_argv(tmp_path: Path, *datasets: str) -> list[str]:
    return ["sweep", "--datasets", *datasets, "--algos", "td3bc", "--seeds", "0", "--steps",
            "200", "--root", str(tmp_path / "root")]  # fmt: skip


@pytest.mark.parametrize("dry_run", [True, False])
def test_a_sweep_whose_run_directory_name_is_too_long_is_refused_before_any_job(tmp_path, dry_run):
    """A dataset file may have a 240-character name; its run directory's name (with the
    algorithm and the seed) then exceeds the file system's 255 bytes. Before: the dry run
    listed it as pending, and the sweep died on it with a traceback, killing its healthy
    running job."""
    good, long = tmp_path / "good.npz", tmp_path / f"{'d' * 236}.npz"
    for path in (good, long):
        np.savez(path, **tiny_arrays(), env_id=np.asarray("Pendulum-v1"))
    before = snapshot(tmp_path)
    argv = sweep_argv(tmp_path, str(good), str(long)) + ["--dry-run"] * dry_run
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    message = str(exit_.value.code)
    assert message.startswith("error: ") and "\n" not in message, message
    assert str(long) in message and "255" in message
    assert snapshot(tmp_path) == before and not (tmp_path / "root").exists()


@pytest.mark.parametrize("dry_run", [True, False])
def test_a_sweep_naming_a_missing_minari_dataset_is_refused_before_any_job(
    tmp_path, monkeypatch, dry_run
):
    """The README promises every dataset is checked before the first run starts. Before: a
    ``minari:`` dataset was found missing only when its job started."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    good = tmp_path / "good.npz"
    np.savez(good, **tiny_arrays(), env_id=np.asarray("Pendulum-v1"))
    argv = sweep_argv(tmp_path, str(good), "minari:test/pendulum/absent-v0")
    with pytest.raises(SystemExit) as exit_:
        main(argv + ["--dry-run"] * dry_run)
    message = str(exit_.value.code)
    assert "test/pendulum/absent-v0" in message and "\n" not in message, message
    assert not (tmp_path / "root").exists()


@pytest.mark.parametrize(
    "junk", [b"", b"not an HDF5 file", b"\x89HDF\r\n\x1a\n" + b"\0" * 100, "directory", "fifo"]
)
def test_a_junk_file_in_the_cache_does_not_stop_data_list(tmp_path, monkeypatch, capsys, junk):
    """Before: one unreadable file in the cache stopped ``eabc data list`` with an error."""
    monkeypatch.setenv("EABC_CACHE_DIR", str(tmp_path / "cache"))
    folder = tmp_path / "cache" / "datasets"
    folder.mkdir(parents=True)
    path = folder / "hopper-random.hdf5"
    if junk == "directory":
        path.mkdir()
    elif junk == "fifo":
        os.mkfifo(path)
    else:
        path.write_bytes(junk)
    (folder / "walker2d-random.info.json").write_text("{junk")  # a sidecar without its file
    main(["data", "list"])
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("hopper-random "))
    assert "unreadable" in row and "eabc data make hopper-random --force" in row
    assert any(line.startswith("walker2d-random ") for line in out.splitlines())
    assert len(out.splitlines()) > 10  # every built-in dataset is listed
