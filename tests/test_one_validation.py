"""One validation path: every setting of every registered algorithm, and every setting of a run
(:class:`TrainConfig`), given a value outside its declared type or range, is refused with the same
message by the Python API (constructing the config), the command line (``eabc train``), a sweep
spec (YAML) and a run's ``config.json`` (as resume reads it). No training, no JAX compile."""

from __future__ import annotations

import dataclasses
import math
import typing
from pathlib import Path

import pytest
import yaml

from eabc import cli, ranges
from eabc.agents import ALGORITHMS
from eabc.experiments.spec import expand, load_spec
from eabc.training import run_config
from eabc.training.config import TrainConfig


def bad_value(hint):
    """A value of ``hint``'s own kind that its declaration refuses (below its lower bound, above
    its upper one, not one of its choices, not a bool), so that text, YAML, JSON and Python all
    give the same value and the same message."""
    hint = ranges._optional(hint)[0]
    base, constraints = ranges._parts(hint)
    if typing.get_origin(base) is typing.Literal:
        return "not-a-choice"
    if base is bool:
        return "maybe"
    if typing.get_origin(base) is tuple:
        return (16, 0) if typing.get_args(base)[0] is not float else (0.5, -1.0)
    if base is str:
        return None  # text from every entry point; checked by what reads it
    bounds = dict(ranges._bounds(constraints))
    low = bounds.get(">=", bounds.get(">"))
    if low is not None:
        below = low - 1 if ">=" in bounds else low
        return int(below) if base is int else float(below)
    high = bounds.get("<=", bounds.get("<"))
    if high is not None:
        return int(high) + 1 if base is int else float(high) + (1.0 if "<=" in bounds else 0.0)
    return math.nan if base is float else "x"


def as_text(value) -> str:
    return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)


def as_json(value):
    return list(value) if isinstance(value, tuple) else value


def declarations(cls) -> dict[str, tuple[type, typing.Any]]:
    """Every setting of a settings dataclass by name: the class that declares it (a group's own
    class for a group's settings) and its declared type."""
    out = {}
    groups = ranges.groups(cls)
    for field in dataclasses.fields(cls):
        if field.name in groups:
            out |= declarations(groups[field.name])
        else:
            out[field.name] = (cls, ranges.hints(cls)[field.name])
    return out


ALGORITHM_SETTINGS = [
    (algo, name)
    for algo, algorithm in ALGORITHMS.items()
    for name in sorted(ranges.names(type(algorithm.preset)))
]


def refused(call) -> str:
    with pytest.raises(ValueError) as error:
        call()
    message = str(error.value)
    assert "\n" not in message, message
    return message


def config_json(algo: str, train: dict | None = None, agent: dict | None = None) -> dict:
    return {
        "train": {
            "dataset": "hopper-medium",
            "algo": algo,
            "seed": 0,
            "steps": 1000,
            **(train or {}),
        },
        "agent": agent or {},
        "dataset": {"name": "hopper-medium"},
    }


def test_every_numeric_setting_declares_its_range():
    """A number without a declared range (an override in a subclass that drops it, a new
    setting) would take any value; every int and float setting says its range in its type."""
    for algo, algorithm in ALGORITHMS.items():
        for name, (_, hint) in declarations(type(algorithm.preset)).items():
            base = ranges._parts(ranges._optional(hint)[0])[0]
            if base in (int, float):
                assert ranges.constrained(hint) or ranges._parts(hint)[1], (algo, name, hint)


@pytest.mark.parametrize(("algo", "name"), ALGORITHM_SETTINGS)
def test_an_algorithm_setting_is_refused_alike_everywhere(algo, name, tmp_path):
    algorithm = ALGORITHMS[algo]
    owner, hint = declarations(type(algorithm.preset))[name]
    bad = bad_value(hint)
    if bad is None:
        pytest.skip(f"{algo} {name} is text")
    expected = f"{name} must be {ranges.describe(hint)}, got {bad!r}"
    # The Python API: the config class itself (a group's settings: the group's own class).
    assert refused(lambda: owner(**{name: bad})) == expected
    # The command line: --set, and a typed flag where the algorithm has one for it.
    argv = ["train", "--algo", algo, "--set", f"{name}={as_text(bad)}"]
    assert refused(lambda: cli.parse(argv)) == f"--set: {algo} setting {expected}"
    base = ranges._parts(ranges._optional(hint)[0])[0]
    if name in algorithm.cli_flags and typing.get_origin(base) is not typing.Literal:
        flag = "--" + name.replace("_", "-")  # (a Literal flag's choices are tyro's to refuse)
        message = refused(lambda: cli.parse(["train", "--algo", algo, flag, as_text(bad)]))
        assert message == f"{algo} setting {expected.replace(name, flag, 1)}"
    # A sweep spec, as YAML: a variant and a grid.
    spec = tmp_path / "spec.yaml"
    variant = {"datasets": ["hopper-medium"], "variants": [{"algo": algo, name: as_json(bad)}]}
    spec.write_text(yaml.safe_dump(variant))
    assert refused(lambda: expand(load_spec(spec))) == f"{algo} setting {expected}"
    grid = {"datasets": ["hopper-medium"], "algos": [algo], "grid": {name: [as_json(bad)]}}
    spec.write_text(yaml.safe_dump(grid))
    assert refused(lambda: expand(load_spec(spec))) == f"grid: {algo} setting {expected}"
    # A run's config.json, as resume reads it.
    path = Path("run/config.json")
    message = refused(lambda: run_config.check(config_json(algo, agent={name: as_json(bad)}), path))
    assert message.startswith(f"{path}: agent: {algo} setting {expected}; "), message


TRAIN_SETTINGS = sorted(
    name for name, (_, hint) in declarations(TrainConfig).items() if bad_value(hint) is not None
)


@pytest.mark.parametrize("name", TRAIN_SETTINGS)
def test_a_run_setting_is_refused_alike_everywhere(name, tmp_path):
    hint = ranges.hints(TrainConfig)[name]
    bad = bad_value(hint)
    expected = f"{name} must be {ranges.describe(hint)}, got {bad!r}"
    assert refused(lambda: TrainConfig(**{name: bad})) == expected
    flag = "--" + name.replace("_", "-")
    base = ranges._parts(ranges._optional(hint)[0])[0]
    if typing.get_origin(base) is not typing.Literal:  # a choice's flag: tyro refuses it
        message = refused(lambda: cli.parse(["train", flag, as_text(bad)]))
        assert message == expected.replace(name, flag, 1), message
    spec = tmp_path / "spec.yaml"
    keys = {"seed": {"seeds": [bad]}, "steps": {"steps": bad}}.get(name, {"train": {name: bad}})
    spec.write_text(yaml.safe_dump({"datasets": ["hopper-medium"], "algos": ["bc"], **keys}))
    want = {"seed": expected.replace(name, "seeds[0]", 1), "steps": expected}
    assert refused(lambda: expand(load_spec(spec))) == want.get(
        name, f"bad train setting: {expected}"
    )
    path = Path("run/config.json")
    message = refused(lambda: run_config.check(config_json("bc", train={name: bad}), path))
    assert message.startswith(f"{path}: train.{expected}; "), message


def test_a_config_json_of_an_earlier_version_maps_its_flat_settings_to_their_config():
    """EABC's BC-weight rule settings live in their own config (bc_rule); config.json keeps them
    flat by their own names, as every earlier version wrote them, and reads them back there."""
    from eabc.training.directory import agent_config_from_json  # noqa: PLC0415

    algorithm = ALGORITHMS["eabc-trust"]
    written = ranges.flat(algorithm.preset)
    assert {"bc_weight", "auto_signal", "auto_rate", "num_critics"} <= set(written)
    old = {**written, "auto_rate": 0.02, "hidden_dims": [64, 64]}  # as JSON holds it
    config = agent_config_from_json(algorithm, old)
    assert config.bc_rule.auto_rate == 0.02 and config.bc_rule.auto_signal == "distance"
    assert config.hidden_dims == (64, 64) and ranges.flat(config) == {
        **old,
        "hidden_dims": (64, 64),
    }
