"""d3rlpy trains on our data as it is, tested against d3rlpy itself (the `d3rlpy`
extra, in `dev`): its transitions are our rows, its file reads back the same, its TD3+BC trains on
it, and its own Minari reader would have shifted the observations."""

from __future__ import annotations

import dataclasses

import d3rlpy  # the dev extras hold it: a missing d3rlpy fails here, never skips
import numpy as np
import pytest

from eabc.cli import main
from eabc.data import loaders
from eabc.data.d3rlpy_export import export_d3rlpy, to_d3rlpy
from eabc.data.dataset import FIELDS, Dataset, DatasetError
from eabc.data.generate import rollout


@pytest.fixture(scope="module")
def hopper():
    """Random Hopper with 25-step episodes: terminals (falls) and timeouts both inside."""
    data = rollout("Hopper-v4", None, 1500, seed=0, max_episode_steps=25)
    assert data.terminals.sum() > 20 and data.timeouts[:-1].sum() > 10
    return data


def handmade() -> Dataset:
    """Rows 0-3 end at a terminal, 4-7 at a timeout, 8-11 at nothing (the data just ends)."""
    obs = np.arange(12 * 3, dtype=np.float32).reshape(12, 3) / 7  # not whole numbers
    next_obs = np.concatenate([obs[1:], [obs[-1] + 1]])
    next_obs[[3, 7]] = [[-1, -2, -3], [-4, -5, -6]]  # s' of an episode's last step: no next row
    return Dataset(
        observations=obs,
        actions=np.tile([[1.0, -1.0]], (12, 1)).astype(np.float32),  # whole numbers
        rewards=np.arange(12, dtype=np.float32),
        next_observations=next_obs,
        terminals=np.eye(12, dtype=bool)[3],
        timeouts=np.eye(12, dtype=bool)[7],
        name="handmade",
    )


def transitions(replay) -> list:
    picker = d3rlpy.dataset.BasicTransitionPicker()
    return [picker(e, i) for e in replay.episodes for i in range(e.transition_count)]


def rows_d3rlpy_keeps(data: Dataset) -> np.ndarray:
    """Every row but the last step of an episode that did not terminate (the data's end too)."""
    ends = data.terminals | data.timeouts
    ends[-1] = True
    return np.flatnonzero(~(ends & ~data.terminals))


def assert_transitions_are_our_rows(replay, data: Dataset) -> None:
    rows = rows_d3rlpy_keeps(data)
    picked = transitions(replay)
    assert replay.transition_count == len(picked) == len(rows)
    stack = lambda key: np.stack([getattr(t, key) for t in picked])  # noqa: E731
    np.testing.assert_array_equal(stack("observation"), data.observations[rows])
    np.testing.assert_array_equal(stack("action"), data.actions[rows])
    np.testing.assert_array_equal(stack("reward")[:, 0], data.rewards[rows])
    terminal = data.terminals[rows]
    np.testing.assert_array_equal(stack("terminal"), terminal.astype(np.float32))
    # s' is ours everywhere but at a terminal, where d3rlpy puts zeros (and never bootstraps).
    next_obs = np.where(terminal[:, None], 0.0, data.next_observations[rows])
    np.testing.assert_array_equal(stack("next_observation"), next_obs)
    info = replay.dataset_info
    assert info.action_space == d3rlpy.constants.ActionSpace.CONTINUOUS
    assert info.action_size == data.actions.shape[1]


@pytest.mark.parametrize("which", ["hopper", "handmade"])
def test_every_d3rlpy_transition_is_our_row(which, hopper):
    data = hopper if which == "hopper" else handmade()
    replay = to_d3rlpy(data)
    assert_transitions_are_our_rows(replay, data)
    timeouts = int(data.timeouts.sum()) + int(not (data.terminals[-1] or data.timeouts[-1]))
    assert replay.transition_count == data.size - timeouts
    if which == "handmade":  # whole-number actions that d3rlpy alone would call discrete
        assert [e.size() for e in replay.episodes] == [4, 4, 4]
        assert replay.transition_count == 10


def test_rows_out_of_episode_order_are_refused(hopper):
    order = np.random.default_rng(0).permutation(hopper.size)
    shuffled = dataclasses.replace(hopper, **{k: getattr(hopper, k)[order] for k in FIELDS})
    with pytest.raises(DatasetError, match=r"must run episode by episode"):
        to_d3rlpy(shuffled)


def test_cli_export_reads_back_with_replay_buffer_load(hopper, tmp_path, capsys):
    source = tmp_path / "hopper.npz"
    loaders.save_npz(hopper, source)
    target = tmp_path / "hopper.h5"
    main(["data", "export", str(source), "--d3rlpy", str(target)])
    assert capsys.readouterr().out == f"{target}\n"  # d3rlpy's log lines go to stderr
    with open(target, "rb") as f:
        replay = d3rlpy.dataset.ReplayBuffer.load(f, d3rlpy.dataset.InfiniteBuffer())
    assert_transitions_are_our_rows(replay, hopper)
    with pytest.raises(SystemExit, match="exists already; pass --force"):
        main(["data", "export", str(source), "--d3rlpy", str(target)])
    with pytest.raises(SystemExit, match="error: dataset file .*missing.npz does not exist"):
        main(["data", "export", str(tmp_path / "missing.npz"), "--d3rlpy", str(tmp_path / "m.h5")])
    main(["data", "export", str(source), "--d3rlpy", str(target), "--force"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hopper.h5", "hopper.npz"]


def test_whole_number_actions_get_a_note_on_how_to_load_them(tmp_path, capsys):
    export_d3rlpy(handmade(), tmp_path / "handmade.h5")
    assert "ActionSpace.CONTINUOUS, action_size=2" in capsys.readouterr().err


def test_d3rlpys_td3_bc_trains_on_the_exported_file(hopper, tmp_path, monkeypatch):
    import torch  # noqa: PLC0415  (d3rlpy's)

    monkeypatch.chdir(tmp_path)  # anything d3rlpy writes would land here
    export_d3rlpy(hopper, tmp_path / "hopper.h5")
    with open(tmp_path / "hopper.h5", "rb") as f:
        replay = d3rlpy.dataset.ReplayBuffer.load(f, d3rlpy.dataset.InfiniteBuffer())
    d3rlpy.seed(0)
    small = d3rlpy.models.VectorEncoderFactory(hidden_units=[32, 32])
    config = d3rlpy.algos.TD3PlusBCConfig(
        batch_size=32, actor_encoder_factory=small, critic_encoder_factory=small
    )
    algo = config.create(device="cpu:0")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # 5 ms a step; two threads on a busy CPU took a second a step
    try:
        metrics = algo.fit(
            replay,
            n_steps=40,
            n_steps_per_epoch=20,
            show_progress=False,
            save_interval=1000,
            logger_adapter=d3rlpy.logging.NoopAdapterFactory(),
            experiment_name="td3bc",
            with_timestamp=False,
        )
        actions = algo.predict(hopper.observations[:5])
    finally:
        torch.set_num_threads(threads)
    assert [epoch for epoch, _ in metrics] == [1, 2]
    losses = [m[k] for _, m in metrics for k in ("critic_loss", "actor_loss", "bc_loss")]
    assert np.all(np.isfinite(losses)), metrics
    assert actions.shape == (5, 3) and np.all(np.abs(actions) <= 1)
    assert [p.name for p in tmp_path.iterdir()] == ["hopper.h5"]  # no d3rlpy_logs


def test_d3rlpys_own_minari_reader_would_shift_the_observations(hopper, tmp_path, monkeypatch):
    """Why the export exists: d3rlpy 2.8.1's get_minari concatenates each episode's final
    observation into the observations, so episode k is shifted by k rows. If this fails, d3rlpy
    fixed it: update docs/datasets.md and the README's Interop section."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    loaders.export_minari(hopper, "test/hopper/d3rlpy-v0")
    replay, _ = d3rlpy.datasets.get_minari("test/hopper/d3rlpy-v0")
    ours = to_d3rlpy(hopper)
    first, second = replay.episodes[1].observations, ours.episodes[1].observations
    np.testing.assert_array_equal(replay.episodes[0].observations, ours.episodes[0].observations)
    np.testing.assert_array_equal(first[1:], second[:-1])  # one row late from the second episode
    np.testing.assert_array_equal(first[0], hopper.next_observations[ours.episodes[0].size() - 1])


def test_the_block_docs_datasets_md_shows_runs(tmp_path, monkeypatch):
    """docs/datasets.md's Python block (d3rlpy's own dataset from ours), on a small dataset of
    the name it uses."""
    import re  # noqa: PLC0415
    from pathlib import Path  # noqa: PLC0415

    from eabc.data import generate  # noqa: PLC0415

    monkeypatch.setenv("EABC_CACHE_DIR", str(tmp_path))
    generate.make("hopper-medium", generate.dataset_path("hopper-medium", tmp_path), size=2_000)
    text = (Path(__file__).resolve().parents[2] / "docs" / "datasets.md").read_text()
    [block] = re.findall(r"(?ms)^```python\n(.*?)^```", text)
    namespace: dict = {}
    exec(block, namespace)  # noqa: S102
    assert namespace["dataset"].transition_count > 0
