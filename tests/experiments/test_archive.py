"""Reports read back (`eabc report ROOT --include DIR`): runs measured on a machine since lost."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from synthetic_results import make_results

from eabc.cli import main
from eabc.experiments import archive_merge, report

pytestmark = pytest.mark.usefixtures("quick_figures")  # tables and text, not figures


def _archive(tmp_path, runs, evaluations, name="earlier"):
    out = tmp_path / name
    report.write_report(runs, evaluations, out)
    return out


def test_a_report_read_back_makes_the_same_tables(tmp_path):
    runs, evaluations = make_results()
    first = _archive(tmp_path, runs, evaluations)
    nothing = (runs.iloc[:0], evaluations.iloc[:0])  # a new machine's empty root
    again = archive_merge.merge(nothing, archive_merge.read_archive(first))
    second = tmp_path / "again"
    report.write_report(*again, second)
    for name in ("table.md", "comparison.md", "aggregate.md", "stability.md"):
        assert (second / name).read_text() == (first / name).read_text(), name
    key = ["run_id", "step"]
    before = evaluations.sort_values(key).reset_index(drop=True)
    after = pd.read_csv(second / "evaluations.csv").sort_values(key).reset_index(drop=True)
    pd.testing.assert_frame_equal(after[before.columns], before, check_exact=True)
    assert set(again[0]["source"]) == {str(first)}


def test_the_copy_that_trained_more_steps_wins_and_brings_its_own_evaluations():
    runs, evaluations = make_results()
    done = runs.iloc[:4].copy()
    evals = evaluations[evaluations["run_id"].isin(done["run_id"])]
    # The live root has begun run 0 again (fewer steps), finished run 1 as well (a tie), and
    # has a run of its own; the archive has runs 0-3 done.
    live = done.iloc[:2].copy()
    live.loc[live.index[0], ["steps", "final_score"]] = [5000, -1.0]
    live.loc[live.index[1], "final_score"] = 99.0
    fresh = runs.iloc[[10]]
    live = pd.concat([live, fresh])
    live_evals = pd.concat(
        [
            evals[evals["run_id"] == done["run_id"].iloc[0]].head(1).assign(score=-1.0),
            evals[evals["run_id"] == done["run_id"].iloc[1]].assign(score=99.0),
            evaluations[evaluations["run_id"] == fresh["run_id"].iloc[0]],
        ]
    )
    archived = (done.assign(source="docs/results/x"), evals)
    merged, merged_evals = archive_merge.merge((live, live_evals), archived, live_source="sweeps/x")

    by_id = merged.set_index("run_id")
    assert len(merged) == 5 and merged["run_id"].is_unique
    first, second = done["run_id"].iloc[0], done["run_id"].iloc[1]
    assert by_id.loc[first, "source"] == "docs/results/x"  # 5,000 live steps lose
    assert by_id.loc[first, "final_score"] == done["final_score"].iloc[0]
    assert by_id.loc[second, "source"] == "sweeps/x"  # a tie: the live run
    assert by_id.loc[second, "final_score"] == 99.0
    assert by_id.loc[fresh["run_id"].iloc[0], "source"] == "sweeps/x"
    # Each run's evaluations come from the copy its row came from, none twice.
    scores = merged_evals.groupby("run_id")["score"]
    assert (scores.min()[first] > -1.0) and (scores.min()[second] == 99.0)
    assert not merged_evals.duplicated(["run_id", "step"]).any()
    assert set(merged_evals["run_id"]) == set(merged["run_id"])


def test_the_command_reports_archived_and_live_runs_together(tmp_path):
    runs, evaluations = make_results()
    datasets = sorted(runs["dataset"].unique())
    old = runs["dataset"] == datasets[0]
    archive = _archive(tmp_path, runs[old], evaluations)  # every evaluation: only its runs' count
    live = _archive(tmp_path, runs[~old], evaluations, name="live")
    empty = tmp_path / "new-machine"  # a sweep root that does not exist yet
    out = tmp_path / "out"
    main(["report", str(empty), "--include", str(archive), str(live), "--out", str(out)])
    page = (out / "report.md").read_text()
    n_old, n_new = int(old.sum()), int((~old).sum())
    earlier = "(an earlier report, read back with `--include`)"
    assert (
        f"{n_old} from `{archive}` {earlier}" in page and f"{n_new} from `{live}` {earlier}" in page
    )
    table = (out / "table.md").read_text()
    assert datasets[0] in table and datasets[1] in table
    merged = pd.read_csv(out / "runs.csv").set_index("run_id")
    assert len(merged) == len(runs)
    assert np.allclose(merged.loc[runs["run_id"], "final_score"], runs["final_score"])
    written = pd.read_csv(out / "evaluations.csv")
    assert len(written) == len(evaluations) and set(written["run_id"]) == set(runs["run_id"])


def test_what_is_not_a_report_is_refused_with_what_to_give(tmp_path):
    with pytest.raises(FileNotFoundError, match="runs.csv or evaluations.csv.*eabc report"):
        archive_merge.read_archive(tmp_path)
    (tmp_path / "runs.csv").write_text("a,b\n1,2\n")
    (tmp_path / "evaluations.csv").write_text(
        "run_id,step,score,score_std,return_mean,return_std\n"
    )
    with pytest.raises(ValueError, match="runs.csv lacks the column.*run_id"):
        archive_merge.read_archive(tmp_path)
    with pytest.raises(SystemExit, match="does not exist"):
        main(["report", str(tmp_path / "nothing")])


def test_a_damaged_report_is_refused_in_one_line_naming_the_file(tmp_path):
    """Before: an empty evaluations.csv ended in pandas' "No columns to parse from file"
    (which file?), and one cut mid-line, or with a row's step or its score and return blank,
    was read as it was: a report stood on a number cut off after its first digits. (A score
    alone may be blank: data without reference returns report the raw return.)"""
    runs, evaluations = make_results()
    out = _archive(tmp_path, runs, evaluations)
    path = out / "evaluations.csv"
    text = path.read_text()
    cut = text[: text.index("\n", len(text) // 2) + 3]  # a row's first three characters
    blank, no_step = pd.read_csv(path), pd.read_csv(path)
    blank.loc[0, ["score", "return_mean"]] = None  # the first row's number left empty
    no_step.loc[1, "step"] = None
    damaged = {
        "": "is not a table `eabc report` wrote \\(No columns to parse from file\\)",
        cut: "ends mid-line: the file was cut short",
        blank.to_csv(index=False): "line 2 has no score or return_mean",
        no_step.to_csv(index=False): "line 3 has no step",
        'run_id,step,score\n"runs/a,5000,3\n': "is not a table `eabc report` wrote",
    }
    assert list(pd.read_csv(out / "evaluations.csv").columns[:3]) == ["run_id", "step", "score"]
    for content, message in damaged.items():
        path.write_text(content)
        with pytest.raises(ValueError, match=f"evaluations.csv {message}") as error:
            archive_merge.read_archive(out)
        assert "\n" not in str(error.value) and "eabc report" in str(error.value)
    path.write_text(text)
    assert len(archive_merge.read_archive(out)[1]) == len(evaluations)  # the file as written


def test_another_sweep_root_is_read_from_its_run_directories_even_before_its_first_run(tmp_path):
    root = tmp_path / "sweeps" / "b"
    (root / "runs").mkdir(parents=True)  # begun, no run directory yet
    runs, evaluations = archive_merge.read_archive(root)
    assert runs.empty and evaluations.empty and "source" in runs
    with pytest.raises(FileNotFoundError, match="or a sweep root"):
        archive_merge.read_archive(tmp_path / "sweeps")  # neither a report nor a root


def test_finished_leaves_out_the_runs_still_training(tmp_path, capsys):
    runs, evaluations = make_results()
    runs = runs.copy()
    still = runs["run_id"].iloc[0]
    runs.loc[runs.index[0], ["status", "steps"]] = ["partial", 5000]
    archive = _archive(tmp_path, runs, evaluations)
    out = tmp_path / "out"
    main(["report", str(tmp_path / "none"), "--include", str(archive), "--out", str(out),
          "--finished"])  # fmt: skip
    assert "leaving out 1 runs not finished yet" in capsys.readouterr().out
    written = pd.read_csv(out / "runs.csv")
    assert still not in set(written["run_id"]) and len(written) == len(runs) - 1
    assert still not in set(pd.read_csv(out / "evaluations.csv")["run_id"])
    assert "0 partial" in (out / "report.md").read_text()
    main(["report", str(tmp_path / "none"), "--include", str(archive), "--out", str(out)])
    assert still in set(pd.read_csv(out / "runs.csv")["run_id"])  # without it, kept


def test_a_run_trained_twice_is_checked_copy_against_copy(tmp_path, capsys):
    runs, evaluations = make_results()
    one, two, three = runs["run_id"].iloc[:3]
    archive = _archive(tmp_path, runs, evaluations)  # every run once, as its root had them
    # Another root trained runs one and two again (other run directories, other wall times): one
    # to the same bits, two with one evaluation off; three is the archived copy read back.
    again = runs[runs["run_id"].isin([one, two])].assign(
        run_dir=lambda f: "elsewhere/" + f["run_id"], wall_time_s=lambda f: f["wall_time_s"] + 7
    )
    again_evals = evaluations[evaluations["run_id"].isin([one, two])].copy()
    off = again_evals.index[again_evals["run_id"] == two][3]
    again_evals.loc[off, "score"] += 0.25
    found = archive_merge.repeats(
        (again, again_evals), archive_merge.read_archive(archive), live_source="elsewhere"
    ).set_index("run_id")
    assert list(found.index) == [one, two]  # not three, nor any run read from one place only
    assert bool(found.loc[one, "identical"]) and found.loc[one, "max_score_difference"] == 0
    assert not bool(found.loc[two, "identical"])
    assert found.loc[two, "max_score_difference"] == pytest.approx(0.25)
    assert found.loc[one, "sources"] == f"elsewhere; {archive}"

    # The command says so, keeps the record, and the next report (read back) keeps it too.
    root = tmp_path / "root"
    (root / "runs").mkdir(parents=True)
    out = tmp_path / "out"
    report.write_report(again, again_evals, tmp_path / "again")
    main(
        ["report", str(root), "--include", str(tmp_path / "again"), str(archive), "--out", str(out)]
    )
    assert f"warning: {two} was trained in" in capsys.readouterr().err
    text = (out / "report.md").read_text()
    assert "Runs trained more than once, to the same step (2" in text and "1 of 2 agree" in text
    assert "ran code with uncommitted changes" not in text
    later = tmp_path / "later"
    main(["report", str(root), "--include", str(out), "--out", str(later)])
    kept = pd.read_csv(later / "repeats.csv")
    assert list(kept["run_id"]) == [one, two] and list(kept["identical"]) == [True, False]
