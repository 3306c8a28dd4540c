"""Which run a checkpoint belongs to, so that a file from another run is never used as this one's.

A run gets a random id when it starts (``run_id`` in ``config.json``). Every checkpoint records,
inside its checksummed payload, the identity of the run that wrote it: that id, the algorithm,
the seed, a hash of the resolved settings, the dataset's name and its content fingerprint. Every
reader (resume, evaluate, ``load_policy``, the ONNX export, ``eabc results``) compares it with the
identity the run directory's ``config.json`` gives and refuses a mismatch in one line naming both:
another run's checkpoint copied in, or another run's ``config.json`` beside this checkpoint, is
caught even when every shape matches (another seed, other data of the same dimensions).

Checkpoints from before the identity (none recorded) still load, with a one-line warning.
"""

from __future__ import annotations

import hashlib
import json
import sys
import uuid
from pathlib import Path
from typing import Any

from eabc.training import run_config
from eabc.training.checkpoint import CHECKPOINT, CONFIG, IDENTITY, CheckpointError, save_json

FIELDS = ("run_id", "algo", "seed", "settings", "dataset", "fingerprint")
"""What an identity holds; two identities must agree in every one."""
LOCATION = ("seed", "steps", "dataset", "cache_dir")
"""Train options left out of the settings hash: the seed and the data are fields of their own (the
data by content, not by path), and more steps extend a run rather than make another."""


def new_run_id() -> str:
    """A random id for a new run: 16 hex digits, unique for every practical number of runs."""
    return uuid.uuid4().hex[:16]


def of_config(config: dict) -> dict[str, Any]:
    """The identity of the run whose ``config.json`` is ``config`` (``run_id`` None for a run
    started before runs had ids). The settings hash is of the train settings as the file holds
    them, not filled with defaults: a setting a later version adds leaves older runs' hashes as
    they were."""
    train, dataset = config.get("train", {}), config.get("dataset", {})
    settings = {
        "algo": train.get("algo"),
        "train": {k: v for k, v in train.items() if k not in LOCATION},
        "agent": config.get("agent", {}),
    }
    text = json.dumps(settings, sort_keys=True, separators=(",", ":"))
    return {
        "run_id": config.get("run_id"),
        "algo": train.get("algo"),
        "seed": train.get("seed"),
        "settings": hashlib.sha256(text.encode()).hexdigest()[:16],
        "dataset": dataset.get("name", train.get("dataset")),
        "fingerprint": dataset.get("fingerprint"),
    }


def of_run(run_dir: Path, saved: dict) -> dict[str, Any]:
    """The run's identity, giving a run from before run ids one (in its config.json) now."""
    if not saved.get("run_id"):
        saved = {"run_id": new_run_id(), **saved}
        save_json(run_dir / CONFIG, saved)
    return of_config(saved)


def checked(raw: dict, run_dir: Path, config: dict, warn: bool = True) -> dict:
    """The checkpoint payload ``raw`` without its identity, after comparing that identity with
    ``config``'s (:class:`CheckpointError` naming both when they differ). A payload without one
    (written before identities were recorded) is accepted, with a warning when ``warn``."""
    recorded = raw.get(IDENTITY)
    rest = {k: v for k, v in raw.items() if k != IDENTITY}
    if recorded is None:
        if warn:
            print(
                f"warning: {Path(run_dir) / CHECKPOINT} does not record which run wrote it (saved "
                f"by an older eabc), so it is used as {Path(run_dir) / CONFIG}'s run unchecked",
                file=sys.stderr,
                flush=True,
            )
        return rest
    expected = of_config(config)
    differ = [f for f in FIELDS if _text(recorded.get(f)) != _text(expected[f])]
    if differ == ["run_id"] and not expected["run_id"]:  # the key alone deleted by hand
        raise CheckpointError(
            f"{Path(run_dir) / CONFIG} has no run_id but {Path(run_dir) / CHECKPOINT} belongs to "
            f"run {recorded.get('run_id')}, which agrees with it in everything else: put "
            f'"run_id": "{recorded.get("run_id")}" back into config.json'
        )
    if differ:
        absent = [k for k in run_config.train_model().model_fields if k not in config["train"]]
        lacks = (
            f" ({Path(run_dir) / CONFIG} lacks train.{', train.'.join(absent)}: put back what "
            "the run was started with)"
            if "settings" in differ and absent
            else ""
        )
        raise CheckpointError(
            f"{Path(run_dir) / CHECKPOINT} belongs to run {describe(recorded)} but "
            f"{Path(run_dir) / CONFIG} is run {describe(expected)} (they differ in "
            f"{', '.join(differ)}){lacks}: a checkpoint is used only beside its own run's "
            "config.json; put this run's own files back, or delete the checkpoint and resume with --restart "
            "to train the run config.json describes again from step 0"
        )
    return rest


def describe(identity: dict) -> str:
    """``ID (ALGO, seed S, DATASET, settings H, data F)``, the hashes shortened."""
    run_id = identity.get("run_id") or "without an id"
    fingerprint = str(identity.get("fingerprint") or "?")[:12]
    return (
        f"{run_id} ({identity.get('algo')}, seed {identity.get('seed')}, "
        f"{identity.get('dataset')}, settings {str(identity.get('settings'))[:8]}, "
        f"data {fingerprint})"
    )


def _text(value) -> str:
    """A field compared as text, so that one seed as an int and as a NumPy int agree."""
    return "" if value is None else str(value)
