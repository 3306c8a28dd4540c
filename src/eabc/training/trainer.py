"""The offline training loop: compiled chunks of gradient steps between evaluations.

A run is started or resumed (:mod:`eabc.training.lifecycle`) into a
:class:`~eabc.training.lifecycle.Run`; :func:`train` and :func:`train_runs` advance it in
compiled chunks (:mod:`eabc.training.chunks`), and between chunks log, evaluate every
``eval_interval`` steps, check the run's health (:mod:`eabc.training.health`) and checkpoint every
``checkpoint_interval`` steps, so that ``resume`` continues bit for bit.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from eabc import timing
from eabc.evaluation import Policy
from eabc.progress import bar as progress_bar
from eabc.training import checkpoint, eval_pool, provenance
from eabc.training.chunks import (
    device_data,
    differing,
    stack_data,
    summarize_metrics,
    train_chunk,
    train_chunk_runs,
)
from eabc.training.config import FINAL_EVALUATIONS
from eabc.training.directory import SUMMARY
from eabc.training.health import (
    divergence_warning,
    first_divergence,
    in_range,
    non_finite,
    value_range,
)
from eabc.training.lifecycle import Run, prepared
from eabc.training.logger import CURVE, RunLogger, plot_curve

PROBE_CHUNKS, PROBE_SECONDS = 3, 5.0
"""With a deadline, how long a program's speed is measured before the end is predicted: this many
chunks after its first (which compiles) and at least these seconds."""
DEADLINE_MARGIN = 1.05
"""A prediction's allowance for what the first chunks do not show (evaluations, checkpoints)."""


class PastDeadline(RuntimeError):
    """Training stopped early: at the speed measured in its first chunks, it would end after its
    deadline. Its runs stay resumable (from their last checkpoint, or from step 0)."""

    def __init__(self, width: int, step: int, steps: int, steps_per_s: float, compile_s: float,
                 late_s: float):  # fmt: skip
        self.width, self.step, self.steps = width, step, steps
        self.steps_per_s = steps_per_s
        """Every run's steps per second: the program's, at this many runs."""
        self.compile_s = compile_s
        """What the first chunk took beyond a chunk at that speed: the program's compilation."""
        self.late_s = late_s
        super().__init__(
            f"{width} run{'s' * (width > 1)} at {steps_per_s:,.0f} steps/s would end about "
            f"{late_s:,.0f} s after the deadline (step {step:,} of {steps:,})"
        )


def estimate_seconds(
    algorithm,
    agent_config,
    steps_left: int,
    evaluations: int,
    pretrain: bool = False,
    steps_per_s: float | None = None,
    speed: timing.HostSpeed = timing.REFERENCE,
) -> float:
    """About how long ``steps_left`` gradient steps of ``algorithm`` at ``agent_config`` take,
    with ``evaluations`` evaluation episodes and, with ``pretrain``, the one-off model fit: at
    ``steps_per_s`` where it was measured on this host, else at the contract's reference-host
    rate (``Algorithm.steps_per_s``, scaled by the settings' relative cost) times this host's
    ``speed`` (:mod:`eabc.timing`)."""
    reference_rate = algorithm.steps_per_s / max(algorithm.relative_cost(agent_config), 1e-9)
    rate = steps_per_s or reference_rate * speed.factor
    fit = algorithm.pretrain_s(agent_config) if algorithm.pretrain_s and pretrain else 0.0
    return steps_left / rate + (evaluations * timing.EPISODE_SECONDS + fit) / speed.factor


def _estimate(run: Run) -> str:
    """``about 12 minutes at ...``: the time the rest of ``run`` takes; this host's speed is
    probed only when the reference estimate is long enough to matter."""
    config = run.config
    left = max(config.steps - run.step, 0)
    evaluations = len(config.evaluation_steps(after=run.step)) * config.eval_episodes
    args = (run.algorithm, run.agent_config, left, evaluations)
    quick = estimate_seconds(*args) < 10
    speed = timing.host_speed(config.cache_dir, measure=not quick)
    seconds = estimate_seconds(*args, speed=speed)
    return f"{'about ' * (seconds >= 1)}{timing.duration(seconds)} {speed.basis()}"


def policy_fn(run: Run) -> Policy:
    """The run's current actor as a NumPy policy on raw observations."""
    actor = jax.device_get(run.state["agent"].actor)
    return Policy(actor, run.normalizer, run.max_action, run.algorithm.gaussian_actor)


def evaluate(run: Run) -> dict[str, float]:
    """The run's current policy evaluated as its evaluation at this step is (the step picks
    AntMaze's goals: :meth:`~eabc.evaluation.Evaluator.seed_at`)."""
    return run.evaluator(policy_fn(run), step=run.step)


def evaluation_task(run: Run) -> eval_pool.Task:
    """The evaluation of ``run`` at its current step, for an evaluation process."""
    evaluator = run.evaluator
    return eval_pool.Task(
        evaluator.env_id, evaluator.seed, evaluator.episodes, evaluator.ref_min_score,
        evaluator.ref_max_score, run.step, jax.device_get(run.state["agent"].actor),
        np.asarray(run.normalizer.mean), np.asarray(run.normalizer.std), run.max_action,
        run.algorithm.gaussian_actor,
    )  # fmt: skip


def train(
    run: Run,
    progress: bool = True,
    eval_workers: int | eval_pool.EvaluationPool = 0,
    deadline: float | None = None,
) -> dict[str, Any]:
    """Train ``run`` to ``config.steps`` from wherever it is; returns the summary."""
    return train_runs([run], progress, eval_workers, deadline)[0]


def train_runs(
    runs: list[Run],
    progress: bool = True,
    eval_workers: int | eval_pool.EvaluationPool = 0,
    deadline: float | None = None,
) -> list[dict[str, Any]]:
    """Train runs that share their networks' shapes together, as one program over a run axis.

    The runs may differ in their seed, their dataset (of one observation and action size) and
    the algorithm's ``traced_settings`` (numbers its update only computes with, such as a BC
    weight); everything else must be the same (:func:`one_program_values` says what is not).
    One compiled chunk advances every run (``vmap`` of the scanned update, each run sampling its
    own dataset with its own key); then every run logs, evaluates and checkpoints into its own
    directory exactly as if trained alone, so each can be resumed or reported on its own. Runs
    that are not at the same step are trained one by one. Each run's writer lock is released
    when this returns or fails.

    ``eval_workers`` > 0 evaluates in that many processes while training goes on
    (:mod:`eabc.training.eval_pool`), or in a given pool (one pool for many calls); the files
    written are the same as with 0, which evaluates in this process between chunks.

    ``deadline`` (a ``time.time()``): once the first chunks have shown the program's speed
    (:data:`PROBE_CHUNKS`, :data:`PROBE_SECONDS`), raises :class:`PastDeadline` if the rest would
    end after it; the runs are then as if killed there, and resume from their last checkpoint.
    """
    own = None
    if isinstance(eval_workers, eval_pool.EvaluationPool):
        pool = eval_workers
    else:
        pool = own = eval_pool.EvaluationPool(eval_workers) if eval_workers else None
    finished = False
    try:
        for run in runs:  # who trains it from here, where, with what code (provenance.json)
            provenance.record(run.run_dir, run.step)
        summaries = _train_together(runs, progress, pool, deadline)
        finished = True
        return summaries
    finally:
        if own is not None:
            own.close(finished)
        for run in runs:
            if run.lock is not None:
                run.lock.release()


def _train_together(
    runs: list[Run],
    progress: bool,
    pool: eval_pool.EvaluationPool | None = None,
    deadline: float | None = None,
) -> list[dict[str, Any]]:
    first = runs[0]
    values = one_program_values(runs)
    if len({run.step for run in runs}) > 1:
        return [_train_together([run], progress, pool, deadline)[0] for run in runs]
    config = first.config
    slots: dict[tuple, int] = {}  # each dataset (with its normaliser) once on the device
    datas, rewards, which, q_ranges = [], [], [], []
    for run in runs:
        slot = (id(run.dataset), run.normalizer.mean.tobytes(), run.normalizer.std.tobytes())
        if slot not in slots:
            slots[slot] = len(datas)
            dataset = prepared(run.algorithm, run.dataset, config.reward_convention)
            datas.append(device_data(dataset, run.normalizer, run.algorithm.next_actions))
            rewards.append(dataset.rewards)
        which.append(slots[slot])
        discount = getattr(run.agent_config, "discount", None)
        q_ranges.append(value_range(rewards[which[-1]], discount))
    sizes = [int(datas[i].rewards.shape[0]) for i in which]
    data = datas[0] if len(runs) == 1 else stack_data(datas)
    update = functools.partial(
        first.algorithm.update, config=first.agent_config, max_action=first.max_action
    )
    delayed = first.algorithm.delayed_period  # a fixed schedule: chunks without a branch
    period = delayed(first.agent_config) if delayed else None
    loggers = [RunLogger(run.run_dir, resume_step=run.step) for run in runs]
    writers = [
        functools.partial(_write, run, logger, q_range)
        for run, logger, q_range in zip(runs, loggers, q_ranges)
    ]
    # With a pool, each run's rows and checkpoints wait for the evaluations before them.
    queues = [eval_pool.InOrder(write) for write in writers] if pool is not None else None
    desc = f"{config.algo} {', '.join(dict.fromkeys(run.dataset.name for run in runs))}"
    if len(runs) > 1:
        desc += f" seeds {','.join(str(run.config.seed) for run in runs)}"
    bar = progress_bar(
        config.steps,
        f"training {desc}",
        initial=first.step,
        enabled=progress,
        estimate=_estimate(first) if progress and first.step < config.steps else None,
        dynamic_ncols=True,
    )
    probe = _Probe(deadline, len(runs), config.steps) if deadline is not None else None
    try:
        while first.step < config.steps:
            length = min(config.log_interval, config.steps - first.step)
            started = time.perf_counter()
            if probe is not None:
                probe.check(first.step)
            if len(runs) == 1:
                agent, key, metrics = train_chunk(
                    first.state["agent"],
                    first.state["key"],
                    data,
                    update,
                    config.batch_size,
                    length,
                    period,
                    first.step,
                )
                outputs = [(agent, key, metrics)]
            else:
                stack = lambda *xs: jnp.stack(xs)
                agents, keys, metrics = train_chunk_runs(
                    jax.tree.map(stack, *[run.state["agent"] for run in runs]),
                    jnp.stack([run.state["key"] for run in runs]),
                    data,
                    which,
                    sizes,
                    values,
                    update,
                    config.batch_size,
                    length,
                    period,
                    first.step,
                )
                outputs = [
                    jax.tree.map(lambda x, i=i: x[i], (agents, keys, metrics))
                    for i in range(len(runs))
                ]
            jax.block_until_ready(outputs)
            seconds = time.perf_counter() - started
            rows = []
            for i, (run, output) in enumerate(zip(runs, outputs)):
                rows.append(_after_chunk(run, *output, length, seconds, q_ranges[i]))
                evaluation = state = None
                if run.diverged_step is None and run.config.evaluates(run.step):
                    if pool is None:
                        evaluation = evaluate(run)
                    else:
                        evaluation = pool.submit(evaluation_task(run))
                if run.diverged_step is None and _checkpoints(run):
                    state = run.state
                if queues is None:
                    writers[i](rows[-1], evaluation, state)
                else:
                    queues[i].add(rows[-1], evaluation, state)
            if queues is not None:  # at most two evaluations a worker out at a time
                keep = max(1, 2 * pool.workers // len(runs))
                for queue in queues:
                    queue.flush(keep)
            bar.update(length)
            bar.set_postfix(_postfix(rows[0], first.state["evaluations"]), refresh=False)
            if any(run.diverged_step is not None for run in runs):
                break
        for queue in queues or []:
            queue.flush(keep=0)
    finally:
        bar.close()
        for logger in loggers:
            logger.close()
    healthy = [run for run in runs if run.diverged_step is None]
    rest = {}  # the other seeds of a group, when one of them stopped on NaN/inf
    if len(healthy) < len(runs) and healthy and healthy[0].step < config.steps:
        rest = dict(zip(map(id, healthy), _train_together(healthy, progress, pool, deadline)))
    summaries = []
    for run, logger, q_range in zip(runs, loggers, q_ranges):
        if id(run) in rest:
            summaries.append(rest[id(run)])
            continue
        summaries.append(summarize_run(run))
        if q_range is not None:
            summaries[-1]["q_range"] = list(q_range)
            summaries[-1]["q_out_of_range_step"] = first_divergence(logger.rows, q_range)
        summaries[-1]["diverged_step"] = run.diverged_step
        checkpoint.save_json(run.run_dir / SUMMARY, summaries[-1])
    return summaries


class _Probe:
    """Times a program's first chunks and, once they show its speed, whether the rest of its steps
    ends before ``deadline``; asked before each chunk with the step reached."""

    def __init__(self, deadline: float, width: int, steps: int):
        self.deadline, self.width, self.steps = deadline, width, steps
        self.calls, self.decided = 0, False
        self.began = self.timed = None  # (step, time) before the first chunk, and after it

    def check(self, step: int) -> None:
        now = time.time()
        self.calls += 1
        if self.calls == 1:
            self.began = (step, now)
        elif self.calls == 2:  # the first chunk (it compiled the program) is done
            self.timed = (step, now)
        if self.timed is None or self.decided:
            return
        done, seconds = step - self.timed[0], now - self.timed[1]
        if self.calls <= PROBE_CHUNKS + 1 or seconds < PROBE_SECONDS:
            return
        self.decided = True
        rate = done / max(seconds, 1e-9)
        end = now + DEADLINE_MARGIN * (self.steps - step) / rate
        if end > self.deadline:
            first_chunk = self.timed[1] - self.began[1]
            compile_s = max(0.0, first_chunk - (self.timed[0] - self.began[0]) / rate)
            raise PastDeadline(self.width, step, self.steps, rate, compile_s, end - self.deadline)


def one_program_values(runs: list[Run]) -> dict[str, list[float]]:
    """The settings in which ``runs`` differ, a value per run, where they may train as one
    program (:func:`train_runs`): the algorithm's ``traced_settings`` that are not the same in
    every run. Raises ValueError where the runs differ in anything but those, their seed and
    their dataset, or their datasets in shape."""
    first = runs[0]
    traced = first.algorithm.traced_settings
    values = differing(traced, [run.agent_config for run in runs])
    for run in runs[1:]:
        common = {name: getattr(first.agent_config, name) for name in values}
        why = [
            what
            for what, differs in (
                ("settings", run.config
                 != dataclasses.replace(first.config, seed=run.config.seed,
                                        dataset=run.config.dataset)),
                ("algorithm settings", dataclasses.replace(run.agent_config, **common)
                 != first.agent_config),
                ("observation or action size", (run.dataset.obs_dim, run.dataset.act_dim)
                 != (first.dataset.obs_dim, first.dataset.act_dim)),
                ("max_action", run.max_action != first.max_action),
            )
            if differs
        ]  # fmt: skip
        if why:
            raise ValueError(
                f"{run.run_dir} differs from {first.run_dir} in its {' and '.join(why)}; only "
                "runs that differ in their seed, dataset (of one shape) or the algorithm's "
                f"traced settings ({', '.join(traced) or 'none'}) train as one program"
            )
    for name, column in values.items():
        if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in column):
            raise ValueError(
                f"{name} differs between runs ({', '.join(map(str, column))}) but is not a "
                "number in every one: such runs train as separate programs"
            )
    return values


def _after_chunk(run: Run, agent, key, metrics, length: int, seconds: float, q_range=None) -> dict:
    """One run's state and log row after a chunk of ``length`` steps (its evaluation and
    checkpoint come after, :func:`_write`)."""
    run.state = {**run.state, "agent": agent, "key": key}
    run.state["elapsed"] += seconds
    row = {"step": run.step, "wall_time": run.state["elapsed"], "steps_per_s": length / seconds}
    row |= summarize_metrics(jax.device_get(metrics), run.algorithm.step_metrics)
    if q_range is not None and "q_mean" in row:
        row["q_out_of_range"] = float(not in_range(row["q_mean"], q_range))
    bad = non_finite(row)
    if bad:  # the weights are NaN/inf from here on: no evaluation, no checkpoint, stop
        run.diverged_step = run.step
        tqdm.write(
            f"error: {run.run_dir.name} at step {run.step}: {', '.join(bad)} became NaN/inf, so "
            "training stops here; summary.json records diverged_step and the last checkpoint is "
            "from before (lower learning rates or more behaviour cloning may avoid it)",
            file=sys.stderr,
        )
    return row


def _checkpoints(run: Run) -> bool:
    """Whether the run saves a checkpoint at its current step."""
    return run.step % run.config.checkpoint_interval == 0 or run.step == run.config.steps


def _write(run: Run, logger, q_range, row: dict, evaluation: dict | None, state: dict | None):
    """Log ``row`` with its step's ``evaluation`` (recorded in the run's history), then save
    ``state`` (the run's state at the row's step) with the history up to that step; warn at the
    run's first row whose Q values leave ``q_range``."""
    if evaluation is not None:
        run.state["evaluations"][str(row["step"])] = evaluation
        row |= evaluation
        _plot(run)
    logger.log(row)
    # Warn at the first flagged row only; the log is scanned only when a row is flagged.
    if row.get("q_out_of_range") and first_divergence(logger.rows, q_range) == row["step"]:
        advice = run.algorithm.divergence_advice
        tqdm.write(
            divergence_warning(run.run_dir.name, row["step"], row["q_mean"], q_range, advice),
            file=sys.stderr,
        )
    if state is not None:
        state = {**state, "evaluations": run.state["evaluations"]}
        checkpoint.save(run.run_dir, state, run.algorithm.state_layout, run.identity)


def _postfix(row, evaluations) -> dict[str, str]:
    out = {"steps/s": f"{row['steps_per_s']:.0f}"}
    if evaluations:
        last = evaluations[max(evaluations, key=int)]
        out["score" if "score" in last else "return"] = (
            f"{last.get('score', last['return_mean']):.1f}"
        )
    return out


def _plot(run: Run) -> None:
    evaluations = [
        {"step": int(s), **e}
        for s, e in sorted(run.state["evaluations"].items(), key=lambda kv: int(kv[0]))
    ]
    plot_curve(evaluations, run.run_dir / CURVE, f"{run.config.algo} on {run.dataset.name}")


def final_window(steps: list[int]) -> str:
    """What a final score averages, from the steps of its evaluations: ``last 10 evaluations
    (steps 955,000-1,000,000)``, or with fewer than :data:`FINAL_EVALUATIONS` ``all 3
    evaluations (fewer than 10; steps 2,000-6,000)``."""
    last = steps[-FINAL_EVALUATIONS:]
    if not last:
        return "no evaluations"
    span = f"step {last[0]:,}" if len(last) == 1 else f"steps {last[0]:,}-{last[-1]:,}"
    if len(steps) >= FINAL_EVALUATIONS:
        return f"last {FINAL_EVALUATIONS} evaluations ({span})"
    which = "the only evaluation" if len(steps) == 1 else f"all {len(steps)} evaluations"
    return f"{which} (fewer than {FINAL_EVALUATIONS}; {span})"


def summarize_run(run: Run) -> dict[str, Any]:
    steps = sorted(run.state["evaluations"], key=int)
    evaluations = [run.state["evaluations"][s] for s in steps]
    last = evaluations[-FINAL_EVALUATIONS:]
    summary: dict[str, Any] = {
        "algo": run.config.algo,
        "dataset": run.dataset.name,
        "seed": run.config.seed,
        "steps": run.step,
        "wall_time_s": run.state["elapsed"],
        "steps_per_s": run.step / max(run.state["elapsed"], 1e-9),
        "evaluations": len(evaluations),
    }
    if last:
        summary["final_return"] = float(np.mean([e["return_mean"] for e in last]))
        if "score" in last[0]:
            summary["final_score"] = float(np.mean([e["score"] for e in last]))
        summary["final_score_window"] = final_window([int(s) for s in steps])
    return summary
