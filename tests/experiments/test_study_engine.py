"""The study engine (``eabc study``, benchmarks/study.sh): the device script's smoke run end to end,
what it streams and how it is read back, the deadline, and the wheels it carries."""

from __future__ import annotations

import importlib.metadata
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from packaging.requirements import Requirement

from eabc import cli
from eabc.experiments import archive_merge, job_process, planning, study
from eabc.experiments.spec import expand
from eabc.training import trainer

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "study.sh"


def test_the_device_script_smoke_run_streams_finished_runs_that_report_reads(tmp_path):
    """The very script a lent GPU runs, at toy sizes on this CPU: the first slice's first three
    groups (TD3+BC on hopper-medium and on halfcheetah-medium, then EABC on hopper-medium: a
    slice goes algorithm by algorithm) and the second slice's first (TD3+BC, one program over
    hopper-medium-replay and hopper-random), two seeds each, train in slice order, and OUT
    holds exactly the study's files and the width table, its runs done and read back by `eabc
    report --include`, and nothing is left in TMPDIR; a second study given --include OUT trains nothing."""
    out = tmp_path / "out"
    env = {**os.environ, "OUT": str(out), "EABC_FAST_COMPILE": "1", "TMPDIR": str(tmp_path)}
    # The script runs `python3`: this interpreter's, as in an activated environment (CI's).
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    done = subprocess.run(
        ["bash", str(SCRIPT), "--smoke"], env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert sorted(p.name for p in out.iterdir()) == sorted([*study.OUT_FILES, "width.md"])
    assert not list(tmp_path.glob("eabc-study-smoke-*"))  # its datasets went with it
    width = (out / "width.md").read_text()  # measured after the study, in its own seconds
    assert "| td3bc | 1 |" in width and "| td3bc | 2 |" in width, width
    runs, evaluations = archive_merge.read_archive(out)
    trained = [("hopper-medium", "td3bc"), ("halfcheetah-medium", "td3bc"),
               ("hopper-medium", "eabc"), ("hopper-medium-replay", "td3bc"),
               ("hopper-random", "td3bc")]  # fmt: skip
    assert sorted(runs["run_id"]) == sorted(
        f"runs/{data}__{algo}__seed{seed}" for data, algo in trained for seed in (0, 1)
    )
    assert (runs["status"] == "done").all() and (runs["steps"] == 40).all()
    assert len(evaluations) == 10 * 2  # every 20 of 40 steps
    logs = pd.read_csv(out / "logs.csv")
    assert list(logs.columns[:2]) == ["run_id", "step"] and len(logs) == 10 * 2
    started = re.findall(r"training (\S+ \(\d+ runs\))", (out / "study.log").read_text())
    assert started == [
        "hopper-medium__td3bc (2 runs)",
        "halfcheetah-medium__td3bc (2 runs)",
        "hopper-medium__eabc (2 runs)",
        "hopper-medium-replay__td3bc+1 (4 runs)",
    ]
    # each compiled in its own thread: the first while its data were made, the others while
    # the group before them trained
    ahead = re.findall(
        r"compiled ahead in \d+ s: (\S+ \(\d+ runs\))", (out / "study.log").read_text()
    )
    assert ahead == started
    again = tmp_path / "again"
    spec = sorted((ROOT / "docs" / "results" / "study-1m").glob("[0-9]*.yaml"))[0]
    argv = ["study", str(spec), "--smoke", "--out", str(again), "--root", str(tmp_path / "r2")]
    cli.main([*argv, "--include", str(out)])
    assert pd.read_csv(again / "runs.csv").empty  # all six were in OUT: none trained again


def _scheduling_only(monkeypatch):
    """A study whose groups' training is stubbed: no dataset made, no program compiled ahead."""
    monkeypatch.setattr(study, "start_datasets", lambda *a: ({}, None))
    monkeypatch.setattr(study, "compile_group", lambda *a: False)


def _queue(tmp_path):
    spec = {"datasets": ["hopper-medium", "walker2d-medium", "halfcheetah-medium"],
            "algos": ["td3bc"], "seeds": [0], "steps": 1000}  # fmt: skip
    return expand(spec)


def test_a_group_starts_only_if_its_scaled_estimate_ends_before_the_deadline(tmp_path, monkeypatch):
    """The first group starts whatever its estimate; it took at least a fifth of its estimate,
    so the next ones are scaled by that: one of 1000 s (200 s or more) does not fit a 30 s
    budget, one of 1 s does, and the queue goes on past the one it skipped."""
    estimates = {"hopper-medium": 1.0, "walker2d-medium": 1000.0, "halfcheetah-medium": 1.0}
    monkeypatch.setattr(planning, "estimate_seconds", lambda run, done=0: estimates[run.dataset])
    trained = []

    def execute(job, root, eval_workers=0, deadline=None):
        trained.append(job[0]["dataset"])
        time.sleep(0.2)

    monkeypatch.setattr(job_process, "execute", execute)
    _scheduling_only(monkeypatch)
    report = study.run_study(
        [_queue(tmp_path)], tmp_path / "root", tmp_path / "out", time.time() + 30, echo=print
    )
    assert trained == ["hopper-medium", "halfcheetah-medium"]
    assert report["skipped"] == ["walker2d-medium__td3bc__seed0 (1 run)"]
    log = (tmp_path / "out" / "study.log").read_text()
    assert re.search(r"not started, ~\d+ s would end past the deadline: walker2d-medium", log)


def test_a_failed_group_is_named_and_the_queue_goes_on(tmp_path, monkeypatch):
    def execute(job, root, eval_workers=0, deadline=None):
        if job[0]["dataset"] == "walker2d-medium":
            raise ValueError("no memory for it")

    monkeypatch.setattr(job_process, "execute", execute)
    _scheduling_only(monkeypatch)
    report = study.run_study(
        [_queue(tmp_path)], tmp_path / "root", tmp_path / "out", echo=lambda _: None
    )
    assert report["failed"] == {"walker2d-medium__td3bc__seed0 (1 run)": "no memory for it"}
    assert report["finished"] == [
        "hopper-medium__td3bc__seed0",
        "halfcheetah-medium__td3bc__seed0",
    ]


def test_a_group_its_first_chunks_show_too_slow_starts_again_narrower(tmp_path, monkeypatch):
    """Five seeds in one program would end past the deadline at the speed its first chunks
    showed: the first runs that fit the time left (two) train again as their own program, then
    the other three are tried, stopped, narrowed to one, and the last two fit; the slices keep
    their order (the second slice's group trains last)."""
    monkeypatch.setattr(planning, "estimate_seconds", lambda run, done=0: 0.01)
    _scheduling_only(monkeypatch)
    widths = []

    def execute(job, root, eval_workers=0, deadline=None):
        widths.append((job[0]["dataset"], len(job)))
        if len(job) > 2:  # the time left holds 2.5 runs' seed-steps at five runs' speed, 1.5 at 3
            seconds = deadline - time.time()
            worth = {5: 2.5, 3: 1.5}[len(job)]
            rate = worth * trainer.DEADLINE_MARGIN * 1_000_000 / (seconds - 1.0) / len(job)
            raise trainer.PastDeadline(len(job), 3_000, 1_000_000, rate, 1.0, 100.0)

    monkeypatch.setattr(job_process, "execute", execute)
    seeds = {"algos": ["td3bc"], "seeds": [0, 1, 2, 3, 4], "steps": 1_000_000}
    slices = [expand({"datasets": ["hopper-medium"], **seeds}),
              expand({"datasets": ["walker2d-medium"], **{**seeds, "seeds": [0]}})]  # fmt: skip
    report = study.run_study(
        slices, tmp_path / "root", tmp_path / "out", time.time() + 30, echo=lambda _: None
    )
    assert widths == [("hopper-medium", w) for w in (5, 2, 3, 1, 2)] + [("walker2d-medium", 1)]
    assert report["narrowed"] == ["hopper-medium__td3bc (5 runs)", "hopper-medium__td3bc (3 runs)"]
    assert report["finished"] == [f"hopper-medium__td3bc__seed{s}" for s in (0, 1, 2, 3, 4)] + [
        "walker2d-medium__td3bc__seed0"
    ]
    log = (tmp_path / "out" / "study.log").read_text()
    assert "stopped: hopper-medium__td3bc (5 runs): 5 runs at" in log
    assert "again with its first 2" in log and "again with its first 1" in log


def test_a_dry_run_lists_each_slices_groups_in_order_and_touches_nothing(tmp_path, capsys):
    specs = []
    for name, spec in (("1-a.yaml", "datasets: [hopper-medium, walker2d-medium]\nalgos: [td3bc, eabc]"),
                       ("2-b.yaml", "datasets: [hopper-random, hopper-medium-replay]\nalgos: [td3bc]")):  # fmt: skip
        specs.append(tmp_path / name)
        specs[-1].write_text(f"{spec}\nseeds: [0, 1, 2]\nsteps: 1000\n")
    out, root = tmp_path / "out", tmp_path / "root"
    cli.main(["study", *map(str, specs), "--dry-run", "--out", str(out), "--root", str(root)])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"{specs[0]}: 12 runs to train, 4 groups"
    assert [line.split(":")[0].strip() for line in lines[1:5]] == [
        "hopper-medium__td3bc (3 runs)",  # algorithm by algorithm: the first on both datasets
        "walker2d-medium__td3bc (3 runs)",
        "hopper-medium__eabc (3 runs)",
        "walker2d-medium__eabc (3 runs)",
    ]
    assert lines[5] == f"{specs[1]}: 6 runs to train, 1 group"
    assert lines[6].startswith("  hopper-random__td3bc+1 (6 runs): hopper-random")
    assert "hopper-medium-replay" in lines[6] and lines[6].endswith(
        " a run on the reference CPU host"
    )
    assert not out.exists() and not root.exists()


def test_a_stopped_group_is_narrowed_to_what_fits(tmp_path):
    stopped = trainer.PastDeadline(10, 5_000, 1_000_000, 2_000.0, 20.0, 300.0)  # 20K seed-steps/s
    assert study.fitting(stopped, 400.0) == 7  # 380 s x 20K / 1.05M seed-steps per run: 7.2
    assert study.fitting(stopped, 1_000.0) == 9  # 18.7, but never as many as it had
    assert study.fitting(stopped, 60.0) == 0  # 40 s: not one run's million steps
    assert study.fitting(stopped, 10.0) == 0  # less time than compiling again


def test_out_must_be_empty_or_a_studys(tmp_path):
    (tmp_path / "study.log").write_text("")
    assert study.check_out(tmp_path) == tmp_path
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"holds other files \(notes.txt\)"):
        study.check_out(tmp_path)
    with pytest.raises(ValueError, match="is a file"):
        study.check_out(tmp_path / "notes.txt")


def test_the_script_starts_nothing_on_an_argument_it_does_not_know(tmp_path):
    """Before: any argument but wheels and --smoke ran the whole study (530 s, the datasets made
    into the user's cache): `bash benchmarks/study.sh --help` did. Now --help prints the
    script's own header and anything else is one error line; neither makes anything."""
    env = {**os.environ, "OUT": str(tmp_path / "out"), "HOME": str(tmp_path)}
    for argv, code in ((["--help"], 0), (["--bogus"], 2), (["--smoke", "x"], 2), (["-h"], 0)):
        done = subprocess.run(["bash", str(SCRIPT), *argv], env=env, capture_output=True,
                              text=True, timeout=60)  # fmt: skip
        assert done.returncode == code, (argv, done.stderr)
        if code:
            assert done.stderr.count("\n") == 1 and "unknown arguments" in done.stderr
        else:
            assert (
                done.stdout.startswith("The next slice of the 1M study")
                and "STUDY_WITHIN" in done.stdout
            )
    assert list(tmp_path.iterdir()) == []


NEWER_THAN_THE_IMAGE = {
    # pydantic's and pydantic-core's wheels need typing-extensions >= 4.16, and the image's version
    # is not known here; it only ever adds names, so a newer one in front of the image's is safe.
    "typing-extensions",
}

NOT_NEEDED_AT_RUN_TIME = {
    "eabc",
    "mujoco-studio",  # MuJoCo's viewer, never imported by training or evaluation
    "mujoco-studio-wasm",
    "websockets",  # the viewer's
    "tzdata",  # pandas' time zones; the image's pandas brings what it needs
}


def _closure(name: str, seen: set[str]) -> None:
    key = re.sub(r"[-_.]+", "-", name).lower()
    if key in seen:
        return
    seen.add(key)
    try:
        requires = importlib.metadata.distribution(name).requires or []
    except importlib.metadata.PackageNotFoundError:
        return
    marker_env = {"python_version": "3.12", "python_full_version": "3.12.3", "extra": ""}
    for line in requires:
        requirement = Requirement(line)
        if requirement.marker is None or requirement.marker.evaluate(marker_env):
            _closure(requirement.name, seen)


def test_the_carried_wheels_are_what_the_gpu_image_lacks():
    """Every package ``eabc`` needs (its requirements' closure, for the image's Python 3.12)
    is in the GPU machine's image (benchmarks/device-packages.txt) or among the wheels
    benchmarks/study.sh carries; no carried wheel is one the image has."""
    text = SCRIPT.read_text()
    wheels = set(re.search(r"WHEELS=\(([^)]*)\)", text).group(1).split())
    image = {
        re.sub(r"[-_.]+", "-", line.strip()).lower()
        for line in (ROOT / "benchmarks" / "device-packages.txt").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    }
    needed: set[str] = set()
    _closure("eabc", needed)
    missing = needed - image - wheels - NOT_NEEDED_AT_RUN_TIME
    assert not missing, f"add to WHEELS in benchmarks/study.sh: {sorted(missing)}"
    extra = wheels & image - NEWER_THAN_THE_IMAGE
    assert not extra, f"the image has these already: {sorted(extra)}"
