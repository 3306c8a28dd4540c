"""Files that were damaged or edited by hand after eabc wrote them, and the names of what a sweep
runs: every one is refused in one line that names the file and says what to do, before any work,
whatever its checksum says. The example tests first (each failed before its fix), then the
generated ones (Hypothesis).

- a run's checkpoint holding NaN/inf weights (its checksum recomputed), its config.json with an
  edited ``max_action`` or without a key every eabc writes (``evaluate``, ``export-policy``,
  ``load_policy``, ``--resume``);
- reference scores in the wrong order (random above expert) in a dataset file, a Minari dataset or
  a run's config.json; a file whose every row is a timeout;
- a sweep naming a dataset whose run directory's name is too long for the file system, or a
  ``minari:`` dataset that is not there; a junk file in the dataset cache (``eabc data list``).

The run is a TD3+BC run's initial checkpoint on 40 transitions: no training.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from eabc import load_policy, pytree
from eabc.agents import get_algorithm
from eabc.cli import main
from eabc.data.dataset import DatasetError
from eabc.data.loaders import load_file
from eabc.experiments import results
from eabc.training import checkpoint, lifecycle, run_config
from eabc.training.config import TrainConfig

SETTINGS = settings(
    deadline=None,
    database=None,  # the same examples on every machine
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


def tiny_arrays(rows: int = 40, **changes) -> dict[str, np.ndarray]:
    """Pendulum-shaped transitions, with ``changes`` (None removes a key)."""
    rng = np.random.default_rng(0)
    arrays = {
        "observations": rng.normal(size=(rows, 3)).astype(np.float32),
        "actions": rng.uniform(-1, 1, (rows, 1)).astype(np.float32),
        "rewards": rng.normal(size=rows).astype(np.float32),
        "terminals": np.zeros(rows, bool),
    }
    return {k: v for k, v in {**arrays, **changes}.items() if v is not None}


@pytest.fixture(scope="module")
def started(tmp_path_factory):
    """A run directory as `eabc train` leaves it after its first checkpoint (the initial state)."""
    root = tmp_path_factory.mktemp("started")
    np.savez(root / "tiny.npz", **tiny_arrays())
    config = TrainConfig(dataset=str(root / "tiny.npz"), algo="td3bc", steps=200,
                         log_interval=100, eval_interval=100, checkpoint_interval=100,
                         eval_episodes=1, env="Pendulum-v1")  # fmt: skip
    run = lifecycle.start(config, root / "run", {"hidden_dims": (32, 32)})
    run.lock.release()
    checkpoint.save(run.run_dir, run.state, run.algorithm.state_layout, run.identity)
    return root / "run"


def snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != results.DATABASE
    }


def copy_run(started: Path, tmp_path: Path) -> Path:
    run_dir = tmp_path / "root" / "run"
    shutil.copytree(started, run_dir)
    return run_dir


def tamper_checkpoint(run_dir: Path, change) -> None:
    """Rewrite the checkpoint with ``change(payload)`` applied, its checksum recomputed (as a
    careful forger, or a bit flip before the checksum was taken, would leave it)."""
    path = run_dir / checkpoint.CHECKPOINT
    raw = pytree.loads(path.read_bytes()[:-40])
    change(raw)
    checkpoint.write_tree(path, raw)


def edit_config(run_dir: Path, change) -> None:
    path = run_dir / checkpoint.CONFIG
    path.write_text(json.dumps(change(json.loads(path.read_text()))))


READERS = (
    lambda run_dir, out: ["evaluate", str(run_dir), "--episodes", "1"],
    lambda run_dir, out: ["export-policy", str(run_dir), "--onnx", str(out / "policy.onnx")],
    lambda run_dir, out: ["train", "--resume", str(run_dir), "--no-progress"],
)


def refused_by_every_reader(run_dir: Path, tmp_path: Path, names: tuple[str, ...]) -> None:
    """``evaluate``, ``export-policy``, ``--resume`` and ``load_policy`` each refuse the run in
    one line naming one of ``names``; nothing on disk changes."""
    before = snapshot(tmp_path)
    for argv in READERS:
        with pytest.raises(SystemExit) as exit_:
            main(argv(run_dir, tmp_path))
        message = str(exit_.value.code)
        assert message.startswith("error: ") and "\n" not in message, message
        assert any(name in message for name in names), (argv(run_dir, tmp_path)[0], message)
    with pytest.raises(ValueError) as error:
        load_policy(run_dir)
    assert "\n" not in str(error.value) and any(name in str(error.value) for name in names)
    assert snapshot(tmp_path) == before


# ----------------------------------------------------------------------------------------------
# Tampered run files


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("where", ["actor", "critic", "normalizer"])
def test_a_checkpoint_with_non_finite_weights_is_refused_whatever_its_checksum(
    started, tmp_path, value, where
):
    """Before: NaN actor weights with a recomputed checksum were evaluated (printing NaN),
    exported to ONNX and returned by load_policy."""
    run_dir = copy_run(started, tmp_path)

    def poison(raw):
        params, key = (
            (raw["normalizer"], "std") if where == "normalizer" else
            (pytree.find(raw["agent"], where), "w0")
        )  # fmt: skip
        array = np.array(params[key])  # a writable copy
        array.reshape(-1)[0] = value
        params[key] = array

    tamper_checkpoint(run_dir, poison)
    refused_by_every_reader(run_dir, tmp_path, (str(run_dir / checkpoint.CHECKPOINT),))
    with pytest.raises(SystemExit, match="NaN/inf"):
        main(["evaluate", str(run_dir), "--episodes", "1"])
    runs, _ = results.collect(tmp_path / "root", write=False)  # listed as unusable, not dropped
    assert list(runs["status"]) == ["damaged"] and "NaN/inf" in runs["config"][0]


@pytest.mark.parametrize("value", [math.nan, math.inf, 0.0, -2.0, 1.0, 1e30])
def test_an_edited_max_action_is_refused(started, tmp_path, value):
    """Pendulum's actions are bounded by 2. Before: an edited max_action was exported and
    returned by load_policy silently (the policy then acted outside the environment's bounds)."""
    run_dir = copy_run(started, tmp_path)
    edit_config(run_dir, lambda c: {**c, "max_action": value})
    refused_by_every_reader(run_dir, tmp_path, ("max_action",))


@pytest.mark.parametrize("key", ["agent", "dataset", "train"])
def test_a_config_without_a_key_every_eabc_writes_is_refused_naming_it(started, tmp_path, key):
    """Before: ``KeyError: 'agent'`` from --resume, and the preset's settings silently in place
    of the run's for evaluate and load_policy."""
    run_dir = copy_run(started, tmp_path)
    edit_config(run_dir, lambda c: {k: v for k, v in c.items() if k != key})
    refused_by_every_reader(run_dir, tmp_path, (f"config.json: {key} is missing",))
    runs, _ = results.collect(tmp_path / "root", write=False)
    assert list(runs["status"]) == ["broken"] and f"{key} is missing" in runs["config"][0]


def test_the_pretraining_progress_file_is_checked_for_finite_values(tmp_path):
    """The model fit's progress (``pretrain.msgpack``) is read through the same check."""
    checkpoint.write_tree(tmp_path / "p.msgpack", {"model": {"w0": np.array([1.0, np.nan])}})
    with pytest.raises(checkpoint.CheckpointError, match="p.msgpack holds NaN/inf in model/w0"):
        checkpoint.read_tree(tmp_path / "p.msgpack")


# ----------------------------------------------------------------------------------------------
# Dataset metadata


@pytest.mark.parametrize("scores", [(3234.3, -20.3), (5.0, 5.0), (-math.inf, 10.0)])
def test_reference_scores_out_of_order_are_refused_in_a_file(tmp_path, scores):
    """Before: random above expert was accepted, and near-random data then scored 98.8."""
    low, high = scores
    path = tmp_path / "d.npz"
    np.savez(path, **tiny_arrays(), env_id=np.asarray("Pendulum-v1"),
             ref_min_score=np.asarray(low), ref_max_score=np.asarray(high))  # fmt: skip
    with pytest.raises(DatasetError) as error:
        load_file(path)
    message = str(error.value)
    assert str(path) in message and "ref_min_score" in message and "\n" not in message
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--dataset", str(path), "--algo", "td3bc", "--dry-run"])
    assert "ref_min_score" in str(exit_.value.code) and str(path) in str(exit_.value.code)


def test_reference_scores_out_of_order_are_refused_in_a_run_config(started, tmp_path):
    run_dir = copy_run(started, tmp_path)
    edit_config(
        run_dir,
        lambda c: {**c, "dataset": {**c["dataset"], "ref_min_score": 10.0, "ref_max_score": 1.0}},
    )
    refused_by_every_reader(run_dir, tmp_path, ("dataset: its reference scores ref_min_score",))


def test_a_file_of_timeouts_only_is_described_as_such(tmp_path):
    """Before: "the dataset is empty", of a file with 40 rows."""
    path = tmp_path / "d.npz"
    np.savez(path, **tiny_arrays(), timeouts=np.ones(40, bool))
    with pytest.raises(DatasetError) as error:
        load_file(path)
    message = str(error.value)
    assert "empty" not in message and "40 rows" in message and "timeout" in message
    assert str(path) in message and "\n" not in message


# ----------------------------------------------------------------------------------------------
# Sweeps: every name and dataset checked before any job starts


def sweep_argv(tmp_path: Path, *datasets: str) -> list[str]:
    return ["sweep", "--datasets", *datasets, "--algos", "td3bc", "--seeds", "0", "--steps",
            "200", "--root", str(tmp_path / "root")]  # fmt: skip


@pytest.mark.parametrize("dry_run", [True, False])
def test_a_sweep_whose_run_directory_name_is_too_long_is_refused_before_any_job(tmp_path, dry_run):
    """A dataset file may have a 240-character name; its run directory's name (with the
    algorithm and the seed) then exceeds the file system's 255 bytes. Before: the dry run
    listed it as pending, and the sweep died on it with a traceback, killing its healthy
    running job."""
    good, long = tmp_path / "good.npz", tmp_path / f"{'d' * 236}.npz"
    for path in (good, long):
        np.savez(path, **tiny_arrays(), env_id=np.asarray("Pendulum-v1"))
    before = snapshot(tmp_path)
    argv = sweep_argv(tmp_path, str(good), str(long)) + ["--dry-run"] * dry_run
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    message = str(exit_.value.code)
    assert message.startswith("error: ") and "\n" not in message, message
    assert str(long) in message and "255" in message
    assert snapshot(tmp_path) == before and not (tmp_path / "root").exists()


@pytest.mark.parametrize("dry_run", [True, False])
def test_a_sweep_naming_a_missing_minari_dataset_is_refused_before_any_job(
    tmp_path, monkeypatch, dry_run
):
    """The README promises every dataset is checked before the first run starts. Before: a
    ``minari:`` dataset was found missing only when its job started."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    good = tmp_path / "good.npz"
    np.savez(good, **tiny_arrays(), env_id=np.asarray("Pendulum-v1"))
    argv = sweep_argv(tmp_path, str(good), "minari:test/pendulum/absent-v0")
    with pytest.raises(SystemExit) as exit_:
        main(argv + ["--dry-run"] * dry_run)
    message = str(exit_.value.code)
    assert "test/pendulum/absent-v0" in message and "\n" not in message, message
    assert not (tmp_path / "root").exists()


@pytest.mark.parametrize(
    "junk", [b"", b"not an HDF5 file", b"\x89HDF\r\n\x1a\n" + b"\0" * 100, "directory", "fifo"]
)
def test_a_junk_file_in_the_cache_does_not_stop_data_list(tmp_path, monkeypatch, capsys, junk):
    """Before: one unreadable file in the cache stopped ``eabc data list`` with an error."""
    monkeypatch.setenv("EABC_CACHE_DIR", str(tmp_path / "cache"))
    folder = tmp_path / "cache" / "datasets"
    folder.mkdir(parents=True)
    path = folder / "hopper-random.hdf5"
    if junk == "directory":
        path.mkdir()
    elif junk == "fifo":
        os.mkfifo(path)
    else:
        path.write_bytes(junk)
    (folder / "walker2d-random.info.json").write_text("{junk")  # a sidecar without its file
    main(["data", "list"])
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("hopper-random "))
    assert "unreadable" in row and "eabc data make hopper-random --force" in row
    assert any(line.startswith("walker2d-random ") for line in out.splitlines())
    assert len(out.splitlines()) > 10  # every built-in dataset is listed


# ----------------------------------------------------------------------------------------------
# Generated: every value of every file, each one refused or used as it is


def one_line(error: BaseException | str, *names: str) -> str:
    message = str(error)
    assert message and "\n" not in message and "Traceback" not in message, message
    assert any(name in message for name in names), (message, names)
    return message


@contextlib.contextmanager
def scratch():
    with tempfile.TemporaryDirectory(prefix="eabc-adversarial-files-") as folder:
        yield Path(folder)


def float_leaves(tree, prefix=""):
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from float_leaves(value, f"{prefix}/{key}".lstrip("/"))
    elif np.asarray(tree).dtype.kind == "f" and np.asarray(tree).size:
        yield prefix


def at(tree, where: str):
    *parents, last = where.split("/")
    for key in parents:
        tree = tree[key]
    return tree, last


@settings(SETTINGS, max_examples=40)
@given(choice=st.integers(0, 10**6), value=st.sampled_from([math.nan, math.inf, -math.inf]),
       element=st.integers(0, 10**6))  # fmt: skip
def test_any_non_finite_value_in_a_checkpoint_is_refused(started, choice, value, element):
    """NaN or +-inf in any float of the agent's state or the normaliser (its checksum
    recomputed), but in the running bounds that start infinite: refused in one line naming the
    file by every reader."""
    data = (started / checkpoint.CHECKPOINT).read_bytes()
    raw = pytree.loads(data[:-40])
    leaves = [f"agent/{p}" for p in float_leaves(raw["agent"])] + ["normalizer/mean",
                                                                  "normalizer/std"]  # fmt: skip
    where = leaves[choice % len(leaves)]
    parent, key = at(raw, where)
    array = np.array(parent[key])
    array.reshape(-1)[element % array.size] = value
    parent[key] = array
    with scratch() as folder:
        run_dir = folder / "run"
        shutil.copytree(started, run_dir)
        checkpoint.write_tree(run_dir / checkpoint.CHECKPOINT, raw)
        infinite = get_algorithm("td3bc").infinite_state
        if key in infinite and not math.isnan(value):
            checkpoint.load_raw(run_dir, infinite=infinite)  # a bound that may be infinite
            return
        for read in (checkpoint.load_raw, load_policy):
            with pytest.raises(checkpoint.CheckpointError) as error:
                read(run_dir)
            one_line(error.value, str(run_dir / checkpoint.CHECKPOINT))
            assert where.split("/", 1)[1] in str(error.value) or where in str(error.value)


CONFIG_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5), st.booleans(),
    st.none(), st.text(max_size=3), st.lists(st.integers(), max_size=2), st.just({}),
)  # fmt: skip


@settings(SETTINGS, max_examples=80)
@given(
    key=st.sampled_from(
        [
            "run_id",
            "train",
            "agent",
            "dataset",
            "max_action",
            "dataset.name",
            "dataset.size",
            "dataset.env_id",
            "dataset.ref_min_score",
            "dataset.ref_max_score",
            "dataset.fingerprint",
        ]
    ),  # fmt: skip
    action=st.sampled_from(["delete", "set"]),
    value=CONFIG_VALUES,
)
def test_any_edit_of_a_config_key_is_used_as_is_or_refused_naming_the_file(
    started, key, action, value
):
    """Each key of config.json deleted or set to any JSON value: load_policy either returns the
    run's own policy (its actions within Pendulum's bound of 2) or refuses in one line naming
    config.json; never a KeyError or a policy scaled by another bound."""
    config = json.loads((started / checkpoint.CONFIG).read_text())
    *parents, last = key.split(".")
    inner = config
    for part in parents:
        inner = inner[part]
    if action == "delete":
        inner.pop(last, None)
    else:
        inner[last] = value
    with scratch() as folder:
        run_dir = folder / "run"
        shutil.copytree(started, run_dir)
        (run_dir / checkpoint.CONFIG).write_text(json.dumps(config))
        try:
            policy = load_policy(run_dir)
        except ValueError as error:
            one_line(error, str(run_dir))
            return
        actions = policy(np.random.default_rng(0).normal(size=(64, 3)).astype(np.float32))
        assert np.isfinite(actions).all() and np.abs(actions).max() <= 2.0 + 1e-6
        saved = run_config.read(run_dir)
        assert saved.get("max_action") in (None, 2.0) and "agent" in saved


REFERENCE = st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True),
                      st.sampled_from([0.0, 1.0, -1.0, 100.0]))  # fmt: skip


@settings(SETTINGS, max_examples=80)
@given(low=REFERENCE, high=REFERENCE)
def test_any_reference_scores_load_in_order_or_are_refused_naming_them(low, high):
    """A file's reference scores: loaded when both are finite with the random one below the
    expert one (or when either is absent: returns only, or refused when a run starts), refused
    in one line naming the file and ref_min_score otherwise."""
    extra = {k: np.asarray(v) for k, v in (("ref_min_score", low), ("ref_max_score", high))
             if v is not None}  # fmt: skip
    with scratch() as folder:
        path = folder / "d.npz"
        np.savez(path, **tiny_arrays(), env_id=np.asarray("Pendulum-v1"), **extra)
        given_ = [v for v in (low, high) if v is not None]
        good = all(math.isfinite(v) for v in given_) and (len(given_) < 2 or low < high)
        if good:
            data = load_file(path)
            assert (data.ref_min_score, data.ref_max_score) == (low, high)
            return
        with pytest.raises(DatasetError) as error:
            load_file(path)
        one_line(error.value, str(path))
        assert "ref_min_score" in str(error.value) or "ref_max_score" in str(error.value)


@settings(SETTINGS, max_examples=60)
@given(timeouts=st.lists(st.booleans(), min_size=1, max_size=12),
       terminals=st.lists(st.booleans(), min_size=12, max_size=12))  # fmt: skip
def test_any_timeouts_load_or_are_refused_saying_why(timeouts, terminals):
    """Any pattern of timeouts and terminals in a file without next observations: it loads
    (each episode kept apart), or, when no row has a next observation, it is refused saying
    so; never "empty" of a file with rows."""
    rows = len(timeouts)
    with scratch() as folder:
        path = folder / "d.npz"
        np.savez(path, **tiny_arrays(rows, terminals=np.asarray(terminals[:rows])),
                 timeouts=np.asarray(timeouts))  # fmt: skip
        if rows > 1 and not all(timeouts[:-1]):
            assert load_file(path).size == sum(not t for t in timeouts[:-1])
            return
        with pytest.raises(DatasetError) as error:
            load_file(path)
        message = one_line(error.value, str(path))
        assert "empty" not in message and ("timeout" in message or "one row" in message)


MINARI_ID_PARTS = st.text(alphabet="ab1-_./~ ", min_size=0, max_size=6)


@settings(SETTINGS, max_examples=150)
@given(parts=st.lists(MINARI_ID_PARTS, min_size=1, max_size=4),
       version=st.sampled_from(["", "-v0", "-v12", "-v", "v1", "-vx"]),
       absolute=st.booleans())  # fmt: skip
def test_any_minari_id_is_inside_the_minari_path_or_refused_before_anything(
    parts, version, absolute
):
    """An export id (and a ``minari:`` id) of any characters: accepted only when it names a
    folder inside the Minari path, ``NAME-vN``; refused in one line naming --dataset-id (or the
    id) otherwise; nothing is made either way, outside the Minari path or in it."""
    from eabc.data import loaders  # noqa: PLC0415

    dataset_id = ("/" if absolute else "") + "/".join(parts) + version
    with scratch() as folder:
        root = folder / "minari" / "datasets"
        old = os.environ.get("MINARI_DATASETS_PATH")
        os.environ["MINARI_DATASETS_PATH"] = str(root)
        try:
            try:
                loaders.check_export_target(dataset_id, overwrite=False)
            except DatasetError as error:
                one_line(error, "--dataset-id")
            else:
                assert loaders.MINARI_ID.fullmatch(dataset_id) and not absolute
                assert (root / dataset_id).resolve().is_relative_to(root.resolve())
                assert ".." not in dataset_id.split("/") and version.startswith("-v")
            with pytest.raises(DatasetError) as error:  # nothing there to load
                load_dataset_by_id(dataset_id)
            one_line(error.value, dataset_id)
        finally:
            if old is None:
                os.environ.pop("MINARI_DATASETS_PATH")
            else:
                os.environ["MINARI_DATASETS_PATH"] = old
        assert sorted(p.name for p in folder.rglob("*")) == []  # nothing made


def load_dataset_by_id(dataset_id: str):
    from eabc.data.sources import load_dataset  # noqa: PLC0415

    return load_dataset(f"minari:{dataset_id}")


@pytest.fixture(scope="module")
def minari_dataset(tmp_path_factory):
    """A Minari path holding one intact Pendulum dataset (Minari's own writer)."""
    import minari  # noqa: PLC0415
    from minari.data_collector import EpisodeBuffer  # noqa: PLC0415

    root = tmp_path_factory.mktemp("minari")
    rng = np.random.default_rng(0)
    episodes = [EpisodeBuffer(observations=rng.normal(size=(n + 1, 3)).astype(np.float32),
                              actions=rng.uniform(-2, 2, (n, 1)).astype(np.float32),
                              rewards=rng.normal(size=n), terminations=np.zeros(n, bool),
                              truncations=np.r_[np.zeros(n - 1, bool), True])
                for n in (5, 7)]  # fmt: skip
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            minari.create_dataset_from_buffers("test/pendulum/tiny-v0", episodes,
                                               env="Pendulum-v1")  # fmt: skip
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH")
        else:
            os.environ["MINARI_DATASETS_PATH"] = old
    return root


@settings(SETTINGS, max_examples=60)
@given(file=st.sampled_from(["main_data.hdf5", "metadata.json"]),
       keep=st.floats(0, 1), flips=st.lists(st.integers(0, 10**6), max_size=3))  # fmt: skip
def test_any_damage_to_a_minari_folder_loads_the_same_data_or_names_the_file(
    minari_dataset, monkeypatch, file, keep, flips
):
    """A Minari dataset's data file or metadata.json cut short anywhere or with bytes changed:
    it loads the very same transitions (the damage missed what is read), or is refused in one
    line naming the damaged dataset's folder; never "not in the local Minari path"."""
    dataset_id = "test/pendulum/tiny-v0"
    with scratch() as folder:
        shutil.copytree(minari_dataset, folder / "m")
        monkeypatch.setenv("MINARI_DATASETS_PATH", str(folder / "m"))
        intact = load_dataset_by_id(dataset_id)
        path = folder / "m" / dataset_id / "data" / file
        data = bytearray(path.read_bytes())
        for flip in flips:
            data[flip % len(data)] ^= 0xFF
        path.write_bytes(bytes(data[: max(0, round(keep * len(data)))]))
        try:
            loaded = load_dataset_by_id(dataset_id)
        except DatasetError as error:
            message = one_line(error, str(folder / "m" / dataset_id))
            assert "not in the local Minari path" not in message and "damaged" in message
            return
        assert loaded.fingerprint() == intact.fingerprint()


@settings(SETTINGS, max_examples=30)
@given(length=st.integers(1, 251))
def test_any_dataset_name_length_plans_or_is_refused_before_a_sweep_starts(length):
    """A dataset file of any name length: the dry run plans it when its run's names fit the
    file system, else refuses naming the file; the sweep's root is never made."""
    with scratch() as folder:
        path = folder / f"{'n' * length}.npz"
        np.savez(path, **tiny_arrays(), env_id=np.asarray("Pendulum-v1"))
        argv = ["sweep", "--datasets", str(path), "--algos", "td3bc", "--seeds", "0", "--steps",
                "200", "--root", str(folder / "root"), "--dry-run"]  # fmt: skip
        out = io.StringIO()
        try:
            with contextlib.redirect_stdout(out):
                main(argv)
        except SystemExit as exit_:
            one_line(exit_.code, str(path))
            assert length + 40 > 255  # a name of about that length, with its algorithm and seed
        else:
            run_name = next(line.split()[-1] for line in out.getvalue().splitlines()
                            if line.strip().startswith("pending"))  # fmt: skip
            assert len(f"{run_name}.log".encode()) <= 255
        assert not (folder / "root").exists()


@settings(SETTINGS, max_examples=25)
@given(junk=st.binary(max_size=64), name=st.sampled_from(["hopper-random", "hopper-medium"]))
def test_any_junk_in_the_cache_is_one_unreadable_row_of_data_list(monkeypatch, junk, name):
    with scratch() as folder:
        monkeypatch.setenv("EABC_CACHE_DIR", str(folder))
        (folder / "datasets").mkdir()
        (folder / "datasets" / f"{name}.hdf5").write_bytes(junk)
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            main(["data", "list"])
        rows = {line.split()[0]: line for line in out.getvalue().splitlines()[1:]}
        assert "unreadable" in rows[name] and f"eabc data make {name} --force" in rows[name]
        assert "(not made)" in rows["walker2d-random"]


def test_the_dry_run_says_what_the_sweep_would_refuse(tmp_path, capsys):
    """A root holding a run of another spec under a run's name: the sweep refuses to start;
    its dry run used to list the run as ``changed`` and say nothing of the refusal."""
    from eabc.experiments.spec import expand  # noqa: PLC0415

    good = tmp_path / "good.npz"
    np.savez(good, **tiny_arrays(), env_id=np.asarray("Pendulum-v1"))
    argv = sweep_argv(tmp_path, str(good))
    (run,) = expand({"datasets": [str(good)], "algos": ["td3bc"], "seeds": [0], "steps": 200})
    run_dir = tmp_path / "root" / "runs" / run.run_id
    run_dir.mkdir(parents=True)
    (run_dir / "sweep.json").write_text(json.dumps({**run.to_json(), "seed": 1}))
    with pytest.raises(SystemExit, match="trained with another spec"):
        main(argv)
    capsys.readouterr()
    main([*argv, "--dry-run"])
    err = capsys.readouterr().err
    assert "the sweep would refuse to start" in err and "trained with another spec" in err


def test_a_junk_file_in_the_cache_is_made_again(tmp_path, monkeypatch, capsys):
    """``eabc data make`` of a dataset whose cached file is junk makes it again (it used to call
    the junk cached and current, so that every later load refused it)."""
    monkeypatch.setenv("EABC_CACHE_DIR", str(tmp_path))
    path = tmp_path / "datasets" / "hopper-random.hdf5"
    path.parent.mkdir()
    path.write_bytes(b"junk")
    main(["data", "make", "hopper-random", "--size", "2000"])
    assert load_file(path).size > 0


def test_a_job_that_cannot_start_fails_alone(tmp_path, monkeypatch):
    """Whatever stops one job from starting (its log file cannot be made, the process cannot be
    spawned), the sweep's other jobs start and finish; the sweep then reports the one failure.
    Before, the exception left the pool and terminated the healthy running jobs."""
    from eabc.experiments import local_pool  # noqa: PLC0415
    from eabc.experiments.spec import expand  # noqa: PLC0415

    runs = expand({"datasets": ["hopper-random"], "algos": ["td3bc"], "seeds": [0, 1]})
    started = []

    class Finished:  # a worker that has already finished, successfully
        returncode = 0

        def __init__(self, cmd, **kwargs):
            (job,) = json.loads(cmd[-1])
            if job["seed"] == runs[0].seed:
                raise OSError(36, "File name too long")
            started.append(job["seed"])

        def poll(self):
            return 0

    monkeypatch.setattr(local_pool.subprocess, "Popen", Finished)
    lines = []
    with pytest.raises(RuntimeError, match=f"1 job\\(s\\) failed: {runs[0].run_id}"):
        local_pool.run_local([[runs[0]], [runs[1]]], tmp_path, workers=1, log=lines.append)
    assert started == [runs[1].seed]
    assert any(line.startswith(f"finished {runs[1].run_id}") for line in lines), lines
