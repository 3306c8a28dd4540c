"""Run logs: a CSV file (one row per log interval), TensorBoard events, and a learning-curve PNG."""

from __future__ import annotations

import collections
import csv
import io
import json
import math
from pathlib import Path

from tensorboardX import SummaryWriter
from tensorboardX.summary import hparams

from eabc import paths
from eabc.training.checkpoint import atomic_write

LOG = "log.csv"
CURVE = "curve.png"


class RunLogger:
    """Appends rows to ``log.csv`` and TensorBoard; on resume it drops rows after the checkpoint.

    Rows read back keep their cells as written (an empty cell stays empty, a number keeps its
    text), so a resumed run's file is byte for byte the file of a run never interrupted.
    """

    def __init__(self, run_dir: Path, resume_step: int = 0, tensorboard: bool = True):
        self.path = Path(run_dir) / LOG
        self.rows: list[dict[str, float]] = []
        """Numbers of every row (an empty cell is absent), for checks such as divergence."""
        self._cells: list[dict[str, str]] = []
        """The same rows as the text written to the file."""
        if self.path.exists():
            for cells in read_log(self.path):
                if int(float(cells["step"])) <= resume_step:
                    self._cells.append(cells)
                    self.rows.append(_numbers(cells))
        self.writer = None
        if tensorboard:
            # TensorBoard drops every event at or after purge_step: the rows after the checkpoint
            # go, the checkpoint's own row (kept in log.csv too) stays.
            # Event files are named by the second they open in; two resumes within one second
            # would share a name and the second would truncate the first's file (its points and
            # its purge marker), so each writer's file also gets its place in the directory.
            tb = Path(run_dir) / "tb"
            order = len(list(tb.glob("events.out.tfevents.*"))) if tb.exists() else 0
            self.writer = SummaryWriter(
                str(tb),
                purge_step=resume_step + 1 if resume_step else None,
                filename_suffix=f".{order:04d}",
            )
            if not resume_step:
                self._write_hparams(Path(run_dir))
        self._write_all()

    def _write_hparams(self, run_dir: Path) -> None:
        """The run's settings (config.json) for TensorBoard's HParams tab, with its evaluation
        scalars as the metrics, so that runs compare by setting."""
        config = read_config_or_none(run_dir)
        if config is None:
            return
        values = {**config.get("train", {}), **config.get("agent", {})}
        values = {k: _hparam(v) for k, v in values.items() if v is not None}
        metrics = {key: math.nan for key in ("score", "return_mean")}
        for summary in hparams(values, metrics):
            self.writer.file_writer.add_summary(summary)

    def log(self, row: dict[str, float]) -> None:
        self.rows.append(row)
        self._cells.append({k: str(v) for k, v in row.items()})  # the text csv would write
        self._write_all()
        if self.writer is not None:
            for key, value in row.items():
                if key != "step" and not math.isnan(value):
                    self.writer.add_scalar(key, value, int(row["step"]))
            self.writer.flush()

    def _write_all(self) -> None:
        """Rewrite the whole file: small (one row per 1000 steps) and never left half-written."""
        if not self._cells:
            return
        columns = list(dict.fromkeys(k for row in self._cells for k in row))
        text = io.StringIO(newline="")
        writer = csv.DictWriter(text, columns, restval="")
        writer.writeheader()
        writer.writerows(self._cells)
        atomic_write(self.path, text.getvalue().encode())

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def read_config_or_none(run_dir: Path) -> dict | None:
    try:
        return json.loads(paths.read_file(run_dir / "config.json").decode())
    except (OSError, ValueError):
        return None


def _hparam(value):
    """A setting as TensorBoard's HParams tab takes it: a number, a string or a boolean."""
    return value if isinstance(value, bool | int | float | str) else str(value)


def read_log(path: Path, data: bytes | None = None) -> list[dict[str, str]]:
    """The rows of a ``log.csv`` (or of its bytes ``data``) as text, without their empty cells;
    ``OSError`` where it is not a regular file (a FIFO would block the reader)."""
    data = paths.read_file(path) if data is None else data
    rows = csv.DictReader(io.StringIO(data.decode(), newline=""))
    return [{k: v for k, v in row.items() if v not in ("", None)} for row in rows]


def log_problem(
    path: Path, evaluations: dict[str, dict], step: int, steps: int | None = None
) -> str | None:
    """Why the ``log.csv`` at ``path`` does not hold what a checkpoint at ``step`` with the
    evaluation history ``evaluations`` says was logged (missing, unreadable, cut short, a step
    twice, past the run's ``steps``, lacking or contradicting an evaluation); None when it holds
    it. Other rows after ``step`` are not judged (a run logs a few rows past its last checkpoint,
    and a resume drops them)."""
    if not path.exists():
        return f"{path} is missing" if step > 0 or evaluations else None
    rows, complete = readable_rows(path)
    if rows is None:
        return f"{path} cannot be read"
    if not complete:
        return f"{path} is cut short (its last line is incomplete)"
    logged_steps = [int(float(row["step"])) for row in rows]
    last = max(logged_steps, default=0)
    twice = sorted(at for at, times in collections.Counter(logged_steps).items() if times > 1)
    if twice:
        return f"{path} has step {twice[0]} more than once"
    if steps is not None and last > steps:
        return f"{path} goes on to step {last}, past the run's {steps} steps"
    if last < step:
        return f"{path} ends at step {last}, before the checkpoint's step {step}"
    logged = {  # an evaluation's return and score (NaN for data without reference scores)
        int(float(row["step"])): (_num(row.get("return_mean")), _num(row.get("score")))
        for row in rows
        if int(float(row["step"])) <= step and not math.isnan(_num(row.get("return_mean")))
    }
    held = {int(s): (float(e["return_mean"]), _num(e.get("score"))) for s, e in evaluations.items()}
    for at in sorted(set(held) | set(logged)):
        if at not in logged:
            return f"{path} lacks the evaluation at step {at} that the checkpoint holds"
        if at not in held or not all(map(_same, logged[at], held[at])):
            return f"{path} has an evaluation at step {at} that the checkpoint does not hold"
    return None


def _same(a: float, b: float) -> bool:
    """Two logged numbers agree (NaN, no value, agrees only with NaN)."""
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9)


def rebuild_log(path: Path, evaluations: dict[str, dict], step: int) -> None:
    """Rewrite ``log.csv`` so that it holds the checkpoint's evaluations: the readable rows up to
    ``step`` are kept, each evaluation's cells are the checkpoint's, and an evaluation the log lost
    becomes a row of its own (the training metrics of lost rows cannot come back)."""
    rows, complete = readable_rows(path) if path.exists() else ([], True)
    rows = (rows or [])[: None if complete else -1]
    by_step = {int(float(row["step"])): row for row in rows if int(float(row["step"])) <= step}
    for cells in by_step.values():
        for key in [k for k in cells if k.split("_")[0] in ("return", "score")]:
            del cells[key]  # an evaluation the checkpoint does not hold is not one of this run's
    for at, evaluation in evaluations.items():
        cells = by_step.setdefault(int(at), {"step": str(int(at))})
        cells.update({k: str(v) for k, v in evaluation.items()})
    ordered = [by_step[at] for at in sorted(by_step)]
    columns = list(dict.fromkeys(k for row in ordered for k in row))
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, columns, restval="")
    writer.writeheader()
    writer.writerows(ordered)
    atomic_write(path, text.getvalue().encode())


def readable_rows(path: Path) -> tuple[list[dict[str, str]] | None, bool]:
    """``log.csv``'s rows (None if it cannot be read as a log) and whether its last line is
    whole (a file cut mid-line ends without a line break)."""
    try:
        data = paths.read_file(path)
        rows = read_log(path, data)
        for row in rows:
            int(float(row["step"]))
    except (OSError, UnicodeDecodeError, csv.Error, KeyError, ValueError, TypeError):
        return None, True
    return rows, not data or data.endswith(b"\n")


def _num(text) -> float:
    try:
        return float(text) if text not in (None, "") else math.nan
    except ValueError:
        return math.nan


def _numbers(cells: dict[str, str]) -> dict[str, float]:
    return {k: int(float(v)) if k == "step" else float(v) for k, v in cells.items()}


def plot_curve(evaluations: list[dict[str, float]], path: Path, title: str) -> None:
    """Normalised score (or return) against gradient steps."""
    from matplotlib.figure import Figure  # noqa: PLC0415 (drawn at a run's end: not on every command's start)

    key = "score" if evaluations and "score" in evaluations[0] else "return_mean"
    steps = [e["step"] for e in evaluations]
    values = [e[key] for e in evaluations]
    spread = [e.get(f"{key.split('_', maxsplit=1)[0]}_std", 0.0) for e in evaluations]
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    ax.plot(steps, values, color="C0")
    ax.fill_between(
        steps,
        [v - s for v, s in zip(values, spread)],
        [v + s for v, s in zip(values, spread)],
        color="C0",
        alpha=0.2,
        label="+-1 std over episodes",
    )
    ax.set_xlabel("gradient steps")
    ax.set_ylabel("D4RL normalised score" if key == "score" else "return")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
