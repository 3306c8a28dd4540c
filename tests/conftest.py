"""Small, fast datasets for the tests: Pendulum from a noisy swing-up controller."""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import shutil
import tempfile

import numpy as np
import pytest
from handcalc import make_batch

from eabc import compile_cache
from eabc.data.generate import rollout
from eabc.training import chunks

PENDULUM_RANDOM_RETURN = -1200.0
PENDULUM_CONTROLLER_RETURN = -130.0


# d3rlpy pins gymnasium 1.0.0 and brings PyTorch, so it lives in an environment of its own
# (`pip install -e ".[d3rlpy,minari,test]"`, made by .ci/run), not in `dev`: its interop tests are collected
# where d3rlpy is installed, and the header says so where it is not.
HAVE_D3RLPY = importlib.util.find_spec("d3rlpy") is not None
collect_ignore = [] if HAVE_D3RLPY else ["data/test_d3rlpy.py"]


def pytest_terminal_summary(terminalreporter):
    if not HAVE_D3RLPY:
        terminalreporter.write_line(
            "d3rlpy interop (tests/data/test_d3rlpy.py) not collected: d3rlpy is not installed here; "
            "it runs in an environment of its own (pip install -e '.[d3rlpy,minari,test]')"
        )


def pytest_configure(config):
    """One fresh compilation cache for the session, shared with the tests' subprocesses (CLI runs,
    sweep workers): each program compiles once, as in a user's sweep (8.5 -> 7 min on 2 cores)."""
    config.xla_cache = tempfile.mkdtemp(prefix="eabc-test-xla-")
    os.environ["EABC_COMPILE_CACHE"] = config.xla_cache
    compile_cache.enable(config.xla_cache)
    # Time estimates at the reference host's figures, not at this host's load of the moment
    # (tests/test_timing.py measures the probe itself).
    os.environ.setdefault("EABC_HOST_SPEED", "1")


def pytest_unconfigure(config):
    shutil.rmtree(getattr(config, "xla_cache", ""), ignore_errors=True)


LONGEST_FIRST = (
    "test_model_based.py", "test_experiments.py", "test_td3_core.py", "test_bear_uwac.py",
    "test_contract_more.py", "test_study_engine.py", "test_sac.py", "test_adversarial_bounds.py",
    "test_iql_cql.py", "test_faults.py", "test_antmaze.py", "test_training.py",
    "test_run_axis.py", "test_contract.py", "test_networks.py", "test_eabc_variants.py",
    "test_eval_pool.py", "test_rebrac.py", "test_zoo.py", "test_benchmarks.py",
    "test_parallel_data.py",
)  # fmt: skip
"""The modules that take longest (each one's summed test durations in a full run: 27-140 s on a
busy 2-core Zen 4, the rest under 25 s each), run first. pytest-xdist hands each worker one
module at a time in collection order (pyproject.toml turns off its own order, by number of
tests, which started test_experiments' 4 tests, a minute, near the end), so the long ones start
early, the short ones fill the end, and the two workers end together."""


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest in order


def swing_up(obs: np.ndarray, rng: np.random.Generator, noise: float = 0.5) -> np.ndarray:
    """Energy-pumping swing-up with a PD balance near the top (about -130 per episode)."""
    cos, sin, velocity = obs
    if cos > 0.9:
        torque = -8.0 * np.arctan2(sin, cos) - 1.5 * velocity
    else:  # E = w^2/2 + 15 cos(theta) rises with torque * w; upright at rest is E = 15
        energy = 0.5 * velocity**2 + 15.0 * cos
        torque = 2.0 * np.sign(velocity * (15.0 - energy)) if abs(velocity) > 1e-3 else 2.0
    return np.clip([torque + noise * rng.normal()], -2.0, 2.0).astype(np.float32)


@pytest.fixture(scope="session")
def pendulum_dataset():
    data = rollout("Pendulum-v1", swing_up, 10_000, seed=0, max_episode_steps=200)
    return dataclasses.replace(
        data,
        name="pendulum-swingup",
        ref_min_score=PENDULUM_RANDOM_RETURN,
        ref_max_score=PENDULUM_CONTROLLER_RETURN,
    )


@pytest.fixture
def quick_chunks(monkeypatch):
    """Training chunks built by $EABC_FAST_COMPILE (XLA O0, see chunks.FAST_COMPILE_OPTIONS) for
    tests of a run's plumbing that train a few hundred steps of a program no other test compiles:
    a fraction of the compile time (BEAR's 64-64 chunk: 1.7 s of CPU against about 7 s), and such
    short runs barely feel the slower steps (2-3 times slower). Learning checks keep the default
    build. (It is the test's own monkeypatch: monkeypatch.undo() undoes it too.)"""
    monkeypatch.setenv(chunks.FAST_COMPILE_ENV, "1")


@pytest.fixture
def quick_figures(monkeypatch):
    """Report figures at screen resolution, for tests of a report's tables, text and merging:
    its PNGs take a fraction of the time at 72 dpi than at 300. tests/experiments/test_report.py checks the
    figure files themselves in full."""
    from eabc.experiments import figures  # noqa: PLC0415

    monkeypatch.setattr(figures, "PRINT_DPI", 72)


@pytest.fixture
def batch():
    """A tiny batch of 7 random transitions (3-d observations, 2-d actions, two terminals)."""
    return make_batch()
