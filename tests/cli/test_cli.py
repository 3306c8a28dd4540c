"""The command line end to end: train, resume, evaluate, data commands and error messages."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from eabc.cli import main
from eabc.data.loaders import save_npz
from eabc.data.sources import load_dataset


@pytest.fixture
def npz(tmp_path, pendulum_dataset):
    path = tmp_path / "pendulum.npz"
    save_npz(pendulum_dataset, path)
    return path


def test_train_then_resume_then_evaluate(tmp_path, npz, capsys, quick_chunks):
    run_dir = tmp_path / "run"
    common = [
        "--dataset",
        str(npz),
        "--log-interval",
        "100",
        "--eval-interval",
        "100",
        "--checkpoint-interval",
        "100",
        "--eval-episodes",
        "1",
        "--num-critics",
        "3",
        "--confidence-level",
        "0.5",
        "--run-dir",
        str(run_dir),
        "--no-progress",
    ]
    main(["train", *common, "--steps", "200"])
    first = json.loads(capsys.readouterr().out)
    assert first["steps"] == 200 and first["evaluations"] == 2 and "final_score" in first
    config = json.loads((run_dir / "config.json").read_text())
    assert config["agent"]["num_critics"] == 3 and config["agent"]["confidence_level"] == 0.5
    assert config["dataset"]["env_id"] == "Pendulum-v1"

    # Re-running into the same directory is refused with a hint; --resume continues (to its steps).
    with pytest.raises(SystemExit, match="--resume"):
        main(["train", *common, "--steps", "200"])
    main(["train", "--resume", str(run_dir), "--no-progress"])
    assert json.loads(capsys.readouterr().out)["steps"] == 200

    main(["evaluate", str(run_dir), "--episodes", "2"])
    result = json.loads(capsys.readouterr().out)
    assert result["step"] == 200 and "score" in result


def test_errors_are_one_clear_line(tmp_path, capsys):
    with pytest.raises(SystemExit, match="error: dataset file .*missing.hdf5 does not exist"):
        main(
            ["train", "--dataset", str(tmp_path / "missing.hdf5"), "--run-dir", str(tmp_path / "r")]
        )
    with pytest.raises(SystemExit, match="--eval-interval must be a multiple"):
        main(["train", "--eval-interval", "150", "--log-interval", "100"])


def test_confidence_level_is_required_for_unknown_data(tmp_path, npz):
    with pytest.raises(SystemExit, match="pass --confidence-level"):
        main(["train", "--dataset", str(npz), "--run-dir", str(tmp_path / "r"), "--no-progress"])


def test_data_commands(tmp_path, capsys, monkeypatch):
    main(["data", "make", "hopper-random", "--size", "600", "--cache-dir", str(tmp_path)])
    assert "hopper-random.hdf5" in capsys.readouterr().out
    main(["data", "list", "--cache-dir", str(tmp_path)])
    listing = capsys.readouterr().out
    assert "hopper-random" in listing and "walker2d-expert" in listing
    main(["data", "info", "hopper-random", "--cache-dir", str(tmp_path)])
    info = json.loads(capsys.readouterr().out)
    assert info["transitions"] == 600 and info["episodes"] > 5 and info["env_id"] == "Hopper-v4"
    assert info["d4rl_normalized_return"] == 1.0 and abs(info["normalized_return"]) < 10
    row = next(line for line in listing.splitlines() if line.startswith("hopper-random "))
    assert row.split()[1:3] == ["600", str(info["episodes"])], row
    # One column each, however long a name (``@planner-v0``'s were wider than the names column):
    # every row's D4RL level ends where the header's ``D4RL`` does.
    rows = listing.splitlines()
    end = rows[0].index("D4RL") + len("D4RL")
    assert any("@" in row for row in rows)
    assert all(row[end - 1] != " " and row[end : end + 2] == "  " for row in rows), listing

    # Export to Minari and read it back through minari:ID: the same transitions.
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    main(["data", "export", "hopper-random", "--cache-dir", str(tmp_path)])
    assert capsys.readouterr().out.strip() == "eabc/hopper/random-v0"
    exported = load_dataset("minari:eabc/hopper/random-v0")
    original = load_dataset("hopper-random", cache_dir=tmp_path)
    for key in ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts"):
        np.testing.assert_array_equal(getattr(exported, key), getattr(original, key))
    assert exported.env_id == "Hopper-v4" and exported.ref_max_score == original.ref_max_score
    with pytest.raises(SystemExit, match="exists already"):
        main(["data", "export", "hopper-random", "--cache-dir", str(tmp_path)])


def test_other_algorithms_and_any_setting_from_the_command_line(
    tmp_path, npz, capsys, quick_chunks
):
    common = ["--dataset", str(npz), "--steps", "100", "--log-interval", "100",
              "--eval-interval", "100", "--checkpoint-interval", "100", "--eval-episodes", "1",
              "--no-progress"]  # fmt: skip
    run_dir = tmp_path / "edac"
    main(["train", *common, "--algo", "edac-10", "--num-critics", "4",
          "--set", "eta=0.5", "hidden_dims=16,16", "--run-dir", str(run_dir)])  # fmt: skip
    assert json.loads(capsys.readouterr().out)["steps"] == 100
    agent = json.loads((run_dir / "config.json").read_text())["agent"]
    assert agent["eta"] == 0.5 and agent["num_critics"] == 4 and agent["hidden_dims"] == [16, 16]
    with pytest.raises(SystemExit, match="bc has no setting.*eta"):
        main(["train", *common, "--algo", "bc", "--set", "eta=1", "--run-dir", str(tmp_path / "b")])
    with pytest.raises(SystemExit, match="unknown algorithm 'nope'"):
        main(["train", *common, "--algo", "nope", "--run-dir", str(tmp_path / "n")])


def test_sac_command_trains_and_resumes(tmp_path, capsys):
    run_dir = tmp_path / "sac"
    args = ["sac", "--env", "Pendulum-v1", "--steps", "400", "--start-steps", "200",
            "--update-after", "100", "--batch-size", "64", "--eval-interval", "200",
            "--snapshot-interval", "200", "--checkpoint-interval", "200", "--eval-episodes", "1",
            "--run-dir", str(run_dir), "--no-progress"]  # fmt: skip
    main(args)
    summary = json.loads(capsys.readouterr().out)
    assert summary["steps"] == 400 and summary["env_id"] == "Pendulum-v1"
    assert sorted(p.name for p in (run_dir / "snapshots").iterdir()) == [
        "actor_00000200.npz", "actor_00000400.npz"
    ]  # fmt: skip
    main(["sac", "--resume", str(run_dir), "--no-progress"])  # already finished: nothing to do
    assert json.loads(capsys.readouterr().out)["steps"] == 400


def test_train_help_names_every_algorithm(capsys):
    from eabc.agents import ALGORITHMS

    with pytest.raises(SystemExit):
        main(["train", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    missing = [name for name in ALGORITHMS if name not in help_text]
    assert not missing, f"eabc train --help does not mention {missing}"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["train", "--pessimism", "bad"],
         "error: --pessimism 'bad' is not one of its choices: mean-std, min, min2"),
        (["sweep", "--preset", "nope"],
         "error: --preset 'nope' is not one of its choices: ablation-k, .*, table6"),
        (["train", "--algo", "nope"], "error: --algo: unknown algorithm 'nope'; choose one of eabc"),
        (["train", "--steps", "abc"], "error: --steps must be an integer, got 'abc'"),
        (["train", "--num-critics=x"], "error: --num-critics must be an integer, got 'x'"),
        (["sweep", "--seeds", "0", "x"], "error: --seeds must be whole numbers, got '0 x'"),
        (["train", "--steps"], "error: --steps needs a value"),
        (["train", "--progress", "maybe"], "error: unrecognized argument.* maybe; see `eabc train"),
        (["evaluate"], "error: eabc evaluate needs RUN_DIR"),
        (["data", "make"], "error: eabc data make needs NAME"),
    ],
)  # fmt: skip
def test_a_bad_flag_value_is_one_error_line_naming_the_flag_and_the_choices(argv, message, capsys):
    """tyro drew a box of many lines (the flag's whole help inside); now one line as for
    numbers out of range."""
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert isinstance(exit_.value.code, str) and "\n" not in exit_.value.code
    assert re.fullmatch(message + ".*", exit_.value.code), exit_.value.code
    assert capsys.readouterr().err == ""  # no box beside it


def _refused(argv, message, monkeypatch=None):
    """``eabc ARGV`` ends in one error line matching ``message``."""
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert isinstance(exit_.value.code, str) and "\n" not in exit_.value.code
    assert re.search(message, exit_.value.code), exit_.value.code


def test_what_would_fail_after_making_data_is_refused_before(tmp_path, npz, monkeypatch):
    """Before: a built-in dataset with --env of other shapes, or data make with --cache-dir a
    file, made the dataset (minutes) and failed only then; a dry run passed data of other shapes
    than --env's."""
    from eabc.data import generate  # noqa: PLC0415

    def made(*args, **kwargs):
        raise AssertionError("a dataset was made before the inputs were checked")

    monkeypatch.setattr(generate, "make", made)
    monkeypatch.setenv("EABC_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    wrong = ["--dataset", "hopper-random", "--env", "Pendulum-v1", "--steps", "100"]
    for dry in ([], ["--dry-run"]):
        _refused(["train", *wrong, *dry], r"--env Pendulum-v1: its observations have shape \(3,\)")
    _refused(["data", "make", "hopper-random", "--cache-dir", "afile"], "--cache-dir afile is not")
    _refused(["train", "--dataset", str(npz), "--env", "MountainCarContinuous-v0", "--dry-run"],
             "observations have dim 3 but MountainCarContinuous-v0")  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "pendulum.npz"]


def test_algorithm_flags_are_named_in_their_errors(npz):
    """Before: 'eabc: num_critics must be at least 2', and an AttributeError traceback for a
    typed flag of another algorithm."""
    dry = ["train", "--dataset", str(npz), "--dry-run"]
    _refused([*dry, "--algo", "eabc", "--num-critics", "0"],
             r"eabc setting --num-critics must be an integer in \[2, 2147483647\], got 0")  # fmt: skip
    _refused([*dry, "--algo", "eabc", "--confidence-level", "7"],
             r"eabc setting --confidence-level must be a finite number in \[0, 1\], got 7.0")  # fmt: skip
    _refused([*dry, "--algo", "bc", "--num-critics", "3"], "--num-critics: bc has no setting")
    _refused([*dry, "--algo", "td3bc", "--set", "alpha=-1"], "--set: td3bc setting alpha")


def test_outputs_under_a_file_and_offline_runs_as_zoo_entries_are_refused(tmp_path, monkeypatch):
    """Before: '[Errno 17] File exists' without the flag, and `zoo pack` copied an offline run
    as if it were a SAC run."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.json").write_text(json.dumps({"train": {"algo": "bc"}}))
    _refused(["export-policy", "run", "--onnx", "afile/p.onnx"], "--onnx afile/p.onnx: its folder")
    _refused(["report", "run", "--out", "afile/r"], r"--out afile/r is not a directory \(afile")
    for argv in (["zoo", "pack", "run", "out"], ["zoo", "build", "run", "hopper"]):
        _refused(argv, "run/config.json is not an `eabc sac` run's")
    _refused(["zoo", "build", "run"], "eabc zoo build needs ENV")
    assert not (tmp_path / "out").exists()


def test_a_sweep_checks_every_dataset_before_its_first_run(tmp_path, npz):
    """Before: the runs on the good file trained, then '1 job(s) failed'."""
    spec = {"datasets": [str(npz), str(tmp_path / "missing.npz")], "algos": ["bc"],
            "steps": 100, "grid": {"hidden_dims": [[8]]}}  # fmt: skip
    (tmp_path / "spec.yaml").write_text(json.dumps(spec))
    _refused(["sweep", str(tmp_path / "spec.yaml"), "--root", str(tmp_path / "root")],
             "dataset file .*missing.npz does not exist")  # fmt: skip
    assert not (tmp_path / "root").exists()
    spec = {**spec, "datasets": [str(npz)], "algos": ["td3bc"], "grid": {"alpha": [-1.0]}}
    (tmp_path / "spec.yaml").write_text(json.dumps(spec))
    _refused(["sweep", str(tmp_path / "spec.yaml"), "--root", str(tmp_path / "root"),
              "--dry-run"], "grid: td3bc setting alpha must be a finite number >= 0, got -1.0")  # fmt: skip


def test_a_dry_run_refuses_the_time_budget_and_out_that_the_run_would(tmp_path, npz):
    """Before: `eabc sweep/study ... --within 5x --dry-run` printed its plan, and only the real
    command refused the budget (a study's its --out and an unknown dataset too, the latter as a
    failed group): a dry run passed what would fail."""
    spec = tmp_path / "spec.yaml"
    spec.write_text(json.dumps({"datasets": [str(npz)], "algos": ["bc"], "steps": 100}))
    root = ["--root", str(tmp_path / "root")]
    bad = r"--within: a duration is a positive number with s, m or h \(90s, 45m, 2.5h\), got '5x'"
    for command in ("sweep", "study"):
        _refused([command, str(spec), *root, "--within", "5x", "--dry-run"], bad)
    _refused(["sweep", str(spec), *root, "--within", "5m", "--backend", "ray", "--dry-run"],
             "--within works with the local backend only")  # fmt: skip
    (tmp_path / "afile").write_text("")
    _refused(["study", str(spec), *root, "--out", str(tmp_path / "afile"), "--dry-run"],
             "--out .*afile is a file")  # fmt: skip
    # and a dataset no group could load (a sweep's dry run refused it; a study's listed it)
    spec.write_text(json.dumps({"datasets": ["nope-medium"], "algos": ["bc"], "steps": 100}))
    _refused(["study", str(spec), *root, "--dry-run"],
             r"unknown dataset 'nope-medium' \(did you mean hopper-medium\?\)")  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "pendulum.npz", "spec.yaml"]
