"""Datasets: loaders round-trip, D4RL conventions, generation, and clear errors on bad input."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import threading
import time
import zipfile

import h5py
import minari
import numpy as np
import pytest
from minari.data_collector import EpisodeBuffer

from eabc.data import describe, generate, hdf5_writer, tasks
from eabc.data.dataset import Dataset, DatasetError, Normalizer
from eabc.data.loaders import load_file, save_npz
from eabc.data.sources import load_dataset
from eabc.evaluation import check_spaces, make_env
from eabc.training.config import resolve_agent_config

MINARI_METADATA = {
    "algorithm_name": "a test's random rows",
    "author": "eabc's tests",
    "author_email": "nobody@example.invalid",
    "code_permalink": "tests/data/test_data.py",
    "description": "made by a test",
    "eval_env": "Pendulum-v1",
}
"""What Minari asks of every dataset (it warns about each field left out)."""


def small(n=50, obs=3, act=2, seed=0, **kw):
    rng = np.random.default_rng(seed)
    arrays = dict(
        observations=rng.normal(size=(n, obs)),
        actions=rng.uniform(-1, 1, size=(n, act)),
        rewards=rng.normal(size=n),
        next_observations=rng.normal(size=(n, obs)),
        terminals=np.zeros(n, bool),
        timeouts=np.zeros(n, bool),
    )
    return {**arrays, **kw}


def test_npz_and_hdf5_round_trip(tmp_path, pendulum_dataset):
    save_npz(pendulum_dataset, tmp_path / "d.npz")
    hdf5_writer.save_hdf5(pendulum_dataset, tmp_path / "d.hdf5")
    for path in (tmp_path / "d.npz", tmp_path / "d.hdf5"):
        loaded = load_dataset(path)
        for key in (
            "observations",
            "actions",
            "rewards",
            "next_observations",
            "terminals",
            "timeouts",
        ):
            np.testing.assert_array_equal(getattr(loaded, key), getattr(pendulum_dataset, key))
        assert (
            loaded.env_id == "Pendulum-v1"
            and loaded.ref_max_score == pendulum_dataset.ref_max_score
        )


def test_d4rl_file_without_next_observations_follows_qlearning_dataset(tmp_path):
    obs = np.arange(12, dtype=np.float32).reshape(6, 2)
    with h5py.File(tmp_path / "hopper_medium-v2.hdf5", "w") as f:
        f["observations"] = obs
        f["actions"] = np.zeros((6, 3), np.float32)
        f["rewards"] = np.arange(6, dtype=np.float32)
        f["terminals"] = np.array([0, 1, 0, 0, 0, 0], bool)
        f["timeouts"] = np.array([0, 0, 0, 1, 0, 0], bool)
    data = load_file(tmp_path / "hopper_medium-v2.hdf5")
    # Row 3 is a timeout (its s' is unknown) and row 5 is the last row: both dropped.
    np.testing.assert_array_equal(data.rewards, [0, 1, 2, 4])
    np.testing.assert_array_equal(data.next_observations, obs[[1, 2, 3, 5]])
    np.testing.assert_array_equal(data.terminals, [0, 1, 0, 0])
    np.testing.assert_array_equal(data.timeouts, [0, 0, 1, 0])  # row 2 now ends its episode
    assert data.env_id == "Hopper-v4" and data.ref_min_score == tasks.ENVS["hopper"].ref_min_score


def test_normalizer_is_td3bc_convention():
    obs = np.random.default_rng(0).normal(3.0, 2.0, size=(1000, 4)).astype(np.float32)
    norm = Normalizer.fit(obs)
    np.testing.assert_allclose(norm.std, obs.std(0) + 1e-3, rtol=1e-5)
    np.testing.assert_allclose(
        norm(obs), (obs - obs.mean(0)) / (obs.std(0) + 1e-3), rtol=1e-4, atol=1e-5
    )


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(rewards=np.ones(49)), "different lengths"),
        (dict(next_observations=np.zeros((50, 4))), "next_observations have dim 4"),
        (dict(actions=np.zeros((50, 2, 2))), r"must be \[N, dim\]"),
        (dict(observations=np.full((50, 3), np.nan)), "NaN/inf"),
        (dict(rewards=np.r_[np.ones(49), np.inf]), "rows \\[49\\]"),
    ],
)
def test_bad_arrays_raise_clear_errors(change, message):
    with pytest.raises(DatasetError, match=message):
        Dataset(**small(**change))


def test_missing_file_keys_and_unknown_names(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        load_dataset(tmp_path / "nope.hdf5")
    np.savez(tmp_path / "partial.npz", observations=np.zeros((5, 2)), actions=np.zeros((5, 1)))
    with pytest.raises(DatasetError, match=r"missing keys \['rewards', 'terminals'\]"):
        load_dataset(tmp_path / "partial.npz")
    np.savez(tmp_path / "short.npz", **small(terminals=np.zeros(10)))
    with pytest.raises(DatasetError, match="terminals has 10 rows but observations have 50"):
        load_dataset(tmp_path / "short.npz")
    (tmp_path / "junk.hdf5").write_text("not hdf5")
    with pytest.raises(DatasetError, match="not a readable HDF5"):
        load_dataset(tmp_path / "junk.hdf5")
    with pytest.raises(DatasetError, match="unknown dataset 'hoper-medium'.*hopper-medium"):
        load_dataset("hoper-medium")


def test_environment_must_match_the_data(pendulum_dataset):
    env = make_env("Hopper-v4")
    with pytest.raises(DatasetError, match="observations have dim 3 but Hopper-v4"):
        check_spaces(env, pendulum_dataset)
    wide = dataclasses.replace(pendulum_dataset, actions=pendulum_dataset.actions * 3)
    with pytest.raises(DatasetError, match="outside Pendulum-v1's bounds"):
        check_spaces(make_env("Pendulum-v1"), wide)
    with pytest.raises(DatasetError, match="cannot make evaluation environment"):
        make_env("NoSuchEnv-v0")


def test_random_dataset_is_deterministic_and_d4rl_shaped(tmp_path):
    a = generate.make("hopper-random", tmp_path / "a.hdf5", seed=3, size=1500)
    b = generate.make("hopper-random", tmp_path / "b.hdf5", seed=3, size=1500)
    c = generate.make("hopper-random", tmp_path / "c.hdf5", seed=4, size=1500)
    da, db, dc = load_file(a), load_file(b), load_file(c)
    np.testing.assert_array_equal(da.observations, db.observations)
    np.testing.assert_array_equal(da.actions, db.actions)
    assert not np.array_equal(da.actions, dc.actions)
    with h5py.File(a) as f:
        assert f["observations"].dtype == np.float32 and f["terminals"].dtype == bool
        assert f["observations"].shape == (1500, 11) and f["actions"].shape == (1500, 3)
    assert da.terminals.sum() > 10, "random hopper falls over: episodes end in terminals"
    ends = np.flatnonzero(da.terminals | da.timeouts)
    starts = ends[:-1] + 1
    # A new episode starts after every end: s' of the end row is not the next row's s.
    assert not np.allclose(da.next_observations[ends[:-1]], da.observations[starts])
    inner = np.setdiff1d(np.arange(1499), ends)
    np.testing.assert_array_equal(da.next_observations[inner], da.observations[inner + 1])
    assert da.name == "hopper-random" and da.metadata["seed"] == 3


def test_built_in_name_is_made_once_then_cached(tmp_path, monkeypatch):
    monkeypatch.setattr(generate, "DATASET_SIZE", 800)
    monkeypatch.setenv("EABC_ZOO_DIR", str(tmp_path / "empty-zoo"))
    first = load_dataset("walker2d-random", cache_dir=tmp_path)
    mtime = generate.dataset_path("walker2d-random", tmp_path).stat().st_mtime_ns
    second = load_dataset("walker2d-random", cache_dir=tmp_path)
    assert generate.dataset_path("walker2d-random", tmp_path).stat().st_mtime_ns == mtime
    np.testing.assert_array_equal(first.actions, second.actions)
    with pytest.raises(DatasetError, match="zoo has no policies for 'walker2d'"):
        load_dataset("walker2d-medium", cache_dir=tmp_path)


def test_confidence_level_defaults_from_table_3():
    assert tasks.parse_task("hopper_medium_replay-v2.hdf5") == ("hopper", "medium-replay")
    assert tasks.parse_task("walker2d-medium-expert") == ("walker2d", "medium-expert")
    assert resolve_agent_config("eabc", "walker2d-random", {}).confidence_level == 0.95
    assert resolve_agent_config("eabc", "halfcheetah-medium", {}).confidence_level == 0.0
    assert (
        resolve_agent_config("eabc", "my-data", {"confidence_level": 0.3}).confidence_level == 0.3
    )
    assert resolve_agent_config("td3bc", "my-data", {}).num_critics == 2
    with pytest.raises(ValueError, match="pass --confidence-level"):
        resolve_agent_config("eabc", "my-data", {})
    with pytest.raises(ValueError, match="unknown algorithm"):
        resolve_agent_config("sac", "hopper-random", {})


def test_minari_dataset_loads_from_the_local_path(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    rng = np.random.default_rng(0)
    episodes = []
    for length in (5, 7):
        obs = rng.normal(size=(length + 1, 3)).astype(np.float32)
        episodes.append(
            EpisodeBuffer(
                observations=obs,
                actions=rng.uniform(-2, 2, size=(length, 1)).astype(np.float32),
                rewards=rng.normal(size=length),
                terminations=np.zeros(length, bool),
                truncations=np.r_[np.zeros(length - 1, bool), True],
            )
        )
    minari.create_dataset_from_buffers(
        "test/pendulum/tiny-v0",
        episodes,
        env="Pendulum-v1",
        ref_min_score=-1200.0,
        ref_max_score=-130.0,
        **MINARI_METADATA,
    )
    data = load_dataset("minari:test/pendulum/tiny-v0")
    assert data.size == 12 and data.env_id == "Pendulum-v1" and data.ref_min_score == -1200.0
    np.testing.assert_array_equal(data.next_observations[:5], episodes[0].observations[1:])
    assert data.timeouts.sum() == 2
    with pytest.raises(DatasetError, match="not in the local Minari path"):
        load_dataset("minari:test/pendulum/other-v0")


def test_minari_ids_resolve_table_3_from_their_task_and_kind():
    assert tasks.parse_task("mujoco/hopper/medium-v0") == ("hopper", "medium")
    assert tasks.parse_task("eabc/walker2d/medium-replay-v0") == ("walker2d", "medium-replay")
    for dataset_id in ("minari:mujoco/hopper/medium-v0", "eabc/hopper/medium-v0"):
        assert resolve_agent_config("eabc", dataset_id, {}).confidence_level == 0.25


def test_export_of_a_file_without_next_observations_keeps_its_episodes(tmp_path, monkeypatch):
    """A timeout inside a file without s' (D4RL's qlearning_dataset drops that step) still ends
    its episode: Minari gets three episodes, not two merged ones with a made-up transition."""
    from eabc.data.loaders import export_minari  # noqa: PLC0415

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    n = 13  # episodes: rows 0-3 (timeout at 3), 4-8 (terminal at 8), 9-12 (the file's end)
    obs = np.arange(3 * n, dtype=np.float32).reshape(n, 3)
    np.savez(
        tmp_path / "pend.npz",
        observations=obs,
        actions=np.zeros((n, 1), np.float32),
        rewards=np.ones(n, np.float32),
        terminals=np.eye(n, dtype=bool)[8],
        timeouts=np.eye(n, dtype=bool)[3],
        env_id=np.asarray("Pendulum-v1"),
    )
    data = load_dataset(tmp_path / "pend.npz")
    np.testing.assert_array_equal(np.flatnonzero(data.timeouts), [2])
    assert describe.describe_dataset(data)["episodes"] == 3
    export_minari(data, "test/pendulum/no-next-v0")
    episodes = list(minari.load_dataset("test/pendulum/no-next-v0").iterate_episodes())
    assert [len(e.rewards) for e in episodes] == [3, 5, 3]
    np.testing.assert_array_equal(episodes[0].observations, obs[0:4])
    np.testing.assert_array_equal(episodes[1].observations, obs[4:10])
    np.testing.assert_array_equal(episodes[2].observations, obs[9:13])
    assert [bool(e.truncations[-1]) for e in episodes] == [True, False, True]
    assert [bool(e.terminations[-1]) for e in episodes] == [False, True, False]


def test_a_dataset_made_with_minaris_data_collector_trains(tmp_path, monkeypatch, capsys):
    import gymnasium as gym  # noqa: PLC0415

    from eabc.cli import main  # noqa: PLC0415

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    env = minari.DataCollector(gym.make("Pendulum-v1", max_episode_steps=50))
    env.action_space.seed(0)
    for episode in range(6):
        env.reset(seed=episode)
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            done = terminated or truncated
    env.create_dataset(
        "test/pendulum/collected-v0", **{**MINARI_METADATA, "algorithm_name": "uniform random"}
    )
    env.close()
    run_dir = tmp_path / "run"
    main(
        ["train", "--dataset", "minari:test/pendulum/collected-v0", "--algo", "bc", "--steps",
         "100", "--log-interval", "100", "--eval-interval", "100", "--checkpoint-interval", "100",
         "--eval-episodes", "1", "--run-dir", str(run_dir), "--no-progress"]
    )  # fmt: skip
    summary = json.loads(capsys.readouterr().out)
    assert summary["steps"] == 100 and summary["evaluations"] == 1
    config = json.loads((run_dir / "config.json").read_text())
    assert config["dataset"]["size"] == 300 and config["dataset"]["env_id"] == "Pendulum-v1"


def _npy(shape, dtype="<f4", data=b"\0" * 64) -> bytes:
    """A .npy file's bytes: a header claiming ``shape`` of ``dtype``, then ``data``."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buffer, {"descr": dtype, "fortran_order": False, "shape": shape}
    )
    return buffer.getvalue() + data


def _write_npz(path, **members):
    """An .npz whose members are arrays (saved as np.save does) or raw bytes, as given."""
    with zipfile.ZipFile(path, "w") as archive:
        for key, value in members.items():
            if not isinstance(value, bytes):
                buffer = io.BytesIO()
                np.save(buffer, value, allow_pickle=True)
                value = buffer.getvalue()
            archive.writestr(f"{key}.npy", value)


N_ROWS = 20
GOOD = dict(
    observations=np.zeros((N_ROWS, 3), np.float32),
    actions=np.zeros((N_ROWS, 2), np.float32),
    rewards=np.zeros(N_ROWS, np.float32),
    terminals=np.zeros(N_ROWS, bool),
)


@pytest.mark.parametrize(
    "change, message",
    [
        # 2 KB whose header claims 68 TB: refused before anything is allocated
        (dict(observations=_npy((10**12, 17))), r"observations claims shape \(1000000000000, 17\) of float32 \(68.0 TB\) but the file holds at most 64 bytes"),
        (dict(actions=_npy((N_ROWS, 2), data=b"\0" * 10)), "actions claims shape .* the file is truncated"),
        (dict(rewards=b"not an array at all"), "member rewards.npy is not a readable .npy array"),
        (dict(rewards=np.zeros(N_ROWS, [("a", "<f4"), ("b", "<i4")])), "rewards holds records"),
        (dict(observations=np.zeros((N_ROWS, 3), complex)), "observations holds complex numbers"),
        (dict(rewards=np.array([None] * N_ROWS, object)), "rewards holds objects"),
        (dict(actions=np.array([["a", "b"]] * N_ROWS)), "actions holds text"),
        (dict(rewards=np.array(1.0)), "rewards is a single value, not an array"),
        (dict(observations=np.zeros((N_ROWS, 3, 2))), r"observations has shape \(20, 3, 2\); it must be \[N\] or \[N, dim\]"),
        (dict(terminals=np.zeros((N_ROWS, 2))), r"terminals has shape \(20, 2\); it must be \[N\] or \[N, 1\]"),
        (dict(ref_min_score=np.array("abc")), "ref_min_score must be a single value .a number."),
        (dict(metadata=np.array("{not json")), "attribute metadata must be a JSON object"),
        (dict(ref_max_score=np.array(np.inf)), "attribute ref_max_score is inf"),
    ],
)  # fmt: skip
def test_a_malformed_npz_is_refused_from_its_headers_in_one_line(tmp_path, change, message):
    path = tmp_path / "bad.npz"
    _write_npz(path, **{**GOOD, **change})
    with pytest.raises(DatasetError, match=message) as error:
        load_dataset(path)
    assert str(error.value).startswith(f"{path}: ") and "\n" not in str(error.value)


def test_an_npy_renamed_npz_and_a_lying_zip_directory_are_refused(tmp_path):
    np.save(tmp_path / "one.npy", np.zeros((5, 3)))
    (tmp_path / "one.npy").rename(tmp_path / "one.npz")
    with pytest.raises(DatasetError, match="one.npz: a single .npy array named .npz"):
        load_dataset(tmp_path / "one.npz")
    # The zip directory claims observations.npy is 68 TB uncompressed; the file is 2 KB.
    _write_npz(tmp_path / "lies.npz", **{**GOOD, "observations": _npy((10**12, 17))})
    data = bytearray((tmp_path / "lies.npz").read_bytes())
    entry = data.index(b"PK\x01\x02")  # the first central directory entry: observations.npy
    data[entry + 24 : entry + 28] = (2**32 - 1).to_bytes(4, "little")  # uncompressed size
    (tmp_path / "lies.npz").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="the file holds at most"):
        load_dataset(tmp_path / "lies.npz")
    # Members a dataset does not use are not read, whatever they are.
    _write_npz(tmp_path / "extra.npz", **GOOD, notes=b"free text")
    assert load_dataset(tmp_path / "extra.npz").size == N_ROWS - 1


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this OS")
def test_a_fifo_or_a_device_named_like_a_dataset_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "x.npz"
    os.mkfifo(fifo)

    def unblock():  # were the loader to open the FIFO, this ends its wait (and the test fails)
        time.sleep(5)
        with contextlib.suppress(OSError):
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))

    threading.Thread(target=unblock, daemon=True).start()
    with pytest.raises(DatasetError, match=r"x.npz is a FIFO, not a regular file"):
        load_dataset(fifo)
    with pytest.raises(DatasetError, match=r"/dev/null is a device, not a regular file"):
        load_file("/dev/null")


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("observations", np.zeros((N_ROWS, 3, 2)), r"observations has shape \(20, 3, 2\)"),
        ("rewards", np.array(["x"] * N_ROWS, dtype=object), "rewards holds text"),
        ("actions", np.zeros((N_ROWS, 2), complex), "actions holds complex numbers"),
        ("rewards", np.float32(1.0), "rewards is a single value"),
        ("observations", ((10**12, 17), "f4"), r"claims shape \(1000000000000, 17\) of float32 .* at most 0 bytes"),
    ],
)  # fmt: skip
def test_hdf5_datasets_of_the_wrong_rank_or_dtype_are_refused(tmp_path, key, value, message):
    path = tmp_path / "bad.hdf5"
    with h5py.File(path, "w") as f:
        for name, array in {**GOOD, key: value}.items():
            if isinstance(array, tuple):  # declared, never written: no storage behind it
                f.create_dataset(name, shape=array[0], dtype=array[1])
            elif array.dtype == object:
                f.create_dataset(name, data=list(array), dtype=h5py.string_dtype())
            else:
                f[name] = array
        f.attrs["ref_min_score"] = 0.0
    with pytest.raises(DatasetError, match=message) as error:
        load_dataset(path)
    assert str(error.value).startswith(f"{path}: ") and "\n" not in str(error.value)


def test_a_dataset_without_transitions_is_refused_in_one_line(tmp_path):
    """Before: an IndexError traceback from deriving next observations of no rows."""
    path = tmp_path / "empty.npz"
    np.savez(path, observations=np.zeros((0, 3), np.float32), actions=np.zeros((0, 1), np.float32),
             rewards=np.zeros(0, np.float32), terminals=np.zeros(0, bool))  # fmt: skip
    with pytest.raises(DatasetError, match="empty.npz: empty: holds no transitions"):
        load_file(path)
