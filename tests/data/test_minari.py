"""Local Minari datasets that are damaged, half written or named outside the Minari path.

Each bad case ends in one line that names the file or the id and says what to do; an export
writes its dataset into a hidden folder of the Minari path and renames it into place only when
it is complete, so that nothing half written is ever listed; an id that is not ``NAME-vN`` of
letters, digits, ``-`` and ``_`` (a ``../``, an absolute path) is refused before any folder is
made. Datasets are made here with Minari's own writer (no download is possible or needed).
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import minari
import numpy as np
import pytest
from minari.data_collector import EpisodeBuffer

from eabc.cli import main
from eabc.data import loaders
from eabc.data.dataset import DatasetError
from eabc.data.sources import check_source, load_dataset


def write_minari(dataset_id: str, ref_scores=(-1200.0, -130.0)) -> None:
    """Two short Pendulum episodes as a local Minari dataset, with Minari's own writer."""
    rng = np.random.default_rng(0)
    episodes = [
        EpisodeBuffer(
            observations=rng.normal(size=(length + 1, 3)).astype(np.float32),
            actions=rng.uniform(-2, 2, size=(length, 1)).astype(np.float32),
            rewards=rng.normal(size=length),
            terminations=np.zeros(length, bool),
            truncations=np.r_[np.zeros(length - 1, bool), True],
        )
        for length in (5, 7)
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        minari.create_dataset_from_buffers(
            dataset_id, episodes, env="Pendulum-v1", ref_min_score=ref_scores[0],
            ref_max_score=ref_scores[1],
        )  # fmt: skip


@pytest.fixture
def minari_root(tmp_path, monkeypatch):
    """A Minari path holding one intact dataset, ``test/pendulum/good-v0``."""
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    write_minari("test/pendulum/good-v0")
    return root


@pytest.fixture
def tiny_file(tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "pend.npz"
    np.savez(path, observations=rng.normal(size=(20, 3)).astype(np.float32),
             actions=rng.uniform(-2, 2, (20, 1)).astype(np.float32),
             rewards=rng.normal(size=20).astype(np.float32), terminals=np.zeros(20, bool),
             env_id=np.asarray("Pendulum-v1"))  # fmt: skip
    return path


def snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        if p.is_file()
        else "d"
        for p in sorted(folder.rglob("*"))
    }


def refused(argv: list[str], *names: str) -> str:
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    message = str(exit_.value.code)
    assert message.startswith("error: ") and "\n" not in message, message
    assert "Traceback" not in message and any(name in message for name in names), message
    return message


def test_an_intact_dataset_still_loads(minari_root):
    data = load_dataset("minari:test/pendulum/good-v0")
    assert data.size == 12 and data.ref_min_score == -1200.0


@pytest.mark.parametrize("damage", ["metadata gone", "metadata junk", "metadata another id"])
def test_a_damaged_dataset_that_exists_is_reported_as_damaged_naming_the_file(minari_root, damage):
    """Before: "Minari dataset ... is not in the local Minari path", of a folder that is there."""
    write_minari("test/pendulum/hurt-v0")
    metadata = minari_root / "test/pendulum/hurt-v0/data/metadata.json"
    if damage == "metadata gone":
        metadata.unlink()
    elif damage == "metadata junk":
        metadata.write_text("{not json")
    else:
        metadata.write_text(json.dumps({**json.loads(metadata.read_text()), "dataset_id": "x-v0"}))
    for call in (load_dataset, check_source):
        with pytest.raises(DatasetError) as error:
            call("minari:test/pendulum/hurt-v0")
        message = str(error.value)
        assert str(metadata) in message and "damaged" in message and "\n" not in message
        assert "not in the local Minari path" not in message
    refused(["data", "info", "minari:test/pendulum/hurt-v0"], str(metadata))
    assert load_dataset("minari:test/pendulum/good-v0").size == 12  # the others are untouched


@pytest.mark.parametrize("keep", [0, 100, 0.5])
def test_a_truncated_data_file_gives_one_line_naming_it(minari_root, keep):
    """Before: ``error: : Unable to synchronously open file (truncated file ...)``, naming no file."""
    write_minari("test/pendulum/cut-v0")
    data_file = minari_root / "test/pendulum/cut-v0/data/main_data.hdf5"
    content = data_file.read_bytes()
    data_file.write_bytes(content[: int(keep * len(content)) if keep < 1 else keep])
    message = refused(["data", "info", "minari:test/pendulum/cut-v0"], str(data_file))
    assert "again" in message  # what to do: export or download it again


@pytest.mark.parametrize("dataset_id", ["eabc/pendulum/mine", "mine", "eabc/pendulum/mine-v",
                                        "eabc//mine-v0", "eabc/pen dulum/mine-v0"])  # fmt: skip
def test_an_export_id_that_is_not_name_v_n_is_refused_before_anything_is_written(
    minari_root, tiny_file, dataset_id
):
    """Before: a traceback, and a half-written folder that broke listing every Minari dataset."""
    before = snapshot(minari_root)
    refused(["data", "export", str(tiny_file), "--dataset-id", dataset_id], "--dataset-id")
    assert snapshot(minari_root) == before
    assert list(minari.list_local_datasets()) == ["test/pendulum/good-v0"]


@pytest.mark.parametrize("dataset_id", ["../outside-v0", "eabc/../../outside-v0", "TMP/outside-v0",
                                        "eabc/./x-v0", "~/outside-v0"])  # fmt: skip
def test_an_id_outside_the_minari_path_is_refused_before_any_folder_is_made(
    minari_root, tiny_file, tmp_path, dataset_id
):
    """Before: ``../`` made folders outside the Minari path, then was refused. (An absolute
    id names a folder under this test's own directory, where a failure can make it.)"""
    dataset_id = dataset_id.replace("TMP", str(tmp_path / "abs"))
    before = snapshot(tmp_path)
    refused(["data", "export", str(tiny_file), "--dataset-id", dataset_id], "--dataset-id")
    with pytest.raises(DatasetError, match="not a Minari id"):
        load_dataset(f"minari:{dataset_id}")
    with pytest.raises(DatasetError, match="not a Minari id"):
        check_source(f"minari:{dataset_id}")
    assert snapshot(tmp_path) == before


def test_an_export_that_fails_half_way_leaves_nothing_listed(minari_root, tiny_file, monkeypatch):
    """The export writes into a hidden folder and renames it at the end: a failure (here, the
    disk filling up while the episodes are written) leaves the Minari path as it was."""
    from minari.dataset._storages.hdf5_storage import HDF5Storage  # noqa: PLC0415

    before = snapshot(minari_root)
    write = HDF5Storage.update_episodes

    def full_disk(self, episodes):
        write(self, episodes)  # the episodes are there, then the disk fills up
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as patch, pytest.raises(OSError, match="No space left"):
        patch.setattr(HDF5Storage, "update_episodes", full_disk)
        loaders.export_minari(load_dataset(tiny_file), "test/pendulum/failed-v0")
    assert snapshot(minari_root) == before
    assert list(minari.list_local_datasets()) == ["test/pendulum/good-v0"]
    loaders.export_minari(load_dataset(tiny_file), "test/pendulum/failed-v0")
    assert load_dataset("minari:test/pendulum/failed-v0").size == load_dataset(tiny_file).size


def test_a_broken_folder_made_elsewhere_does_not_stop_the_other_datasets(minari_root, tiny_file):
    """A half-written folder of an older export (or another tool), its id without ``-vN``,
    makes Minari's own listing raise; eabc never depends on that listing, so every other
    dataset still loads, exports and is checked by a sweep."""
    broken = minari_root / "eabc/pendulum/mine/data"
    broken.mkdir(parents=True)
    (broken / "metadata.json").write_text(json.dumps({"dataset_id": "eabc/pendulum/mine"}))
    with pytest.raises((ValueError, TypeError)):
        minari.list_local_datasets()  # Minari's own listing: every dataset unlisted
    check_source("minari:test/pendulum/good-v0")
    assert load_dataset("minari:test/pendulum/good-v0").size == 12
    assert load_dataset("test/pendulum/good-v0").size == 12  # a bare id of a local dataset
    main(["data", "export", str(tiny_file), "--dataset-id", "test/pendulum/new-v0"])
    assert load_dataset("minari:test/pendulum/new-v0").size == load_dataset(tiny_file).size


def test_an_export_replaces_an_existing_dataset_only_with_force(minari_root, tiny_file):
    refused(["data", "export", str(tiny_file), "--dataset-id", "test/pendulum/good-v0"],
            "test/pendulum/good-v0")  # fmt: skip
    assert load_dataset("minari:test/pendulum/good-v0").size == 12
    main(["data", "export", str(tiny_file), "--dataset-id", "test/pendulum/good-v0", "--force"])
    assert load_dataset("minari:test/pendulum/good-v0").size == load_dataset(tiny_file).size
    assert sorted(p.name for p in minari_root.iterdir()) == ["test"]  # no temporary left


def test_reversed_reference_scores_of_a_minari_dataset_are_refused(minari_root):
    write_minari("test/pendulum/reversed-v0", ref_scores=(-130.0, -1200.0))
    with pytest.raises(DatasetError, match=r"reference scores .* wrong order"):
        load_dataset("minari:test/pendulum/reversed-v0")
