"""Numbers with their real bounds, flags never silently ignored or merged, output paths that never
overwrite what is not the command's own, and Ctrl-C ending in one line.

Each case failed before its fix: ``--steps 3000000000`` was accepted (the step counter is int32),
``--batch-size 1000000000`` died in an out-of-memory error and left a run directory that blocked
every retry, ``--resume`` with ``--seed`` ignored ``--seed``, ``--set tau=0.005 tau=0.5`` took
the last, a grid ``[1, 1.0]`` trained one run twice, ``--dry-run`` refused ``--log-interval 100
--eval-interval 200`` that the run accepts, ``export-policy --onnx RUN/config.json`` overwrote
the run's config and ``--onnx`` onto a device replaced it, a read-only root made ``eabc results``
fail, a full disk said ``error: : No space left on device``, Ctrl-C printed a traceback, and
Ctrl-C while ``eabc data make`` wrote its file was dropped (exit code 0).
No training here but one short run for the export and the interrupt (BC, 32-unit networks).
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from eabc import cli, ranges
from eabc.cli import main
from eabc.experiments import results
from eabc.experiments.spec import expand
from eabc.training import checkpoint
from eabc.training.config import TrainConfig

SETTINGS = settings(
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
SCHEDULE = ["--steps", "200", "--log-interval", "100", "--eval-interval", "100",
            "--checkpoint-interval", "100", "--eval-episodes", "1", "--no-progress"]  # fmt: skip


@pytest.fixture(scope="module")
def npz(tmp_path_factory):
    """40 Pendulum-shaped transitions that name their environment."""
    path = tmp_path_factory.mktemp("data") / "tiny.npz"
    rng = np.random.default_rng(0)
    np.savez(path, observations=rng.normal(size=(40, 3)).astype(np.float32),
             actions=rng.uniform(-1, 1, (40, 1)).astype(np.float32),
             rewards=rng.normal(size=40).astype(np.float32), terminals=np.zeros(40, bool),
             env_id=np.asarray("Pendulum-v1"))  # fmt: skip
    return str(path)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, npz):
    """One finished tiny BC run (200 steps)."""
    folder = tmp_path_factory.mktemp("run") / "run"
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("EABC_FAST_COMPILE", "1")
        with contextlib.redirect_stdout(io.StringIO()):
            main(["train", "--dataset", npz, "--algo", "bc", "--set", "hidden_dims=32,32",
                  "--run-dir", str(folder), *SCHEDULE])  # fmt: skip
    return folder


def refusal(argv: list[str]) -> str:
    """The one ``error:`` line ``eabc ARGV`` ends with (it must refuse)."""
    with pytest.raises(SystemExit) as exit_, contextlib.redirect_stdout(io.StringIO()):
        main(argv)
    message = str(exit_.value.code)
    assert message.startswith("error: ") and "\n" not in message, message
    return message


# ----------------------------------------------------------------------------------------------
# 1. Numbers with their real upper bounds


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--steps", str(2**31)],
        ["train", "--eval-interval", str(2**31)],
        ["train", "--batch-size", str(2**31)],
        ["sac", "--steps", "3000000000"],
        ["sweep", "--steps", str(2**31)],
        ["sweep", "--batch-size", str(2**40)],
        ["data", "make", "hopper-random", "--size", str(2**31)],
    ],
)
def test_steps_and_sizes_beyond_int32_are_refused_naming_the_flag(argv):
    with pytest.raises(ValueError, match=rf"^{argv[-2]} must be an integer in \[1, 2147483647\]"):
        cli.parse(argv)


def test_every_config_that_counts_steps_bounds_them_where_it_is_declared(tmp_path, run_dir):
    """TrainConfig, a sweep spec, a run's config.json and the algorithm settings: one bound."""
    with pytest.raises(ValueError, match=r"steps must be an integer in \[1, 2147483647\]"):
        TrainConfig(steps=2**31)
    assert TrainConfig(steps=2**31 - 1).steps == 2**31 - 1
    with pytest.raises(ValueError, match=r"^steps must be an integer in \[1, 2147483647\]"):
        expand({"datasets": ["hopper-random"], "algos": ["bc"], "steps": 2**31})
    with pytest.raises(ValueError, match="eval_interval"):
        expand({"datasets": ["hopper-random"], "algos": ["bc"], "train": {"eval_interval": 2**40}})
    with pytest.raises(
        SystemExit, match=r"total_steps must be an integer in \[1, 2147483647\], got 2147483648"
    ):
        main(["train", "--algo", "iql", "--set", f"total_steps={2**31}", "--dry-run"])
    from eabc.training import run_config  # noqa: PLC0415

    config = json.loads((run_dir / "config.json").read_text())
    config["train"]["steps"] = 2**31
    with pytest.raises(run_config.ConfigError, match=r"train\.steps"):
        run_config.check(config, tmp_path / "config.json")


def test_a_batch_or_buffer_that_does_not_fit_is_refused_before_any_run_directory(tmp_path, npz):
    target = tmp_path / "run"
    for argv, flag in [
        (["train", "--dataset", npz, "--batch-size", "1000000000", "--algo", "bc"], "--batch-size"),
        (["train", "--dataset", npz, "--algo", "bc", "--set", "hidden_dims=200000,200000"],
         "--set hidden_dims"),
        (["sac", "--env", "Pendulum-v1", "--steps", "2000000000"], "--steps"),
    ]:  # fmt: skip
        for extra in ([], ["--dry-run"]) if argv[0] == "train" else ([],):
            message = refusal([*argv, "--run-dir", str(target), *extra])
            assert message.startswith(f"error: {flag}") and "of memory" in message, message
            assert "give a smaller" in message and not target.exists()


def test_check_memory_names_the_largest_part_and_lets_what_fits_through():
    parts = [("--batch-size", "9", "a batch", 700.0), ("--dataset", "d", "the data", 300.0)]
    ranges.check_memory(parts, available=1000)
    with pytest.raises(ValueError, match=r"^--batch-size 9: a batch would take .*smaller --batch"):
        ranges.check_memory(parts, available=999)


@settings(SETTINGS, max_examples=60)
@given(
    st.sampled_from(
        ["steps", "batch-size", "eval-interval", "log-interval", "checkpoint-interval"]
    ),  # fmt: skip
    st.one_of(st.integers(2**31 - 3, 2**31 + 3), st.integers(2**31, 2**80), st.integers(1, 2**31)),
)
def test_any_count_is_within_int32_or_refused_naming_its_flag(flag, value):
    """Through ``parse``, as every command and ``--dry-run`` check them."""
    try:
        cmd = cli.parse(["train", f"--{flag}={value}"])
    except ValueError as error:
        assert "\n" not in str(error) and str(error).startswith("--"), error
        assert value > ranges.INT32_MAX or "multiple" in str(error), error
        event("refused")
        return
    event("accepted")
    got = getattr(cmd.config, flag.replace("-", "_"))
    assert got == value <= ranges.INT32_MAX


# ----------------------------------------------------------------------------------------------
# 2. Flags never silently ignored or merged


@pytest.mark.parametrize(
    "extra",
    [["--seed", "3"], ["--algo=td3bc"], ["--steps", "400"], ["--dataset", "x.npz"],
     ["--set", "tau=0.5"], ["--num-critics", "5"], ["--run-dir", "elsewhere"]],
)  # fmt: skip
def test_resume_with_an_option_it_would_ignore_is_refused(run_dir, extra):
    message = refusal(["train", "--resume", str(run_dir), *extra, "--no-progress"])
    assert extra[0].split("=")[0] in message and "--resume" in message
    before = json.loads((run_dir / "config.json").read_text())
    assert before["train"]["seed"] == 0  # nothing changed


def test_resume_takes_its_own_options(run_dir, capsys):
    main(["train", "--resume", str(run_dir), "--no-progress", "--dry-run"])
    assert "resume" in capsys.readouterr().out
    with pytest.raises(ValueError, match="--steps would be ignored"):
        cli.parse(["sac", "--resume", str(run_dir), "--steps", "10"])


def test_a_setting_given_twice_is_refused(npz):
    base = ["train", "--dataset", npz, "--algo", "eabc", "--confidence-level", "0.5", "--dry-run"]
    assert "tau twice" in refusal([*base, "--set", "tau=0.005", "tau=0.5"])
    assert "num_critics" in refusal([*base, "--num-critics", "3", "--set", "num_critics=5"])
    message = refusal(["sweep", "--datasets", npz, "--algos", "eabc", "--grid", "tau=0.1",
                       "tau=0.2", "--dry-run"])  # fmt: skip
    assert "--grid gives tau twice" in message
    for argv, flag in ((["--set", "tau=0.1", "--set", "tau=0.2"], "--set is given twice"),
                       (["--seed", "1", "--seed=2"], "--seed is given twice"),
                       (["--progress", "--no-progress"], "--progress and --no-progress")):  # fmt: skip
        assert flag in refusal([*base, *argv])


@pytest.mark.parametrize(
    ("key", "values", "runs"),
    [("num_critics", [2, 2.0], None), ("num_critics", [5, 5], 1), ("num_critics", [2, 3], 2),
     ("confidence_level", [0.25, 0.250], 1), ("confidence_level", [1, 1.0], None),
     ("hidden_dims", [[32, 32], [32.0, 32]], None)],
)  # fmt: skip
def test_a_grid_value_written_two_ways_is_refused(key, values, runs):
    spec = {"datasets": ["hopper-medium"], "algos": ["eabc"], "grid": {key: values}}
    if runs is None:
        with pytest.raises(ValueError, match=rf"^grid\.{key} lists .* written two ways"):
            expand(spec)
    else:
        assert len(expand(spec)) == runs


@pytest.mark.parametrize(
    "flags",
    [["--log-interval", "100", "--eval-interval", "200"],
     ["--log-interval", "300", "--eval-interval", "900", "--checkpoint-interval", "900"],
     ["--log-interval", "100", "--eval-interval", "150"],
     ["--batch-size", "1000000000"]],
)  # fmt: skip
def test_dry_run_judges_flags_as_the_run_does(tmp_path, npz, flags, monkeypatch):
    """The same verdict with and without --dry-run; the run is stopped where it would train."""
    from eabc.training import trainer  # noqa: PLC0415

    class Started(Exception):
        pass

    def started(run, progress=True, **kwargs):
        run.lock.release()
        raise Started

    monkeypatch.setattr(trainer, "train", started)
    verdicts = []
    for extra in ([], ["--dry-run"]):
        argv = ["train", "--dataset", npz, "--algo", "bc", *flags, "--no-progress",
                "--run-dir", str(tmp_path / f"run{len(extra)}"), *extra]  # fmt: skip
        try:
            with (
                contextlib.redirect_stdout(io.StringIO()),
                contextlib.redirect_stderr(io.StringIO()),
            ):
                main(argv)
            verdicts.append("accepted")
        except Started:
            verdicts.append("accepted")
        except SystemExit as exit_:
            verdicts.append(str(exit_.code).split(":")[1].split()[0])  # the flag it names
    assert verdicts[0] == verdicts[1], verdicts


# ----------------------------------------------------------------------------------------------
# 5. Output paths


def test_export_never_overwrites_the_runs_own_files_or_what_is_not_a_file(run_dir, tmp_path):
    pytest.importorskip("onnx")
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    link = tmp_path / "link.onnx"
    link.symlink_to(run_dir / "config.json")
    os.mkfifo(tmp_path / "fifo.onnx")
    for target in [run_dir / "checkpoint.msgpack", run_dir / "config.json", run_dir / "log.csv",
                   link, tmp_path, tmp_path / "fifo.onnx", Path("/dev/null")]:  # fmt: skip
        message = refusal(["export-policy", str(run_dir), "--onnx", str(target)])
        assert "--onnx" in message and str(target) in message, message
    assert Path("/dev/null").is_char_device()
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} == before
    for target in [run_dir / "policy.onnx", run_dir / "policy.onnx", tmp_path / "p.onnx"]:
        with contextlib.redirect_stdout(io.StringIO()):
            main(["export-policy", str(run_dir), "--onnx", str(target)])  # again: its own file
        assert target.read_bytes().startswith(b"\x08")
    (run_dir / "policy.onnx").unlink()


def test_a_read_only_root_is_read_and_never_written(run_dir, tmp_path, monkeypatch, capsys):
    """Run as root the mode bits do not stop a write; os.access is made to read them."""
    root = tmp_path / "root"
    root.mkdir()
    shutil.copytree(run_dir, root / "a")
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: real(p, mode) and not (
        mode == os.W_OK and not os.stat(p).st_mode & 0o222))  # fmt: skip
    root.chmod(0o555)
    try:
        main(["results", str(root), "--csv"])
        assert "a,done,200" in capsys.readouterr().out
        message = refusal(["report", str(root)])
        assert "--out" in message and "read-only" in message
        with contextlib.redirect_stdout(io.StringIO()):
            main(["report", str(root), "--out", str(tmp_path / "rep")])
        assert (tmp_path / "rep" / "report.md").exists()
        assert sorted(p.name for p in root.iterdir()) == ["a"]
    finally:
        root.chmod(0o755)


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EACCES])
def test_a_failed_write_names_the_file(tmp_path, monkeypatch, capsys, code):
    def fail(fd):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(OSError) as error:
        checkpoint.atomic_write(tmp_path / "x.json", b"{}")
    assert error.value.filename == str(tmp_path / "x.json")
    assert list(tmp_path.iterdir()) == []  # no temporary left

    def full(*args, **kwargs):
        raise OSError(code, os.strerror(code))

    monkeypatch.undo()
    monkeypatch.setattr(results.tempfile, "mkstemp", full)
    (tmp_path / "empty").mkdir()
    results.store(tmp_path / "empty", *results.collect(tmp_path / "empty", write=False))
    assert list((tmp_path / "empty").iterdir()) == []
    warning = capsys.readouterr().err.strip()  # the store is a cache: a warning, not an error
    assert "\n" not in warning and str(tmp_path / "empty" / "results.sqlite") in warning


# ----------------------------------------------------------------------------------------------
# 7. Ctrl-C

WALL = ("wall_time", "steps_per_s", "wall_time_s")


def _without_wall(run_dir: Path) -> tuple[str, dict]:
    """log.csv without its wall-clock columns, and summary.json without its wall-clock keys."""
    lines = (run_dir / "log.csv").read_text().splitlines()
    keep = [i for i, name in enumerate(lines[0].split(",")) if name not in WALL]
    log = "\n".join(",".join(line.split(",")[i] for i in keep) for line in lines)
    summary = json.loads((run_dir / "summary.json").read_text())
    return log, {k: v for k, v in summary.items() if k not in WALL}


def _eabc(*argv: str, **kwargs) -> subprocess.Popen:
    """``eabc ARGV`` in its own session (a terminal's Ctrl-C reaches its whole group)."""
    env = {**os.environ, "EABC_FAST_COMPILE": "1"}
    # SIGINT as a terminal gives it: a suite started in the background (nohup, a CI runner's
    # job) has it ignored, and children inherit that, so Python would never see the Ctrl-C. A
    # handled signal is reset to its default in the child, an ignored one stays ignored: so it
    # is handled here while the child starts (a preexec_fn would do it in the child, but makes
    # subprocess fork this process, which JAX's threads warn against).
    assert threading.current_thread() is threading.main_thread()  # where handlers are set
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return subprocess.Popen([sys.executable, "-m", "eabc.cli", *argv], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                start_new_session=True, **kwargs)  # fmt: skip
    finally:
        signal.signal(signal.SIGINT, previous)


def _ctrl_c(proc: subprocess.Popen, ready, timeout: float = 600) -> tuple[int, list[str]]:
    """Ctrl-C to ``proc``'s group once ``ready()``; its exit code and stderr lines. Waits up to
    ``timeout`` for that (a loaded 2-core host compiles slowly): an interrupt before the state
    the test names would test something else."""
    deadline = time.time() + timeout
    while not ready() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, "it ended before it could be interrupted"
    assert ready(), f"not ready within {timeout} s"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, [line for line in err.decode().splitlines() if line.strip()]


def _logged_past(log: Path, step: int):
    def ready() -> bool:
        text = log.read_text() if log.exists() else ""
        return any(line.split(",")[0].isdigit() and int(line.split(",")[0]) >= step
                   for line in text.splitlines()[1:])  # fmt: skip

    return ready


def test_ctrl_c_on_train_is_one_line_exit_130_and_the_resume_is_exact(tmp_path, npz):
    common = ["train", "--dataset", npz, "--algo", "bc", "--set", "hidden_dims=32,32", "--steps",
              "20000", "--log-interval", "100", "--eval-interval", "10000",
              "--checkpoint-interval", "100", "--eval-episodes", "1", "--no-progress"]  # fmt: skip
    straight = _eabc(*common, "--run-dir", str(tmp_path / "straight"))
    interrupted = tmp_path / "interrupted"
    code, lines = _ctrl_c(_eabc(*common, "--run-dir", str(interrupted)),
                          _logged_past(interrupted / "log.csv", 300))  # fmt: skip
    assert code == 130 and not any("Traceback" in line for line in lines), lines
    assert lines[-1].startswith("interrupted at step "), lines
    assert f"resume with: eabc train --resume {interrupted}" in lines[-1]
    assert not list(interrupted.glob(".*.tmp")) and not (interrupted / "summary.json").exists()
    resumed = _eabc("train", "--resume", str(interrupted), "--no-progress")
    assert resumed.wait(timeout=300) == 0 and straight.wait(timeout=300) == 0
    assert _without_wall(interrupted) == _without_wall(tmp_path / "straight")


def test_ctrl_c_on_a_sweep_is_one_line_and_stops_its_workers_quietly(tmp_path, npz):
    from eabc.experiments import run_status  # noqa: PLC0415

    spec = {"datasets": [npz], "algos": ["bc"], "steps": 200000, "grid": {"hidden_dims": [[32, 32]]},
            "train": {"log_interval": 100, "eval_interval": 100000, "checkpoint_interval": 100,
                      "eval_episodes": 1}}  # fmt: skip
    (tmp_path / "spec.yaml").write_text(json.dumps(spec))
    (run,) = expand(spec)
    root = tmp_path / "root"
    proc = _eabc("sweep", str(tmp_path / "spec.yaml"), "--root", str(root))
    code, lines = _ctrl_c(proc, lambda: run_status.status(run, root)[0] == "partial")
    assert code == 130 and not any("Traceback" in line for line in lines), lines
    assert lines[-1].startswith("sweep interrupted") and str(root) in lines[-1], lines
    for log in (root / "logs").glob("*.log"):
        assert "Traceback" not in log.read_text(), log.read_text()[-2000:]
    assert run_status.status(run, root)[0] == "partial"  # resumable


def test_ctrl_c_on_data_make_is_one_line_and_leaves_no_half_file(tmp_path):
    """Ctrl-C while the dataset is written (its temporary file has just appeared: writing 100K
    rows takes about a third of a second, the test's poll 0.05 s). It used to end with exit code 0
    and "Exception ignored ... KeyboardInterrupt" (the interrupt raised in an h5py weakref
    callback, where Python drops exceptions)."""
    from eabc.data.loaders import load_file  # noqa: PLC0415

    datasets = tmp_path / "cache" / "datasets"
    proc = _eabc("data", "make", "hopper-random", "--size", "100000", "--cache-dir",
                 str(tmp_path / "cache"))  # fmt: skip
    code, lines = _ctrl_c(proc, lambda: any(datasets.glob("*.tmp")))
    assert code == 130, lines
    assert not any("Traceback" in line or "ignored" in line for line in lines), lines
    assert lines[-1].startswith("interrupted"), lines
    left = [p for p in datasets.rglob("*") if p.is_file()]
    if "complete and kept" in lines[-1]:  # the signal came as the file was renamed
        assert [p.name for p in left] == ["hopper-random.hdf5"]
        assert load_file(left[0]).size == 100_000
    else:
        assert "was not made" in lines[-1] and "eabc data make hopper-random" in lines[-1], lines
        assert not left


def test_a_signal_inside_an_h5py_callback_still_stops_the_write(tmp_path, monkeypatch):
    """The root cause, without a subprocess: SIGINT that arrives while h5py runs Python code in a
    weakref callback (there Python prints the KeyboardInterrupt and drops it) still stops
    ``save_hdf5`` with KeyboardInterrupt, and leaves neither the dataset nor its temporary file."""
    import weakref  # noqa: PLC0415

    import h5py  # noqa: PLC0415

    from eabc.data import hdf5_writer  # noqa: PLC0415
    from eabc.data.dataset import Dataset  # noqa: PLC0415

    real = h5py.Group.create_dataset

    def create_dataset(self, name, **kwargs):
        class Freed:
            pass

        freed = Freed()
        keep = weakref.ref(freed, lambda ref: signal.raise_signal(signal.SIGINT))
        del freed  # the callback runs now, and the handler inside it
        assert keep() is None
        return real(self, name, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", create_dataset)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    rows = np.zeros((5, 1), np.float32)
    dataset = Dataset(observations=rows, actions=rows, rewards=rows[:, 0], terminals=rows[:, 0] > 0,
                      next_observations=rows, timeouts=rows[:, 0] > 0, name="x")  # fmt: skip
    try:
        with pytest.raises(KeyboardInterrupt):
            hdf5_writer.save_hdf5(dataset, tmp_path / "x.hdf5")
    finally:
        signal.signal(signal.SIGINT, previous)
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------------------------
# Generated: any mix of these inputs is refused in one line naming what is wrong, or accepted as is

RESUME_IGNORES = {"--seed": "3", "--steps": "400", "--algo": "bc", "--dataset": "x.npz",
                  "--batch-size": "64", "--eval-episodes": "2", "--run-dir": "elsewhere",
                  "--set": "tau=0.5", "--num-critics": "5", "--env": "Pendulum-v1"}  # fmt: skip


@settings(SETTINGS, max_examples=40)
@given(
    st.lists(st.sampled_from(sorted(RESUME_IGNORES)), min_size=1, max_size=4, unique=True),
    st.sampled_from([[], ["--no-progress"], ["--dry-run"], ["--restart"]]),
    st.booleans(),
)
def test_resume_refuses_every_option_it_would_ignore(flags, own, equals):
    argv = ["train", "--resume", "RUN", *own]
    for flag in flags:
        argv += [f"{flag}={RESUME_IGNORES[flag]}"] if equals else [flag, RESUME_IGNORES[flag]]
    with pytest.raises(ValueError) as error:
        cli.parse(argv)
    message = str(error.value)
    assert "\n" not in message and all(flag in message for flag in flags), message


@settings(SETTINGS, max_examples=60)
@given(
    st.lists(
        st.tuples(st.sampled_from(["tau", "actor_lr", "discount", "policy_noise"]),
                  st.sampled_from(["0.005", "0.1", "5e-4", "0.5"])),
        min_size=1, max_size=4,
    ),
    st.booleans(),
)  # fmt: skip
def test_a_setting_is_taken_once_or_refused_naming_it(items, one_flag):
    """``--set a=1 a=2`` or ``--set a=1 --set a=2``: refused; each key once: the values as given."""
    texts = [f"{k}={v}" for k, v in items]
    argv = ["train", "--algo", "td3bc", *(["--set", *texts] if one_flag else
                                          [t for text in texts for t in ("--set", text)])]  # fmt: skip
    keys = [k for k, _ in items]
    try:
        cmd = cli.parse(argv)
    except ValueError as error:
        message = str(error)
        assert "\n" not in message and "--set" in message, message
        twice = len(set(keys)) < len(keys) or (not one_flag and len(items) > 1)
        assert twice or "must be" in message, message  # a repeat, or a value out of range
        event("refused")
        return
    event("accepted")
    assert len(set(keys)) == len(keys) and (one_flag or len(items) == 1)
    assert cmd.set == tuple(texts)


@settings(SETTINGS, max_examples=60)
@given(st.lists(st.sampled_from([2, 2.0, 3, 3.0, "3", 4]), min_size=1, max_size=4))
def test_a_grid_runs_each_setting_once(values):
    """A grid axis: one run per distinct setting, or refused where a setting is written two ways."""
    spec = {"datasets": ["hopper-medium"], "algos": ["eabc"], "grid": {"num_critics": values}}
    spellings: dict[int, set[str]] = {}
    for value in values:
        spellings.setdefault(int(value), set()).add(str(value))
    try:
        runs = expand(spec)
    except ValueError as error:
        assert str(error).startswith("grid.num_critics lists"), error
        assert any(len(texts) > 1 for texts in spellings.values())
        event("refused")
        return
    event("expanded")
    assert len(runs) == len(spellings) and all(len(t) == 1 for t in spellings.values())


OUTPUTS = ["checkpoint.msgpack", "config.json", "log.csv", "summary.json", "new.onnx",
           "folder", "fifo", "link-config", "link-new", "/dev/null", "outside.onnx"]  # fmt: skip


@settings(SETTINGS, max_examples=30)
@given(st.sampled_from(OUTPUTS), st.booleans())
def test_export_writes_only_a_new_or_its_own_file(run_dir, where, inside):
    """Any output path: written where it is a new file or one the export wrote, else refused
    with the run directory and the device untouched."""
    import tempfile  # noqa: PLC0415

    pytest.importorskip("onnx")
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    with tempfile.TemporaryDirectory() as scratch:
        folder = run_dir if inside and where.endswith(".onnx") else Path(scratch)
        target = {"folder": Path(scratch), "/dev/null": Path("/dev/null")}.get(where)
        if where in ("checkpoint.msgpack", "config.json", "log.csv", "summary.json"):
            target = run_dir / where
        elif where == "fifo":
            target = Path(scratch) / "p.onnx"
            os.mkfifo(target)
        elif where.startswith("link"):
            target = Path(scratch) / "l.onnx"
            target.symlink_to(run_dir / "config.json" if where.endswith("config") else
                              Path(scratch) / "nowhere.onnx")  # fmt: skip
        elif target is None:
            target = folder / where
        writable = where in ("new.onnx", "outside.onnx", "link-new")
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                main(["export-policy", str(run_dir), "--onnx", str(target)])
            event("written")
            assert writable, target
        except SystemExit as exit_:
            message = str(exit_.code)
            assert message.startswith("error: --onnx") and "\n" not in message, message
            assert not writable or where == "link-new", message
            event("refused")
        finally:
            for name in ("new.onnx", "outside.onnx"):
                (run_dir / name).unlink(missing_ok=True)
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} == before
    assert Path("/dev/null").is_char_device()


@settings(SETTINGS, max_examples=20)
@given(st.sampled_from([["train", "--dry-run"], ["results", "."], ["data", "list"],
                        ["sweep", "--preset", "table1", "--dry-run"], ["report", "."]]))  # fmt: skip
def test_ctrl_c_anywhere_in_a_command_is_one_line_and_exit_130(argv):
    """Ctrl-C where the command's work begins: exit code 130 and one line, never a traceback."""
    err = io.StringIO()
    command = type(cli.parse(argv))
    real = cli.HANDLERS[command]

    def interrupted(cmd):
        raise KeyboardInterrupt

    cli.HANDLERS[command] = interrupted
    try:
        with pytest.raises(SystemExit) as exit_, contextlib.redirect_stderr(err):
            main(argv)
    finally:
        cli.HANDLERS[command] = real
    assert exit_.value.code == 130
    assert err.getvalue().strip() == "interrupted", err.getvalue()
