"""Class 3 of the probe: malformed dataset files, config.json, checkpoints, run files that are
FIFOs, sweep specs."""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np

from probe_cases.case import Case, Outcome
from probe_cases.common import (
    EVAL,
    EXPORT,
    RESULTS,
    RESUME,
    SCHEDULE,
    edit,
    fifo,
    intact_after_resume,
    listed,
    npz,
    run_copy,
    then,
    transitions,
    unchanged_and_says,
    write,
)


def _npy_member(header_shape: str) -> bytes:
    """An .npy member whose header claims ``header_shape`` over 16 bytes of data."""
    header = f"{{'descr': '<f4', 'fortran_order': False, 'shape': {header_shape}, }}"
    header = header.ljust(118) + "\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode() + b"\0" * 16


def _zip(name: str, members: dict[str, bytes], compression=zipfile.ZIP_STORED):
    def make(folder: Path) -> None:
        with zipfile.ZipFile(folder / name, "w", compression) as archive:
            for member, data in members.items():
                archive.writestr(member, data)

    return make


def _npy_bytes(array: np.ndarray) -> bytes:
    import io  # noqa: PLC0415

    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    return buffer.getvalue()


def _good_members(**changes) -> dict[str, bytes]:
    return {f"{k}.npy": _npy_bytes(v) for k, v in transitions(**changes).items()}


def _hdf5(name: str, build):
    def make(folder: Path) -> None:
        import h5py  # noqa: PLC0415

        with h5py.File(folder / name, "w") as f:
            build(f)

    return make


def _hdf5_arrays(**changes):
    def build(f):
        for key, value in transitions(**changes).items():
            f[key] = value

    return build


def _external_link(f) -> None:
    """The arrays but observations, which link to another file."""
    import h5py  # noqa: PLC0415

    _hdf5_arrays(observations=None)(f)
    f["observations"] = h5py.ExternalLink("/etc/passwd", "x")


def _truncated(name: str):
    def make(folder: Path) -> None:
        np.savez(folder / "whole.npz", **transitions())
        data = (folder / "whole.npz").read_bytes()
        (folder / "whole.npz").unlink()
        (folder / name).write_bytes(data[: len(data) // 2])

    return make


def _link(name: str, target: str):
    return lambda folder: os.symlink(target, folder / name)


DATASETS = {
    # name: (how the file is made, whether it is a good dataset)
    "a FIFO named .npz": ("d.npz", fifo("d.npz"), False),
    "a FIFO named .hdf5": ("d.hdf5", fifo("d.hdf5"), False),
    "a directory named .npz": ("d.npz", lambda f: (f / "d.npz").mkdir(), False),
    "an empty file": ("d.npz", write("d.npz", b""), False),
    "text named .npz": ("d.npz", write("d.npz", "observations,actions\n1,2\n"), False),
    "an .npy renamed .npz": ("d.npz", write("d.npz", _npy_bytes(np.zeros((40, 3)))), False),
    "a truncated .npz": ("d.npz", _truncated("d.npz"), False),
    "a link to /dev/zero": ("d.npz", _link("d.npz", "/dev/zero"), False),
    "a link loop": ("d.npz", then(_link("d.npz", "e.npz"), _link("e.npz", "d.npz")), False),
    "a header claiming 60 TB": ("d.npz", _zip("d.npz", {**_good_members(),
        "observations.npy": _npy_member("(4000000000000, 4)")}), False),
    "a header claiming a negative shape": ("d.npz", _zip("d.npz", {**_good_members(),
        "observations.npy": _npy_member("(-40, 3)")}), False),
    "a text member among arrays": ("d.npz", _zip("d.npz", {**_good_members(),
        "observations.npy": b"not an array"}), False),
    "a zip claiming a huge deflated member": ("d.npz", _zip("d.npz", {**_good_members(),
        "observations.npy": _npy_member("(400000000, 3)")[:200] + b"\0" * 4_000_000},
        zipfile.ZIP_DEFLATED), False),
    "structured observations": ("d.npz", npz("d.npz", observations=np.zeros(
        40, [("a", "<f4"), ("b", "<f4"), ("c", "<f4")])), False),
    "complex observations": ("d.npz", npz("d.npz", observations=np.zeros((40, 3), complex)),
                             False),
    "object observations (a pickle)": ("d.npz", _zip("d.npz", {**_good_members(),
        "observations.npy": _npy_bytes(np.full((40, 3), None, object))}), False),
    "text observations": ("d.npz", npz("d.npz", observations=np.full((40, 3), "ab")), False),
    "scalar rewards": ("d.npz", npz("d.npz", rewards=np.float32(1.0)), False),
    "3-d observations": ("d.npz", npz("d.npz", observations=np.zeros((40, 3, 2), "f4")), False),
    "no actions": ("d.npz", npz("d.npz", actions=None), False),
    "no rows": ("d.npz", npz("d.npz", rows=0), False),
    "one row": ("d.npz", npz("d.npz", rows=1), False),
    "lengths that differ": ("d.npz", npz("d.npz", rewards=np.zeros(39, "f4")), False),
    "NaN observations": ("d.npz", npz("d.npz", observations=np.full((40, 3), np.nan, "f4")),
                         False),
    "inf rewards": ("d.npz", npz("d.npz", rewards=np.full(40, np.inf, "f4")), False),
    "terminals of 0.5": ("d.npz", npz("d.npz", terminals=np.full(40, 0.5, "f4")), False),
    "reference score as text": ("d.npz", npz("d.npz", ref_min_score=np.asarray("low"),
                                              ref_max_score=np.asarray(1.0)), False),
    "observations of 5 where the environment has 3": (
        "d.npz", npz("d.npz", observations=np.zeros((40, 5), "f4")), False),
    "actions of 2 where the environment has 1": (
        "d.npz", npz("d.npz", actions=np.zeros((40, 2), "f4")), False),
    "HDF5 garbage": ("d.hdf5", write("d.hdf5", b"\x89HDF\r\n\x1a\n" + b"\x07" * 300), False),
    "HDF5 without actions": ("d.hdf5", _hdf5("d.hdf5", _hdf5_arrays(actions=None)), False),
    "HDF5 with a group for observations": ("d.hdf5", _hdf5("d.hdf5", lambda f: (
        f.create_group("observations"), _hdf5_arrays(observations=None)(f))), False),
    "HDF5 with an external link": ("d.hdf5", _hdf5("d.hdf5", _external_link), False),
    "a good .npz": ("d.npz", npz("d.npz"), True),
    "a good HDF5": ("d.hdf5", _hdf5("d.hdf5", _hdf5_arrays()), True),
    "a good .npz of float64 and int flags": ("d.npz", npz("d.npz", observations=np.zeros(
        (40, 3)), terminals=np.zeros(40, "i8")), True),
}  # fmt: skip


MISMATCHED = ("observations of 5 where the environment has 3",
              "actions of 2 where the environment has 1")  # fmt: skip


def _planned(folder: Path, outcome: Outcome) -> str | None:
    return None if "dataset" in outcome.out else f"no plan printed: {outcome.out[-200:]!r}"


HAND_EDITS = {
    "{}": lambda c: {},
    "no train": lambda c: {k: v for k, v in c.items() if k != "train"},
    "no train.steps": lambda c: {**c, "train": {k: v for k, v in c["train"].items() if k != "steps"}},
    "an extra key": lambda c: {**c, "notes": "x"},
    "an extra train key": lambda c: {**c, "train": {**c["train"], "lr": 0.1}},
    "steps as text": lambda c: {**c, "train": {**c["train"], "steps": "200"}},
    "seed as text": lambda c: {**c, "train": {**c["train"], "seed": "0"}},
    "seed 1.5": lambda c: {**c, "train": {**c["train"], "seed": 1.5}},
    "algo a number": lambda c: {**c, "train": {**c["train"], "algo": 3}},
    "train a list": lambda c: {**c, "train": [1]},
    "dataset a string": lambda c: {**c, "dataset": "tiny"},
    "dataset.size as text": lambda c: {**c, "dataset": {**c["dataset"], "size": "40"}},
    "agent a list": lambda c: {**c, "agent": [1]},
    "agent setting of the wrong type": lambda c: {**c, "agent": {**c["agent"], "alpha": "x"}},
    "max_action as text": lambda c: {**c, "max_action": "2"},
    "a JSON list": lambda c: [c],
    "null": lambda c: None,
}  # fmt: skip


def malformed(base: Path) -> list[Case]:
    """Malformed files end in one line naming the file (or the key), never in a traceback or a
    hang; good files are read."""
    cases = []
    for label, (name, make, good) in DATASETS.items():
        train = ["train", "--dataset", name, "--env", "Pendulum-v1", "--algo", "td3bc"]
        for command, argv in (
            ("train --dry-run", [*train, "--dry-run"]),
            ("data info", ["data", "info", name]),
            ("train", [*train, "--run-dir", "r", "--set", "hidden_dims=32,32", *SCHEDULE]),
        ):
            expect = "work" if good else "refuse"
            if label in MISMATCHED and command == "data info":
                expect = "work"  # a good file; only its pairing with --env is wrong
            check = _planned if command == "train --dry-run" else None
            names = (name, "e.npz", "--env", "Pendulum-v1", "environment")
            cases.append(Case(3, f"{label}: {command}", argv, expect, make, names, check,
                              read_only=command != "train", timeout=90))  # fmt: skip
    for label, change in HAND_EDITS.items():
        prepare = then(run_copy(base), edit("run/config.json",
                                            lambda t, c=change: json.dumps(c(json.loads(t)))))  # fmt: skip
        names = ("run/config.json",)
        cases += [
            Case(3, f"config.json {label}: evaluate", EVAL, "refuse", prepare, names),
            Case(3, f"config.json {label}: resume", RESUME, "refuse", prepare, names),
            Case(3, f"config.json {label}: export-policy", EXPORT, "refuse", prepare, names),
            Case(3, f"config.json {label}: results", RESULTS, "work", prepare,
                 check=listed(base, "A", names, contradiction=True)),
        ]  # fmt: skip
    data = (base / "runs" / "A" / "checkpoint.msgpack").read_bytes
    checkpoints = {
        "a flipped byte": lambda f: write("run/checkpoint.msgpack", bytes(
            b ^ 0xFF if i == len(data()) // 2 else b for i, b in enumerate(data())))(f),
        "cut in half": lambda f: write("run/checkpoint.msgpack", data()[: len(data()) // 2])(f),
        "empty": write("run/checkpoint.msgpack", b""),
        "its checksum only": lambda f: write("run/checkpoint.msgpack", data()[-40:])(f),
        "random bytes": write("run/checkpoint.msgpack", bytes(range(256)) * 40),
        "a directory": lambda f: (write("run/checkpoint.msgpack", None)(f),
                                  (f / "run/checkpoint.msgpack").mkdir()),
        "a FIFO": fifo("run/checkpoint.msgpack"),
        "a link to /dev/zero": then(write("run/checkpoint.msgpack", None),
                                    _link("run/checkpoint.msgpack", "/dev/zero")),
        "a msgpack list": write("run/checkpoint.msgpack", b"\x93\x01\x02\x03"),
        "a msgpack map claiming 2**32 entries": write("run/checkpoint.msgpack",
                                                      b"\xdf\xff\xff\xff\xff"),
    }  # fmt: skip
    for label, damage in checkpoints.items():
        prepare = then(run_copy(base), damage)
        names = ("run/checkpoint.msgpack",)
        cases += [
            Case(3, f"checkpoint {label}: evaluate", EVAL, "refuse", prepare, names),
            Case(3, f"checkpoint {label}: resume", RESUME, "refuse", prepare, names),
            Case(3, f"checkpoint {label}: export-policy", EXPORT, "refuse", prepare, names),
            Case(3, f"checkpoint {label}: results", RESULTS, "work", prepare,
                 check=listed(base, "A", names, contradiction=True)),
        ]  # fmt: skip
    for file in ("config.json", "log.csv", "summary.json", "provenance.json", "sweep.json"):
        prepare = then(run_copy(base), fifo(f"run/{file}"))
        names = (f"run/{file}",)
        contradiction = file in ("config.json", "log.csv", "summary.json")
        cases += [
            Case(3, f"{file} a FIFO: results", RESULTS, "work", prepare,
                 check=listed(base, "A", names, contradiction)),
            Case(3, f"{file} a FIFO: resume", RESUME, "either", prepare, names,
                 check=intact_after_resume(base)),
            Case(3, f"{file} a FIFO: evaluate", EVAL, "either", prepare, names, read_only=True,
                 check=unchanged_and_says('"step": 200')),
        ]  # fmt: skip
    laughs = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{c}: &{c} [{', '.join(['*' + p] * 9)}]\n"
        for p, c in zip("abcdefghi", "bcdefghij")
    )  # fmt: skip
    specs = {
        "a FIFO": fifo("spec.yaml"),
        "a directory": lambda f: (f / "spec.yaml").mkdir(),
        "binary": write("spec.yaml", bytes(range(256))),
        "not UTF-8": write("spec.yaml", "datasets: [caf\xe9]".encode("latin-1")),
        "a billion laughs": write("spec.yaml", laughs + "datasets: *j\n"),
        "a python tag": write("spec.yaml", "datasets: !!python/object/apply:os.system [ls]\n"),
        "a list": write("spec.yaml", "- datasets\n"),
        "empty": write("spec.yaml", ""),
        "a huge number of seeds": write("spec.yaml", "datasets: [x.npz]\nalgos: [bc]\n"
                                                     "seeds: [" + "1, " * 200000 + "1]\n"),
        "deeply nested": write("spec.yaml", "datasets: " + "[" * 5000 + "]" * 5000 + "\n"),
        "bad YAML": write("spec.yaml", "datasets: [a, b\nalgos: {"),
    }  # fmt: skip
    for label, make in specs.items():
        argv = ["sweep", "spec.yaml", "--root", "root", "--dry-run"]
        cases.append(Case(3, f"sweep spec {label}", argv, "refuse", make,
                          ("spec.yaml", "datasets", "seeds", "x.npz")))  # fmt: skip
    return cases
