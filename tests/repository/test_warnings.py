"""No command warns: a warning either points at a fix we owe (our use of a deprecated API, a
NumPy operation on nothing) and is fixed where it comes from, or it comes from another package's
own code and is filtered by its exact message in pyproject.toml, never hidden wholesale.

The suite makes every warning raised from our modules an error (pyproject.toml's
``filterwarnings``); here a representative session of commands runs in a fresh interpreter, every
warning shown (imports included), and any warning not filtered by name fails the test, naming it.
"""

from __future__ import annotations

import builtins
import json
import subprocess
import sys
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

SESSION = """
import builtins, json, sys, warnings
seen = []
warnings.simplefilter("always")  # every warning, every time, from every module
for action, message, category, module in json.loads(sys.argv[2]):  # the named filters
    warnings.filterwarnings(action, message, getattr(builtins, category), module)
warnings.showwarning = lambda message, category, filename, lineno, *rest: seen.append(
    f"{category.__name__}: {str(message)[:300]} ({filename}:{lineno})")
from eabc.cli import main
cache = sys.argv[1]
schedule = ["--steps", "20", "--log-interval", "10", "--eval-interval", "20",
            "--checkpoint-interval", "20", "--eval-episodes", "1", "--no-progress"]
for argv in (["data", "make", "hopper-random", "--size", "2000", "--cache-dir", cache],
             ["data", "info", "hopper-random", "--cache-dir", cache],
             ["train", "--dataset", "hopper-random", "--cache-dir", cache, "--algo", "eabc",
              "--num-critics", "3", "--run-dir", "runs/eabc", *schedule],
             ["train", "--dataset", "hopper-random", "--cache-dir", cache, "--algo", "iql",
              "--run-dir", "runs/iql", *schedule],
             ["evaluate", "runs/eabc", "--episodes", "1"],
             ["results", "runs"], ["report", "runs"]):
    main(argv)
print("WARNINGS " + json.dumps(seen))
"""


def filter_lines() -> list[str]:
    """pyproject.toml's ``[tool.pytest.ini_options] filterwarnings``."""
    import tomllib  # noqa: PLC0415 (Python 3.11+; the suite's own interpreter)

    options = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]
    return options["ini_options"].get("filterwarnings", [])


def named_filters() -> list[tuple[str, str, str, str]]:
    """pyproject.toml's ``ignore`` filters (action, message regex, category, module regex)."""
    filters = []
    for line in filter_lines():
        action, message, category, module = (line.split(":", 4) + [""] * 4)[:4]
        if action == "ignore":
            filters.append((action, message, category or "Warning", module))
    return filters


def test_the_filters_name_a_message_a_category_and_a_module():
    """Each third-party warning is filtered by what it says, its class and where it is raised;
    warnings from our own modules are errors."""
    lines = filter_lines()
    for _, message, category, module in named_filters():
        assert message and category != "Warning" and module and not module.startswith("eabc")
        assert issubclass(getattr(builtins, category), Warning), category
    assert any(line.startswith("error:") and line.endswith(":eabc") for line in lines), lines


def test_the_filters_apply_as_written():
    """A filter line parses as Python's warning filter (a bad regex would fail every test)."""
    for action, message, category, module in named_filters():
        with warnings.catch_warnings():
            warnings.filterwarnings(action, message, getattr(builtins, category), module)


def test_a_session_of_commands_warns_nothing_unnamed(tmp_path):
    """data make, data info, train (EABC and IQL), evaluate, results and report on a tiny
    dataset, each as a user types it: no warning but those filtered by name."""
    done = subprocess.run(
        [sys.executable, "-c", SESSION, str(tmp_path / "cache"), json.dumps(named_filters())],
        cwd=tmp_path, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    [line] = [line for line in done.stdout.splitlines() if line.startswith("WARNINGS ")]
    seen = json.loads(line.removeprefix("WARNINGS "))
    assert not seen, "\n".join(seen)
