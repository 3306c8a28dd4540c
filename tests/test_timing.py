"""Time estimates from one source (eabc.timing), said on a terminal and in a log; commands that
only describe make nothing; help texts against the commands they describe."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pandas as pd
import pytest

from eabc import progress, timing
from eabc.agents import get_algorithm
from eabc.cli import COMMANDS, GROUPS, main
from eabc.data import generate
from eabc.data.loaders import save_npz
from eabc.experiments import tables
from eabc.training import lifecycle, trainer
from eabc.training.config import TrainConfig

ROOT = Path(__file__).resolve().parents[1]


# One source of time estimates, scaled to the host


def test_estimates_scale_with_the_hosts_measured_speed(tmp_path, monkeypatch):
    monkeypatch.delenv("EABC_HOST_SPEED", raising=False)
    speed = timing.host_speed(tmp_path)  # probed now, and kept
    assert speed.measured and speed.gflops > 0 and (tmp_path / timing.PROBE_FILE).exists()
    assert speed.factor == pytest.approx(speed.gflops / timing.REFERENCE_PROBE_GFLOPS)
    monkeypatch.setattr(timing, "probe_gflops", lambda *a, **k: pytest.fail("probed again"))
    assert timing.host_speed(tmp_path) == speed
    assert timing.host_speed(tmp_path / "elsewhere", measure=False) == timing.REFERENCE
    assert (
        "measured speed" in speed.basis() and "reference host's speed" in timing.REFERENCE.basis()
    )

    half = timing.HostSpeed(0.5, timing.REFERENCE_PROBE_GFLOPS / 2, measured=True)
    low, high = timing.DATASET_SECONDS_PER_1M["mujoco"]
    assert timing.dataset_seconds("hopper-medium", 2_000_000, half) == (4 * low, 4 * high)
    eabc = get_algorithm("eabc")
    at_reference = trainer.estimate_seconds(eabc, eabc.preset, 10_000, 20)
    assert at_reference == pytest.approx(10_000 / eabc.steps_per_s + 20 * timing.EPISODE_SECONDS)
    assert trainer.estimate_seconds(eabc, eabc.preset, 10_000, 20, speed=half) == pytest.approx(
        2 * at_reference
    )
    measured = trainer.estimate_seconds(eabc, eabc.preset, 10_000, 0, steps_per_s=50.0, speed=half)
    assert measured == pytest.approx(200.0)  # a rate measured on this host is not scaled again


def _figures() -> dict[str, str]:
    """The texts README and docs must state, from eabc.timing."""
    eabc = get_algorithm("eabc")
    return {
        "mujoco": timing.making_time("hopper-medium"),
        "antmaze": timing.making_time("antmaze-umaze"),
        "eabc": f"{timing.hours_per_million(eabc.steps_per_s):.1f} hours per 1M steps",
    }


def test_readme_and_docs_state_the_one_sources_figures():
    """Before: "1-8 minutes" and "5-8 minutes" for the same dataset in the README, AntMaze's "6-8
    minutes per 1M" there and "15-25 minutes" in the dry run."""
    figures = _figures()
    readme = re.sub(r"\s+", " ", (ROOT / "README.md").read_text())
    assert f"{figures['mujoco']} per 1M transitions" in readme
    assert f"{figures['antmaze']} per 1M transitions" in readme
    assert figures["eabc"] in readme
    # Every estimate of making a dataset in README and docs is one of these.
    stated = {figures["mujoco"], figures["antmaze"]}
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = re.sub(r"\s+", " ", path.read_text())
        for found in re.findall(r"((?:about|under) [\d.-]+ minutes?) (?:for|per) 1M", text):
            assert found in stated, f"{path.name}: {found!r} is not eabc.timing's {stated}"


def test_the_data_commands_help_states_the_one_sources_figures(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "400")
    with pytest.raises(SystemExit):
        main(["data", "make", "--help"])
    text = re.sub(r"[\s│]+", " ", capsys.readouterr().out)
    assert f"{timing.making_time('hopper-medium')} per 1M transitions" in text
    assert f"AntMaze {timing.making_time('antmaze-umaze')}" in text


@pytest.fixture
def npz(tmp_path, pendulum_dataset):
    path = tmp_path / "pendulum.npz"
    save_npz(pendulum_dataset, path)
    return path


def test_the_dry_run_states_training_time_per_million_steps_as_the_report_measures_it(
    npz, tmp_path, capsys
):
    """Before: the dry run's hours per 1M steps came from one formula and `eabc report`'s from
    another; now both are 1e6 / steps/s, the dry run's at the contract's reference rate."""
    main(["train", "--dataset", str(npz), "--algo", "td3bc", "--env", "Pendulum-v1",
          "--run-dir", str(tmp_path / "run"), "--dry-run"])  # fmt: skip
    out = capsys.readouterr().out
    rate = get_algorithm("td3bc").steps_per_s
    run = {"run_id": "r", "dataset": "d", "algo": "td3bc", "seed": 0, "variant": "",
           "steps_per_s": rate}  # fmt: skip
    runs = tables.runtime_table(pd.DataFrame([run]))
    hours = float(runs["mean"].iloc[0])
    assert hours == pytest.approx(timing.hours_per_million(rate))
    assert f"{timing.duration(hours * 3600)} per 1M gradient steps" in out
    assert "at the reference host's speed (" in out  # conftest: EABC_HOST_SPEED=1


# Long work says what it does, in a log too


def test_making_a_dataset_says_what_and_how_long_in_a_log(tmp_path, capfd, monkeypatch):
    """Before: nothing at all when stderr is not a terminal (tqdm's disable=None)."""
    monkeypatch.setattr(progress, "LOG_SECONDS", 0.0)  # a line per update, to see them
    path = generate.make("hopper-random", tmp_path / "hopper-random.hdf5", size=300)
    err = capfd.readouterr().err
    assert f"eabc: making hopper-random: 300 transitions into {path}, " in err
    assert "less than a minute at the reference host's speed" in err
    assert re.search(r"eabc: hopper-random: \d+/300 steps \(\d+%\), [\d.,]+ steps/s", err)
    assert "eabc: hopper-random: 300/300 steps in " in err
    assert "\r" not in err


def test_training_says_what_and_how_long_in_a_log(tmp_path, capfd, pendulum_dataset, monkeypatch):
    monkeypatch.setattr(progress, "LOG_SECONDS", 0.0)
    config = TrainConfig(
        dataset="pendulum", algo="td3bc", steps=200, eval_interval=200, eval_episodes=1,
        log_interval=100, checkpoint_interval=200, env="Pendulum-v1",
    )  # fmt: skip
    run = lifecycle.start(config, tmp_path / "run", {"hidden_dims": (32, 32)}, pendulum_dataset)
    capfd.readouterr()
    trainer.train(run, progress=True)
    err = capfd.readouterr().err
    what = f"eabc: training td3bc {pendulum_dataset.name}"
    assert f"{what}: 200 steps, less than a second at the reference host's speed" in err
    assert f"{what}: 100/200 steps (50%)" in err
    assert f"{what}: 200/200 steps in " in err
    assert "\r" not in err
    trainer.train(lifecycle.resume(tmp_path / "run", pendulum_dataset), progress=False)
    assert capfd.readouterr().err == ""  # --no-progress: silent


def test_a_line_progress_reads_like_tqdm_to_its_callers():
    lines = []
    bar = progress.LineProgress(10, "work", every=1e-9, iterable=range(10))
    bar.stream = None
    bar._say = lines.append
    bar.set_postfix({"score": 1.5})
    assert list(bar) == list(range(10))
    assert lines[-1].startswith("work: 10/10 steps in ") and lines[-1].endswith("(score=1.5)")
    assert len(lines) == 10  # 9 on the way (not at the end), then the end; closed once
    bar.close()
    assert len(lines) == 10


# Commands that only describe make nothing


def test_data_info_never_makes_a_dataset(tmp_path, monkeypatch):
    """Before: `eabc data info antmaze-umaze --plot cover.png` silently started making 1M
    AntMaze transitions."""
    monkeypatch.setattr(generate, "make", lambda *a, **k: pytest.fail("data info made a dataset"))
    cache = tmp_path / "cache"
    for argv in (["antmaze-umaze", "--plot", str(tmp_path / "cover.png")], ["hopper-medium"]):
        name = argv[0]
        with pytest.raises(SystemExit) as stop:
            main(["data", "info", *argv, "--cache-dir", str(cache)])
        message = str(stop.value.code)
        assert f"{name} is not made yet" in message
        assert f"`eabc data make {name} --cache-dir {cache}` makes it, " in message
        assert timing.making_time(name) in message
    assert not (tmp_path / "cover.png").exists()


# Help texts against the commands they describe


def _help(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit):
        main([*argv, "--help"])
    return re.sub(r"[\s│]+", " ", capsys.readouterr().out)


def test_eabc_help_describes_each_command_by_its_own_text(capsys, monkeypatch):
    """Before: `data` described by `data list`'s text, `zoo` by `zoo pack`'s."""
    monkeypatch.setenv("COLUMNS", "400")
    text = _help([], capsys)
    for name, command in COMMANDS.items():
        doc = GROUPS[name][1] if name in GROUPS else command.__doc__
        first = re.sub(r"\s+", " ", doc.strip().split("\n\n")[0])
        assert f"• {name} {first}" in text, name
    assert "List the built-in datasets" not in text and "Copy a SAC run" not in text
    for group, (commands, description) in GROUPS.items():
        text = _help([group], capsys)
        assert description in text
        for name, command in commands.items():
            assert f"• {name} {command.__doc__.split('.')[0].split()[0]}" in text


def test_no_help_prints_default_none_or_points_where_nothing_is(capsys, monkeypatch):
    """Before: `(default: None)` after "(default runs/DATASET_ALGO_seedS)", and --set's settings
    "listed in the README", which lists none."""
    monkeypatch.setenv("COLUMNS", "400")
    every = [[name] for name in COMMANDS if name not in GROUPS]
    every += [[group, name] for group, (commands, _) in GROUPS.items() for name in commands]
    for argv in every:
        text = _help(argv, capsys)
        assert "(default: None)" not in text, argv
    train = _help(["train"], capsys)
    assert "(default runs/DATASET_ALGO_seedS)." in train
    assert "listed in the README" not in train
    assert "`eabc train --algo ALGO --dry-run` lists an algorithm's settings" in train


def test_the_settings_the_train_help_points_to_are_in_the_dry_run(npz, tmp_path, capsys):
    main(["train", "--dataset", str(npz), "--algo", "edac-10", "--env", "Pendulum-v1",
          "--run-dir", str(tmp_path / "run"), "--dry-run"])  # fmt: skip
    out = capsys.readouterr().out
    algorithm = get_algorithm("edac-10")
    for field in dataclasses.fields(algorithm.preset):
        assert f"{field.name}=" in out, field.name
