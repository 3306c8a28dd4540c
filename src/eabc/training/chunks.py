"""The compiled programs of offline training: chunks of gradient steps on device-resident data.

The dataset lives in device memory; every chunk of ``log_interval`` steps is one ``lax.scan`` that
samples its own mini-batches (:func:`train_chunk`), or the same for a stack of seeds in one program
(:func:`train_chunk_seeds`). The trainer calls them between its evaluations and checkpoints; the
benchmarks time them directly.
"""

from __future__ import annotations

import copy
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np

from eabc import programs
from eabc.agents import get_algorithm
from eabc.agents.common import Batch, BatchWithNextActions
from eabc.agents.contract import CRITIC_METRICS
from eabc.data.dataset import Dataset, DatasetError, Normalizer


def device_data(dataset: Dataset, normalizer: Normalizer, next_actions: bool = False) -> Batch:
    """The whole dataset as one device-resident batch (observations normalised once, up front).
    Where ``next_actions`` asks, with the data's next actions (:func:`data_next_actions`), and
    only the transitions that have one (:func:`next_action_known`)."""
    rows = next_action_known(dataset) if next_actions else slice(None)
    fields = {
        "observations": jnp.asarray(normalizer(dataset.observations[rows])),
        "actions": jnp.asarray(dataset.actions[rows]),
        "rewards": jnp.asarray(dataset.rewards[rows]),
        "next_observations": jnp.asarray(normalizer(dataset.next_observations[rows])),
        "dones": jnp.asarray(dataset.terminals[rows], jnp.float32),
    }
    if next_actions:
        if not fields["rewards"].shape[0]:
            raise DatasetError(
                f"{dataset.name}: no transition has the data's next action (every one ends its "
                "episode at a time limit, or the next row does not start at its s')"
            )
        next_ = data_next_actions(dataset)[rows]
        return BatchWithNextActions(**fields, next_actions=jnp.asarray(next_))
    return Batch(**fields)


def _continues(dataset: Dataset) -> np.ndarray:
    """Rows 0 .. n-2 that the next row continues: no terminal or time limit ends them, and the
    next row's observation is their s'."""
    ends = dataset.terminals | dataset.timeouts
    return ~ends[:-1] & np.all(dataset.observations[1:] == dataset.next_observations[:-1], 1)


def data_next_actions(dataset: Dataset) -> np.ndarray:
    """The action the data took at each transition's s': the next row's, where that row continues
    the episode (:func:`_continues`); elsewhere the row's own action (the data has no other)."""
    continues = _continues(dataset)
    out = dataset.actions.copy()
    out[:-1][continues] = dataset.actions[1:][continues]
    return out


def next_action_known(dataset: Dataset) -> np.ndarray:
    """Rows whose next action the data has (the next row continues them) or that need none (a
    terminal: its target does not bootstrap). The others end at a time limit or where the data
    stops; D4RL's ``qlearning_dataset`` drops them too."""
    known = dataset.terminals.copy()
    known[:-1] |= _continues(dataset)
    return known


FAST_COMPILE_ENV = "EABC_FAST_COMPILE"
"""Set to 1 to compile the training chunks at XLA's lowest optimisation level: a program compiles
in about half the time and runs slower, so a run of a few hundred steps starts sooner (the test
suite's contract checks use it). Its scan runs one step per iteration, not two: the unrolled body
is twice the code for XLA to compile (the slowest algorithm's contract chunk: 7-9 -> 5-6 s of
CPU). Its fusions are emitted by XLA's older LLVM emitter rather than the MLIR fusion emitters,
which take twice as long to compile at O0 (three algorithms' contract chunks: 23.7 -> 10.5 s of
CPU together; one 64-64 chunk: 3.8 -> 1.7 s, its steps about 15% slower). Results differ from the
default build in the last bits."""
FAST_COMPILE_OPTIONS = {
    "xla_backend_optimization_level": 0,
    "xla_llvm_disable_expensive_passes": True,
    "xla_cpu_use_fusion_emitters": False,
}
_STATIC = ("update", "batch_size", "length", "unroll", "period", "phase")


def fast_compile() -> bool:
    """Whether ``$EABC_FAST_COMPILE`` asks for quickly compiled chunks."""
    return os.environ.get(FAST_COMPILE_ENV, "").strip().lower() in ("1", "true", "yes", "on")


def _static(update, batch_size: int, length: int, period: int | None, start: int) -> dict:
    """The compile-time arguments of every chunk program."""
    return dict(
        update=update, batch_size=batch_size, length=length, unroll=1 if fast_compile() else 2,
        period=period, phase=start % period if period else 0,
    )  # fmt: skip


def _chunk(
    agent_state, key, data: Batch, update, batch_size: int, length: int, unroll: int,
    period: int | None = None, phase: int = 0,
):  # fmt: skip
    size = data.rewards.shape[0]

    def sample(key):
        index = jax.random.randint(key, (batch_size,), 0, size)
        return jax.tree.map(lambda x: x[index], data)

    return _steps(agent_state, key, sample, update, length, unroll, period, phase)


def _steps(agent_state, key, sample, update, length: int, unroll: int, period, phase: int):
    """``length`` steps of ``update`` on mini-batches ``sample(key)`` draws."""

    def step(carry, delayed: bool | None = None):
        agent_state, key = carry
        key, sample_key, update_key = jax.random.split(key, 3)
        batch = sample(sample_key)
        kwargs = {} if delayed is None else {"delayed": delayed}
        agent_state, metrics = update(agent_state, batch, update_key, **kwargs)
        return (agent_state, key), metrics

    carry = (agent_state, key)
    if period is None:
        # Two steps per loop iteration (a delayed actor's period of 2): +6% steps/s at K = 2 on
        # CPU, same results.
        carry, metrics = jax.lax.scan(step, carry, None, length=length, unroll=unroll)
    else:
        carry, metrics = _scheduled_steps(step, carry, length, period, phase, unroll)
    return *carry, metrics


def _scheduled_steps(step, carry, length: int, period: int, phase: int, unroll: int):
    """``length`` steps of an update with a delayed part (the contract's ``delayed_period``), the
    first one being step ``phase + 1`` of the period: step ``t`` runs it where ``t % period ==
    0``. The steps up to the first period boundary and those after the last are laid out one by
    one; between them, a scan of whole periods (``period - 1`` plain steps, then a delayed one),
    so that the program holds no branch."""

    def run(carry, flags):
        out = []
        for delayed in flags:
            carry, metrics = step(carry, delayed)
            out.append(metrics)
        return carry, jax.tree.map(lambda *xs: jnp.stack(xs), *out) if out else None

    head = min((-phase) % period, length)
    periods, tail = divmod(length - head, period)
    flags = [(phase + i + 1) % period == 0 for i in range(length)]
    carry, first = run(carry, flags[:head])
    middle = None
    if periods:
        cycle = functools.partial(run, flags=[False] * (period - 1) + [True])
        carry, middle = jax.lax.scan(
            lambda c, _: cycle(c), carry, None, length=periods, unroll=max(unroll // period, 1)
        )
        middle = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), middle)
    carry, last = run(carry, flags[length - tail :])
    parts = [part for part in (first, middle, last) if part is not None]
    return carry, jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)


def _chunk_seeds(
    agent_states, keys, data: Batch, update, batch_size: int, length: int, unroll: int,
    period: int | None = None, phase: int = 0,
):  # fmt: skip
    chunk = functools.partial(
        _chunk, update=update, batch_size=batch_size, length=length, unroll=unroll,
        period=period, phase=phase,
    )  # fmt: skip
    return jax.vmap(chunk, in_axes=(0, 0, None))(agent_states, keys, data)


def _chunk_runs(
    agent_states, keys, datas: Batch, which, sizes, values: dict, update, batch_size: int,
    length: int, unroll: int, period: int | None = None, phase: int = 0,
):  # fmt: skip
    def one(agent_state, key, which, size, values):
        def sample(key):  # the run's own dataset: its first ``size`` rows of ``datas[which]``
            index = jax.random.randint(key, (batch_size,), 0, size)
            return jax.tree.map(lambda x: x[which, index], datas)

        run_update = update
        if values:
            config = with_settings(update.keywords["config"], values)
            run_update = functools.partial(update, config=config)
        return _steps(agent_state, key, sample, run_update, length, unroll, period, phase)

    return jax.vmap(one)(agent_states, keys, which, sizes, values)


def with_settings(config, values: dict):
    """``config`` with the fields ``values`` names set to those (traced) values. The dataclass's
    own checks do not run again: they ran on every run's concrete settings."""
    new = copy.copy(config)
    for name, value in values.items():
        object.__setattr__(new, name, value)
    return new


_PROGRAMS = {
    False: tuple(jax.jit(f, static_argnames=_STATIC) for f in (_chunk, _chunk_seeds, _chunk_runs)),
    True: tuple(
        programs.Program(f, FAST_COMPILE_OPTIONS, static_argnames=_STATIC)
        for f in (_chunk, _chunk_seeds, _chunk_runs)
    ),
}


def train_chunk(
    agent_state, key, data: Batch, update, batch_size: int, length: int,
    period: int | None = None, start: int = 0,
):  # fmt: skip
    """``length`` gradient steps in one compiled scan; batches are sampled with replacement inside.
    ``update`` is hashable (e.g. a ``functools.partial`` of an algorithm's update); one program is
    compiled per update, batch size and length. ``period``: the algorithm's ``delayed_period``
    for its config, if it has one (``update`` then takes ``delayed``), and ``start`` the steps
    the state has taken, so that the delayed steps fall where they would one step at a time."""
    static = _static(update, batch_size, length, period, start)
    return _PROGRAMS[fast_compile()][0](agent_state, key, data, **static)


def train_chunk_seeds(
    agent_states, keys, data: Batch, update, batch_size: int, length: int,
    period: int | None = None, start: int = 0,
):  # fmt: skip
    """:func:`train_chunk` for a stack of seeds (leading axis of states and keys), one program;
    every seed is at step ``start``."""
    static = _static(update, batch_size, length, period, start)
    return _PROGRAMS[fast_compile()][1](agent_states, keys, data, **static)


def padded_rows(rows: int) -> int:
    """The length :func:`stack_data` pads datasets of at most ``rows`` rows to: ``rows`` rounded
    up to a multiple of a sixteenth of its highest power of two (1,000,000 -> 1,015,808), at most
    6% more. So a program's shape can be known before its data exist (from the size a recipe
    makes; an algorithm that drops the rows without a next action rarely leaves that multiple),
    and is compiled while they are made (:func:`compile_chunk`)."""
    block = 1 << max(0, int(rows).bit_length() - 5)
    return -(-int(rows) // block) * block


def stack_data(datas: list[Batch]) -> Batch:
    """Device datasets of one shape but any lengths as one ``[datasets, rows, ...]`` batch for
    :func:`train_chunk_runs`, padded with zeros (never sampled) to :func:`padded_rows` of the
    longest."""
    longest = padded_rows(max(data.rewards.shape[0] for data in datas))

    def stack(*xs):
        return jnp.stack(
            [jnp.pad(x, [(0, longest - x.shape[0])] + [(0, 0)] * (x.ndim - 1)) for x in xs]
        )

    return jax.tree.map(stack, *datas)


def train_chunk_runs(
    agent_states, keys, datas: Batch, which, sizes, values: dict, update, batch_size: int,
    length: int, period: int | None = None, start: int = 0,
):  # fmt: skip
    """:func:`train_chunk` for runs that share their networks' shapes, one program over a run
    axis (the leading axis of states, keys, ``which``, ``sizes`` and each of ``values``): run
    ``i`` samples the first ``sizes[i]`` rows of dataset ``which[i]`` of ``datas``
    (:func:`stack_data`), and trains with ``update``'s config but for the settings ``values``
    holds, numbers traced per run (the algorithm's ``traced_settings``). Every run is at step
    ``start``; each equals the same run trained alone to float tolerance."""
    static = _static(update, batch_size, length, period, start)
    return _PROGRAMS[fast_compile()][2](
        agent_states, keys, datas, jnp.asarray(which, jnp.int32), jnp.asarray(sizes, jnp.int32),
        {name: jnp.asarray(v, jnp.float32) for name, v in values.items()}, **static,
    )  # fmt: skip


def compile_chunk(
    agent_states, keys, data, width: int | None, names, update, batch_size: int, length: int,
    period: int | None = None, start: int = 0,
):  # fmt: skip
    """Compile, without running it, the program that :func:`train_chunk` (``width`` None) or
    :func:`train_chunk_runs` (``width`` runs; ``names``: the traced settings its ``values``
    holds) runs on arguments of these shapes (trees of ``jax.ShapeDtypeStruct``); returns the
    compiled program. Where XLA's persistent cache is on (:mod:`eabc.compile_cache`), the real
    call finds it there, however its ``update`` was made."""
    static = _static(update, batch_size, length, period, start)
    if width is None:
        return _PROGRAMS[fast_compile()][0].lower(agent_states, keys, data, **static).compile()
    each = jax.ShapeDtypeStruct((width,), jnp.int32)
    values = {name: jax.ShapeDtypeStruct((width,), jnp.float32) for name in names}
    program = _PROGRAMS[fast_compile()][2]
    return program.lower(agent_states, keys, data, each, each, values, **static).compile()


def differing(names, agent_configs: list) -> dict[str, list]:
    """The settings among ``names`` that are not the same in every config, a value per config."""
    return {
        name: [getattr(c, name) for c in agent_configs]
        for name in names
        if len({getattr(c, name) for c in agent_configs}) > 1
    }


def compile_first_chunk(
    config, agent_configs: list, obs_dim: int, act_dim: int, max_action: float, rows: list[int]
) -> None:
    """Compile the program of the first chunk that :func:`eabc.training.trainer.train_runs`
    trains new runs in, before the runs or their data exist: runs of ``config``'s settings (the
    first run's), an agent config each, on the datasets whose lengths ``rows`` gives (one entry
    per dataset), as the trainer lays them out (:func:`stack_data`). Where XLA's
    persistent cache is on (:mod:`eabc.compile_cache`), their first chunk then loads it from
    there: ``eabc study`` compiles a group while its data are made or the group before it
    trains. Datasets of other lengths (rows an algorithm drops, e.g. those without a next
    action) ask for another program, which their first chunk compiles as usual."""
    algorithm = get_algorithm(config.algo)
    key = jax.ShapeDtypeStruct((2,), jnp.uint32)
    states = [
        jax.eval_shape(lambda k, c=c: algorithm.init(k, obs_dim, act_dim, c), key)
        for c in agent_configs
    ]
    width = len(states)
    update = functools.partial(algorithm.update, config=agent_configs[0], max_action=max_action)
    period = algorithm.delayed_period(agent_configs[0]) if algorithm.delayed_period else None
    length = min(config.log_interval, config.steps)
    if width == 1:
        lead, names = (rows[0],), ()
    else:
        lead = (len(rows), padded_rows(max(rows)))
        names = tuple(differing(algorithm.traced_settings, agent_configs))
        stack = lambda *xs: jnp.stack(xs)  # noqa: E731
        states = [jax.eval_shape(lambda *xs: jax.tree.map(stack, *xs), *states)]
        key = jax.eval_shape(stack, *[key] * width)
    fields = {"observations": obs_dim, "actions": act_dim, "rewards": None,
              "next_observations": obs_dim, "dones": None}  # fmt: skip
    if algorithm.next_actions:
        fields["next_actions"] = act_dim
    shaped = {
        name: jax.ShapeDtypeStruct(lead + ((size,) if size else ()), jnp.float32)
        for name, size in fields.items()
    }
    data = (BatchWithNextActions if algorithm.next_actions else Batch)(**shaped)
    compile_chunk(
        states[0], key, data, None if width == 1 else width, names, update, config.batch_size,
        length, period,
    )  # fmt: skip


def summarize_metrics(
    metrics: dict[str, np.ndarray], step_metrics: frozenset[str] = CRITIC_METRICS
) -> dict[str, float]:
    """Means over a chunk; metrics other than ``step_metrics`` (the algorithm's contract says which
    its every step computes) only over the steps that updated the actor."""
    actor_steps = metrics.pop("actor_updated", None)
    out = {}
    for key, values in metrics.items():
        if actor_steps is not None and key not in step_metrics and actor_steps.any():
            values = values[actor_steps.astype(bool)]
        out[key] = float(np.mean(values))
    return out
