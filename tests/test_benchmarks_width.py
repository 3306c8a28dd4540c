"""benchmarks/width.py: its table at tiny sizes, its speed-up column, and the commands the docs
give for it."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

import width  # noqa: E402


def _table(text: str) -> list[list[str]]:
    """The Markdown table's rows under its header, as cells."""
    lines = text.splitlines()
    start = lines.index(width.HEADER)
    assert lines[start + 1] == "|---|---|---|---|---|"
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip("|").split("|")])
    return rows


def test_tiny_run_prints_one_row_per_width_and_the_speed_up_is_the_ratio(tmp_path):
    out = tmp_path / "width.json"
    result = subprocess.run(
        [sys.executable, str(BENCHMARKS / "width.py"), "--algos", "td3bc", "--widths", "1", "2",
         "--steps", "4", "--repeats", "2", "--size", "2000", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=400,
        # The quick build and the cheapest step: this checks what the script prints, not how
        # fast a chunk runs (EABC's widths are the run-axis tests' and the device's).
        env={**os.environ, "EABC_FAST_COMPILE": "1"},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    text = result.stdout
    assert text.startswith("host: ") and "\ndevice: " in text
    assert "load average before: " in text and "load average after: " in text
    table = _table(text)
    assert [row[:2] for row in table] == [["td3bc", "1"], ["td3bc", "2"]]
    assert all(len(row) == 5 for row in table)
    steps, seed_steps, speed_up = ([float(row[i]) for row in table] for i in (2, 3, 4))
    assert all(rate > 0 for rate in steps + seed_steps)
    assert seed_steps[0] == pytest.approx(steps[0], abs=0.1)
    assert seed_steps[1] == pytest.approx(2 * steps[1], abs=0.2)  # printed to one decimal
    assert speed_up[0] == 1.0
    # The printed ratio against the ratio of the printed rates, each rounded: 0.005 for the
    # speed-up's two decimals, 0.05 on each rate's one.
    ratio = seed_steps[1] / seed_steps[0]
    rounding = 0.005 + ratio * (0.05 / seed_steps[1] + 0.05 / seed_steps[0]) + 1e-9
    assert abs(speed_up[1] - ratio) <= rounding

    figures = json.loads(out.read_text())
    rows = figures["rows"]
    assert [(r["width"], len(r["seed_steps_per_s_each_chunk"])) for r in rows] == [(1, 2), (2, 2)]
    assert rows[1]["speed_up"] == pytest.approx(
        rows[1]["seed_steps_per_s"] / rows[0]["seed_steps_per_s"]
    )


def test_rows_take_medians_and_divide_by_width_1():
    rows = width.rows("td3bc", {1: [100.0, 90.0, 110.0], 4: [260.0, 250.0, 240.0]})
    assert [(r["steps_per_s"], r["seed_steps_per_s"], r["speed_up"]) for r in rows] == [
        (100.0, 100.0, 1.0),
        (62.5, 250.0, 2.5),
    ]
    assert width.table_line(rows[1]) == "| td3bc | 4 | 62.5 | 250.0 | 2.50 |"


def test_width_1_is_always_measured_and_bad_sizes_are_refused(capsys):
    assert width.parse(["--widths", "8", "2"]).widths == [1, 2, 8]
    with pytest.raises(SystemExit):
        width.parse(["--widths", "0", "2"])
    assert "must be at least 1" in capsys.readouterr().err


def _documented_commands() -> list[list[str]]:
    """Every ``python benchmarks/width.py ...`` line in docs/ and the script's own docstring."""
    pages = [*sorted((ROOT / "docs").rglob("*.md")), BENCHMARKS / "width.py"]
    commands = []
    for page in pages:
        for line in page.read_text(encoding="utf-8").splitlines():
            if line.strip().startswith("python benchmarks/width.py"):  # prose may name the file
                commands.append(shlex.split(line.strip(), comments=True)[2:])
    return commands


def test_the_documented_commands_parse():
    """The docs' commands use flags the script has (the tiny run above runs the same entry point)."""
    commands = _documented_commands()
    assert len(commands) >= 4  # three in the docstring, one in docs/speed.md
    for argv in commands:
        width.parse(argv)
