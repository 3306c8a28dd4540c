"""Evaluation off the training path: processes that evaluate runs' parameters while training goes
on, and the queue that writes each run's results in step order.

The trainer hands each evaluation to an :class:`EvaluationPool` as a :class:`Task` (the actor's
weights and the observation normaliser as NumPy arrays, the evaluation's environment and step)
and trains on. A worker runs the episodes side by side in a batch of environments with one policy
call per step (:class:`eabc.evaluation.Evaluator`, ``vectorised=True``): the same returns as the
episodes run one by one in the training process. Workers are spawned, single-threaded and import
neither JAX nor the trainer; one pool serves any number of runs (the seeds of ``train_runs``, or
the runs of one program after another).

A run's log rows and checkpoints wait in its :class:`InOrder` queue until the evaluations up to
their step are in, then are written as training in one process writes them: each row with its
evaluation, each checkpoint (the state at its step, kept meanwhile) with every evaluation up to
its step. So log.csv, summary.json and the checkpoints' evaluation histories are the same files,
and a run killed meanwhile resumes from its last written checkpoint as it always did.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import multiprocessing
from collections.abc import Callable
from typing import Any

import numpy as np

from eabc.data.dataset import Normalizer
from eabc.data.parallel import bare_children
from eabc.evaluation import Evaluator, Policy


@dataclasses.dataclass(frozen=True)
class Task:
    """One evaluation, in plain values and NumPy arrays: the policy at ``step`` and where to run
    it (the fields of its run's :class:`~eabc.evaluation.Evaluator`)."""

    env_id: str
    seed: int
    episodes: int
    ref_min_score: float | None
    ref_max_score: float | None
    step: int
    actor: dict[str, np.ndarray]
    """The actor's weights (``w0, b0, ...``)."""
    mean: np.ndarray
    """The observation normaliser's mean."""
    std: np.ndarray
    """The observation normaliser's standard deviation."""
    max_action: float
    gaussian: bool
    """Whether the actor outputs a Gaussian's mean and log std (its mean is acted on)."""


_EVALUATORS: dict[tuple[str, int], Evaluator] = {}
"""A worker's evaluators by environment and episodes: environments are made once per worker."""


def evaluate(task: Task) -> dict[str, float]:
    """Run ``task`` (in a worker): the evaluation's returns and scores."""
    key = (task.env_id, task.episodes)
    if key not in _EVALUATORS:
        _EVALUATORS[key] = Evaluator(task.env_id, task.seed, task.episodes)
    evaluator = _EVALUATORS[key]
    evaluator.seed = task.seed
    evaluator.ref_min_score, evaluator.ref_max_score = task.ref_min_score, task.ref_max_score
    policy = Policy(task.actor, Normalizer(task.mean, task.std), task.max_action, task.gaussian)
    return evaluator(policy, task.step, vectorised=True)


class EvaluationPool:
    """``workers`` processes that run :class:`Task` s; a context manager. Leaving it on an error
    cancels the evaluations not started."""

    def __init__(self, workers: int):
        if workers < 1:
            raise ValueError(f"an evaluation pool needs at least one worker, got {workers}")
        self.workers = workers
        context = multiprocessing.get_context("spawn")  # not fork: the trainer runs JAX's threads
        self._executor = concurrent.futures.ProcessPoolExecutor(workers, mp_context=context)

    def submit(self, task: Task) -> concurrent.futures.Future:
        """The future of ``task``'s result."""
        with bare_children():  # the executor starts its processes as work arrives
            return self._executor.submit(evaluate, task)

    def close(self, finished: bool = True) -> None:
        """Stop the workers: after the evaluations submitted, or (not ``finished``) cancelling
        those not started."""
        self._executor.shutdown(wait=finished, cancel_futures=not finished)

    def __enter__(self) -> EvaluationPool:
        return self

    def __exit__(self, kind, error, trace) -> None:
        self.close(finished=kind is None)


Write = Callable[[dict[str, Any], "dict[str, float] | None", "dict[str, Any] | None"], None]
"""``write(row, evaluation, state)``: log ``row`` with its evaluation (None: none at its step),
then checkpoint ``state`` (None: no checkpoint at its step)."""


@dataclasses.dataclass
class _Held:
    row: dict[str, Any]
    evaluation: concurrent.futures.Future | None
    state: dict[str, Any] | None


class InOrder:
    """A run's rows, evaluations and checkpoints, written by ``write`` in step order as soon as
    the evaluations up to them are in."""

    def __init__(self, write: Write):
        self._write = write
        self._held: collections.deque[_Held] = collections.deque()

    def add(
        self,
        row: dict[str, Any],
        evaluation: concurrent.futures.Future | None,
        state: dict[str, Any] | None,
    ) -> None:
        """Hold ``row`` (and its step's evaluation and state to checkpoint) until its turn."""
        self._held.append(_Held(row, evaluation, dict(state) if state is not None else None))

    def waiting(self) -> int:
        """How many of the held evaluations are not in yet."""
        return sum(h.evaluation is not None and not h.evaluation.done() for h in self._held)

    def flush(self, keep: int | None = None) -> None:
        """Write what is ready; with ``keep``, first wait until at most ``keep`` evaluations are
        still out (0: write everything)."""
        while self._held:
            head = self._held[0]
            ready = head.evaluation is None or head.evaluation.done()
            if not ready and (keep is None or self.waiting() <= keep):
                return
            self._held.popleft()
            evaluation = head.evaluation.result() if head.evaluation is not None else None
            self._write(head.row, evaluation, head.state)
