"""What a run records about the machine and code that trained it (training/provenance.py)."""

from __future__ import annotations

import json
import subprocess

import pytest
from synthetic_results import make_results

from eabc.experiments import report, results
from eabc.training import provenance

pytestmark = pytest.mark.usefixtures("quick_figures")  # tables and text, not figures


def test_a_segment_names_the_step_machine_code_and_libraries():
    record = provenance.segment(1200)
    assert record["from_step"] == 1200
    assert record["started"].endswith("Z") and record["host"]
    assert record["cpu"] == provenance.cpu_model() and record["isa"] == provenance.vector_isa()
    assert record["device"].startswith("cpu")
    assert set(record["libraries"]) == set(provenance.LIBRARIES)
    assert record["code"].startswith(provenance.code_version().split(" ")[0])
    json.dumps(record)  # plain JSON


def test_record_appends_and_unreadable_records_read_as_none(tmp_path):
    assert provenance.read(tmp_path) == []  # a run from before the record
    provenance.record(tmp_path, 0)
    provenance.record(tmp_path, 5000)
    assert [s["from_step"] for s in provenance.read(tmp_path)] == [0, 5000]
    (tmp_path / provenance.PROVENANCE).write_text("{not json")
    assert provenance.read(tmp_path) == []
    provenance.record(tmp_path, 7000)  # a corrupt record is started again, not a crash
    assert [s["from_step"] for s in provenance.read(tmp_path)] == [7000]


def test_code_version_names_the_commit_and_uncommitted_changes(tmp_path):
    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    assert "git" not in provenance.code_version(tmp_path)  # not a checkout: the version alone
    git("init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    git("add", "a.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "one")
    commit = subprocess.run(
        ["git", "rev-parse", "--short=12", "HEAD"], cwd=tmp_path, capture_output=True, text=True
    ).stdout.strip()
    assert provenance.code_version(tmp_path).endswith(f"(git {commit})")
    (tmp_path / "a.py").write_text("x = 2\n")
    assert provenance.code_version(tmp_path).endswith(f"(git {commit}, uncommitted changes)")


def test_the_results_store_names_each_runs_machines_and_code(tmp_path):
    run = tmp_path / "root" / "hopper-medium__eabc__seed0"
    run.mkdir(parents=True)
    config = {"train": {"algo": "eabc", "seed": 0, "steps": 100, "dataset": "hopper-medium"},
              "agent": {}, "dataset": {"name": "hopper-medium"}}  # fmt: skip
    (run / "config.json").write_text(json.dumps(config))
    first = {"from_step": 0, "cpu": "Zen 4", "isa": "AVX-512", "code": "0.1 (git a)"}
    again = {"from_step": 50, "cpu": "Zen 4", "isa": "AVX-512", "code": "0.1 (git b)"}
    later = {"from_step": 80, "cpu": "Xeon", "isa": "AVX2", "code": "0.1 (git b)"}
    (run / provenance.PROVENANCE).write_text(json.dumps({"segments": [first, again, later]}))
    runs, _ = results.collect(tmp_path / "root", write=False)
    assert runs.loc[0, "machine"] == "Zen 4, AVX-512 + Xeon, AVX2"
    assert runs.loc[0, "code"] == "0.1 (git a) + 0.1 (git b)"
    (run / provenance.PROVENANCE).unlink()
    runs, _ = results.collect(tmp_path / "root", write=False)
    assert runs.loc[0, "machine"] == "" and runs.loc[0, "code"] == ""


def test_the_report_counts_runs_per_machine_and_flags_uncommitted_code(tmp_path):
    runs, evaluations = make_results()
    runs["machine"], runs["code"] = "", ""  # most predate the record
    runs.loc[:1, "machine"] = "Zen 5, AVX-512"
    runs.loc[2, "machine"] = "Xeon, AVX2"
    runs.loc[:2, "code"] = "0.1.0 (git abc)"
    runs.loc[1, "code"] = "0.1.0 (git abc, uncommitted changes)"
    report.write_report(runs, evaluations, tmp_path)
    text = (tmp_path / "report.md").read_text()
    assert (
        f"{len(runs) - 3} runs predate that record): 2 on Zen 5, AVX-512, 1 on Xeon, AVX2" in text
    )
    assert (
        f"**1 run(s) ran code with uncommitted changes**, which no commit reproduces: `{runs.loc[1, 'run_id']}`"
        in text
    )
    assert (
        "**These tables merge runs from hosts of different vector extensions (AVX-512, AVX2).**"
        in text
    )
    runs.loc[1, "code"] = "0.1.0 (git abc)"
    runs.loc[2, "machine"] = "Zen 4, AVX-512 (+BF16)"  # BF16 changes no float32 kernel
    report.write_report(runs, evaluations, tmp_path)
    text = (tmp_path / "report.md").read_text()
    assert "uncommitted" not in text and "different vector extensions" not in text


def test_vector_extensions_are_read_from_every_segment_of_a_run():
    machines = ["Zen 5, AVX-512", "", "Zen 4, AVX-512 (+BF16) + EPYC, AVX2", "Xeon, AVX2"]
    assert report.vector_extensions(machines) == ["AVX-512", "AVX2"]
