"""The command line follows the conventions of the tools around it: --version, usage lines that
name the command, readable metavars, errors that name the user's flag, one-line empty results."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import yaml

import eabc
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
    from eabc.experiments import sweep  # noqa: PLC0415

    monkeypatch.setitem(sys.modules, "ray", None)  # as if not installed
    monkeypatch.setitem(sys.modules, "minari", None)
    monkeypatch.setitem(sys.modules, "d3rlpy", None)
    with pytest.raises(RuntimeError, match=r"pip install 'eabc\[ray\]'"):
        sweep.run_ray([], "root")
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
