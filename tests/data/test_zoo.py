"""Datasets from behaviour policies: a zoo built from a short SAC run, and the D4RL recipes."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from eabc import cli, networks
from eabc.data import generate, hdf5_writer, zoo
from eabc.data.loaders import load_file
from eabc.training import online, zoo_build


@pytest.fixture(scope="module")
def tiny_zoo(tmp_path_factory):
    """A hopper zoo from a 3000-step SAC run (snapshots every 500 steps); not a good policy, but
    every mechanism of the real zoo: card, medium/expert choice, replay snapshots. Batches of 64,
    not 256: the SAC updates were most of the module's time, and the card comes out the same
    (medium at step 1000, expert at 3000)."""
    root = tmp_path_factory.mktemp("zoo")
    config = online.SACTrainConfig(
        env="hopper",
        steps=3000,
        start_steps=1000,
        update_every=50,
        batch_size=64,
        eval_interval=1000,
        snapshot_interval=500,
        checkpoint_interval=1000,
        eval_episodes=1,
    )
    run = online.start_sac(config, root / "run")
    online.train_sac(run, progress=False)
    card = zoo_build.build(
        root / "run", "hopper", root / "zoo", episodes=2, medium_return=0.0, log=print
    )
    return root / "zoo", card


def test_zoo_card_and_files(tiny_zoo):
    root, card = tiny_zoo
    assert card == json.loads((root / "hopper" / zoo.CARD).read_text())
    assert card["training_steps"] == 3000
    assert card["expert"]["step"] in range(1000, 3001, 500)
    medium = card["medium"]["step"]
    assert card["replay"]["snapshots"] == list(range(500, medium, 500))
    for name in (
        "medium",
        "expert",
        *[f"replay/actor_{s:08d}" for s in card["replay"]["snapshots"]],
    ):
        with np.load(zoo.policy_path("hopper", name, root), allow_pickle=False) as f:
            assert {f[k].dtype for k in f.files} == {np.dtype(np.float16)}
    phases = zoo.replay_schedule("hopper", root)
    assert phases[0] == (0, 500, None) and phases[-1][1] == medium
    assert all(a[1] == b[0] for a, b in zip(phases, phases[1:])), "phases must tile training"


def test_policy_dataset_layout_boundaries_and_determinism(tiny_zoo, tmp_path):
    root, card = tiny_zoo
    path = generate.make("hopper-medium", tmp_path / "a.hdf5", seed=3, size=2500, zoo_root=root)
    again = generate.make("hopper-medium", tmp_path / "b.hdf5", seed=3, size=2500, zoo_root=root)
    other = generate.make("hopper-medium", tmp_path / "c.hdf5", seed=4, size=2500, zoo_root=root)
    with h5py.File(path) as f, h5py.File(again) as g, h5py.File(other) as h:
        assert set(f.keys()) == set(hdf5_writer.ARRAYS)
        for key in hdf5_writer.ARRAYS:
            expected = bool if key in ("terminals", "timeouts") else np.float32
            assert f[key].dtype == expected and len(f[key]) == 2500
            np.testing.assert_array_equal(f[key][:], g[key][:])
        assert not np.array_equal(f["actions"][:], h["actions"][:])
        metadata = json.loads(f.attrs["metadata"])
    assert metadata["seed"] == 3 and metadata["policy"]["step"] == card["medium"]["step"]
    data = load_file(path)
    assert not (data.terminals & data.timeouts).any()
    ends = np.flatnonzero(data.terminals | data.timeouts)
    assert ends[-1] == data.size - 1
    # Within an episode the next observation is the following observation; across ends it is not.
    inside = np.setdiff1d(np.arange(data.size - 1), ends)
    np.testing.assert_array_equal(data.next_observations[inside], data.observations[inside + 1])
    # Actions are sampled, not the deterministic mean: the dataset is not a deterministic rollout.
    mean_action = zoo.numpy_networks.numpy_actor(
        zoo.load_actor(zoo.policy_path("hopper", "medium", root)), 1.0, gaussian=True
    )
    assert np.abs(mean_action(data.observations[:100]) - data.actions[:100]).mean() > 1e-3


def test_medium_replay_follows_the_training_phases(tiny_zoo, tmp_path):
    root, card = tiny_zoo
    size = 3000
    path = generate.make(
        "hopper-medium-replay", tmp_path / "mr.hdf5", seed=0, size=size, zoo_root=root
    )
    data = load_file(path)
    assert data.size == size
    phases = data.metadata["phases"]
    assert sum(p["transitions"] for p in phases) == size
    medium = card["medium"]["step"]
    for p in phases:  # each phase's share is its share of the training steps up to medium
        start, stop = p["train_steps"]
        assert abs(p["transitions"] - size * (stop - start) / medium) <= 1
    assert phases[0]["policy"] == "uniform random"


def test_medium_expert_is_medium_then_expert(tiny_zoo, tmp_path):
    root, _ = tiny_zoo
    me = load_file(
        generate.make(
            "hopper-medium-expert",
            tmp_path / "hopper-medium-expert.hdf5",
            seed=1,
            size=2000,
            zoo_root=root,
        )
    )
    medium = load_file(
        generate.make("hopper-medium", tmp_path / "m.hdf5", seed=1, size=1000, zoo_root=root)
    )
    expert = load_file(
        generate.make("hopper-expert", tmp_path / "e.hdf5", seed=1, size=1000, zoo_root=root)
    )
    np.testing.assert_array_equal(
        me.observations, np.concatenate([medium.observations, expert.observations])
    )
    np.testing.assert_array_equal(me.actions, np.concatenate([medium.actions, expert.actions]))


def test_packed_run_resumes_without_its_replay_buffer(tiny_zoo, tmp_path):
    run_dir = tiny_zoo[0].parent / "run"
    packed = zoo_build.pack(run_dir, tmp_path / "packed")
    assert not (packed / online.REPLAY).exists()
    snapshots = sorted((packed / online.SNAPSHOTS).glob("actor_*.npz"))
    assert [p.name for p in snapshots] == sorted(
        p.name for p in (run_dir / online.SNAPSHOTS).glob("actor_*.npz")
    )
    # Half-size snapshots, and build() reads them exactly as it reads the float32 originals.
    for name in (snapshots[0].name, snapshots[-1].name):
        original = zoo.rounded(zoo.load_actor(run_dir / online.SNAPSHOTS / name))
        for k, v in zoo.load_actor(packed / online.SNAPSHOTS / name).items():
            np.testing.assert_array_equal(v, original[k])
    # Continue the packed run past its end: it resumes from the checkpoint's networks, refills
    # the buffer with its current policy (no gradient or training steps), and trains on.
    config = json.loads((packed / "config.json").read_text())
    config["sac"] |= {"steps": 4500, "refill_steps": 2000}
    (packed / "config.json").write_text(json.dumps(config))
    run = online.resume_sac(packed)
    assert run.state["step"] == 3000 and run.buffer.size == 0
    episodes = len(run.state["episodes"])
    actor, rng_state = (
        {k: np.array(v) for k, v in run.state["agent"].actor.items()},
        run.state["rng"],
    )
    before = actor["w0"]
    np.testing.assert_array_equal(before, online.resume_sac(run_dir).state["agent"].actor["w0"])
    summary = online.train_sac(run, progress=False)
    assert summary["steps"] == 4500
    assert run.buffer.size == 2000 + 1500
    # The refill's actions are the resumed policy's samples, drawn with the checkpoint's random
    # state: replaying the sampler on the stored (float32-rounded) observations reproduces them.
    rng = np.random.default_rng()
    rng.bit_generator.state = json.loads(rng_state)
    sampler = networks.numpy_gaussian_sampler(actor, run.max_action)
    data = run.buffer.data
    for i in range(20):
        expected = sampler(data["observations"][i], rng)
        np.testing.assert_allclose(data["actions"][i], expected, atol=1e-5)
    # The refill's episodes are not training episodes: only 1,500 more steps' worth were logged.
    assert sum(e[2] for e in run.state["episodes"][episodes:]) <= 1500
    assert not np.array_equal(before, np.asarray(run.state["agent"].actor["w0"]))


def test_refill_during_the_warm_up_uses_uniform_actions(tiny_zoo, tmp_path):
    """A run packed before ``start_steps`` refills with what it would have collected: noise."""
    packed = zoo_build.pack(tiny_zoo[0].parent / "run", tmp_path / "packed")
    config = json.loads((packed / "config.json").read_text())
    config["sac"]["start_steps"] = 5000
    (packed / "config.json").write_text(json.dumps(config))
    run = online.resume_sac(packed)
    online.refill_buffer(run, None, np.random.default_rng(7), 50, progress=False)
    low, high = run.env.action_space.low, run.env.action_space.high
    rng = np.random.default_rng(7)
    expected = [rng.uniform(low, high).astype(np.float32) for _ in range(50)]
    np.testing.assert_array_equal(run.buffer.data["actions"][:50], expected)
    assert run.buffer.size == 50 and run.state["step"] == 3000


def test_cached_dataset_from_an_older_zoo_is_noticed(tiny_zoo, tmp_path, monkeypatch):
    root = tmp_path / "zoo"
    shutil.copytree(tiny_zoo[0], root)
    medium = generate.make(
        "hopper-medium", tmp_path / "hopper-medium.hdf5", size=300, zoo_root=root
    )
    expert = generate.make(
        "hopper-expert", tmp_path / "hopper-expert.hdf5", size=300, zoo_root=root
    )
    assert generate.is_current(medium, "hopper-medium", root)
    assert generate.is_current(expert, "hopper-expert", root)
    # A retrained medium policy makes the cached medium dataset stale, and only that one.
    actor = zoo.load_actor(zoo.policy_path("hopper", "medium", root))
    zoo.save_actor(
        zoo.policy_path("hopper", "medium", root), {k: v + 0.01 for k, v in actor.items()}
    )
    assert not generate.is_current(medium, "hopper-medium", root)
    assert generate.is_current(expert, "hopper-expert", root)
    assert not generate.is_current(tmp_path / "missing.hdf5", "hopper-expert", root)
    # So does a dataset made by an older version of the rollout code from the same policy.
    older = shutil.copy(expert, tmp_path / "older.hdf5")
    with h5py.File(older, "r+") as f:
        metadata = json.loads(f.attrs["metadata"])
        f.attrs["metadata"] = json.dumps({**metadata, "version": generate.FORMAT_VERSION - 1})
    assert not generate.is_current(older, "hopper-expert", root)
    # `eabc data make` remakes the stale file and keeps the current one.
    cache = tmp_path / "cache"
    (cache / "datasets").mkdir(parents=True)
    shutil.copy(medium, generate.dataset_path("hopper-medium", cache))
    shutil.copy(expert, generate.dataset_path("hopper-expert", cache))
    expert_bytes = generate.dataset_path("hopper-expert", cache).read_bytes()
    monkeypatch.setenv("EABC_ZOO_DIR", str(root))
    for name in ("hopper-medium", "hopper-expert"):
        cli.main(["data", "make", name, "--size", "300", "--cache-dir", str(cache)])
    assert generate.is_current(generate.dataset_path("hopper-medium", cache), "hopper-medium")
    assert generate.dataset_path("hopper-expert", cache).read_bytes() == expert_bytes


SHIPPED_ROOT = Path(zoo.__file__).parent.parent / "zoo"


@pytest.mark.parametrize("env", ["hopper", "halfcheetah", "walker2d"])
@pytest.mark.parametrize("which", ["medium", "expert"])
def test_shipped_policy_scores_within_its_card_range(env, which):
    """The package's medium and expert policies, rolled out afresh (other seeds, 3 episodes of
    sampled actions), score within their card's mean +- 2 std (with a floor for near-zero spread).

    The median of the 3 episodes is compared: a good hopper falls in about one episode of ten or
    twenty, which the card's 10 episodes may not have shown; a wrong or corrupted policy file
    (medium and expert differ by over 1,000) still fails.
    """
    card = zoo.card(env, SHIPPED_ROOT)
    entry = card[which]
    actor = zoo.load_actor(zoo.policy_path(env, which, SHIPPED_ROOT))
    env_id = zoo.tasks.ENVS[env].env_id
    seed = card["evaluation_seed"] + 1
    returns = [zoo_build.stochastic_return(env_id, actor, 1, seed + i)[0] for i in range(3)]
    tolerance = max(2 * entry["return_std"], 0.05 * abs(entry["return_mean"]), 20.0)
    assert abs(np.median(returns) - entry["return_mean"]) <= tolerance, (returns, entry)


def test_rebuilding_the_zoo_keeps_its_medium_policy(tiny_zoo, tmp_path):
    """A rebuild after more training moves the expert only: the shipped medium policy, its replay
    snapshots and so the medium datasets' fingerprints stay as they were."""
    root, card = tiny_zoo
    run_dir = root.parent / "run"
    zoo_copy = tmp_path / "zoo"
    shutil.copytree(root, zoo_copy)
    before = {k: zoo.fingerprint("hopper", k, zoo_copy) for k in ("medium", "medium-replay")}
    # Searching again with another target would pick another snapshot ...
    other = [s for s in card["replay"]["snapshots"] if s != card["medium"]["step"]][-1]
    searched = zoo_build.build(
        run_dir, "hopper", tmp_path / "searched", episodes=1, medium_step=other
    )
    assert searched["medium"]["step"] == other
    # ... but the command line keeps the medium policy of the zoo it rebuilds.
    cli.main(["zoo", "build", str(run_dir), "hopper", "--root", str(zoo_copy), "--episodes", "1"])
    rebuilt = zoo.card("hopper", zoo_copy)
    assert rebuilt["medium"]["step"] == card["medium"]["step"]
    assert rebuilt["replay"] == card["replay"]
    assert {k: zoo.fingerprint("hopper", k, zoo_copy) for k in before} == before


def test_expert_is_the_best_of_the_last_snapshots_asked_for(tiny_zoo, tmp_path, capsys):
    root, card = tiny_zoo
    run_dir = root.parent / "run"
    zoo_copy = tmp_path / "zoo"
    shutil.copytree(root, zoo_copy)
    steps = sorted(int(p.stem.split("_")[1]) for p in (run_dir / "snapshots").glob("actor_*.npz"))
    args = ["zoo", "build", str(run_dir), "hopper", "--root", str(zoo_copy), "--episodes", "1"]
    cli.main([*args, "--expert-candidates", str(len(steps))])
    measured = {
        int(line.split()[2].rstrip(":")): float(line.split()[4])
        for line in capsys.readouterr().out.splitlines()
        if line.startswith("hopper snapshot ")
    }
    assert set(steps) <= set(measured)  # every snapshot was a candidate, the first one included
    expert = zoo.card("hopper", zoo_copy)["expert"]
    assert round(expert["return_mean"]) == round(max(measured[s] for s in steps))


ROLLOUT = """
import hashlib, sys
import h5py
from eabc.data import generate, hdf5_writer
generate.make("hopper-medium", sys.argv[1], seed=0, size=int(sys.argv[2]))
with h5py.File(sys.argv[1]) as f:
    print(hashlib.sha256(f["observations"][:].tobytes() + f["actions"][:].tobytes()).hexdigest())
"""


def test_policy_datasets_do_not_depend_on_the_blas_kernel(tmp_path):
    """OpenBLAS picks its kernels by CPU, and kernels sum in different orders; a dataset made on
    one machine must still be the dataset made on another. OPENBLAS_CORETYPE forces an old SSE3
    kernel here, as an older CPU would."""
    digests = []
    for i, coretype in enumerate([None, "Prescott"]):
        env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
        if coretype:
            env["OPENBLAS_CORETYPE"] = coretype
        out = subprocess.run(
            [sys.executable, "-c", ROLLOUT, str(tmp_path / f"{i}.hdf5"), "5000"],
            env=env, capture_output=True, text=True, check=True,
        )  # fmt: skip
        digests.append(out.stdout.split()[-1])
    assert digests[0] == digests[1]
