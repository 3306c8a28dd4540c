"""Files edited or damaged after eabc wrote them, and names a sweep or Minari cannot use, spread
over the probe's classes: a run's checkpoint with NaN/inf values under a recomputed checksum and
its config.json with an edited ``max_action``, a key deleted or reference scores reversed (2);
damaged, truncated or half-written Minari folders, Minari ids outside the Minari path and data
files of timeouts only (3); reversed reference scores in data, a sweep whose run name is too
long for the file system or whose ``minari:`` dataset is missing, and a junk file in the dataset
cache (4).

The Minari datasets are written with Minari's own writer into the case's ``minari`` folder
(``$MINARI_DATASETS_PATH``); nothing is downloaded.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path

import numpy as np

from probe_cases.case import Case, Outcome
from probe_cases.common import (
    EVAL,
    EXPORT,
    RESULTS,
    RESUME,
    SCHEDULE,
    edit_json,
    listed,
    npz,
    run_copy,
    then,
    write,
)

MINARI = {"MINARI_DATASETS_PATH": "./minari"}
GOOD = "test/pendulum/good-v0"


def _tamper(where: str, value: float):
    """Put ``value`` into the checkpoint's ``where`` (``actor``, ``critic`` or ``normalizer``)
    and recompute its checksum, as someone who edits the payload can."""

    def make(folder: Path) -> None:
        from eabc import pytree  # noqa: PLC0415
        from eabc.training import checkpoint  # noqa: PLC0415

        path = folder / "run" / checkpoint.CHECKPOINT
        raw = pytree.loads(path.read_bytes()[:-40])
        if where == "normalizer":
            params, key = raw["normalizer"], "std"
        else:
            params, key = pytree.find(raw["agent"], where), "w0"
        array = np.array(params[key])
        array.reshape(-1)[0] = value
        params[key] = array
        checkpoint.write_tree(path, raw)

    return make


def _minari(dataset_id: str, scores=(-1200.0, -130.0)):
    """Two short Pendulum episodes as the case's Minari dataset ``dataset_id``."""

    def make(folder: Path) -> None:
        import minari  # noqa: PLC0415
        from minari.data_collector import EpisodeBuffer  # noqa: PLC0415

        rng = np.random.default_rng(0)
        episodes = [
            EpisodeBuffer(
                observations=rng.normal(size=(n + 1, 3)).astype(np.float32),
                actions=rng.uniform(-2, 2, (n, 1)).astype(np.float32),
                rewards=rng.normal(size=n),
                terminations=np.zeros(n, bool),
                truncations=np.r_[np.zeros(n - 1, bool), True],
            )
            for n in (5, 7)
        ]
        old = os.environ.get("MINARI_DATASETS_PATH")
        os.environ["MINARI_DATASETS_PATH"] = str(folder / "minari")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                minari.create_dataset_from_buffers(
                    dataset_id, episodes, env="Pendulum-v1", ref_min_score=scores[0],
                    ref_max_score=scores[1],
                )  # fmt: skip
        finally:
            if old is None:
                os.environ.pop("MINARI_DATASETS_PATH", None)
            else:
                os.environ["MINARI_DATASETS_PATH"] = old

    return make


def _cut(relative: str, keep: float):
    def make(folder: Path) -> None:
        path = folder / relative
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * keep)])

    return make


def _says(*words: str):
    def check(folder: Path, outcome: Outcome) -> str | None:
        missing = [w for w in words if w not in outcome.out]
        return f"output lacks {missing}: {outcome.out[-300:]!r}" if missing else None

    return check


def _run_files(base: Path) -> list[Case]:
    cases = []
    for where in ("actor", "critic", "normalizer"):
        for value in (math.nan, math.inf):
            prepare = then(run_copy(base), _tamper(where, value))
            label = f"checkpoint with {value} in its {where} (checksum recomputed)"
            names = ("run/checkpoint.msgpack",)
            cases += [
                Case(2, f"{label}: evaluate", EVAL, "refuse", prepare, names),
                Case(2, f"{label}: export-policy", EXPORT, "refuse", prepare, names),
                Case(2, f"{label}: resume", RESUME, "refuse", prepare, names),
                Case(2, f"{label}: results", RESULTS, "work", prepare,
                     check=listed(base, naming=("NaN/inf",), contradiction=True)),
            ]  # fmt: skip
    edits = {
        "max_action NaN": lambda c: {**c, "max_action": math.nan},
        "max_action inf": lambda c: {**c, "max_action": math.inf},
        "max_action 0": lambda c: {**c, "max_action": 0.0},
        "max_action -2": lambda c: {**c, "max_action": -2.0},
        "max_action 1 (Pendulum's is 2)": lambda c: {**c, "max_action": 1.0},
        "max_action 1e30": lambda c: {**c, "max_action": 1e30},
        "no agent key": lambda c: {k: v for k, v in c.items() if k != "agent"},
        "no dataset key": lambda c: {k: v for k, v in c.items() if k != "dataset"},
        "reference scores reversed": lambda c: {
            **c, "dataset": {**c["dataset"], "ref_min_score": 10.0, "ref_max_score": 1.0}},
    }  # fmt: skip
    for label, change in edits.items():
        prepare = then(run_copy(base), edit_json("run/config.json", change))
        names = ("run/config.json",)
        cases += [
            Case(2, f"config.json {label}: evaluate", EVAL, "refuse", prepare, names),
            Case(2, f"config.json {label}: export-policy", EXPORT, "refuse", prepare, names),
            Case(2, f"config.json {label}: resume", RESUME, "refuse", prepare, names),
        ]
    return cases


def _minari_folders() -> list[Case]:
    hurt = "test/pendulum/hurt-v0"
    metadata = f"minari/{hurt}/data/metadata.json"
    data_file = f"minari/{hurt}/data/main_data.hdf5"
    info = ["data", "info", f"minari:{hurt}"]
    damages = {
        "metadata.json gone": (write(metadata, None), ("metadata.json",)),
        "metadata.json junk": (write(metadata, "{junk"), ("metadata.json",)),
        "metadata.json of another id": (edit_json(metadata, lambda m: {**m, "dataset_id": "x-v0"}),
                                        ("metadata.json",)),
        "data file empty": (_cut(data_file, 0.0), ("main_data.hdf5",)),
        "data file cut in half": (_cut(data_file, 0.5), ("main_data.hdf5",)),
    }  # fmt: skip
    cases = []
    for label, (damage, names) in damages.items():
        prepare = then(_minari(hurt), damage)
        cases += [
            Case(3, f"Minari dataset, {label}: data info", info, "refuse", prepare, names,
                 env=MINARI),
            Case(3, f"Minari dataset, {label}: train", ["train", "--dataset", f"minari:{hurt}",
                 "--algo", "td3bc", "--dry-run"], "refuse", prepare, names, env=MINARI),
        ]  # fmt: skip
    data = npz("d.npz", env_id=np.asarray("Pendulum-v1"))
    export = ["data", "export", "d.npz", "--dataset-id"]
    for dataset_id in (
        "test/pendulum/mine",
        "mine",
        "test/pendulum/mine-v",
        "../outside-v0",
        "test/../../outside-v0",
        "test/./mine-v0",
        "~/mine-v0",
        "test//mine-v0",
    ):
        cases.append(Case(3, f"export id {dataset_id!r}", [*export, dataset_id], "refuse",
                          then(data, _minari(GOOD)), ("--dataset-id",), env=MINARI))  # fmt: skip
        cases.append(Case(3, f"load id {dataset_id!r}", ["data", "info", f"minari:{dataset_id}"],
                          "refuse", _minari(GOOD), (dataset_id,), env=MINARI))  # fmt: skip
    broken = then(
        _minari(GOOD),
        lambda folder: (folder / "minari/eabc/pendulum/mine/data").mkdir(parents=True),
        write("minari/eabc/pendulum/mine/data/metadata.json",
              json.dumps({"dataset_id": "eabc/pendulum/mine"})),
    )  # fmt: skip
    cases += [
        Case(3, "a broken Minari folder beside: data info of an intact one",
             ["data", "info", f"minari:{GOOD}"], "work", broken, env=MINARI,
             check=_says('"transitions": 12')),
        Case(3, "a broken Minari folder beside: export", [*export, "test/pendulum/new-v0"],
             "work", then(broken, data), env=MINARI, check=_says("test/pendulum/new-v0")),
        Case(3, "export over an existing id without --force", [*export, GOOD], "refuse",
             then(data, _minari(GOOD)), (GOOD,), env=MINARI),
        Case(3, "a file of timeouts only: data info", ["data", "info", "d.npz"], "refuse",
             npz("d.npz", env_id=np.asarray("Pendulum-v1"), timeouts=np.ones(40, bool)),
             ("timeouts",)),
    ]  # fmt: skip
    return cases


def _late(base: Path) -> list[Case]:
    cases = []
    for low, high in ((3234.3, -20.3), (1.0, 0.0)):
        prepare = npz("d.npz", env_id=np.asarray("Pendulum-v1"), ref_min_score=np.asarray(low),
                      ref_max_score=np.asarray(high))  # fmt: skip
        label = f"reference scores reversed ({low} > {high})"
        cases += [
            Case(4, f"{label}: train", ["train", "--dataset", "d.npz", "--algo", "td3bc",
                 "--run-dir", "r", *SCHEDULE], "refuse", prepare, ("ref_min_score",)),
            Case(4, f"{label}: data info", ["data", "info", "d.npz"], "refuse", prepare,
                 ("ref_min_score",)),
        ]  # fmt: skip
    reversed_id = "test/pendulum/reversed-v0"
    cases.append(Case(4, "Minari reference scores reversed: data info",
                      ["data", "info", f"minari:{reversed_id}"], "refuse",
                      _minari(reversed_id, (-130.0, -1200.0)), ("ref_min_score",), env=MINARI))  # fmt: skip
    long = f"{'d' * 236}.npz"
    data = then(npz("good.npz", env_id=np.asarray("Pendulum-v1")),
                npz(long, env_id=np.asarray("Pendulum-v1")))  # fmt: skip
    sweep = ["sweep", "--algos", "td3bc", "--seeds", "0", "--steps", "200", "--root", "root"]
    for dry in ([], ["--dry-run"]):
        word = "dry run" if dry else "sweep"
        cases += [
            Case(4, f"a dataset name too long for a run directory: {word}",
                 [*sweep, "--datasets", "good.npz", long, *dry], "refuse", data, (long,)),
            Case(4, f"a missing minari: dataset: {word}",
                 [*sweep, "--datasets", "good.npz", "minari:test/pendulum/absent-v0", *dry],
                 "refuse", data, ("absent-v0",), env=MINARI),
        ]  # fmt: skip
    for label, content in (("empty", b""), ("text", b"junk"), ("a directory", None)):
        path = "cache/datasets/hopper-random.hdf5"

        def prepare(folder: Path, content=content, path=path) -> None:
            (folder / path).parent.mkdir(parents=True)
            if content is None:
                (folder / path).mkdir()
            else:
                (folder / path).write_bytes(content)

        cases.append(Case(4, f"a junk dataset in the cache ({label}): data list",
                          ["data", "list"], "work", prepare, env={"EABC_CACHE_DIR": "./cache"},
                          check=_says("unreadable", "walker2d-random")))  # fmt: skip
    return cases


def tampered(base: Path) -> list[Case]:
    """Every case of this module."""
    return [*_run_files(base), *_minari_folders(), *_late(base)]
