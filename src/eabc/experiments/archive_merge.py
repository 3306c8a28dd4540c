"""Runs measured elsewhere, read back and merged with a sweep root's own: an earlier report's
``runs.csv`` and ``evaluations.csv``, or another sweep root's run directories (``--include``), and
the runs that more than one of them trained (the repeats, and whether their copies agree to the
last bit).

A sweep root lives on one machine and is lost with it; the report committed to the repository is
what survives, so a later machine's report stands on every run measured so far.
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from eabc.experiments import results

ARCHIVE_FILES = ("runs.csv", "evaluations.csv")
"""What an earlier ``eabc report`` wrote that :func:`read_archive` reads back."""


def read_archive(path: str | Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The runs and evaluations of an earlier report (its ``runs.csv`` and ``evaluations.csv``),
    or of another sweep root's run directories.

    A sweep root lives on one machine and is lost with it; the report committed to the repository
    is what survives. Reading it back lets a later machine's report stand on every run measured
    so far, not only on the run directories still on disk (:func:`merge`). Another root on the
    same machine (a second core's sweep of other runs) is read from its run directories, its
    broken and damaged runs left out. Each row's ``source`` says where it came from."""
    path = Path(path)
    missing = [name for name in ARCHIVE_FILES if not (path / name).is_file()]
    # A sweep root: run directories, or its runs/ folder before the first run writes one.
    if missing and path.is_dir() and ((path / "runs").is_dir() or results.run_dirs(path)):
        runs, evals = results.collect(path, write=False)
        runs = runs[~runs["status"].isin(results.UNUSABLE)].assign(source=str(path), archived=False)
        return runs.reindex(columns=[*results.RUN_COLUMNS, "source", "archived"]), evals
    if missing:
        raise FileNotFoundError(
            f"{path} has no {' or '.join(missing)} and no run directories: give a directory "
            "that `eabc report` wrote (its --out) or a sweep root"
        )
    runs = _read_table(path / "runs.csv", keep_default_na=False, na_values=[""])
    evals = _read_table(path / "evaluations.csv")
    needed = {
        "runs.csv": (runs, ["run_id", "dataset", "algo", "seed", "status", "steps", "final_score"]),
        "evaluations.csv": (evals, ["run_id", "step", "score"]),
    }
    for name, (frame, columns) in needed.items():
        lacking = [c for c in columns if c not in frame.columns]
        if lacking:
            raise ValueError(
                f"{path / name} lacks the column(s) {', '.join(lacking)}: it was not "
                "written by `eabc report`"
            )
        _check_filled(path / name, frame, [c for c in columns if c not in OPTIONAL])
    runs["variant"] = runs["variant"].astype(object).fillna("") if "variant" in runs else ""
    runs["source"], runs["archived"] = str(path), True
    columns = [*results.RUN_COLUMNS, "source", "archived"]
    return runs.reindex(columns=columns), evals.reindex(columns=results.EVAL_COLUMNS)


OPTIONAL = {
    "final_score": None,  # a run with no evaluation yet has none
    "score": "return_mean",  # data without reference returns: the raw return instead
}
"""Columns a report may leave empty, each with the column that then holds the number (None: no
other is needed)."""


def _check_filled(path: Path, frame: pd.DataFrame, required: list[str]) -> None:
    """Refuse a table with a required cell empty, or a score missing where no return stands in
    for it, naming the file's line."""
    empty = frame[required].isna()
    for column, instead in OPTIONAL.items():
        if instead and column in frame and instead in frame:
            empty[f"{column} or {instead}"] = frame[column].isna() & frame[instead].isna()
    rows = empty.any(axis=1).to_numpy()
    if rows.any():
        row = int(rows.argmax())
        blank = [c for c in empty.columns if empty[c].iloc[row]]
        raise ValueError(
            f"{path} line {row + 2} has no {', '.join(blank)}: the file is damaged; {_RESTORE}"
        )  # line 1 is the header


_RESTORE = "restore it (git checkout -- FILE) or write it again with `eabc report`"


def _read_table(path: Path, **options) -> pd.DataFrame:
    """A CSV table ``eabc report`` wrote, refused in one line where it is not one: empty, not
    CSV, or cut short (the report ends every file with a newline: a last line without one may
    hold a number cut off after its first digits)."""
    with path.open("rb") as file:
        file.seek(0, 2)
        size = file.tell()
        if size:
            file.seek(size - 1)
            if file.read(1) != b"\n":
                raise ValueError(f"{path} ends mid-line: the file was cut short; {_RESTORE}")
    try:
        return pd.read_csv(path, **options)
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError) as error:
        why = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ValueError(f"{path} is not a table `eabc report` wrote ({why}); {_RESTORE}") from None


def merge(
    live: tuple[pd.DataFrame, pd.DataFrame],
    *archives: tuple[pd.DataFrame, pd.DataFrame],
    live_source: str = "",
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """One ``(runs, evaluations)`` from the live runs and archived ones (:func:`read_archive`).

    A run is known by its ``run_id`` (its path under the sweep root, which names the dataset,
    algorithm, variant and seed). Where several sources hold it, the one that trained the most
    steps wins, the live run on a tie: a run that a new machine has only begun again does not
    hide the finished one of an earlier machine, and a live run that has caught up replaces its
    archived copy. A run's evaluations always come from the same source as its row."""
    sources, rows = _pool(live, archives, live_source)
    rows = rows.sort_values(["_steps", "_rank"], ascending=[False, True], kind="stable")
    chosen = rows.drop_duplicates("run_id", keep="first").sort_values("run_id", kind="stable")
    evals = pd.concat(
        [e[e["run_id"].isin(chosen.loc[chosen["_rank"] == i, "run_id"])] for i, _, e in sources],
        ignore_index=True,
    ).infer_objects()
    runs = chosen.drop(columns=["_rank", "_steps"]).reset_index(drop=True)
    return runs, evals.sort_values(["run_id", "step"], kind="stable").reset_index(drop=True)


def _pool(live, archives, live_source: str):
    """Every source's runs in one frame, ranked (``_rank``: the live root first) and with their
    steps as numbers (``_steps``), beside the list of ``(rank, runs, evaluations)``."""
    live_runs = live[0].assign(source=live_source, archived=False)  # archives carry their own
    sources = [(i, r, e) for i, (r, e) in enumerate(((live_runs, live[1]), *archives))]
    # An empty frame (a new machine's root) would make every column of the union an object.
    sources = [x for x in sources if not x[1].empty] or sources[:1]
    rows = pd.concat([r.assign(_rank=i) for i, r, _ in sources], ignore_index=True)
    rows["_steps"] = pd.to_numeric(rows["steps"], errors="coerce").fillna(-1)
    return sources, rows


REPEAT_COLUMNS = ["run_id", "steps", "sources", "machines", "evaluations", "max_score_difference",
                  "identical"]  # fmt: skip


def repeats(
    live: tuple[pd.DataFrame, pd.DataFrame],
    *archives: tuple[pd.DataFrame, pd.DataFrame],
    live_source: str = "",
) -> pd.DataFrame:
    """Runs trained more than once to the same step, in different places, and whether the copies
    agree: one row per run with the sources, the machines (where recorded), the evaluations
    compared, the largest score difference between copies and ``identical`` (every evaluation's
    score and return equal to the last bit, at the same steps).

    The same run read twice (a root's run directory and the report that archived it) is one
    copy, not two: copies are told apart by their run directory or their training time. Training
    is deterministic for a seed, so copies made on other machines or by other code that changes
    no numerics must agree; one that does not says the merged numbers mix two computations."""
    sources, rows = _pool(live, archives, live_source)
    evals = {i: e for i, _, e in sources}
    found = []
    for run_id, group in rows.groupby("run_id", sort=True):
        group = group[group["_steps"] == group["_steps"].max()]
        wall = pd.to_numeric(group["wall_time_s"], errors="coerce").round(6)
        copies = group.assign(_wall=wall).drop_duplicates(["run_dir", "_wall"])
        if len(copies) < 2 or copies["_steps"].iloc[0] <= 0:
            continue
        series = []
        for rank in copies["_rank"]:
            e = evals[rank]
            series.append(e[e["run_id"] == run_id].set_index("step")[["score", "return_mean"]])
        first = series[0]
        same_steps = all(list(other.index) == list(first.index) for other in series[1:])
        differences = [
            (other["score"] - first["score"]).abs().max() for other in series[1:] if same_steps
        ]
        identical = same_steps and all(other.equals(first) for other in series[1:])
        machines = [m for m in copies["machine"] if isinstance(m, str) and m]  # NaN: not recorded
        found.append({
            "run_id": run_id,
            "steps": int(copies["_steps"].iloc[0]),
            "sources": "; ".join(str(x) for x in copies["source"]),
            "machines": "; ".join(dict.fromkeys(machines)),
            "evaluations": len(first),
            "max_score_difference": float(max(differences, default=math.nan)),
            "identical": bool(identical),
        })  # fmt: skip
    return pd.DataFrame(found, columns=REPEAT_COLUMNS)


REPEATS = "repeats.csv"
"""Where ``eabc report`` keeps the runs it found trained twice, so later reports keep them."""


def read_repeats(path: str | Path) -> pd.DataFrame:
    """The repeats an earlier report recorded (``repeats.csv``); none for a sweep root."""
    file = Path(path) / REPEATS
    if not file.is_file():
        return pd.DataFrame(columns=REPEAT_COLUMNS)
    found = pd.read_csv(file, keep_default_na=False, na_values=[""])
    return found.reindex(columns=REPEAT_COLUMNS)


def combined_repeats(*frames: pd.DataFrame) -> pd.DataFrame:
    """Repeats from several places, each run once (the first frame's row first)."""
    frames = [f for f in frames if not f.empty]
    if not frames:
        return pd.DataFrame(columns=REPEAT_COLUMNS)
    both = pd.concat(frames, ignore_index=True).drop_duplicates("run_id", keep="first")
    return both.sort_values("run_id", kind="stable").reset_index(drop=True)
