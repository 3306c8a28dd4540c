"""Numbers past what the code can hold, flags that would be ignored or merged, output paths onto
what a command must not replace, spread over the probe's classes: step counts beyond the int32
counters, a batch, a network, a replay buffer or a dataset larger than the memory free, --resume
with options it would ignore, a flag or a setting given twice, a grid value written two ways, and
--dry-run judging flags as the run does (5); export-policy onto the run's own files, a folder, a
FIFO, a device or a link to the run's config.json (2); Ctrl-C while train, sac or sweep works
and while data make writes its file (7).

Every refusal must come before anything is written: the probe checks that the case's directory
is as it was (no run directory left to block a retry).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from probe_cases.case import Case, Outcome
from probe_cases.common import RESUME, fifo, npz, run_copy, then

BIG = str(2**31)
"""One past the largest step count, interval or batch size (an int32 counter's)."""
DATA = ["--dataset", "d.npz", "--algo", "bc", "--run-dir", "r", "--no-progress"]


def _spec(**keys):
    """A sweep spec ``s.yaml`` on the case's ``d.npz`` with ``keys``."""

    def make(folder: Path) -> None:
        spec = {"datasets": ["d.npz"], "algos": ["eabc"], "steps": 200,
                "train": {"eval_interval": 100, "log_interval": 100, "checkpoint_interval": 100},
                **keys}  # fmt: skip
        (folder / "s.yaml").write_text(json.dumps(spec))

    return make


def _link(name: str, target: str):
    return lambda folder: os.symlink(folder / target, folder / name)


def numbers_and_flags(base: Path) -> list[Case]:
    """Class 5: numbers bounded by what the code holds; no flag silently ignored or merged."""
    data = npz("d.npz", env_id=np.asarray("Pendulum-v1"))
    cases = [
        Case(5, f"train {flag} past int32", ["train", *DATA, flag, BIG], "refuse", data, (flag,))
        for flag in ("--steps", "--eval-interval", "--log-interval", "--batch-size")
    ]
    cases += [
        Case(5, "train --steps past int32 --dry-run", ["train", *DATA, "--steps", "3000000000",
             "--dry-run"], "refuse", data, ("--steps",)),
        Case(5, "train a batch larger than memory", ["train", *DATA, "--batch-size",
             "1000000000"], "refuse", data, ("--batch-size",)),
        Case(5, "train a batch larger than memory --dry-run", ["train", *DATA, "--batch-size",
             "1000000000", "--dry-run"], "refuse", data, ("--batch-size",)),
        Case(5, "train networks larger than memory", ["train", *DATA, "--set",
             "hidden_dims=200000,200000"], "refuse", data, ("--set", "hidden_dims")),
        Case(5, "train an algorithm's step count past int32", ["train", *DATA[:2], "--algo", "iql",
             "--set", f"total_steps={BIG}", "--dry-run"], "refuse", data, ("total_steps",)),
        Case(5, "sac --steps past int32", ["sac", "--env", "Pendulum-v1", "--steps", BIG,
             "--run-dir", "r"], "refuse", names=("--steps",)),
        Case(5, "sac a replay buffer larger than memory", ["sac", "--env", "Pendulum-v1",
             "--steps", "2000000000", "--run-dir", "r"], "refuse", names=("--steps",)),
        Case(5, "sweep --steps past int32", ["sweep", "s.yaml", "--root", "root", "--steps", BIG],
             "refuse", then(data, _spec()), ("--steps",)),
        Case(5, "sweep spec steps past int32", ["sweep", "s.yaml", "--root", "root",
             "--dry-run"], "refuse", then(data, _spec(steps=2**31)), ("steps",)),
        Case(5, "data make --size past int32", ["data", "make", "hopper-random", "--size", BIG,
             "--cache-dir", "cache"], "refuse", names=("--size",)),
        Case(5, "data make a dataset larger than memory", ["data", "make", "hopper-random",
             "--size", "2000000000", "--cache-dir", "cache"], "refuse", names=("--size",)),
        Case(5, "train --set tau twice", ["train", *DATA[:2], "--algo", "td3bc", "--set",
             "tau=0.005", "tau=0.5", "--dry-run"], "refuse", data, ("tau",)),
        Case(5, "train --set given twice", ["train", *DATA, "--set", "actor_lr=0.001", "--set",
             "actor_lr=0.002", "--dry-run"], "refuse", data, ("--set",)),
        Case(5, "train --seed given twice", ["train", *DATA, "--seed", "1", "--seed=2",
             "--dry-run"], "refuse", data, ("--seed",)),
        Case(5, "train --progress and --no-progress", ["train", *DATA, "--progress",
             "--dry-run"], "refuse", data, ("--progress", "--no-progress")),
        Case(5, "train a typed flag and --set of one setting", ["train", *DATA[:2], "--algo",
             "eabc", "--confidence-level", "0.5", "--num-critics", "3", "--set",
             "num_critics=5", "--dry-run"], "refuse", data, ("num_critics", "--num-critics")),
        Case(5, "sweep --grid of one key twice", ["sweep", "s.yaml", "--root", "root", "--grid",
             "tau=0.1", "tau=0.2", "--dry-run"], "refuse", then(data, _spec()), ("--grid",)),
        Case(5, "sweep grid value written two ways", ["sweep", "s.yaml", "--root", "root",
             "--dry-run"], "refuse", then(data, _spec(grid={"num_critics": [2, 2.0]})),
             ("grid.num_critics",)),
        Case(5, "sweep grid value written once, twice", ["sweep", "s.yaml", "--root", "root",
             "--dry-run"], "work", then(data, _spec(grid={"num_critics": [2, 2]})),
             read_only=True),
        Case(5, "dry run of intervals the run accepts", ["train", *DATA, "--log-interval", "100",
             "--eval-interval", "200", "--dry-run"], "work", data, read_only=True),
        Case(5, "dry run of intervals the run refuses", ["train", *DATA, "--log-interval", "100",
             "--eval-interval", "150", "--dry-run"], "refuse", data, ("--eval-interval",)),
    ]  # fmt: skip
    for extra in (["--seed", "3"], ["--steps", "400"], ["--algo", "bc"], ["--dataset", "x.npz"],
                  ["--set", "tau=0.5"], ["--run-dir", "elsewhere"], ["--batch-size=64"]):  # fmt: skip
        flag = extra[0].split("=")[0]
        cases.append(Case(5, f"train --resume with {flag}", [*RESUME, *extra], "refuse",
                          run_copy(base), (flag,)))  # fmt: skip
    cases.append(Case(5, "sac --resume with --steps", ["sac", "--resume", "run", "--steps", "9"],
                      "refuse", run_copy(base), ("--steps",)))  # fmt: skip
    return cases


def output_paths(base: Path) -> list[Case]:
    """Class 2: export-policy never replaces a run's own file or what is not a regular file."""
    run = run_copy(base)
    export = ["export-policy", "run", "--onnx"]
    cases = [
        Case(2, f"export-policy --onnx onto the run's {name}", [*export, f"run/{name}"], "refuse",
             run, ("--onnx",))
        for name in ("checkpoint.msgpack", "config.json", "log.csv", "summary.json")
    ]  # fmt: skip
    cases += [
        Case(2, "export-policy --onnx onto a folder", [*export, "run"], "refuse", run,
             ("--onnx",)),
        Case(2, "export-policy --onnx onto a FIFO", [*export, "p.onnx"], "refuse",
             then(run, fifo("p.onnx")), ("--onnx",)),
        Case(2, "export-policy --onnx onto a link to config.json", [*export, "p.onnx"], "refuse",
             then(run, _link("p.onnx", "run/config.json")), ("--onnx",)),
        Case(2, "export-policy --onnx onto /dev/null", [*export, "/dev/null"], "refuse", run,
             ("--onnx",)),
        Case(2, "export-policy --onnx into the run directory", [*export, "run/policy.onnx"],
             "either", run),
    ]  # fmt: skip
    return cases


def _no_temporaries(*folders: str):
    """A check of an interrupted command: no temporary file left in ``folders``."""

    def check(folder: Path, outcome: Outcome) -> str | None:
        for name in folders:
            left = [p.name for p in (folder / name).rglob("*") if p.name.endswith(".tmp")]
            if left:
                return f"temporary files left in {name}: {left[:3]}"
        return None

    return check


def interrupted(base: Path) -> list[Case]:
    """Class 7: Ctrl-C ends a command in one line, exit code 130, with nothing half-written."""
    data = npz("d.npz", env_id=np.asarray("Pendulum-v1"))
    long = ["--steps", "200000", "--log-interval", "100", "--eval-interval", "100000",
            "--checkpoint-interval", "100", "--eval-episodes", "1"]  # fmt: skip
    return [
        Case(7, "Ctrl-C on train", ["train", *DATA, "--set", "hidden_dims=32,32", *long],
             "interrupted", data, ("eabc train --resume r",), _no_temporaries("r"),
             timeout=180, interrupt="r/log.csv"),
        Case(7, "Ctrl-C on sac", ["sac", "--env", "Pendulum-v1", "--steps", "200000",
             "--run-dir", "r", "--no-progress"], "interrupted", names=("eabc sac --resume r",),
             check=_no_temporaries("r"), timeout=180, interrupt="r/config.json"),
        Case(7, "Ctrl-C on sweep", ["sweep", "s.yaml", "--root", "root"], "interrupted",
             then(data, _spec(steps=200000, grid={"hidden_dims": [[32, 32]]})),
             ("sweep interrupted",), _no_temporaries("root"), timeout=180,
             interrupt="root/logs"),
        # the folder appears as the file is written (1M rows: seconds), after a minute or two
        Case(7, "Ctrl-C on data make as it writes", ["data", "make", "hopper-random",
             "--cache-dir", "c"], "interrupted", names=("eabc data make hopper-random",
             "complete and kept"), check=_no_half_dataset, timeout=900,
             interrupt="c/datasets"),
    ]  # fmt: skip


def _no_half_dataset(folder: Path, outcome: Outcome) -> str | None:
    """An interrupted data make: no temporary file, and a dataset only where it says it kept one
    whole (one that loads with all its rows)."""
    from eabc.data.loaders import load_file  # noqa: PLC0415

    left = sorted(p.name for p in (folder / "c" / "datasets").glob("*") if p.is_file())
    kept = "complete and kept" in outcome.err
    if left != (["hopper-random.hdf5"] if kept else []):
        return f"left in the cache: {left} ({'kept' if kept else 'nothing kept'}, it says)"
    if kept and load_file(folder / "c" / "datasets" / left[0]).size != 1_000_000:
        return "the dataset it kept is not whole"
    return None
