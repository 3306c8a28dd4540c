"""Fault injection: kills at any moment, corrupt and foreign files, two writers, bad inputs.

Every test here failed before the fixes it guards. Runs are tiny (BC or K = 2 EABC, 32-unit
networks, a few hundred steps) so the file takes well under a minute and a half.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from eabc.cli import main
from eabc.data.dataset import Dataset, DatasetError
from eabc.data.loaders import save_npz
from eabc.data.sources import load_dataset
from eabc.experiments import job_process, local_pool, planning, results, run_status
from eabc.experiments.spec import expand
from eabc.ranges import SettingError
from eabc.training import checkpoint, chunks, lifecycle, logger, trainer
from eabc.training.checkpoint import CheckpointError
from eabc.training.config import TrainConfig, resolve_agent_config
from eabc.training.lock import OWNER, RunLockedError

SMALL = dict(
    dataset="pendulum-swingup",
    steps=400,
    log_interval=100,
    eval_interval=200,
    checkpoint_interval=200,
    eval_episodes=1,
    env="Pendulum-v1",
)
AGENT = dict(num_critics=2, confidence_level=0.5, hidden_dims=(32, 32))
WALL = ("wall_time", "steps_per_s", "wall_time_s")
"""Wall-clock fields, the only ones allowed to differ between a resumed and a straight run."""


@pytest.fixture(scope="module", autouse=True)
def quick_chunks_for_the_module():
    """Every run here, the sweeps' workers included, trains quickly compiled chunks (conftest's
    quick_chunks, for the whole module: the straight run and the runs compared with it must run
    the same build)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(chunks.FAST_COMPILE_ENV, "1")
        yield


def start(tmp_path, name, dataset, agent=AGENT, **overrides):
    config = TrainConfig(**{**SMALL, **overrides})
    return lifecycle.start(config, tmp_path / name, agent, dataset=dataset)


def log_without_wall(run_dir) -> str:
    """log.csv as text, the wall-clock columns blanked (everything else byte for byte)."""
    lines = (run_dir / "log.csv").read_text().splitlines()
    header = lines[0].split(",")
    keep = [i for i, name in enumerate(header) if name not in WALL]
    return "\n".join(",".join(line.split(",")[i] for i in keep) for line in lines)


def summary_without_wall(run_dir) -> dict:
    summary = json.loads((run_dir / "summary.json").read_text())
    return {k: v for k, v in summary.items() if k not in WALL}


def results_without_wall(run_dir):
    row, evaluations = results.read_run(run_dir)
    drop = {"run_dir", "wall_time_s", "steps_per_s", "config"}
    return {k: v for k, v in row.items() if k not in drop}, evaluations


def assert_same_results(a, b):
    assert log_without_wall(a) == log_without_wall(b)
    assert summary_without_wall(a) == summary_without_wall(b)
    row_a, evals_a = results_without_wall(a)
    row_b, evals_b = results_without_wall(b)
    assert {**row_a, "run_id": ""} == {**row_b, "run_id": ""}
    assert [{**e, "run_id": ""} for e in evals_a] == [{**e, "run_id": ""} for e in evals_b]


class Killed(BaseException):
    """Stands for kill -9: nothing after it runs, no handler catches it."""


@pytest.fixture(scope="module")
def straight(tmp_path_factory, pendulum_dataset):
    """The uninterrupted run every kill/resume sequence is compared against."""
    root = tmp_path_factory.mktemp("straight")
    trainer.train(start(root, "run", pendulum_dataset), progress=False)
    return root / "run"


@pytest.mark.parametrize("where", ["log", "checkpoint"])
def test_kill_during_a_write_then_resumes_give_the_uninterrupted_results(
    tmp_path, pendulum_dataset, straight, monkeypatch, where
):
    """Killed halfway through writing log.csv (step 300) or the checkpoint (step 400): the file
    on disk is the old one plus a stray temporary file; two resumes (the second a no-op) end with
    the straight run's log, summary and results rows."""
    run = start(tmp_path, "run", pendulum_dataset)
    real = checkpoint.atomic_write

    def die_midway(path, data):
        if (where == "log" and path.name == "log.csv" and b"\n300," in data) or (
            where == "checkpoint" and path.name == checkpoint.CHECKPOINT and run.step == 400
        ):
            (path.parent / f".{path.name}.half.tmp").write_bytes(data[: len(data) // 2])
            raise Killed
        real(path, data)

    monkeypatch.setattr(checkpoint, "atomic_write", die_midway)
    monkeypatch.setattr(logger, "atomic_write", die_midway)
    with pytest.raises(Killed):
        trainer.train(run, progress=False)
    monkeypatch.undo()
    run.lock.release()  # the kernel does this for a killed process

    for _ in range(2):  # the second resume finds the run finished: nothing may change
        trainer.train(lifecycle.resume(tmp_path / "run", pendulum_dataset), progress=False)
        assert_same_results(straight, tmp_path / "run")


def test_run_killed_before_its_first_checkpoint_starts_again(
    tmp_path, pendulum_dataset, straight, monkeypatch
):
    run = start(tmp_path, "run", pendulum_dataset)
    monkeypatch.setattr(checkpoint, "save", lambda *a: (_ for _ in ()).throw(Killed()))
    with pytest.raises(Killed):
        trainer.train(run, progress=False)
    monkeypatch.undo()
    run.lock.release()
    assert (tmp_path / "run/log.csv").exists() and not (
        tmp_path / "run/checkpoint.msgpack"
    ).exists()
    trainer.train(lifecycle.resume(tmp_path / "run", pendulum_dataset), progress=False)
    assert_same_results(straight, tmp_path / "run")


def test_corrupt_truncated_and_foreign_checkpoints_are_refused(
    tmp_path, pendulum_dataset, straight
):
    ckpt = straight / checkpoint.CHECKPOINT
    good = ckpt.read_bytes()
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_bytes((straight / "config.json").read_bytes())

    rng = np.random.default_rng(0)
    flipped = bytearray(good)
    for i in rng.choice(len(good) - 40, 50, replace=False):
        flipped[i] ^= 0xFF
    for _name, data in [("flipped", bytes(flipped)), ("truncated", good[: len(good) // 3])]:
        (run_dir / checkpoint.CHECKPOINT).write_bytes(data)
        with pytest.raises(CheckpointError, match="checkpoint.msgpack.*(corrupt|truncated)"):
            lifecycle.resume(run_dir, pendulum_dataset)

    # A checkpoint from before the checksum trailer still resumes.
    (run_dir / checkpoint.CHECKPOINT).write_bytes(good[:-40])
    assert lifecycle.resume(run_dir, pendulum_dataset, lock=False).step == 400

    # Another run's checkpoint (K = 2 EABC) in a TD3+BC run of other width is refused: by the
    # run it records, and where it records none (an older eabc's), by its structure.
    other = start(tmp_path, "td3bc", pendulum_dataset, {"hidden_dims": (16, 16)}, algo="td3bc")
    other.lock.release()
    (tmp_path / "td3bc" / checkpoint.CHECKPOINT).write_bytes(good)
    with pytest.raises(CheckpointError, match=r"belongs to run \w+ \(eabc, .* is run \w+ \(td3bc"):
        lifecycle.resume(tmp_path / "td3bc", pendulum_dataset)
    raw = checkpoint.load_raw(straight)
    checkpoint.save(tmp_path / "td3bc", {k: v for k, v in raw.items() if k != checkpoint.IDENTITY})
    with pytest.raises(CheckpointError, match="not a checkpoint of this td3bc run"):
        lifecycle.resume(tmp_path / "td3bc", pendulum_dataset)

    # A directory where the checkpoint should be: one line, no traceback.
    (tmp_path / "td3bc" / checkpoint.CHECKPOINT).unlink()
    (tmp_path / "td3bc" / checkpoint.CHECKPOINT).mkdir()
    with pytest.raises(CheckpointError, match="cannot be read"):
        lifecycle.resume(tmp_path / "td3bc", pendulum_dataset)


def test_resume_refuses_other_data_and_old_runs_skip_the_check(
    tmp_path, pendulum_dataset, straight
):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    for name in ("config.json", checkpoint.CHECKPOINT):
        (run_dir / name).write_bytes((straight / name).read_bytes())
    changed = dataclasses.replace(pendulum_dataset, rewards=pendulum_dataset.rewards + 1.0)
    with pytest.raises(DatasetError, match="content fingerprint"):
        lifecycle.resume(run_dir, changed)
    config = json.loads((run_dir / "config.json").read_text())
    del config["dataset"]["fingerprint"]  # a run from before the fingerprint (and identities)
    del config["run_id"]
    (run_dir / "config.json").write_text(json.dumps(config))
    raw = checkpoint.load_raw(run_dir)
    checkpoint.save(run_dir, {k: v for k, v in raw.items() if k != checkpoint.IDENTITY})
    assert lifecycle.resume(run_dir, changed, lock=False).step == 400


def test_two_writers_on_one_run_directory(tmp_path, pendulum_dataset):
    first = start(tmp_path, "run", pendulum_dataset, steps=100, checkpoint_interval=100)
    with pytest.raises(RunLockedError, match=f"in use by process {os.getpid()} on "):
        lifecycle.resume(tmp_path / "run", pendulum_dataset)
    trainer.train(first, progress=False)  # releases the lock when done
    assert not (tmp_path / "run" / OWNER).exists()
    again = lifecycle.resume(tmp_path / "run", pendulum_dataset)
    with pytest.raises(RunLockedError):
        lifecycle.resume(tmp_path / "run", pendulum_dataset)
    again.lock.release()
    assert not [p for p in (tmp_path / "run").iterdir() if p.name.endswith(".tmp")]


def test_bad_flags_and_settings_are_refused(tmp_path, pendulum_dataset):
    n = 4
    obs, act = np.zeros((n, 3)), np.zeros((n, 1))
    for bad in (0.5, -1.0, np.nan):
        with pytest.raises(DatasetError, match="terminals must be 0 or 1"):
            Dataset(obs, act, np.zeros(n), obs, np.array([0, bad, 0, 0]), np.zeros(n))
    for setting, message in [
        ({"tau": -1}, r"tau must be a finite number in \(0, 1\], got -1.0"),
        ({"actor_lr": -1}, "actor_lr must be a finite number > 0, got -1.0"),
        ({"discount": 1.5}, r"discount must be a finite number in \[0, 1\), got 1.5"),
        ({"alpha": float("nan")}, "alpha must be a finite number >= 0, got nan"),
        ({"tau": float("nan")}, r"tau must be a finite number in \(0, 1\], got nan"),
        ({"policy_freq": 1.5}, r"policy_freq must be an integer in \[1, 2147483647\], got 1.5"),
        ({"behavior_cloning": "maybe"}, "behavior_cloning must be true or false, got 'maybe'"),
    ]:
        with pytest.raises(SettingError, match=message):
            resolve_agent_config("eabc", "x", {**AGENT, **setting})
    assert resolve_agent_config("eabc", "x", {**AGENT, "num_critics": 3.0}).num_critics == 3


def test_nan_losses_stop_the_run_and_are_reported(tmp_path, pendulum_dataset):
    huge = dataclasses.replace(
        pendulum_dataset, rewards=np.full_like(pendulum_dataset.rewards, 1e38)
    )
    run = start(tmp_path, "nan", huge)
    summary = trainer.train(run, progress=False)
    assert summary["diverged_step"] == 100 and summary["steps"] == 100
    assert json.loads((tmp_path / "nan/summary.json").read_text())["diverged_step"] == 100
    assert not (tmp_path / "nan" / checkpoint.CHECKPOINT).exists(), "no NaN checkpoint"
    row, _ = results.read_run(tmp_path / "nan")
    assert row["status"] == "diverged" and row["diverged_step"] == 100


def test_unreadable_files_end_in_one_line(tmp_path, monkeypatch, pendulum_dataset):
    npz = tmp_path / "data.npz"
    save_npz(pendulum_dataset, npz)
    (tmp_path / "cut.npz").write_bytes(npz.read_bytes()[:5000])
    (tmp_path / "dir.npz").mkdir()
    with h5py.File(tmp_path / "group.hdf5", "w") as f:
        f.create_group("observations")
        for key in ("actions", "rewards", "terminals"):
            f[key] = np.zeros(3)
    cases = [
        ("cut.npz", "cut.npz: not a readable .npz archive"),
        ("dir.npz", "dir.npz is a directory"),
        ("group.hdf5", "'observations' is an HDF5 group, not an array"),
    ]
    for name, message in cases:
        with pytest.raises(DatasetError, match=message):
            load_dataset(tmp_path / name)
    monkeypatch.setitem(sys.modules, "minari", None)  # not installed
    with pytest.raises(DatasetError, match=r"pip install 'eabc\[minari\]'"):
        load_dataset("minari:mujoco/hopper/medium-v0")

    # A corrupt config.json: eabc train --resume says so in one line; results list it as broken.
    run_dir = tmp_path / "runs" / "bad"
    run_dir.mkdir(parents=True)
    (run_dir / "config.json").write_text('{"train": {"algo"')
    with pytest.raises(SystemExit, match="config.json cannot be read"):
        main(["train", "--resume", str(run_dir), "--no-progress"])
    table, _ = results.collect(tmp_path / "runs")
    assert table.loc[table.run_id == "bad", "status"].tolist() == ["broken"]


def test_sweep_identity_paths_changed_specs_and_broken_files(tmp_path, pendulum_dataset):
    for folder in ("a", "b"):  # the same file name in two folders: two datasets, two runs
        (tmp_path / folder).mkdir()
        save_npz(pendulum_dataset, tmp_path / folder / "pend.npz")
    spec = {
        "datasets": [str(tmp_path / "a/pend.npz"), str(tmp_path / "b/pend.npz")],
        "algos": ["bc"],
        "steps": 200,
        "grid": {"hidden_dims": [[32, 32]]},
        "train": {k: v for k, v in SMALL.items() if k not in ("dataset", "steps")},
    }
    runs = expand(spec)
    assert len({r.run_id for r in runs}) == 2
    root = tmp_path / "sweep"
    for run in runs:
        job_process.execute([run.to_json()], str(root))
    assert [run_status.status(r, root)[0] for r in runs] == ["done", "done"]

    longer = expand({**spec, "steps": 400})  # more steps extend the runs
    assert [run_status.status(r, root) for r in longer] == [("partial", 200)] * 2
    job_process.execute([longer[0].to_json()], str(root))
    assert run_status.status(longer[0], root) == ("done", 400)
    assert run_status.status(runs[0], root)[0] == "changed"  # fewer steps than trained: refused

    other = expand({**spec, "train": {**spec["train"], "eval_interval": 100}})
    assert run_status.status(other[1], root)[0] == "changed"
    with pytest.raises(ValueError, match="eval_interval 200 -> 100"):
        job_process.execute([other[1].to_json()], str(root))

    # One corrupt file: that run is broken and left out, the others are still planned.
    (root / "runs" / runs[1].run_id / checkpoint.CHECKPOINT).write_bytes(b"\x00" * 100)
    (root / "runs" / runs[1].run_id / "summary.json").write_text("{")
    assert run_status.status(longer[1], root)[0] == "broken"
    assert [j[0].run_id for j in planning.jobs(longer, root, "processes")] == []


def test_killed_sweep_leaves_no_worker_and_its_restart_matches(tmp_path, pendulum_dataset):
    """SIGKILL of `eabc sweep` (the parent alone): its worker stops within seconds; the sweep
    started again resumes the run and ends with the results of an uninterrupted run."""
    save_npz(pendulum_dataset, tmp_path / "pend.npz")
    spec = {
        "datasets": [str(tmp_path / "pend.npz")],
        "algos": ["eabc"],
        "steps": 600,
        "grid": {k: [list(v) if isinstance(v, tuple) else v] for k, v in AGENT.items()},
        "train": {**{k: v for k, v in SMALL.items() if k not in ("dataset", "steps")},
                  "checkpoint_interval": 100},
    }  # fmt: skip
    (tmp_path / "spec.yaml").write_text(json.dumps(spec))
    (run,) = expand(spec)
    root = tmp_path / "sweep"
    cli = [
        sys.executable,
        "-m",
        "eabc.cli",
        "sweep",
        str(tmp_path / "spec.yaml"),
        "--root",
        str(root),
    ]
    proc = subprocess.Popen(cli, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    run_dir = root / "runs" / run.run_id
    deadline = time.time() + 120
    while run_status.status(run, root)[0] != "partial" and time.time() < deadline:
        time.sleep(0.05)
    worker = json.loads((run_dir / OWNER).read_text())["pid"]
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 10
    while _alive(worker) and time.time() < deadline:
        time.sleep(0.1)
    assert not _alive(worker), "the worker went on training after its sweep was killed"
    assert run_status.status(run, root)[0] == "partial"

    subprocess.run(cli, check=True, stdout=subprocess.DEVNULL)
    # The same run never interrupted, in the worker a sweep starts (single-threaded, so the same
    # arithmetic), from this process's own pool: no third sweep process to start.
    straight = tmp_path / "straight"
    local_pool.run_local(
        planning.jobs([run], straight, "processes"), straight, 1, log=lambda _: None
    )
    assert_same_results(straight / "runs" / run.run_id, run_dir)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        with open(f"/proc/{pid}/stat") as f:  # a zombie has stopped
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


def test_in_use_reads_the_owner_note_without_taking_the_lock(tmp_path):
    from eabc.training.lock import RunLock, in_use

    run_dir = tmp_path / "run"
    assert not in_use(run_dir)  # no directory, no note
    lock = RunLock(run_dir).acquire()
    assert in_use(run_dir) and lock.held  # probing did not take it from its holder
    lock.release()
    assert not in_use(run_dir)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    note = {"pid": dead.pid, "host": socket.gethostname(), "since": "", "command": ""}
    (run_dir / OWNER).write_text(json.dumps(note))
    assert not in_use(run_dir)  # a killed holder's note on this host does not count
    (run_dir / OWNER).write_text(json.dumps({**note, "host": "elsewhere"}))
    assert in_use(run_dir)  # another host's process cannot be checked: assume it runs
    (run_dir / OWNER).write_text("{not json")
    assert not in_use(run_dir)
