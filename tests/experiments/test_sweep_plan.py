"""A sweep's plan: what is left and what it costs, from speeds measured in the root when it has them."""

from __future__ import annotations

import dataclasses
import json
import re

import pandas as pd
import pytest

from eabc import timing
from eabc.agents import get_algorithm
from eabc.cli import main
from eabc.experiments import planning, run_status
from eabc.experiments.spec import RunSpec, expand

TRAIN = (("eval_episodes", 10), ("eval_interval", 5000), ("steps", 20000))


def _run(algo="td3bc", seed=0, overrides=(), dataset="hopper-medium"):
    return RunSpec(dataset, algo, seed, tuple(overrides), TRAIN)


def _fake_run_dir(root, run: RunSpec, speeds: list[float]):
    """A run directory with a config and a log whose chunks ran at ``speeds`` (steps/s)."""
    run_dir = root / run_status.RUNS / run.run_id
    run_dir.mkdir(parents=True)
    train = {"algo": run.algo, "seed": run.seed, "steps": 20000, "dataset": run.dataset}
    (run_dir / "config.json").write_text(json.dumps({"train": train, "agent": {}, "dataset": {}}))
    (run_dir / run_status.SPEC).write_text(json.dumps({"run_id": run.run_id, **run.to_json()}))
    rows = ["step,steps_per_s,q_mean"] + [f"{1000 * (i + 1)},{v},1.0" for i, v in enumerate(speeds)]
    (run_dir / "log.csv").write_text("\n".join(rows) + "\n")
    return run_dir


def test_without_measurements_the_contract_hint_and_the_evaluations_set_the_cost():
    run = _run()
    algorithm = get_algorithm("td3bc")
    expected = 20000 / algorithm.steps_per_s + 4 * 10 * timing.EPISODE_SECONDS
    assert planning.estimate_seconds(run) == pytest.approx(expected)
    # Half the steps done: half the steps and half the evaluations left.
    half = 10000 / algorithm.steps_per_s + 2 * 10 * timing.EPISODE_SECONDS
    assert planning.estimate_seconds(run, 10000) == pytest.approx(half)
    assert planning.estimate_seconds(run, 10000, steps_per_s=50.0) == pytest.approx(
        10000 / 50.0 + 2 * 10 * timing.EPISODE_SECONDS
    )


def test_speeds_measured_in_the_root_replace_the_hint_for_the_run_and_its_siblings(tmp_path):
    measured = _run(seed=0)
    sibling = _run(seed=1)  # same algorithm and settings, not begun
    other_data = _run(seed=2, dataset="walker2d-medium")
    other_setting = _run(seed=0, algo="eabc", overrides=(("num_critics", 5),))
    # The first chunk compiled (slow); the median ignores it.
    _fake_run_dir(tmp_path, measured, [3.0, 40.0, 42.0, 44.0])
    runs = [measured, sibling, other_data, other_setting]
    speeds = planning.measured_speeds(runs, tmp_path)
    assert speeds[measured.run_id] == pytest.approx(41.0)
    assert speeds[sibling.run_id] == speeds[other_data.run_id] == pytest.approx(41.0)
    assert other_setting.run_id not in speeds
    # A sweep deciding what to start next sees the runs begun by others (not in its list).
    assert planning.measured_speeds([sibling], tmp_path) == {sibling.run_id: pytest.approx(41.0)}
    (cost,) = planning.job_estimates([[sibling]], tmp_path)
    assert cost == pytest.approx(20000 / 41.0 + 4 * 10 * timing.EPISODE_SECONDS)
    rows = {r["run"].run_id: r for r in planning.plan(runs, tmp_path)}
    assert rows[sibling.run_id]["measured"] and not rows[other_setting.run_id]["measured"]
    assert rows[sibling.run_id]["seconds"] == pytest.approx(
        20000 / 41.0 + 4 * 10 * timing.EPISODE_SECONDS
    )
    eabc = get_algorithm("eabc")
    config = dataclasses.replace(eabc.preset, num_critics=5)
    hint = eabc.steps_per_s / eabc.relative_cost(config)
    assert rows[other_setting.run_id]["seconds"] == pytest.approx(
        20000 / hint + 4 * 10 * timing.EPISODE_SECONDS
    )


def test_uwac_costs_less_with_fewer_dropout_passes_and_its_preset_is_the_measured_one():
    uwac = get_algorithm("uwac")
    costs = [
        uwac.relative_cost(dataclasses.replace(uwac.preset, num_dropout_samples=t))
        for t in (2, 10, 100, 200)
    ]
    assert costs[2] == pytest.approx(1.0)
    assert costs == sorted(costs) and costs[0] < 0.15 and costs[3] > 1.8
    # At T = 2 the step is close to BEAR's (its fixed work) plus two passes.
    assert uwac.steps_per_s / costs[0] == pytest.approx(34.3, rel=0.02)


def test_a_model_fit_is_counted_once_before_a_run_begins():
    for algo in ("mopo", "morel"):
        algorithm = get_algorithm(algo)
        assert algorithm.pretrain is not None and algorithm.pretrain_s is not None
        run = _run(algo=algo)
        fit = algorithm.pretrain_s(algorithm.preset)
        assert fit > 60
        begun = planning.estimate_seconds(run, 5000)  # one evaluation in, no fit left
        assert planning.estimate_seconds(run) == pytest.approx(
            begun + fit + 5000 / algorithm.steps_per_s + 10 * timing.EPISODE_SECONDS
        )
    # A capped fit costs less than MOPO's (trained until the patience runs out).
    mopo = get_algorithm("mopo")
    capped = dataclasses.replace(mopo.preset, model_max_epochs=5)
    assert mopo.pretrain_s(capped) < mopo.pretrain_s(mopo.preset)


def test_the_dry_run_says_what_its_estimate_rests_on(tmp_path, capsys):
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        "datasets: [hopper-medium]\nalgos: [td3bc]\nseeds: [0, 1]\nsteps: 20000\n"
        "train: {eval_interval: 5000, eval_episodes: 10}\n"
    )
    root = tmp_path / "root"
    main(["sweep", str(spec), "--root", str(root), "--dry-run"])
    assert "at the reference host's speed (" in capsys.readouterr().out
    _fake_run_dir(root, _run(seed=0), [100.0, 100.0])
    main(["sweep", str(spec), "--root", str(root), "--dry-run"])
    out = capsys.readouterr().out
    assert "at speeds measured in the root" in out
    # Two runs of 20K steps at 100 steps/s (the second not begun), plus 80 evaluation episodes.
    hours = (2 * 20000 / 100.0 + 2 * 40 * timing.EPISODE_SECONDS) / 3600
    assert f"about {hours:.1f} CPU-core-hours" in out


def test_durations_and_the_first_job_that_fits_a_deadline():
    assert [planning.parse_duration(t) for t in ("90s", "45m", "2.5h", "10")] == [
        90,
        2700,
        9000,
        600,
    ]
    for bad in ("", "h", "-5m", "0s", "soon", "nanh"):
        with pytest.raises(ValueError, match="positive number with s, m or h"):
            planning.parse_duration(bad)
    jobs, costs = ["a", "b", "c"], [500.0, 50.0, 10.0]
    assert planning.next_job(jobs, costs, now=0.0, deadline=None) == 0
    assert planning.next_job(jobs, costs, now=0.0, deadline=600.0) == 0
    assert planning.next_job(jobs, costs, now=0.0, deadline=100.0) == 1  # "a" would end at 500
    assert planning.next_job(jobs, costs, now=95.0, deadline=100.0) is None
    assert planning.next_job([], [], now=0.0, deadline=100.0) is None


def test_within_starts_only_the_runs_that_end_in_time(
    tmp_path, capsys, pendulum_dataset, quick_chunks
):
    from eabc.data.loaders import save_npz

    data = tmp_path / "pend.npz"
    save_npz(pendulum_dataset, data)
    spec = tmp_path / "spec.yaml"
    # td3bc: ~0.5 s by its hint; EABC with 50 critics: ~10 s. Only the first fits in 5 s.
    spec.write_text(
        f"datasets: [{data}]\nvariants:\n- {{algo: eabc, num_critics: 50, confidence_level: 1.0}}"
        "\n- {algo: td3bc, hidden_dims: [32, 32]}\nseeds: [0]\nsteps: 300\n"
        "train: {eval_interval: 300, eval_episodes: 1, log_interval: 100, env: Pendulum-v1}\n"
    )
    root = tmp_path / "root"
    main(["sweep", str(spec), "--root", str(root), "--workers", "2", "--within", "5s"])
    out = capsys.readouterr().out
    started = sorted(p.name for p in (root / run_status.RUNS).iterdir())
    assert len(started) == 1 and "__td3bc__" in started[0]
    assert "left for a later sweep (1, their estimates end after the deadline)" in out
    assert "__eabc__" in out.split("left for a later sweep")[1]
    with pytest.raises(SystemExit, match="a duration is a positive number"):
        main(["sweep", str(spec), "--root", str(root), "--within", "later"])


def test_runs_an_earlier_report_holds_as_done_are_not_run_again(tmp_path, capsys):
    import pandas as pd

    archive = tmp_path / "earlier"
    archive.mkdir()
    rows = [  # done at the spec's 20K; done at only 10K; partial
        ("runs/" + _run(seed=0).run_id, "done", 20000, 20000),
        ("runs/" + _run(seed=1).run_id, "done", 10000, 10000),
        ("runs/" + _run(seed=2).run_id, "partial", 15000, 20000),
    ]
    pd.DataFrame(
        [
            {
                "run_id": r,
                "dataset": "hopper-medium",
                "algo": "td3bc",
                "seed": i,
                "status": st,
                "steps": n,
                "steps_target": t,
                "final_score": 50.0,
            }
            for i, (r, st, n, t) in enumerate(rows)
        ]  # fmt: skip
    ).to_csv(archive / "runs.csv", index=False)
    (archive / "evaluations.csv").write_text("run_id,step,score\n")
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        "datasets: [hopper-medium]\nalgos: [td3bc]\nseeds: [0, 1, 2]\nsteps: 20000\n"
        "train: {eval_interval: 5000, eval_episodes: 10}\n"
    )
    main(["sweep", str(spec), "--root", str(tmp_path / "root"), "--include", str(archive),
          "--dry-run"])  # fmt: skip
    out = capsys.readouterr().out
    assert f"1 runs done in {archive}: not run again" in out
    assert "2 runs in" in out and _run(seed=0).run_id not in out
    assert _run(seed=1).run_id in out and _run(seed=2).run_id in out


def test_a_run_another_root_has_done_or_is_training_is_left_to_it(
    tmp_path, capsys, pendulum_dataset, quick_chunks, quick_figures
):
    import os
    import socket

    import yaml

    from eabc.data.loaders import save_npz
    from eabc.experiments import archive_merge
    from eabc.experiments.spec import expand
    from eabc.training.lock import OWNER

    data = tmp_path / "pend.npz"
    save_npz(pendulum_dataset, data)
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        f"datasets: [{data}]\nalgos: [td3bc]\nseeds: [0, 1, 2]\nsteps: 300\n"
        "grid: {hidden_dims: [[32, 32]]}\n"
        "train: {eval_interval: 300, eval_episodes: 1, log_interval: 100, env: Pendulum-v1}\n"
    )
    done, busy, free = expand(yaml.safe_load(spec.read_text()))
    other = tmp_path / "other"  # the second core's root
    run_dir = other / run_status.RUNS / done.run_id
    run_dir.mkdir(parents=True)
    train = {"algo": "td3bc", "seed": 0, "steps": 300, "dataset": str(data)}
    (run_dir / "config.json").write_text(json.dumps({"train": train, "agent": {}, "dataset": {}}))
    (run_dir / run_status.SPEC).write_text(json.dumps({"run_id": done.run_id, **done.to_json()}))
    (run_dir / "log.csv").write_text("step,q_mean,return_mean,score\n300,1.0,-500.0,42.0\n")
    (run_dir / "summary.json").write_text(json.dumps({"steps": 300}))
    (other / run_status.RUNS / busy.run_id).mkdir()  # begun there by a live process (this one)
    owner = {"pid": os.getpid(), "host": socket.gethostname(), "since": "", "command": ""}
    (other / run_status.RUNS / busy.run_id / OWNER).write_text(json.dumps(owner))

    root = tmp_path / "root"
    main(["sweep", str(spec), "--root", str(root), "--include", str(other), "--workers", "1"])
    out = capsys.readouterr().out
    assert f"1 runs done in {other}: not run again" in out
    assert f"not starting {busy.run_id}: being trained in {other}" in out
    assert sorted(p.name for p in (root / run_status.RUNS).iterdir()) == [free.run_id]
    assert run_status.status(free, root)[0] == "done"

    # The report stands on both roots: the other's finished run with its score.
    runs, _ = archive_merge.read_archive(other)
    assert list(runs["run_id"]) == [f"{run_status.RUNS}/{done.run_id}"]
    assert runs["final_score"].iloc[0] == 42.0 and runs["source"].iloc[0] == str(other)
    main(["report", str(root), "--include", str(other), "--out", str(tmp_path / "report")])
    merged = pd.read_csv(tmp_path / "report" / "runs.csv")
    assert sorted(merged["seed"]) == [0, 2]
    assert f"1 from `{other}` (run directories)" in (tmp_path / "report" / "report.md").read_text()


BASE = {"datasets": ["hopper-random"], "algos": ["bc"]}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"datasets": "hopper-random"}, r"^datasets must be a list, e.g. datasets: \[hopper-random\]$"),
        ({"algos": "bc"}, r"^algos must be a list, e.g. algos: \[bc\]$"),
        ({"seeds": 5}, r"^seeds must be a list, e.g. seeds: \[5\] for the seed 5, or \[0, 1, 2\]"),
        ({"seeds": []}, r"^seeds is empty: list at least one seed"),
        ({"seeds": [1.5]}, r"^seeds\[0\] must be an integer in \[0, 4294967295\], got 1.5$"),
        ({"seeds": [0, True]}, r"^seeds\[1\] must be an integer in \[0, 4294967295\], got True$"),
        ({"seeds": [2**32]}, r"^seeds\[0\] must be an integer in \[0, 4294967295\]"),
        ({"seeds": [-1]}, r"^seeds\[0\] must be an integer"),
        ({"steps": 0}, r"^steps must be an integer in \[1, 2147483647\], got 0$"),
        ({"steps": 1.0e6}, r"^steps must be an integer in \[1, 2147483647\], got 1000000.0$"),
        ({"datasets": [5]}, r"^datasets\[0\] must be a name \(text\), got 5$"),
        ({"grid": {"num_critics": []}}, r"^grid.num_critics is empty"),
        ({"grid": ["num_critics"]}, r"^grid must be a mapping of setting -> values"),
        ({"train": {"eval_episodes": True}}, r"^bad train setting: eval_episodes must be an integer >= 1, got True$"),
        ({"train": {"checkpoint_interval": 0}}, r"^bad train setting: checkpoint_interval must be an integer in \[1, 2147483647\]"),
        ({"train": "fast"}, r"^train must be a mapping of TrainConfig settings"),
        ({"variants": [{"algo": "td3bc", "datasets": 5}]}, r"'datasets' must be a non-empty list"),
        ({"variants": [7]}, r"a sweep variant is a mapping with an 'algo' key, got 7"),
    ],
)  # fmt: skip
def test_a_spec_of_the_wrong_shape_is_refused_naming_the_key(change, message):
    with pytest.raises(ValueError, match=message):
        expand({**BASE, **change})


def test_a_spec_key_of_the_wrong_shape_from_yaml_ends_in_one_line(tmp_path):
    """Before: ``datasets: hopper-random`` made one run per character and ``seeds: 5`` a
    traceback; every refusal is one line and leaves the root as it was."""
    for text, message in [
        ("datasets: hopper-random\nalgos: [bc]\n", "error: datasets must be a list"),
        ("datasets: [hopper-random]\nalgos: [bc]\nseeds: 5\n", "error: seeds must be a list"),
        ("datasets: [hopper-random]\nalgos: [bc]\nseeds: []\n", "error: seeds is empty"),
        ("datasets: [hopper-random\n", "error: .*not valid YAML at line 2"),
        ("datasets: " + "[" * 5000 + "]" * 5000, "error: .*spec.yaml: nested too deeply"),
    ]:
        spec = tmp_path / "spec.yaml"
        spec.write_text(text)
        with pytest.raises(SystemExit) as error:
            main(["sweep", str(spec), "--root", str(tmp_path / "root"), "--dry-run"])
        assert re.match(message, str(error.value.code)) and "\n" not in str(error.value.code)
        assert not (tmp_path / "root").exists()
