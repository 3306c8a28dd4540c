"""A run's config.json is checked by one schema wherever it is read (eabc.training.run_config).

A hand-edited file ends in one line that names the file, the key and what to do: resume, evaluate
and export-policy refuse, ``eabc results`` lists the run as broken with that reason (never drops
it), and nothing on disk changes. Files of earlier versions (no run id, no data fingerprint, agent
settings a later version added or removed) keep loading. The run is a TD3+BC run's initial
checkpoint on 40 transitions: no training, no compilation beyond the agent's initialisation.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil

import numpy as np
import pytest

from eabc import load_policy
from eabc.cli import main
from eabc.experiments import results
from eabc.training import checkpoint, lifecycle
from eabc.training.config import TrainConfig
from eabc.training.run_config import ConfigError


@pytest.fixture(scope="module")
def started(tmp_path_factory):
    """A run directory as `eabc train` leaves it after its first checkpoint (the initial state)."""
    root = tmp_path_factory.mktemp("started")
    rng = np.random.default_rng(0)
    columns = {"observations": rng.normal(size=(40, 3)), "actions": rng.uniform(-1, 1, (40, 1)),
               "rewards": rng.normal(size=40)}  # fmt: skip
    np.savez(root / "tiny.npz", **{k: v.astype(np.float32) for k, v in columns.items()},
             terminals=np.zeros(40, bool))  # fmt: skip
    config = TrainConfig(dataset=str(root / "tiny.npz"), algo="td3bc", steps=200,
                         log_interval=100, eval_interval=100, checkpoint_interval=100,
                         eval_episodes=1, env="Pendulum-v1")  # fmt: skip
    run = lifecycle.start(config, root / "run", {"hidden_dims": (32, 32)})
    run.lock.release()
    checkpoint.save(run.run_dir, run.state, run.algorithm.state_layout, run.identity)
    return root / "run"


def snapshot(folder) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != results.DATABASE
    }


def edited(started, tmp_path, edit):
    """A copy of the run under ``tmp_path/root`` with its config.json as ``edit`` makes it."""
    run_dir = tmp_path / "root" / "run"
    shutil.copytree(started, run_dir)
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps(edit(config)))
    return run_dir


def without(config, *keys):
    """``config`` without the key at the dotted path ``keys``."""
    config = json.loads(json.dumps(config))
    *parents, last = keys
    inner = config
    for key in parents:
        inner = inner[key]
    del inner[last]
    return config


def setting(config, section, key, value):
    return {**config, section: {**config[section], key: value}}


HAND_EDITS = {
    "empty": (lambda c: {}, "train is missing"),
    "missing steps": (lambda c: without(c, "train", "steps"), "train.steps is missing"),
    "missing algo": (lambda c: without(c, "train", "algo"), "train.algo is missing"),
    "extra key": (lambda c: {**c, "notes": "mine"}, "notes is not a key"),
    "extra train key": (lambda c: setting(c, "train", "lr", 1e-3), "train.lr is not a key"),
    "steps as text": (
        lambda c: setting(c, "train", "steps", "200"),
        "train.steps must be an integer .*'200'",
    ),
    "seed as text": (
        lambda c: setting(c, "train", "seed", "zero"),
        "train.seed must be an integer .*'zero'",
    ),
    "seed negative": (
        lambda c: setting(c, "train", "seed", -1),
        "train.seed must be an integer .*-1",
    ),
    "steps as bool": (
        lambda c: setting(c, "train", "steps", True),
        "train.steps must be an integer .*True",
    ),
    "algo unknown": (
        lambda c: setting(c, "train", "algo", "td4"),
        "train.algo: unknown algorithm 'td4'",
    ),
    "intervals": (
        lambda c: setting(c, "train", "eval_interval", 150),
        "train.eval_interval must be a multiple",
    ),
    "train a list": (lambda c: {**c, "train": [1, 2]}, "train: input should be a valid dict"),
    "dataset a string": (lambda c: {**c, "dataset": "tiny"}, "dataset: input should be a valid"),
    "size as text": (lambda c: setting(c, "dataset", "size", "39"), "dataset.size: .*'39'"),
    "agent a string": (lambda c: {**c, "agent": "x"}, "agent: input should be a valid dict"),
    "agent setting": (
        lambda c: setting(c, "agent", "num_critics", "two"),
        "agent: td3bc setting num_critics must be an integer .*, got 'two'",
    ),
    "max_action as text": (lambda c: {**c, "max_action": "2"}, "max_action: .*'2'"),
}


@pytest.mark.parametrize("case", HAND_EDITS)
def test_a_hand_edited_config_is_refused_in_one_line_naming_the_key(started, tmp_path, case):
    """Before: KeyError and TypeError tracebacks, a run resumed as 1,000,000 steps when its
    ``steps`` was deleted, ``eabc results`` dropping the run or crashing on it."""
    edit, why = HAND_EDITS[case]
    run_dir = edited(started, tmp_path, edit)
    before = snapshot(tmp_path)
    for argv in (
        ["train", "--resume", str(run_dir), "--no-progress"],
        ["evaluate", str(run_dir)],
        ["export-policy", str(run_dir), "--onnx", str(tmp_path / "policy.onnx")],
    ):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        message = str(exit_.value.code)
        assert message.startswith(f"error: {run_dir / 'config.json'}"), (argv[0], message)
        assert "\n" not in message
        assert re.search(why, message), (argv[0], message)
    with pytest.raises(ConfigError, match=why):
        load_policy(run_dir)
    runs, _ = results.collect(tmp_path / "root", write=False)  # a sweep root: listed, not dropped
    assert list(runs["status"]) == ["broken"]
    assert re.search(why, runs["config"][0]) and "config.json" in runs["config"][0]
    assert snapshot(tmp_path) == before


def test_configs_of_earlier_versions_keep_loading(started, tmp_path, capsys):
    """No run id, no data fingerprint (before either was recorded), an agent setting this
    version dropped and one it added (the preset's value), a checkpoint without an identity."""

    def old(config):
        config = without(without(config, "run_id"), "dataset", "fingerprint")
        config = without(config, "agent", "critic_layer_norm")
        return setting(config, "agent", "a_setting_since_removed", 3)

    run_dir = edited(started, tmp_path, old)
    raw = checkpoint.load_raw(run_dir)
    checkpoint.save(run_dir, {k: v for k, v in raw.items() if k != checkpoint.IDENTITY})
    assert lifecycle.resume(run_dir, lock=False).step == 0
    load_policy(run_dir)
    assert results.read_run(run_dir)[0]["status"] == "partial"


def test_a_missing_train_setting_reads_as_its_default_and_a_missing_key_is_named(started, tmp_path):
    """A train setting left out reads as TrainConfig's default; where the checkpoint records
    the run's identity, whose settings hash then differs, the refusal names the absent key. A
    deleted run_id is named with the value to put back; a missing max_action stops only the
    policy's readers."""
    run_dir = edited(started, tmp_path, lambda c: without(c, "train", "batch_size"))
    with pytest.raises(checkpoint.CheckpointError, match="lacks train.batch_size: put back"):
        lifecycle.resume(run_dir, lock=False)
    raw = checkpoint.load_raw(run_dir)  # an older eabc's checkpoint: nothing to compare with
    checkpoint.save(run_dir, {k: v for k, v in raw.items() if k != checkpoint.IDENTITY})
    assert lifecycle.resume(run_dir, lock=False).config.batch_size == 256  # td3bc's default

    shutil.rmtree(tmp_path / "root")
    run_id = json.loads((started / "config.json").read_text())["run_id"]
    run_dir = edited(started, tmp_path, lambda c: without(c, "run_id"))
    with pytest.raises(SystemExit, match=f'no run_id .* put "run_id": "{run_id}" back'):
        main(["evaluate", str(run_dir)])

    shutil.rmtree(tmp_path / "root")
    run_dir = edited(started, tmp_path, lambda c: without(c, "max_action"))
    assert lifecycle.resume(run_dir, lock=False).step == 0
    with pytest.raises(ConfigError, match="config.json: max_action is missing"):
        load_policy(run_dir)
