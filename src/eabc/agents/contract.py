"""The algorithm contract: everything generic code (the trainer, sweeps, results, reports, the CLI)
may know of an algorithm, in one typed description defined in the algorithm's own file.

An algorithm file ends with ``ALGORITHMS = (Algorithm(...), ...)``; ``eabc.agents`` registers every
file listed in its one tuple of modules. Generic code asks the description and never names an
algorithm or its settings. The state ``init`` returns is a pytree (a dataclass of :mod:`eabc.pytree`) with
``.actor`` (the policy's parameters) and ``.step`` (gradient steps taken); a state built on another
algorithm's holds that state as one field and delegates both to it (read-only properties), and in
a checkpoint :func:`eabc.pytree.find` reaches them either way. ``update`` is pure, so the
trainer can run it inside one ``lax.scan`` and ``vmap`` it over seeds.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal, Protocol

from eabc import ranges

ActorKind = Literal["deterministic", "tanh-gaussian"]

CRITIC_METRICS = frozenset({"critic_loss", "q_mean", "q_ensemble_std", "target_mean"})
"""Metrics that every gradient step computes: a chunk's log row averages them over every step.
Any other metric (the actor's) is averaged over the steps whose ``actor_updated`` metric is true."""

SHORT_NAMES = {"num_critics": "K", "confidence_level": "p"}
"""The paper's symbols, used in run ids (``hopper-medium__eabc__K5__seed0``) and labels."""


class PretrainProgress(Protocol):
    """Where a long ``pretrain`` keeps its progress, so that a killed run continues it: the
    trainer gives one per run (a file in the run directory, dropped once the fitted state is in
    the run's checkpoint)."""

    def load(self) -> dict[str, Any] | None:
        """What the last :meth:`save` stored (nested dicts of arrays and plain values), or None."""

    def save(self, tree: Any) -> None:
        """Store a pytree of arrays and plain values, atomically."""


@dataclasses.dataclass(frozen=True)
class Algorithm:
    """One ``--algo`` choice."""

    name: str
    """What ``eabc train --algo`` accepts, e.g. ``td3bc``."""
    display_name: str
    """The paper's name in tables and figures, e.g. ``TD3+BC``."""
    preset: Any
    """The default settings: a frozen dataclass whose fields carry one-line docstrings."""
    init: Callable[..., Any]
    """``init(key, obs_dim, act_dim, config) -> state``."""
    update: Callable[..., tuple[Any, dict]]
    """``update(state, batch, key, config, max_action) -> (state, metrics)``, pure."""
    actor: ActorKind = "deterministic"
    """deterministic: ``max_action * tanh(MLP(s))``; tanh-gaussian: the MLP's first half is the
    mean, and the deterministic action is ``max_action * tanh(mean)``."""
    preprocess: Callable[[Any], Any] | None = None
    """``preprocess(dataset) -> dataset`` before training (e.g. IQL's reward scaling); the run
    keeps the data as loaded."""
    pretrain: Callable[..., Any] | None = None
    """``pretrain(state, data, key, config, normalizer, progress) -> state``, once before the
    first step of a new run (e.g. MOPO's dynamics model); what it learns lives in the state, so it
    is saved. ``progress`` (a :class:`PretrainProgress`, or None) keeps its progress as it goes:
    a run killed during the pretraining continues it where it stopped."""
    resolve: Callable[..., Any] | None = None
    """``resolve(config, dataset_name, steps, given) -> config``: settings that depend on the data
    or the run's length (``steps``; None when unknown), where the user did not set them (``given``
    is the set of names they set): the paper's defaults per dataset (EABC's Table 3 p, MOPO's
    h and lambda), IQL's schedule. Its tables live in the algorithm's own file."""
    batch_size: int = 256
    """The mini-batch size a run trains with where the user gives none (``--batch-size``):
    Table 2's 256, ReBRAC's 1024."""
    next_actions: bool = False
    """Its batches carry the data's action at s' (:class:`~eabc.agents.common.BatchWithNextActions`,
    e.g. ReBRAC's critic penalty), and it trains on the transitions that have one only (a
    time-limit end has none: :func:`eabc.training.chunks.next_action_known`); others get a plain
    :class:`~eabc.agents.common.Batch` of every transition."""
    normalize_observations: bool = True
    """Train and act on ``(s - mean) / (std + 1e-3)`` of the dataset's states (TD3+BC's
    normaliser); False: on the raw states (the normaliser is the identity, mean 0 and std 1, so
    evaluation, export and checkpoints work alike), as ReBRAC's authors train."""
    delayed_period: Callable[[Any], int] | None = None
    """``delayed_period(config)``, for an update with a delayed part that runs on the steps ``t``
    with ``t % period == 0`` (the TD3 family's actor and targets: :mod:`eabc.agents.td3_core`).
    Its ``update`` then takes ``delayed`` (a Python bool, whether this step runs that part), and
    the training chunks pass it: a fixed schedule, so that their compiled program has no branch."""
    traced_settings: tuple[str, ...] = ()
    """Numeric settings that ``update`` only computes with, never branches on: runs that differ
    in them (and in seed and dataset) train as one compiled program, each run's values traced
    (:func:`eabc.training.chunks.train_chunk_runs`; e.g. EABC's p and alpha)."""
    step_metrics: frozenset[str] = CRITIC_METRICS
    """Metrics averaged over every step of a chunk (see :data:`CRITIC_METRICS`)."""
    steps_per_s: float = 60.0
    """A cost hint for sweeps: steps/s of the preset in one process of the reference host
    (:data:`eabc.timing.REFERENCE_HOST`; ``benchmarks/algorithms.py``), hopper's shapes."""
    cost: Callable[[Any], float] | None = None
    """``cost(config)``: how many times slower than the preset these settings are (e.g. K / 10)."""
    pretrain_s: Callable[[Any], float] | None = None
    """``pretrain_s(config)``: a cost hint for sweeps, seconds of the one-off ``pretrain`` (MOPO's
    model fit) on a 1M-transition dataset, which ``steps_per_s`` does not count."""
    short_names: Mapping[str, str] = dataclasses.field(default_factory=lambda: dict(SHORT_NAMES))
    """Short names of settings in run ids and labels (the paper's K and p by default)."""
    report_settings: tuple[str, ...] = ()
    """Settings that the results store keeps as columns and that ablation figures may vary."""
    cli_flags: tuple[str, ...] = ()
    """Settings that ``eabc train`` offers as typed flags (``--num-critics 5``); every other one
    is reachable with ``--set KEY=VALUE``."""
    column: float = 50.0
    """Where its column goes in the paper's tables (Table 1's order, then Table 6's, then the
    rest); ties by name."""
    reward_convention: str = "minus-one"
    """What it trains on where the data's rewards are sparse goal rewards (AntMaze's stored 0/1)
    and the user sets no ``reward_convention``: ``raw`` or ``minus-one`` (``r - 1``), as its
    published code (or the code it is built on) does; ``minus-one``, what every run trained on
    before the setting existed, where that code says nothing (:mod:`eabc.training.rewards`)."""
    reward_conventions: Mapping[str, Callable[[Any], Any]] = dataclasses.field(default_factory=dict)
    """Reward conventions its file defines, by name: ``rule(dataset) -> dataset`` on the stored
    0/1 rewards (IQL's ``iql-scale``), which a run of any algorithm may choose."""
    comparison_baseline: bool = False
    """Reports compare every other label against it when a sweep ran it (TD3+BC, the study's
    reference); where several are, the first in the registry's order."""
    recommended_variant: str | None = None
    """Another registered algorithm that reports set beside this one, dataset by dataset, where
    this one fails (``failures.md``; EABC's is ``eabc-ln``); ``eabc report --fix`` names another."""
    divergence_advice: str = ""
    """What to try when its critics run away: the trainer's warning ends with it."""
    infinite_state: frozenset[str] = frozenset()
    """Entries of its state (by their last name) that may hold +-inf, such as running bounds that
    start infinite before any data is seen; a checkpoint with +-inf anywhere else, or NaN
    anywhere, is refused as corrupt (:func:`eabc.training.checkpoint.check_values`)."""
    state_layout: int = 1
    """The layout of ``init``'s state in checkpoints, which record it: raise it when the state's
    entries move or are renamed, so that checkpoints of the old layout are refused with a message
    that says so (2: wPC, CQL, UWAC, MOPO and MOReL, whose states came to hold their base's as one
    field)."""

    @property
    def gaussian_actor(self) -> bool:
        return self.actor == "tanh-gaussian"

    def settings(self) -> set[str]:
        """The names of every setting of this algorithm (a group's, such as EABC's BC-weight
        rule's, by their own names: :func:`eabc.ranges.names`)."""
        return set(ranges.names(type(self.preset)))

    def resolved(self, config: Any, dataset_name: str, steps: int | None, given: set[str]) -> Any:
        """``config`` with the settings that depend on the data and the run resolved."""
        if self.resolve is None:
            return config
        return self.resolve(config, dataset_name, steps, frozenset(given))

    def relative_cost(self, config: Any) -> float:
        return 1.0 if self.cost is None else float(self.cost(config))


def field_docs(cls: type) -> dict[str, str]:
    """The one-line docstrings under a config dataclass's fields (its bases' too, and a group's
    settings', :func:`eabc.ranges.groups`), by name."""
    docs: dict[str, str] = {}
    for group in ranges.groups(cls).values():
        docs |= field_docs(group)
    for klass in reversed(cls.__mro__[:-1]):
        try:
            source = inspect.getsourcefile(klass)
        except TypeError:  # a built-in class
            source = None
        if source is not None:
            docs |= _source_field_docs(source).get(klass.__qualname__, {})
    return docs


@functools.cache
def _source_field_docs(path: str) -> dict[str, dict[str, str]]:
    """Every class of one source file (by qualified name), its fields' docstrings: the file is
    parsed once for all its classes (``inspect.getsource`` parsed it again for each, most of
    what starting ``eabc`` cost)."""
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    except (OSError, SyntaxError, UnicodeDecodeError):
        return {}
    found: dict[str, dict[str, str]] = {}

    def visit(body: list[ast.stmt], prefix: str) -> None:
        for node in body:
            if isinstance(node, ast.ClassDef):
                found.setdefault(prefix + node.name, _body_field_docs(node.body))
                visit(node.body, f"{prefix}{node.name}.")
            elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                visit(node.body, f"{prefix}{node.name}.<locals>.")

    visit(tree.body, "")
    return found


def _body_field_docs(body: list[ast.stmt]) -> dict[str, str]:
    docs = {}
    for node, after in zip(body, body[1:]):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            docs[node.target.id] = " ".join(after.value.value.split())
    return docs
