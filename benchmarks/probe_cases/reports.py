"""Class 6 of the probe: reports and results of runs without reference scores."""

from __future__ import annotations

from pathlib import Path

from probe_cases.case import Case, Outcome
from probe_cases.common import original, run_copy, then, write


def _report_says(*words: str, out: str = "root/report"):
    def check(folder: Path, outcome: Outcome) -> str | None:
        report = folder / out / "report.md"
        if not report.exists():
            return f"no {out}/report.md: {outcome.out[-200:]!r}"
        text = report.read_text()
        missing = [w for w in words if w not in text]
        return f"report.md lacks {missing}" if missing else None

    return check


def _results_show(*words: str):
    def check(folder: Path, outcome: Outcome) -> str | None:
        missing = [w for w in words if w not in outcome.out]
        return f"results lack {missing}: {outcome.out[-300:]!r}" if missing else None

    return check


def _earlier_report(folder: Path) -> None:
    """``rep``: the report of ``root`` made by `eabc report` before the case runs."""
    import subprocess  # noqa: PLC0415
    import sys  # noqa: PLC0415

    subprocess.run([sys.executable, "-m", "eabc.cli", "report", "root", "--out", "rep"],
                   cwd=folder, capture_output=True, check=True)  # fmt: skip


def no_reference_scores(base: Path) -> list[Case]:
    """Runs on a user's own data (no reference scores) report raw returns and say so; a mix with
    scored runs reports both; an empty or unusable root is refused in one line."""
    a = "{:.1f}".format(original(base, "A")["final_return"]) if (base / "runs").exists() else ""
    raw = "no D4RL-normalised score"
    plain = then(run_copy(base, "A", "root/a"), run_copy(base, "D", "root/d"))
    mixed = then(plain, run_copy(base, "R", "root/r"))
    broken = then(run_copy(base, "A", "root/a"), write("root/a/config.json", "{}"))
    cases = [
        Case(6, "report of runs without reference scores", ["report", "root"], "work", plain,
             check=_report_says("TD3+BC", "| BC |", "Raw return", raw, a)),
        Case(6, "report --baseline bc", ["report", "root", "--baseline", "bc"], "work", plain,
             check=_report_says("Against BC", "Raw return")),
        Case(6, "report --baseline td3bc --fix bc", ["report", "root", "--baseline", "td3bc",
             "--fix", "bc"], "work", plain, check=_report_says("Against TD3+BC")),
        Case(6, "report --out elsewhere", ["report", "root", "--out", "rep"], "work", plain,
             check=_report_says("TD3+BC", "Raw return", out="rep")),
        Case(6, "report of scored and unscored runs", ["report", "root"], "work", mixed,
             check=_report_says("TD3+BC", "| BC |", "tiny_ref", "Raw return")),
        Case(6, "report of one run directory", ["report", "root/a"], "work",
             run_copy(base, "A", "root/a"), check=_report_says("TD3+BC", out="root/a/report")),
        Case(6, "report --finished of finished runs", ["report", "root", "--finished"], "work",
             plain, check=_report_says("TD3+BC", "Raw return")),
        Case(6, "report of an empty root", ["report", "root"], "refuse",
             lambda f: (f / "root").mkdir(), ("root",)),
        Case(6, "report of a missing root", ["report", "root"], "refuse", names=("root",)),
        Case(6, "report of only broken runs", ["report", "root"], "either", broken,
             ("root", "broken", "config.json"), check=_report_says()),
        Case(6, "report --include an earlier report", ["report", "root", "--include", "rep"],
             "work", then(plain, _earlier_report), check=_report_says("TD3+BC")),
        Case(6, "results of runs without reference scores", ["results", "root", "--columns",
             "algo", "final_return", "final_score"], "work", plain,
             check=_results_show("td3bc", "bc", a)),
        Case(6, "results --csv", ["results", "root", "--csv"], "work", plain,
             check=_results_show("a,done,200", "d,done,200")),
        Case(6, "results --filter algo=bc", ["results", "root", "--filter", "algo=bc"], "work",
             plain, check=_results_show("d")),
        Case(6, "results --filter of a missing column", ["results", "root", "--filter", "x=1"],
             "refuse", plain, ("x=1", "x", "--filter")),
        Case(6, "results --columns unknown", ["results", "root", "--columns", "bogus"], "refuse",
             plain, ("bogus", "--columns")),
        Case(6, "results of a mixed root", ["results", "root", "--columns", "algo", "dataset",
             "final_return", "final_score"], "work", mixed, check=_results_show("tiny_ref")),
    ]  # fmt: skip
    return cases
