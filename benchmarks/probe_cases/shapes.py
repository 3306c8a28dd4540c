"""Class 5 of the probe: numbers, settings and sweep specs of the wrong shape."""

from __future__ import annotations

import json
from pathlib import Path

from probe_cases.case import Case, Outcome
from probe_cases.common import EVAL, run_copy, write

VALUES = ["0", "-1", "-100", "1.5", "nan", "inf", "1e400", "99999999999999999999", "0x10", "",
          "7", "5000"]  # fmt: skip


def _valid(flag: str, text: str) -> bool:
    """Whether ``--FLAG TEXT`` is a good value for `eabc train` (its other flags at their
    defaults: log interval 1000, evaluation and checkpoint intervals 5000)."""
    try:
        value = int(text)
    except ValueError:
        return flag == "confidence-level" and _unit(text)
    if flag == "seed":
        return 0 <= value <= 2**32 - 1
    if flag == "log-interval":
        return value >= 1 and 5000 % value == 0
    if flag in ("eval-interval", "checkpoint-interval"):
        return value >= 1000 and value % 1000 == 0
    if flag == "confidence-level":
        return 0 <= value <= 1
    return value >= 1


def _unit(text: str) -> bool:
    try:
        return 0 <= float(text) <= 1
    except ValueError:
        return False


def _planned_with(flag: str, text: str):
    """A check of a dry run: it printed a plan with the flag's value in it."""

    def check(folder: Path, outcome: Outcome) -> str | None:
        number = f"{int(text):,}" if text.lstrip("-").isdigit() else text
        if not outcome.out.strip():
            return "a dry run that printed no plan"
        return (
            None
            if number in outcome.out or text in outcome.out
            else (f"the plan does not show --{flag} {text}: {outcome.out[-300:]!r}")
        )

    return check


def _nested_keys(spec: dict) -> list[str]:
    return [str(k) for v in spec.values() if isinstance(v, dict) for k in v]


def wrong_shapes(base: Path) -> list[Case]:
    """Numbers out of range or of the wrong kind, malformed --set items and sweep specs of the
    wrong shape: refused in one line naming the flag or key, before any work; good values
    accepted."""
    data = str(base / "tiny.npz")
    cases = []
    flags = ("seed", "steps", "batch-size", "eval-interval", "eval-episodes", "log-interval",
             "checkpoint-interval", "num-critics", "confidence-level")  # fmt: skip
    for flag in flags:
        for text in VALUES:
            argv = ["train", "--dataset", data, "--algo", "eabc", f"--{flag}={text}", "--dry-run"]
            if flag != "confidence-level":
                argv.insert(-1, "--confidence-level=0.5")
            expect = "work" if _valid(flag, text) else "refuse"
            if text == "99999999999999999999" and flag != "seed":
                expect = "either"  # a plan of absurd size, or a refusal
            cases.append(Case(5, f"train --{flag} {text!r}", argv, expect,
                              names=(f"--{flag}",), check=_planned_with(flag, text),
                              read_only=True))  # fmt: skip
    for flag, text in [("episodes", v) for v in ("0", "-1", "x", "1.5", "")] + [
        ("seed", v) for v in ("-1", "4294967296", "x", "1e3")
    ]:
        cases.append(Case(5, f"evaluate --{flag} {text!r}", [*EVAL, f"--{flag}={text}"],
                          "refuse", run_copy(base), (f"--{flag}",)))  # fmt: skip
    sweep = ["sweep", "--datasets", data, "--algos", "td3bc", "--root", "root", "--dry-run"]
    for flag, texts in {
        "seeds": ("-1", "4294967296", "1.5", "x"),
        "steps": ("0", "-5", "1.5", "x"),
        "workers": ("0", "-1", "x"),
        "eval-interval": ("0", "-1", "x"),
        "batch-size": ("0", "x"),
        "cpus-per-job": ("0", "-1", "nan", "inf", "x"),
        "gpus-per-job": ("-1", "nan", "x"),
    }.items():
        for text in texts:
            cases.append(Case(5, f"sweep --{flag} {text!r}", [*sweep, f"--{flag}={text}"],
                              "refuse", names=(f"--{flag}",)))  # fmt: skip
    for flag, text in [
        ("steps", "0"),
        ("steps", "-1"),
        ("seed", "-1"),
        ("batch-size", "0"),
        ("eval-interval", "0"),
        ("lr", "0"),
        ("lr", "nan"),
        ("alpha", "-1"),
    ]:
        cases.append(Case(5, f"sac --{flag} {text!r}", ["sac", f"--{flag}={text}"], "refuse",
                          names=(f"--{flag}",)))  # fmt: skip
    for label, item in {
        "no =": "alpha", "no key": "=1", "an unknown setting": "alphaa=1",
        "a negative learning rate": "actor_lr=-1", "a bad list": "hidden_dims=a,b",
        "a zero size": "hidden_dims=0", "a float critic count": "num_critics=2.5",
        "an empty value": "alpha=", "NaN": "alpha=nan", "a huge number": "alpha=1e400",
    }.items():  # fmt: skip
        argv = ["train", "--dataset", data, "--algo", "td3bc", "--set", item, "--dry-run"]
        cases.append(Case(5, f"--set {label}", argv, "refuse", names=("--set", item,
                          item.split("=")[0])))  # fmt: skip
    good = {"datasets": [data], "algos": ["td3bc"], "seeds": [0]}
    specs = {
        "datasets a string": {**good, "datasets": data},
        "datasets empty": {**good, "datasets": []},
        "datasets of numbers": {**good, "datasets": [1, 2]},
        "algos a string": {**good, "algos": "td3bc"},
        "algos unknown": {**good, "algos": ["td4"]},
        "seeds a number": {**good, "seeds": 5},
        "seeds empty": {**good, "seeds": []},
        "seeds of 1.5": {**good, "seeds": [1.5]},
        "seeds as text": {**good, "seeds": ["1"]},
        "seeds negative": {**good, "seeds": [-1]},
        "seeds too large": {**good, "seeds": [2**32]},
        "seeds of booleans": {**good, "seeds": [True]},
        "steps as text": {**good, "steps": "1000"},
        "steps zero": {**good, "steps": 0},
        "steps 1000.0": {**good, "steps": 1000.0},
        "grid a list": {**good, "grid": [1]},
        "grid empty values": {**good, "grid": {"alpha": []}},
        "grid an unknown setting": {**good, "grid": {"alphaa": [1]}},
        "grid a bad value": {**good, "grid": {"alpha": [-1]}},
        "train a list": {**good, "train": [1]},
        "train an unknown key": {**good, "train": {"lr": 1}},
        "train eval_interval as text": {**good, "train": {"eval_interval": "x"}},
        "train log_interval zero": {**good, "train": {"log_interval": 0}},
        "variants a string": {**good, "variants": "td3bc"},
        "variants without algo": {**good, "variants": [{"alpha": 1}]},
        "variants with empty datasets": {**good, "variants": [{"algo": "bc", "datasets": []}]},
        "an unknown key": {**good, "sweeps": 1},
        "no algos": {"datasets": [data], "seeds": [0]},
        "a good spec": good,
        "a good spec with a grid": {**good, "grid": {"alpha": [1.0, 2.5]}},
    }
    for label, spec in specs.items():
        expect = "work" if label.startswith("a good") else "refuse"
        cases.append(Case(5, f"sweep spec {label}", ["sweep", "spec.yaml", "--root", "root",
                          "--dry-run"], expect, write("spec.yaml", json.dumps(spec)),
                          (*spec.keys(), *_nested_keys(spec), "spec.yaml", "algorithm", "sweep"),
                          read_only=True))  # fmt: skip
    return cases
