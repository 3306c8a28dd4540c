"""Class 4 of the probe: inputs that could be found bad only after work."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from probe_cases.case import Case, Outcome
from probe_cases.common import SCHEDULE, npz, run_copy, then, write


def _made(*paths: str):
    def check(folder: Path, outcome: Outcome) -> str | None:
        missing = [p for p in paths if not (folder / p).is_file()]
        return f"did not make {missing}" if missing else None

    return check


def too_late(base: Path) -> list[Case]:
    """What would fail after minutes of work (making data, training, a sweep's first runs) is
    refused before it, in one line, with nothing made."""
    data = str(base / "tiny.npz")
    train = ["train", "--algo", "td3bc", "--set", "hidden_dims=32,32", *SCHEDULE]
    cases = []
    scores = {
        "equal reference scores": (-100.0, -100.0),
        "a NaN reference score": (math.nan, -100.0),
        "an infinite reference score": (-100.0, math.inf),
        "only a minimum reference score": (-100.0, None),
    }
    for label, (low, high) in scores.items():
        extra = {"ref_min_score": np.asarray(low)}
        if high is not None:
            extra["ref_max_score"] = np.asarray(high)
        make = npz("d.npz", env_id=np.asarray("Pendulum-v1"), **extra)
        cases.append(Case(4, f"{label}: train", [*train, "--dataset", "d.npz", "--run-dir", "r"],
                          "refuse", make, ("d.npz", "ref_min_score", "ref_max_score")))  # fmt: skip
    afile = write("afile", "")
    runs = {
        "--cache-dir a file": (["--dataset", "hopper-random", "--cache-dir", "afile"], afile),
        "--cache-dir under a file": (["--dataset", "hopper-random", "--cache-dir", "afile/c"],
                                     afile),
        "--run-dir a file": (["--dataset", data, "--run-dir", "afile"], afile),
        "--run-dir under a file": (["--dataset", data, "--run-dir", "afile/r"], afile),
        "--env unknown": (["--dataset", data, "--env", "NoSuchEnv-v9"], None),
        "--env of discrete actions": (["--dataset", data, "--env", "CartPole-v1"], None),
        "--env of other shapes": (["--dataset", data, "--env", "MountainCarContinuous-v0"], None),
        "--dataset missing": (["--dataset", "missing.npz"], None),
        "--dataset unknown name": (["--dataset", "hopper-nonsense"], None),
        "--dataset a built-in, --env of other shapes": (
            ["--dataset", "hopper-random", "--env", "Pendulum-v1"], None),
        "--set of an unknown setting": (["--dataset", data, "--set", "etaa=1"], None),
        "--set of a bad value": (["--dataset", data, "--set", "alpha=-1"], None),
    }  # fmt: skip
    for label, (flags, make) in runs.items():
        argv = [*train, *flags] + ([] if "--run-dir" in flags else ["--run-dir", "r"])
        names = tuple(f for f in flags if f.startswith("--")) + tuple(flags[1::2]) + ("--set",)
        cases.append(Case(4, f"{label}: train", argv, "refuse", make or (lambda f: None), names,
                          timeout=45))  # fmt: skip
    cases.append(Case(4, "$EABC_CACHE_DIR a file: train",
                      [*train, "--dataset", "hopper-random", "--run-dir", "r"], "refuse", afile,
                      ("EABC_CACHE_DIR",), env={"EABC_CACHE_DIR": "./afile"}, timeout=45))  # fmt: skip
    cases.append(Case(4, "data make --cache-dir a file", ["data", "make", "hopper-random",
                      "--cache-dir", "afile"], "refuse", afile, ("afile",), timeout=45))  # fmt: skip
    exports = {
        "--onnx a directory": "run",
        "--onnx under a file": "afile/policy.onnx",
    }
    for label, target in exports.items():
        cases.append(Case(4, f"export-policy {label}", ["export-policy", "run", "--onnx", target],
                          "refuse", then(run_copy(base), afile), (target, "onnx")))  # fmt: skip
    cases.append(Case(4, "export-policy --onnx in a missing directory (made)", ["export-policy",
                      "run", "--onnx", "new/policy.onnx"], "work", run_copy(base),
                      check=_made("new/policy.onnx")))  # fmt: skip
    both = then(run_copy(base, "A", "root/a"), run_copy(base, "D", "root/d"), afile)
    reports = {
        "--baseline unknown": (["--baseline", "nope"], ("nope", "--baseline")),
        "--fix unknown": (["--fix", "nope"], ("nope", "--fix")),
        "--out a file": (["--out", "afile"], ("afile",)),
        "--out under a file": (["--out", "afile/r"], ("afile",)),
        "--include missing": (["--include", "missing"], ("missing",)),
    }
    for label, (flags, names) in reports.items():
        cases.append(Case(4, f"report {label}", ["report", "root", *flags], "refuse", both,
                          names))  # fmt: skip
    spec = {"datasets": [data], "algos": ["td3bc"], "steps": 200,
            "train": {"log_interval": 100, "eval_interval": 100, "checkpoint_interval": 100,
                      "eval_episodes": 1}, "grid": {"hidden_dims": [[32, 32]]}}  # fmt: skip
    sweeps = {
        "a missing dataset beside a good one": {**spec, "datasets": [data, "missing.npz"]},
        "a variant with an unknown setting": {**spec, "variants": [{"algo": "bc", "etaa": 1}]},
        "a variant of a bad value": {**spec, "variants": [{"algo": "td3bc", "alpha": -1}]},
        "an unknown algorithm after a good one": {**spec, "algos": ["td3bc", "td4"]},
        "a grid setting no algorithm has": {**spec, "grid": {"etaa": [1]}},
        "intervals that do not divide": {**spec, "train": {**spec["train"], "log_interval": 30}},
    }
    for label, content in sweeps.items():
        make = write("spec.yaml", json.dumps(content))
        cases.append(Case(4, f"sweep {label}", ["sweep", "spec.yaml", "--root", "root"],
                          "refuse", make, ("spec.yaml", "missing.npz", "etaa", "td4", "alpha",
                                           "log_interval", "interval"), timeout=60))  # fmt: skip
    cases.append(
        Case(
            4,
            "sweep --root a file",
            ["sweep", "spec.yaml", "--root", "afile"],
            "refuse",
            then(afile, write("spec.yaml", json.dumps(spec))),
            ("afile",),
        )
    )
    cases.append(Case(4, "sweep --workers 0", ["sweep", "spec.yaml", "--root", "root",
                      "--workers", "0"], "refuse", write("spec.yaml", json.dumps(spec)),
                      ("--workers",)))  # fmt: skip
    cases.append(Case(4, "zoo build of an offline run", ["zoo", "build", "run", "hopper"],
                      "refuse", run_copy(base), ("run",), timeout=60))  # fmt: skip
    cases.append(Case(4, "zoo pack of an offline run", ["zoo", "pack", "run", "out"],
                      "refuse", run_copy(base), ("run",), timeout=60))  # fmt: skip
    return cases
