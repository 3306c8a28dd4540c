"""The command line follows the conventions of the tools around it: --version, usage lines that
name the command, readable metavars, errors that name the user's flag, one-line empty results."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
import yaml

import eabc
from eabc import cli
from eabc.cli import Sweep, main, sweep_spec


def test_version(capsys):
    main(["--version"])
    assert capsys.readouterr().out.strip() == f"eabc {eabc.__version__}"


@pytest.mark.parametrize(
    ("argv", "usage"),
    [
        (["train", "--help"], "usage: eabc train "),
        (["data", "export", "--help"], "usage: eabc data export "),
        (["sweep", "--help"], "usage: eabc sweep "),
    ],
)
def test_usage_names_the_command_and_metavars_read_plainly(argv, usage, capsys):
    with pytest.raises(SystemExit):
        main(argv)
    text = capsys.readouterr().out
    assert text.startswith(usage), text.splitlines()[0]
    assert sys.executable not in text and "{None}" not in text
    if argv[0] == "data":
        assert "NAME" in text.splitlines()[0]  # the positional, not STR


def _cut_help_lines(text: str) -> list[str]:
    """Lines of ``--help`` (printed wide, in boxes or plain) whose text stops well short of the
    width and goes on in the next, indented line: a paragraph cut mid-sentence. A flag too long
    to have its help beside it (``--set [STR [STR ...]]``) is no cut."""
    rows = [line.strip("│").rstrip() for line in text.splitlines()]
    cut = []
    for row, after in zip(rows, rows[1:]):
        words = row.strip()
        if words.startswith(("-", "•")):  # a flag or subcommand, its help after two spaces
            words = re.split(r"\s{2,}", words, maxsplit=1)[1:]
            words = words[0] if words else ""
        goes_on = len(after) - len(after.lstrip()) > 4 and after.strip()
        if words and set(words) - set("-─") and goes_on and len(row) < 300:
            cut.append(f"{row.strip()} / {after.strip()}")
    return cut


def test_help_paragraphs_are_not_cut_mid_sentence(capsys, monkeypatch):
    """Before: tyro kept the line break before every indented docstring line, so `eabc train
    --help` read "...with the settings it was" / "started with (other options than ... refused:
    they" / "would be ignored)", and `eabc --help` broke `sac` and `study` the same way."""
    monkeypatch.setenv("COLUMNS", "400")
    every = [[]] + [[name] for name in cli.COMMANDS]
    every += [[group, name] for group, (commands, _) in cli.GROUPS.items() for name in commands]
    for argv in every:
        with pytest.raises(SystemExit):
            main([*argv, "--help"])
        cut = _cut_help_lines(capsys.readouterr().out)
        assert not cut, (argv, cut)


def test_the_cut_line_check_can_fail():
    box = "│ --resume STR  Continue the run, with the settings it was   │\n│               started with. │"
    assert _cut_help_lines(box) and _cut_help_lines(box.replace("│", " "))
    long_flag = "│ --set [STR [STR ...]]   │\n│               Any other setting. │"
    assert not _cut_help_lines(long_flag)


def test_eabc_study_without_a_spec_is_refused(tmp_path, monkeypatch):
    """Before: `eabc study` alone trained nothing, wrote an empty study-out and exited 0."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(["study"])
    assert str(exit_.value.code).startswith("error: eabc study: no spec given")  # exit code 1
    assert not list(tmp_path.iterdir())


def test_an_interval_mismatch_names_the_flags(capsys):
    with pytest.raises(SystemExit) as error:
        main(["train", "--eval-interval", "150", "--log-interval", "100"])
    assert str(error.value.code) == (
        "error: --eval-interval must be a multiple of --log-interval=100: "
        "e.g. --eval-interval 200, or a --log-interval that divides 150"
    )
    assert "tyro" not in capsys.readouterr().err


def test_sweep_takes_the_common_train_options_as_flags(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        yaml.safe_dump(
            {"datasets": ["hopper-random"], "algos": ["bc"], "train": {"eval_episodes": 3}}
        )
    )
    flags = dict(eval_interval=500, log_interval=100, checkpoint_interval=500, batch_size=64)
    merged = sweep_spec(Sweep(spec=str(spec), **flags))
    assert merged["train"] == {"eval_episodes": 3, **flags}
    assert sweep_spec(Sweep(spec=str(spec), eval_episodes=1))["train"] == {"eval_episodes": 1}


def test_algos_and_datasets_flags_narrow_a_spec_of_variants(tmp_path):
    """`--algos td3bc` on a spec of variants runs its td3bc variants only, not every variant plus
    a plain td3bc; `--datasets` narrows a variant's own dataset list too."""
    from eabc.experiments.spec import expand  # noqa: PLC0415

    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump({
        "datasets": ["hopper-medium", "hopper-random"], "seeds": [0, 1], "steps": 1000,
        "variants": [
            {"algo": "td3bc"},
            {"algo": "eabc", "critic_layer_norm": True},
            {"algo": "eabc", "confidence_level": 1.0, "datasets": ["hopper-random"]},
        ],
    }))  # fmt: skip

    def ids(**flags):
        return sorted(run.run_id for run in expand(sweep_spec(Sweep(spec=str(spec), **flags))))

    assert ids(algos=("td3bc",), seeds=(2,)) == [
        "hopper-medium__td3bc__seed2", "hopper-random__td3bc__seed2"
    ]  # fmt: skip
    eabc = ids(algos=("eabc",), datasets=("hopper-medium",), seeds=(0,))
    assert len(eabc) == 1 and "td3bc" not in eabc[0] and "hopper-medium__eabc__" in eabc[0]
    assert len(ids(algos=("eabc",), datasets=("hopper-random",), seeds=(0,))) == 2
    bc = ids(algos=("td3bc", "bc"), datasets=("hopper-random",), seeds=(0,))  # bc: no variant
    assert bc == ["hopper-random__bc__seed0", "hopper-random__td3bc__seed0"]
    assert len(ids()) == 2 * (2 + 2 + 1)  # no flags: every variant, as the spec says


def test_results_on_a_missing_or_empty_root_say_so_in_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit, match=r"error: .*nothing does not exist"):
        main(["results", str(tmp_path / "nothing")])
    main(["results", str(tmp_path)])
    assert capsys.readouterr().out == f"no runs under {tmp_path}\n"


def test_a_missing_extra_is_one_line_that_names_it(monkeypatch, pendulum_dataset):
    from eabc.data.d3rlpy_export import to_d3rlpy  # noqa: PLC0415
    from eabc.data.dataset import DatasetError  # noqa: PLC0415
    from eabc.data.loaders import export_minari  # noqa: PLC0415
    from eabc.experiments import ray_pool  # noqa: PLC0415

    monkeypatch.setitem(sys.modules, "ray", None)  # as if not installed
    monkeypatch.setitem(sys.modules, "minari", None)
    monkeypatch.setitem(sys.modules, "d3rlpy", None)
    with pytest.raises(RuntimeError, match=r"pip install 'eabc\[ray\]'"):
        ray_pool.run_ray([], "root")
    with pytest.raises(DatasetError, match=r"pip install 'eabc\[minari\]'"):
        export_minari(pendulum_dataset, "test/pendulum/x-v0")
    with pytest.raises(DatasetError, match=r"pip install 'eabc\[d3rlpy\]'"):
        to_d3rlpy(pendulum_dataset)
    with pytest.raises(SystemExit, match=r"^error: exporting to d3rlpy needs .*eabc\[d3rlpy\]'$"):
        main(["data", "export", "hopper-random", "--d3rlpy", "x.h5"])  # before making the data


def test_output_piped_into_a_reader_that_stops_early_ends_quietly(tmp_path):
    """`eabc sweep --help | head -1`, `eabc data list | head -1`: no traceback, no error line."""
    for args in (["sweep", "--help"], ["data", "list", "--cache-dir", str(tmp_path)]):
        proc = subprocess.Popen(
            [sys.executable, "-m", "eabc.cli", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env={**os.environ, "COLUMNS": "80"},
        )
        assert proc.stdout.readline().startswith((b"usage: eabc sweep", b"dataset")), args
        proc.stdout.close()  # as `| head -1` does
        _, err = proc.communicate(timeout=60)
        assert not err.strip(), (args, err.decode()[-500:])


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["train", "--checkpoint-interval", "0"], r"--checkpoint-interval must be an integer in \[1, 2147483647\], got 0"),
        (["train", "--log-interval", "100", "--checkpoint-interval", "-100"],
         r"--checkpoint-interval must be an integer in \[1, 2147483647\], got -100"),
        (["train", "--seed", "12345678901234567890"],
         r"--seed must be an integer in \[0, 4294967295\], got 12345678901234567890"),
        (["train", "--seed", "-1"], r"--seed must be an integer in \[0, 4294967295\], got -1"),
        (["evaluate", "RUN", "--episodes", "0"], "--episodes must be an integer >= 1, got 0"),
        (["evaluate", "RUN", "--seed", "4294967296"], r"--seed must be an integer in \[0, "),
        (["sac", "--update-every", "0"], r"--update-every must be an integer in \[1, 2147483647\], got 0"),
        (["sac", "--seed", "99999999999999999999"], r"--seed must be an integer in \[0, "),
        (["sac", "--lr", "0"], "--lr must be a finite number > 0, got 0.0"),
        (["sweep", "--seeds", "0", "-5"], r"--seeds must be an integer in \[0, 4294967295\], got -5"),
        (["sweep", "--steps", "0"], r"--steps must be an integer in \[1, 2147483647\], got 0"),
        (["sweep", "--workers", "0"], "--workers must be an integer >= 1, got 0"),
        (["sweep", "--cpus-per-job", "nan"], "--cpus-per-job must be a finite number > 0, got nan"),
        (["sweep", "--eval-episodes", "-3"], "--eval-episodes must be an integer >= 1, got -3"),
        (["data", "make", "hopper-random", "--size", "0"], r"--size must be an integer in \[1, 2147483647\]"),
    ],
)  # fmt: skip
def test_a_number_out_of_its_range_is_refused_naming_the_flag(argv, message, tmp_path):
    """Checked as the command is parsed; ``eabc`` prints it as one ``error:`` line. (Train and
    sweep run as dry runs and SAC and data make are only parsed here: without the check, the
    command would start its work.)"""
    argv = [str(tmp_path / "run") if a == "RUN" else a for a in argv]
    with pytest.raises(ValueError, match=message) as error:
        cli.parse(argv)
    assert "\n" not in str(error.value)
    if argv[0] in ("train", "sweep", "evaluate"):
        before = sorted(tmp_path.rglob("*"))
        dry = ["--dry-run"] if argv[0] != "evaluate" else []
        with pytest.raises(SystemExit) as exit_:
            main([*argv, *dry])
        assert exit_.value.code == f"error: {error.value}"
        assert sorted(tmp_path.rglob("*")) == before  # nothing made


def test_every_number_flag_declares_its_range():
    """A new numeric flag without a range (eabc.ranges) fails here, not in a user's run."""
    import typing  # noqa: PLC0415

    from eabc import ranges  # noqa: PLC0415
    from eabc.cli import COMMANDS, GROUPS  # noqa: PLC0415

    commands = {*COMMANDS.values(), *(c for group, _ in GROUPS.values() for c in group.values())}
    unchecked = []
    for command in commands:
        for name, hint in typing.get_type_hints(command, include_extras=True).items():
            numeric = {int, float} & {
                typing.get_args(a)[0] if typing.get_args(a) else a
                for a in (hint, *typing.get_args(hint))
            }
            if numeric and not ranges.constrained(hint):
                unchecked.append(f"{command.__name__}.{name}")
    assert not unchecked, unchecked
