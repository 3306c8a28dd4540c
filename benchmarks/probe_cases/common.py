"""What the probe's cases share: the tiny runs and datasets they copy, and building blocks.

Every case runs in a directory of its own: ``run`` is a copy of one of the tiny runs (``A``
unless it says otherwise), ``.`` the sweep root that holds it, ``d.npz`` and the like a dataset
file the case wrote. The runs (:data:`RUNS`) are TD3+BC and BC on 40 Pendulum-shaped transitions,
200 steps with an evaluation of one episode every 100.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sqlite3
from pathlib import Path

import numpy as np

from probe_cases.case import Outcome

RUNS = {
    "A": ("td3bc", 0, "tiny.npz", "32,32", 1),
    "B": ("td3bc", 1, "tiny.npz", "32,32", 1),  # another seed
    "C": ("td3bc", 0, "tiny2.npz", "32,32", 1),  # other data of the same shapes
    "D": ("bc", 0, "tiny.npz", "32,32", 1),  # another algorithm
    "E": ("td3bc", 0, "tiny.npz", "16,16", 1),  # other network sizes
    "F": ("td3bc", 0, "tiny.npz", "32,32", 2),  # another setting, the same shapes
    "R": ("td3bc", 0, "tiny_ref.npz", "32,32", 1),  # data with reference scores
}
"""name: (algorithm, seed, dataset, hidden sizes, evaluation episodes)."""
SCHEDULE = ["--steps", "200", "--log-interval", "100", "--eval-interval", "100",
            "--checkpoint-interval", "100", "--no-progress"]  # fmt: skip
EVAL = ["evaluate", "run", "--episodes", "1"]
RESUME = ["train", "--resume", "run", "--no-progress"]
EXPORT = ["export-policy", "run", "--onnx", "policy.onnx"]
RESULTS = ["results", "."]
UNUSABLE = ("broken", "damaged")


def write_data(base: Path) -> None:
    """tiny.npz, tiny2.npz (its rewards + 1: same shapes, other content) and tiny_ref.npz (with
    reference scores)."""
    rng = np.random.default_rng(0)
    arrays = {
        "observations": rng.normal(size=(40, 3)).astype(np.float32),
        "actions": rng.uniform(-1, 1, (40, 1)).astype(np.float32),
        "rewards": rng.normal(size=40).astype(np.float32),
        "terminals": np.zeros(40, bool),
        "env_id": np.asarray("Pendulum-v1"),
    }
    np.savez(base / "tiny.npz", **arrays)
    np.savez(base / "tiny2.npz", **{**arrays, "rewards": arrays["rewards"] + 1})
    np.savez(base / "tiny_ref.npz", **arrays, ref_min_score=np.asarray(-1200.0),
             ref_max_score=np.asarray(-130.0))  # fmt: skip


def make_base(base: Path, run) -> None:
    """The datasets and the tiny runs (:data:`RUNS`), trained by ``run(argv, folder)``."""
    (base / "runs").mkdir(parents=True, exist_ok=True)
    if not (base / "tiny_ref.npz").exists():
        write_data(base)
    for name, (algo, seed, data, hidden, episodes) in RUNS.items():
        if (base / "runs" / name / "summary.json").exists():
            continue
        shutil.rmtree(base / "runs" / name, ignore_errors=True)
        argv = ["train", "--dataset", str(base / data), "--algo", algo, "--seed", str(seed),
                "--eval-episodes", str(episodes), "--set", f"hidden_dims={hidden}",
                "--run-dir", f"runs/{name}", *SCHEDULE]  # fmt: skip
        outcome = run(argv, base)
        if outcome.code != 0:
            raise SystemExit(f"making run {name} failed: {outcome.err[-2000:]}")


# ----------------------------------------------------------------------------------------------
# Building blocks: what a case's directory holds, and checks of what a command left


def run_copy(base: Path, name: str = "A", dest: str = "run"):
    return lambda folder: shutil.copytree(base / "runs" / name, folder / dest, symlinks=True)


def then(*steps):
    """The preparations ``steps`` one after the other."""

    def prepare(folder: Path) -> None:
        for step in steps:
            step(folder)

    return prepare


def original(base: Path, name: str = "A") -> dict:
    return json.loads((base / "runs" / name / "summary.json").read_text())


def stored_rows(folder: Path) -> list[dict]:
    """The runs table `eabc results` wrote (``results.sqlite``)."""
    path = folder / "results.sqlite"
    if not path.exists():
        return []
    with sqlite3.connect(path) as db:
        db.row_factory = sqlite3.Row
        rows = [dict(r) for r in db.execute("SELECT run_id, status, steps, final_return, config "
                                             "FROM runs")]  # fmt: skip
    db.close()
    return rows


def listed(base: Path, name: str = "A", naming: tuple[str, ...] = (), contradiction=False):
    """A check of `eabc results`: the run is listed, as broken or damaged for a reason naming
    one of ``naming``, or (unless its files ``contradiction``) with the very numbers of the
    original run. Never dropped, never other numbers."""

    def check(folder: Path, outcome: Outcome) -> str | None:
        rows = stored_rows(folder)
        if len(rows) != 1:
            return f"{len(rows)} runs listed where the root holds one: {outcome.out[-200:]!r}"
        row = rows[0]
        if row["status"] in UNUSABLE:
            if naming and not any(n in (row["config"] or "") for n in naming):
                return f"{row['status']} for a reason naming none of {naming}: {row['config']}"
            return None
        if contradiction:  # the run's files contradict each other: that must be said
            return f"status {row['status']} although the run's files contradict each other"
        want = original(base, name)
        same = row["steps"] == want["steps"] and math.isclose(
            row["final_return"] or math.nan, want["final_return"], rel_tol=1e-9
        )
        return (
            None
            if same
            else (
                f"listed as {row['status']} with steps {row['steps']}, final return "
                f"{row['final_return']} where the run has {want['steps']}, {want['final_return']}"
            )
        )

    return check


def intact_after_resume(base: Path, name: str = "A"):
    """A check of `eabc train --resume` on a finished run: nothing lost or retrained, the files
    agree again (the run reads as done with its own final return)."""

    def check(folder: Path, outcome: Outcome) -> str | None:
        from eabc.experiments import results  # noqa: PLC0415

        row, _ = results.read_run(folder / "run")
        want = original(base, name)
        if row["status"] != "done":
            return f"after resume the run is {row['status']}: {row['config']}"[:300]
        if row["steps"] != want["steps"] or not math.isclose(
            row["final_return"], want["final_return"], rel_tol=1e-9
        ):
            return f"after resume: steps {row['steps']}, final return {row['final_return']}"
        return None

    return check


def unchanged_and_says(*words: str):
    """A check of a read-only command: it printed each of ``words``."""

    def check(folder: Path, outcome: Outcome) -> str | None:
        missing = [w for w in words if w not in outcome.out + outcome.err]
        return f"output lacks {missing}: {outcome.out[-200:]!r}" if missing else None

    return check


def fifo(relative: str):
    def make(folder: Path) -> None:
        path = folder / relative
        path.unlink(missing_ok=True) if not path.is_dir() else shutil.rmtree(path)
        os.mkfifo(path)

    return make


def write(relative: str, content: bytes | str | None):
    """Write (or, with None, delete) a file or directory of the case."""

    def make(folder: Path) -> None:
        path = folder / relative
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)
        if content is not None:
            path.write_bytes(content.encode() if isinstance(content, str) else content)

    return make


def edit(relative: str, change):
    """Replace the text of a file of the case by ``change(text)``."""

    def make(folder: Path) -> None:
        path = folder / relative
        path.write_text(change(path.read_text()))

    return make


def edit_json(relative: str, change):
    return edit(relative, lambda text: json.dumps(change(json.loads(text))))


def copy_from(base: Path, name: str, file: str):
    """Put run ``name``'s ``file`` into the case's run."""
    return lambda folder: shutil.copy(base / "runs" / name / file, folder / "run" / file)


def transitions(rows: int = 40, **changes) -> dict:
    """Pendulum-shaped arrays of ``rows`` transitions, with ``changes`` (None removes a key)."""
    rng = np.random.default_rng(1)
    arrays = {
        "observations": rng.normal(size=(rows, 3)).astype(np.float32),
        "actions": rng.uniform(-1, 1, (rows, 1)).astype(np.float32),
        "rewards": rng.normal(size=rows).astype(np.float32),
        "terminals": np.zeros(rows, bool),
    }
    return {k: v for k, v in {**arrays, **changes}.items() if v is not None}


def npz(name: str, **changes):
    """Write :func:`transitions` with ``changes`` as the case's ``name``."""

    def make(folder: Path) -> None:
        np.savez(folder / name, **transitions(**changes))

    return make
