"""Malformed input, generated: dataset files (members, dtypes, shapes, headers, attributes), sweep
specs (each key's type and value) and flag values (numbers and text). Each ends one of two ways:
it works, or it is refused in one line (``error: ...`` from the command, or a ``DatasetError`` /
``ValueError`` of one line) that names the file, the key or the flag, and the disk is as it was.

No training and no compilation: every input is checked before work starts, and the commands run
here stop there (``--dry-run``, or parsing alone where a valid input would start work).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import tempfile
import zipfile
from collections import defaultdict
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from eabc import cli, ranges
from eabc.data.dataset import DatasetError
from eabc.data.loaders import load_file
from eabc.experiments.spec import KEYS, TRAIN_FIELDS, expand

CASES: dict[str, set[str]] = defaultdict(set)
"""The distinct inputs each test generated (written to $EABC_ADVERSARIAL_CASES when set)."""

SETTINGS = settings(
    deadline=None,
    database=None,  # the same examples on every machine
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


@pytest.fixture(scope="module", autouse=True)
def count_cases():
    yield
    target = os.environ.get("EABC_ADVERSARIAL_CASES")
    if target:
        counts = {name: len(cases) for name, cases in CASES.items()}
        Path(target).write_text(json.dumps({**counts, "total": sum(counts.values())}, indent=1))


def snapshot(root: Path) -> dict[str, str]:
    """Every path under ``root`` with its content's SHA-256 (its kind for other than files)."""
    out = {}
    for path in sorted(root.rglob("*")):
        kind = "file" if path.is_file() else "dir" if path.is_dir() else "other"
        digest = hashlib.sha256(path.read_bytes()).hexdigest() if kind == "file" else kind
        out[str(path.relative_to(root))] = digest
    return out


@contextlib.contextmanager
def workspace():
    """A fresh directory, the working directory and the dataset cache for one example."""
    old, cache = os.getcwd(), os.environ.get("EABC_CACHE_DIR")
    with tempfile.TemporaryDirectory(prefix="eabc-adversarial-") as folder:
        os.chdir(folder)
        os.environ["EABC_CACHE_DIR"] = str(Path(folder) / "cache")
        try:
            yield Path(folder)
        finally:
            os.chdir(old)
            if cache is None:
                os.environ.pop("EABC_CACHE_DIR", None)
            else:
                os.environ["EABC_CACHE_DIR"] = cache


def assert_one_line(message: str, *names: str) -> None:
    """A refusal: one line that names one of ``names`` (a file, a key, a flag or the value)."""
    assert message and "\n" not in message and "Traceback" not in message, message
    assert any(name and name in message for name in names), (message, names)


# ----------------------------------------------------------------------------------------------
# Dataset files

ARRAY_KEYS = ("observations", "actions", "rewards", "terminals", "timeouts", "next_observations")
DTYPES = tuple(
    np.dtype(d)
    for d in ("<f4", "<f8", ">f8", "<f2", "<i4", "<i8", "|u1", "|b1", "<c8", "|O", "<U3", "|S2",
              "<M8[s]", [("a", "<f4"), ("b", "<i2")])
)  # fmt: skip
GOOD_DTYPES = DTYPES[:2] + DTYPES[4:5] + DTYPES[7:8]


def _array(shape: tuple[int, ...], dtype: np.dtype, fill: float) -> np.ndarray:
    if dtype.kind == "O":
        return np.full(shape, None, dtype=object)
    if dtype.kind in "US":
        return np.full(shape, "ab", dtype=dtype)
    array = np.zeros(shape, dtype)
    if dtype.kind in "fc" or (dtype.kind in "iu" and math.isfinite(fill)):
        with np.errstate(invalid="ignore"):
            array[...] = fill if dtype.kind in "fc" else int(max(0, fill))
    return array


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    return buffer.getvalue()


@st.composite
def members(draw, key: str, rows: int):
    """One member: a shape, a dtype, a fill value and how it is stored (as written, with a
    header that claims another shape, cut short, or not an array at all); half of them as a
    dataset file holds it, so that whole files of good members come up too."""
    width = draw(st.integers(1, 3))
    good = (rows, width) if key in ("observations", "actions", "next_observations") else (rows,)
    if draw(st.booleans()):
        return (
            good,
            draw(st.sampled_from(GOOD_DTYPES)),
            draw(st.sampled_from([0.0, 1.0])),
            "written",
            (),
        )
    rank = draw(
        st.sampled_from(["good", "row", "column", "scalar", "cube", "empty-dim", "other-n"])
    )
    shape = {
        "good": good, "row": (rows, width), "column": (rows,), "scalar": (),
        "cube": (rows, width, 2), "empty-dim": (rows, 0), "other-n": (draw(st.integers(0, 7)), width),
    }[rank]  # fmt: skip
    dtype = draw(st.sampled_from(GOOD_DTYPES + DTYPES))
    fill = draw(st.sampled_from([0.0, 1.0, 0.5, -2.0, math.nan, math.inf]))
    form = draw(st.sampled_from(["written"] * 5 + ["claims", "cut", "garbage"]))
    claimed = draw(st.sampled_from([(10**12, 17), (rows + 5, width), (2**40,)]))
    return shape, dtype, fill, form, claimed


def _member_bytes(shape, dtype, fill, form, claimed) -> bytes:
    if form == "garbage":
        return b"neither zip nor npy"
    data = _npy(_array(shape, dtype, fill))
    if form == "cut":
        return data[: max(1, len(data) // 2)]
    if form == "claims":
        buffer = io.BytesIO()
        descr = np.lib.format.dtype_to_descr(np.dtype("<f4"))
        header = {"descr": descr, "fortran_order": False, "shape": claimed}
        np.lib.format.write_array_header_1_0(buffer, header)
        return buffer.getvalue() + b"\0" * 32
    return data


ATTRIBUTE_VALUES = st.one_of(
    st.sampled_from(["hopper-medium", "", "Pendulum-v1", '{"recipe": "x"}', "{nope", "1.5"]),
    st.sampled_from([0.0, -1200.0, math.inf, math.nan, 3]),
)


@st.composite
def npz_files(draw):
    rows = draw(st.integers(1, 6))
    keys = draw(st.sets(st.sampled_from(ARRAY_KEYS), min_size=2) | st.just(set(ARRAY_KEYS[:4])))
    chosen = {key: draw(members(key, rows)) for key in keys}
    attributes = draw(
        st.dictionaries(
            st.sampled_from(["name", "env_id", "metadata", "ref_min_score", "ref_max_score"]),
            ATTRIBUTE_VALUES,
            max_size=3,
        )
    )
    compression = draw(st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED]))
    whole = draw(st.sampled_from(["zip"] * 8 + ["npy", "empty", "text"]))
    return rows, chosen, attributes, compression, whole


@settings(SETTINGS, max_examples=150)
@given(npz_files())
def test_any_npz_loads_or_is_refused_in_one_line_naming_the_file(case):
    CASES["npz"].add(repr(case))
    rows, chosen, attributes, compression, whole = case
    with workspace() as folder:
        path = folder / "data.npz"
        if whole == "npy":
            path.write_bytes(_npy(np.zeros((rows, 3))))
        elif whole == "empty":
            path.write_bytes(b"")
        elif whole == "text":
            path.write_text("observations,actions\n1,2\n")
        else:
            with zipfile.ZipFile(path, "w", compression=compression) as archive:
                for key, member in chosen.items():
                    archive.writestr(f"{key}.npy", _member_bytes(*member))
                for key, value in attributes.items():
                    archive.writestr(f"{key}.npy", _npy(np.asarray(value)))
        before = snapshot(folder)
        try:
            dataset = load_file(path)
        except DatasetError as error:
            assert_one_line(str(error), str(path))
            event("refused")
        else:  # a dataset: float32 arrays of one length, finite, flags as booleans
            event("loaded")
            assert dataset.size >= 1 and dataset.observations.dtype == np.float32
            assert len({len(getattr(dataset, k)) for k in ARRAY_KEYS}) == 1
            assert np.isfinite(dataset.observations).all() and dataset.terminals.dtype == bool
        assert snapshot(folder) == before


@settings(SETTINGS, max_examples=40)
@given(
    st.integers(1, 5),
    st.dictionaries(
        st.sampled_from(ARRAY_KEYS),
        st.tuples(st.just("good"), st.sampled_from(GOOD_DTYPES))
        | st.tuples(
            st.sampled_from(["row", "column", "scalar", "cube", "unwritten", "group"]),
            st.sampled_from([*GOOD_DTYPES, np.dtype("<c8"), np.dtype("|S2"), "text"]),
        ),
        min_size=2,
    ),
    st.dictionaries(st.sampled_from(["name", "ref_min_score", "metadata"]), ATTRIBUTE_VALUES),
)
def test_any_hdf5_loads_or_is_refused_in_one_line_naming_the_file(rows, chosen, attributes):
    CASES["hdf5"].add(repr((rows, chosen, attributes)))
    with workspace() as folder:
        path = folder / "data.hdf5"
        with h5py.File(path, "w") as f:
            for key, (rank, dtype) in chosen.items():
                if rank == "good":
                    rank = "row" if key in ("observations", "actions") else "column"
                shape = {"row": (rows, 2), "column": (rows,), "scalar": (), "cube": (rows, 2, 2),
                         "unwritten": (10**12, 17), "group": None}[rank]  # fmt: skip
                if shape is None:
                    f.create_group(key)
                elif rank == "unwritten":
                    f.create_dataset(key, shape=shape, dtype="<f4")
                elif dtype == "text":
                    f.create_dataset(key, data=["x"] * rows, dtype=h5py.string_dtype())
                else:
                    f.create_dataset(key, data=np.zeros(shape, dtype))
            for key, value in attributes.items():
                f.attrs[key] = value
        before = snapshot(folder)
        try:
            dataset = load_file(path)
        except DatasetError as error:
            assert_one_line(str(error), str(path))
            event("refused")
        else:
            event("loaded")
            assert dataset.size >= 1 and dataset.observations.dtype == np.float32
        assert snapshot(folder) == before


# ----------------------------------------------------------------------------------------------
# Sweep specs

JUNK = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=6),
    st.lists(
        st.one_of(st.integers(-5, 5), st.text(max_size=4), st.none(), st.floats()), max_size=3
    ),
    st.dictionaries(st.text(max_size=5), st.integers(), max_size=2),
)
DATASETS = st.sampled_from(["hopper-random", "hopper-medium", "walker2d-random", "~nouser/d.npz"])
ALGOS = st.sampled_from(["bc", "td3bc", "iql", "eabc"])
SETTING_VALUES = st.one_of(
    st.integers(-3, 12),
    st.floats(-1, 2),
    st.sampled_from(["min", "mean-std", "yes"]),
    st.booleans(),
)
TRAIN_KEYS = st.sampled_from(sorted(TRAIN_FIELDS | {"seed", "bogus"}))
SPECS = st.fixed_dictionaries(
    {},
    optional={
        "datasets": st.one_of(st.lists(DATASETS, min_size=1, max_size=2), DATASETS, JUNK),
        "algos": st.one_of(st.lists(ALGOS, min_size=1, max_size=2), ALGOS, JUNK),
        "variants": st.one_of(
            st.lists(
                st.one_of(
                    ALGOS,
                    st.fixed_dictionaries(
                        {"algo": ALGOS},
                        optional={
                            "datasets": st.one_of(st.lists(DATASETS, max_size=2), JUNK),
                            "num_critics": SETTING_VALUES,
                            "critic_layer_norm": SETTING_VALUES,
                        },
                    ),
                    JUNK,
                ),
                max_size=2,
            ),
            JUNK,
        ),
        "seeds": st.one_of(
            st.lists(st.integers(0, ranges.SEED_MAX), min_size=1, max_size=3),
            st.lists(
                st.one_of(st.integers(-(2**40), 2**40), st.floats(), st.booleans()), max_size=3
            ),
            JUNK,
        ),
        "steps": st.one_of(st.integers(-10, 10**7), JUNK),
        "grid": st.one_of(
            st.dictionaries(
                st.sampled_from(["num_critics", "confidence_level", "pessimism", "eta"]),
                st.one_of(st.lists(SETTING_VALUES, max_size=2), SETTING_VALUES),
                max_size=2,
            ),
            JUNK,
        ),
        "train": st.one_of(
            st.dictionaries(
                TRAIN_KEYS,
                st.one_of(st.integers(-5, 10**6), st.sampled_from([1000, 5000]), JUNK),
                max_size=3,
            ),
            JUNK,
        ),
        "bogus": JUNK,
    },
)


def spec_names(spec: dict) -> list[str]:
    """What a refusal of ``spec`` may name: its keys, their settings, an algorithm."""
    names = [*KEYS, *map(str, spec), "algorithm", "sweep"]
    for key in ("grid", "train"):
        if isinstance(spec.get(key), dict):
            names += [str(k) for k in spec[key]]
    variants = spec.get("variants")
    for entry in variants if isinstance(variants, list) else []:
        if isinstance(entry, dict):
            names += [str(k) for k in entry]
    return names


@settings(SETTINGS, max_examples=300)
@given(SPECS)
def test_any_spec_expands_to_runs_or_is_refused_naming_the_key(spec):
    CASES["spec"].add(repr(spec))
    try:
        runs = expand(spec)
    except ValueError as error:
        assert_one_line(str(error), *spec_names(spec))
        event("refused")
        return
    event("expanded")
    assert runs, "a valid spec makes at least one run"
    for run in runs:
        assert type(run.seed) is int and 0 <= run.seed <= ranges.SEED_MAX
        config = run.train_config()  # every run's train settings make a TrainConfig
        assert config.steps >= 1 and config.checkpoint_interval >= 1


@settings(SETTINGS, max_examples=25)
@given(SPECS)
def test_eabc_sweep_dry_run_plans_or_ends_in_one_error_line(spec):
    CASES["sweep-cli"].add(repr(spec))
    with workspace() as folder:
        path = folder / "spec.yaml"
        path.write_text(yaml.safe_dump(spec))
        before = snapshot(folder)
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                cli.main(["sweep", str(path), "--root", str(folder / "root"), "--dry-run"])
        except SystemExit as exit_:
            assert isinstance(exit_.code, str) and exit_.code.startswith("error: ")
            assert_one_line(exit_.code, *spec_names(spec))
            event("refused")
        else:
            event("planned")
        assert snapshot(folder) == before


# ----------------------------------------------------------------------------------------------
# Flag values

NUMBERS = st.one_of(
    st.integers(-3, 3), st.integers(-(2**70), 2**70), st.sampled_from([100, 1000, 5000, 2**32 - 1])
)
FLOATS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(1e-6, 10.0))
TEXT = st.one_of(
    st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=8),
    st.sampled_from(
        ["~nouser/x.npz", "/dev/null", ".", "x.hdf5", "minari:nope", "-", "hopper-random"]
    ),
)
TRAIN_NUMBER_FLAGS = ("seed", "steps", "batch-size", "eval-interval", "eval-episodes",
                      "log-interval", "checkpoint-interval")  # fmt: skip


@pytest.fixture(scope="module")
def small_npz(tmp_path_factory):
    """A 40-transition Pendulum-shaped dataset without reference scores."""
    path = tmp_path_factory.mktemp("data") / "tiny.npz"
    rng = np.random.default_rng(0)
    np.savez(path, observations=rng.normal(size=(40, 3)), actions=rng.uniform(-1, 1, (40, 1)),
             rewards=rng.normal(size=40), terminals=np.zeros(40, bool))  # fmt: skip
    return str(path)


def refused_or_planned(argv: list[str], names: list[str]) -> None:
    """``eabc ARGV`` (a dry run) prints its plan, or exits with one ``error:`` line naming one
    of ``names``."""
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            cli.main(argv)
    except SystemExit as exit_:
        assert isinstance(exit_.code, str) and exit_.code.startswith("error: "), exit_.code
        assert_one_line(exit_.code, *names)
        event("refused")
    else:
        event("planned")


@settings(SETTINGS, max_examples=40, suppress_health_check=list(HealthCheck))
@given(
    st.dictionaries(st.sampled_from(TRAIN_NUMBER_FLAGS), NUMBERS, max_size=4),
    st.dictionaries(st.sampled_from(["env", "run-dir", "algo", "dataset"]), TEXT, max_size=2),
    st.sampled_from(["bc", "td3bc", "iql"]),
)
def test_eabc_train_flags_plan_or_end_in_one_error_line(small_npz, numbers, texts, algo):
    CASES["train-flags"].add(repr((numbers, texts, algo)))
    flags = {"dataset": small_npz, "algo": algo, **{k: str(v) for k, v in numbers.items()}, **texts}
    argv = ["train", *(f"--{k}={v}" for k, v in flags.items()), "--dry-run"]
    with workspace() as folder:
        before = snapshot(folder)
        names = [f"--{k}" for k in flags] + [v for v in texts.values() if v.strip()]
        refused_or_planned(argv, names + ["algorithm", "dataset"])
        assert snapshot(folder) == before


NUMBER_FLAGS = {
    "evaluate": ("episodes", "seed"),
    "sac": ("seed", "steps", "update-every", "batch-size", "eval-interval", "checkpoint-interval",
            "start-steps", "lr", "alpha"),
    "sweep": ("seed", "steps", "workers", "eval-interval", "checkpoint-interval", "batch-size",
              "cpus-per-job", "gpus-per-job"),
}  # fmt: skip
"""The number flags of commands whose valid values would start work (parsed only here)."""
FLOAT_FLAGS = {"lr", "alpha", "cpus-per-job", "gpus-per-job"}


@st.composite
def number_flags(draw):
    command = draw(st.sampled_from(sorted(NUMBER_FLAGS)))
    names = draw(st.sets(st.sampled_from(NUMBER_FLAGS[command]), max_size=3))
    return command, {k: draw(FLOATS if k in FLOAT_FLAGS else NUMBERS) for k in sorted(names)}


@settings(SETTINGS, max_examples=60)
@given(number_flags())
def test_number_flags_parse_in_range_or_are_refused_naming_the_flag(case):
    """Through ``parse``: where a valid value would start work (an evaluation, SAC training),
    the checks before it are what is tested."""
    command, values = case
    CASES["number-flags"].add(repr(case))
    flag = lambda k: "seeds" if command == "sweep" and k == "seed" else k  # noqa: E731
    argv = [command, *(["RUN_DIR"] if command == "evaluate" else [])]
    argv += [f"--{flag(k)}={v}" for k, v in values.items()]
    try:
        cmd = cli.parse(argv)
    except ValueError as error:
        assert_one_line(str(error), *(f"--{flag(k)}" for k in values))
        event("refused")
        return
    event("accepted")
    for key, value in values.items():  # accepted: the value as given, within its range
        name = flag(key).replace("-", "_")
        got = getattr(getattr(cmd, "config", cmd), name, None)
        got = getattr(cmd, name) if got is None else got
        got = got[0] if isinstance(got, tuple) else got
        assert got == value or (isinstance(value, float) and math.isclose(got, value))
        if isinstance(value, float):
            assert math.isfinite(value)
        else:
            assert value >= 0 and (name not in ("seed", "seeds") or value <= ranges.SEED_MAX)
