"""The benchmarks' own machinery: the host line, the ceiling's sources, and the GPU script's smoke mode."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

import machine  # noqa: E402


def test_host_line_names_the_cpu_and_its_vector_isa():
    line = machine.host_line()
    assert line.startswith("host: ") and " cores; " in line
    assert machine.vector_isa() in line and machine.cpu_model() in line


def test_xla_peak_is_a_positive_rate_of_the_size_it_names():
    gflops, n = machine.xla_peak(sizes=(64, 128), chain=2, seconds=0.06)
    assert gflops > 0 and n in (64, 128)


def test_openblas_peak_lifts_the_kernel_override_for_its_measurement_only(monkeypatch):
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Sandybridge")
    monkeypatch.delenv("OPENBLAS_L2_SIZE", raising=False)  # some hosts' environments set it too
    monkeypatch.setenv("EABC_BENCH_SECONDS", "0.02")
    blas = machine.openblas_peak()
    assert blas["overrides"] == {"OPENBLAS_CORETYPE": "Sandybridge"} and blas["gflops"] > 0
    assert os.environ["OPENBLAS_CORETYPE"] == "Sandybridge"  # this process keeps its setting
    lines = machine.ceiling_lines(400.0, 2048, blas)
    assert lines[0] == "ceiling: XLA fp32 [2048, 2048] product, 400 GFLOP/s (measured now)"
    assert "OPENBLAS_CORETYPE=Sandybridge" in lines[1]


def test_gpu_script_smoke_mode_prints_what_the_readme_quotes(tmp_path):
    out = tmp_path / "gpu.json"
    result = subprocess.run(
        [sys.executable, str(BENCHMARKS / "gpu.py"), "--smoke", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=400,
        # The quick build: this checks what the script prints, not how fast the chunk runs.
        env={**os.environ, "EABC_FAST_COMPILE": "1"},
    )
    assert result.returncode == 0, result.stderr[-2000:]
    text = result.stdout
    assert "| K | seeds in one program | program steps/s | seed-steps/s |" in text
    assert "evaluation round: 2 policies x 1 episodes x 50 steps" in text
    assert "| algorithm | seeds per program | programs | hours (training only) |" in text
    figures = json.loads(out.read_text())
    assert [(r["k"], r["seeds"]) for r in figures["steps_per_s"]] == [(2, 2)]
    assert all(r["program_steps_per_s"] > 0 for r in figures["steps_per_s"])
    rows = figures["projection"]
    assert [r["programs"] for r in rows] == [38]  # ceil(75 runs / 2 per program)
    assert all(r["hours"] >= r["train_hours"] > 0 for r in rows)


def test_the_probe_has_at_least_300_cases_in_its_six_classes(tmp_path):
    """benchmarks/probe.py --list: the cases are made without running any (the runs they copy
    are made only by a real probe)."""
    import probe_cases  # noqa: PLC0415

    cases = probe_cases.all_cases(tmp_path / "base")
    counts = {group: sum(c.group == group for c in cases) for group in range(1, 7)}
    assert len(cases) >= 300 and all(counts.values()), counts
    assert len({(c.group, c.name) for c in cases}) == len(cases), "every case has its own name"


def test_the_probe_judges_refusals_and_results_as_its_docstring_says(tmp_path):
    import probe  # noqa: PLC0415
    from probe_cases.case import Case, Outcome  # noqa: PLC0415

    refuse = Case(5, "x", ["train"], "refuse", names=("--steps",))
    work = Case(5, "y", ["train"], "work", check=lambda folder, outcome: None)
    line = "error: --steps must be an integer, got 'x'\n"
    judged = {
        "good refusal": (refuse, Outcome(1, "", line, 0.1), {}, {}),
        "a refusal naming nothing": (refuse, Outcome(1, "", "error: no\n", 0.1), {}, {}),
        "a refusal that wrote": (refuse, Outcome(1, "", line, 0.1), {}, {"f": "1"}),
        "exit 0 on bad input": (refuse, Outcome(0, "ok", "", 0.1), {}, {}),
        "a traceback": (
            refuse,
            Outcome(1, "", "Traceback (most recent call last):\nE\n", 0.1),
            {},
            {},
        ),  # fmt: skip
        "a hang": (refuse, Outcome(-9, "", "", 60.0, timed_out=True), {}, {}),
        "good work": (work, Outcome(0, "ok", "", 0.1), {}, {"f": "1"}),
        "good input refused": (work, Outcome(1, "", line, 0.1), {}, {}),
    }
    verdicts = {k: probe.verdict(*v, tmp_path) for k, v in judged.items()}
    assert [k for k, why in verdicts.items() if why is None] == ["good refusal", "good work"]
