"""Datasets made by several processes (eabc.data.parallel) are the ones one process makes."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from eabc import cli
from eabc.cli import main
from eabc.data import antmaze_collect, generate, hdf5_writer, parallel
from eabc.data.dataset import FIELDS
from eabc.data.loaders import load_file


def digest(path) -> str:
    """SHA-256 of a dataset file's arrays, in D4RL's field order."""
    data, sha = load_file(path), hashlib.sha256()
    for field in FIELDS:
        sha.update(np.ascontiguousarray(getattr(data, field)).tobytes())
    return sha.hexdigest()


@pytest.fixture
def table(tmp_path, monkeypatch):
    """An empty table of episode starts in place of the shipped one."""
    path = tmp_path / "episode_starts.json"
    monkeypatch.setattr(parallel, "TABLE", path)
    return path


def test_a_mujoco_dataset_made_by_two_processes_is_the_one_made_by_one(tmp_path, table, capfd):
    """hopper-medium-replay: rollouts of uniform random actions (its first phase) and of sampled
    policy actions, cut at episode starts read from the one-process file."""
    name, size = "hopper-medium-replay", 3_000
    one = generate.make(name, tmp_path / "one.hdf5", seed=0, size=size)
    generate.add_episode_starts([one], table, spacing=60)
    rollouts = json.loads(table.read_text())["rollouts"]
    assert sum(len(entry["starts"]) for entry in rollouts.values()) >= 5
    assert any(key.split()[1] == "uniform" and entry["starts"] for key, entry in rollouts.items())
    capfd.readouterr()
    two = generate.make(name, tmp_path / "two.hdf5", seed=0, size=size, workers=2)
    assert "on 2 processes" in capfd.readouterr().err  # the pieces were made by the workers
    assert digest(two) == digest(one)
    assert load_file(two).metadata == load_file(one).metadata

    # A start that is not one (an episode counted twice) is noticed; that rollout is made again.
    key = next(k for k, entry in rollouts.items() if len(entry["starts"]) >= 2)
    rollouts[key]["starts"][0][1] += 1
    table.write_text(json.dumps({"rollouts": rollouts}))
    again = generate.make(name, tmp_path / "again.hdf5", seed=0, size=size, workers=2)
    assert "do not fit" in capfd.readouterr().err
    assert digest(again) == digest(one)


@pytest.mark.parametrize("name", ["antmaze-umaze-diverse", "antmaze-umaze-diverse@planner-v0"])
def test_an_antmaze_dataset_made_by_two_processes_is_the_one_made_by_one(
    tmp_path, monkeypatch, name
):
    """Both recipes: 2,500 rows are 3 (1,001-step) or 4 (700-step) episodes, 2 batches of 2."""
    monkeypatch.setattr(antmaze_collect, "NUM_ENVS", 2)
    size = 2_500
    one = generate.make(name, tmp_path / "one.hdf5", seed=5, size=size)
    two = generate.make(name, tmp_path / "two.hdf5", seed=5, size=size, workers=2)
    assert digest(two) == digest(one)
    assert load_file(two).metadata == load_file(one).metadata


def test_a_rollout_the_table_does_not_know_is_made_by_one_process(tmp_path, table, capfd):
    one = generate.make("hopper-random", tmp_path / "one.hdf5", seed=7, size=400)
    two = generate.make("hopper-random", tmp_path / "two.hdf5", seed=7, size=400, workers=3)
    assert "no episode starts of Hopper-v4 uniform seed 7 known" in capfd.readouterr().err
    assert digest(two) == digest(one)


def test_the_table_keeps_the_longest_rollout_it_is_given(tmp_path, table):
    """hopper-random and medium-replay's warm-up share a rollout (uniform actions, seed 0): a
    shorter one's starts are the longer one's first starts, and the table keeps the longer."""
    short = generate.make("hopper-random", tmp_path / "short.hdf5", seed=0, size=300)
    long = generate.make("hopper-random", tmp_path / "long.hdf5", seed=0, size=900)
    generate.add_episode_starts([long, short], table, spacing=100)
    entry = json.loads(table.read_text())["rollouts"]["Hopper-v4 uniform seed 0"]
    first = generate.episode_starts(short, spacing=100)["Hopper-v4 uniform seed 0"]["starts"]
    assert entry["transitions"] == 900 and len(entry["starts"]) > len(first) >= 2
    assert entry["starts"][: len(first)] == first


@pytest.mark.parametrize(
    "name", ["hopper-medium", "halfcheetah-medium", "walker2d-medium", "hopper-medium-replay",
             "hopper-random", "walker2d-random", "halfcheetah-medium-replay"],
)  # fmt: skip
def test_the_shipped_table_covers_the_random_medium_and_replay_datasets(name):
    """Every rollout of each, at full size, with a start about every SPACING rows."""
    rollouts = json.loads(parallel.TABLE.read_text())["rollouts"]
    for spec in generate.rollouts(name, 0, generate.default_size(name)):
        entry = rollouts[spec.key()]
        rows = [0] + [row for row, _ in entry["starts"] if row < spec.size]
        assert entry["transitions"] >= spec.size and len(rows) >= spec.size // parallel.SPACING
        assert (
            np.all(np.diff(rows) > 0) and np.diff([*rows, spec.size]).max() < 2 * parallel.SPACING
        )


def test_workers_0_is_refused_in_one_line(tmp_path):
    with pytest.raises(ValueError, match="--workers must be an integer >= 1, got 0") as error:
        cli.parse(["data", "make", "hopper-random", "--workers", "0"])
    assert "\n" not in str(error.value)
    with pytest.raises(SystemExit) as exit_:
        main(["data", "make", "hopper-random", "--workers", "0", "--cache-dir", str(tmp_path)])
    assert exit_.value.code == f"error: {error.value}"
    assert not any(tmp_path.rglob("*.hdf5*"))


def test_an_interrupted_write_leaves_no_temporary_file(tmp_path, monkeypatch):
    data = load_file(generate.make("hopper-random", tmp_path / "d.hdf5", seed=0, size=50))

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr("h5py.Group.create_dataset", interrupted)
        with pytest.raises(KeyboardInterrupt):
            hdf5_writer.save_hdf5(data, tmp_path / "e.hdf5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.hdf5"]
    # One killed outright (no cleanup possible) is removed by the next write of that file.
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip
    orphan = tmp_path / f"e.hdf5.{dead}.tmp"
    orphan.write_bytes(b"half")
    os.utime(orphan, (0, 0))
    hdf5_writer.save_hdf5(data, tmp_path / "e.hdf5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.hdf5", "e.hdf5"]


def test_a_make_killed_while_its_workers_run_stops_them_and_leaves_no_file(tmp_path):
    """SIGTERM to ``eabc data make --workers 2`` (a job's time limit, ``kill``): the command ends
    at once, its worker processes with it, and nothing is left in the cache."""
    argv = ["data", "make", "hopper-random", "--size", "300000", "--workers", "2"]
    maker = subprocess.Popen(
        [sys.executable, "-c", "import sys; from eabc.cli import main; main(sys.argv[1:])", *argv,
         "--cache-dir", str(tmp_path / "cache")],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    lines = []
    for line in maker.stderr:  # the pieces are handed out: the workers are running
        lines.append(line)
        if "pieces on 2 processes" in line:
            break
    time.sleep(1.0)
    workers = subprocess.run(["pgrep", "-P", str(maker.pid)], capture_output=True, text=True)
    workers = [int(pid) for pid in workers.stdout.split()]
    assert len(workers) >= 2, lines
    maker.send_signal(signal.SIGTERM)
    assert maker.wait(timeout=30) != 0
    deadline = time.monotonic() + 10
    while any(os.path.exists(f"/proc/{pid}") for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not [pid for pid in workers if os.path.exists(f"/proc/{pid}")]
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]
