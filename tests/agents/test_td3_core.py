"""The TD3 family's shared update on its fixed schedule: the training chunks (no branch in their
compiled program) against a plain step-by-step TD3 loop written here, for every algorithm built on
it; seeds trained together against each alone; the trainer's chunks of any length."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from handcalc import ACT, OBS, make_batch

from eabc import ranges
from eabc.agents import bc_weights, eabc, get_algorithm, rebrac, wpc
from eabc.agents.common import Batch, BatchWithNextActions
from eabc.programs import Program
from eabc.training import chunks, lifecycle, trainer
from eabc.training.chunks import FAST_COMPILE_OPTIONS, summarize_metrics
from eabc.training.config import TrainConfig

MAX_ACTION = 1.5
TINY = {"hidden_dims": (8, 8)}
CASES = {
    "td3bc": ("td3bc", {}),
    "td3-every-3": ("td3", {"policy_freq": 3}),  # chunks of 5 and 4 cut its period of 3
    "eabc": ("eabc", {"num_critics": 3, "confidence_level": 0.5}),
    "eabc-ln": ("eabc-ln", {"num_critics": 3}),
    "eabc-quantile": ("eabc-quantile", {"num_critics": 3, "quantile_level": 0.7}),
    "eabc-auto": ("eabc-auto", {"num_critics": 3, "auto_rate": 0.2, "auto_initial_p": 0.8}),
    "rebrac": ("rebrac", {"actor_bc_weight": 0.05, "critic_bc_weight": 0.01, "hidden_dims": (8,) * 3}),
    "wpc": ("wpc", {}),
}  # fmt: skip


def _adam(params, opt_state, grads, learning_rate):
    updates, opt_state = optax.adam(learning_rate).update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state


def _polyak(target, online, tau):
    return jax.tree.map(lambda t, o: tau * o + (1.0 - tau) * t, target, online)


def _reference_td3(state, critic_loss, actor_loss, actor_args, batch, critic_key, config,
                   max_action, actor_turn):  # fmt: skip
    """TD3 as Fujimoto et al. write it: the critics every step; on the actor's turn the actor on
    the new critics, then both targets. ``actor_args`` follow ``(actor, critic)`` in the loss."""
    grads, metrics = jax.grad(critic_loss, has_aux=True)(
        state.critic, state.critic_target, state.actor_target, batch, critic_key, config, max_action
    )
    critic, critic_opt = _adam(state.critic, state.critic_opt, grads, config.critic_lr)
    state = state.replace(critic=critic, critic_opt=critic_opt, step=state.step + 1)
    if actor_turn:
        grads, actor_metrics = jax.grad(actor_loss, has_aux=True)(state.actor, critic, *actor_args)
        actor, actor_opt = _adam(state.actor, state.actor_opt, grads, config.actor_lr)
        state = state.replace(
            actor=actor,
            actor_opt=actor_opt,
            actor_target=_polyak(state.actor_target, actor, config.tau),
            critic_target=_polyak(state.critic_target, critic, config.tau),
        )
        metrics = {**metrics, **actor_metrics}
    return state, metrics


def _reference_eabc(state, batch, key, config, max_action, actor_turn):
    critic_key, actor_key = jax.random.split(key)
    keep = None
    if config.bc_rule.bc_weight == "quantile":  # the critics before this step's update
        keep = bc_weights.quantile_keep(state.critic, batch, config)
    p = state.controller["p"] if config.bc_rule.bc_weight == "auto" else None
    new, metrics = _reference_td3(
        state, eabc.critic_loss, eabc.actor_loss,
        (batch, actor_key, config, max_action, keep, p), batch, critic_key, config, max_action,
        actor_turn,
    )  # fmt: skip
    if actor_turn and config.bc_rule.bc_weight == "auto":
        controller, more = bc_weights.adapt_confidence_level(
            state.controller, batch, metrics, config, new.step
        )
        new, metrics = new.replace(controller=controller), {**metrics, **more}
    return new, metrics


def _reference_rebrac(state, batch, key, config, max_action, actor_turn):
    return _reference_td3(
        state, rebrac.critic_loss, rebrac.actor_loss, (batch, config, max_action),
        batch, key, config, max_action, actor_turn,
    )  # fmt: skip


def _reference_wpc(state, batch, key, config, max_action, actor_turn):
    critic_key, actor_key = jax.random.split(key)
    grads, (advantage, value_metrics) = jax.grad(wpc.value_loss, has_aux=True)(
        state.value, state.td3bc.critic_target, batch
    )
    value, value_opt = _adam(state.value, state.value_opt, grads, config.value_lr)
    base, metrics = _reference_td3(
        state.td3bc, eabc.critic_loss, eabc.actor_loss,
        (batch, actor_key, config, max_action, advantage > 0), batch, critic_key, config,
        max_action, actor_turn,
    )  # fmt: skip
    return wpc.WPCState(td3bc=base, value=value, value_opt=value_opt), {**metrics, **value_metrics}


REFERENCES = {"eabc": _reference_eabc, "rebrac": _reference_rebrac, "wpc": _reference_wpc}


def _case(name):
    algo, changes = CASES[name]
    algorithm = get_algorithm(algo)
    config = ranges.validated(algorithm.preset, {**TINY, **changes})
    module = {"rebrac": "rebrac", "wpc": "wpc"}.get(algo, "eabc")
    return algorithm, config, module


def _data(next_actions: bool, size: int = 40) -> Batch:
    parts = [make_batch(seed) for seed in range(size // 7 + 1)]
    data = jax.tree.map(lambda *xs: jnp.concatenate(xs)[:size], *parts)
    if not next_actions:
        return data
    flipped = jnp.flip(data.actions, axis=0)
    return BatchWithNextActions(**vars(data), next_actions=flipped)


def reference_train(module, state, key, data, config, batch_size, steps, start=0,
                    max_action=MAX_ACTION):  # fmt: skip
    """Steps one at a time, the actor's turn decided in Python from the step count, with the
    chunks' sampling (three keys per step: the carry, the batch's indices, the update)."""
    step = Program(REFERENCES[module], FAST_COMPILE_OPTIONS, static_argnums=(3, 4, 5))
    size = data.rewards.shape[0]
    rows = []
    for t in range(start + 1, start + steps + 1):
        key, sample_key, update_key = jax.random.split(key, 3)
        index = jax.random.randint(sample_key, (batch_size,), 0, size)
        batch = jax.tree.map(lambda x, index=index: x[index], data)
        turn = t % config.policy_freq == 0
        state, metrics = step(state, batch, update_key, config, max_action, turn)
        rows.append((turn, jax.device_get(metrics)))
    return state, key, rows


def expected_row(rows, step_metrics) -> dict[str, float]:
    """A log row as the chunk's metrics should give it: the critics' metrics averaged over every
    step, the actor's over the actor's turns."""
    names = set().union(*(metrics for _, metrics in rows))
    out = {}
    for name in names:
        values = [m[name] for turn, m in rows if name in step_metrics or turn]
        out[name] = float(np.mean(values))
    return out


def assert_trees_close(a, b, rtol=1e-5, atol=1e-6):
    leaves_a, tree_a = jax.tree.flatten(jax.device_get(a))
    leaves_b, tree_b = jax.tree.flatten(jax.device_get(b))
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b, strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


@pytest.mark.parametrize("name", list(CASES))
def test_chunks_on_the_fixed_schedule_equal_a_step_by_step_td3_loop(name, quick_chunks):
    """Chunks of 3 and 4 steps (5 and 4 at policy_freq 3) cut the actor's period anywhere: the
    parameters, the sampling key and every log row's means equal the plain loop's."""
    algorithm, config, module = _case(name)
    data = _data(algorithm.next_actions)
    state = algorithm.init(jax.random.PRNGKey(0), OBS, ACT, config)
    key = jax.random.PRNGKey(11)
    update = functools.partial(algorithm.update, config=config, max_action=MAX_ACTION)
    period = algorithm.delayed_period(config)
    assert period == config.policy_freq
    lengths = (5, 4) if period == 3 else (3, 4)
    got, done = (state, key), 0
    expected = (state, key)
    for length in lengths:
        agent, got_key, metrics = chunks.train_chunk(*got, data, update, 8, length, period, done)
        got = (agent, got_key)
        *expected, rows = reference_train(module, *expected, data, config, 8, length, done)
        metrics = jax.device_get(metrics)
        flags = [turn for turn, _ in rows]
        np.testing.assert_array_equal(metrics["actor_updated"], flags)
        row = summarize_metrics(dict(metrics), algorithm.step_metrics)
        want = expected_row(rows, algorithm.step_metrics)
        assert set(row) == set(want)
        for metric, value in want.items():
            np.testing.assert_allclose(row[metric], value, rtol=1e-5, atol=1e-6, err_msg=metric)
        done += length
    assert int(got[0].step) == done
    np.testing.assert_array_equal(got[1], expected[1])
    assert_trees_close(got[0], expected[0])


@pytest.mark.parametrize("algo", ["eabc", "rebrac"])
def test_seeds_in_one_chunk_equal_each_seed_trained_alone(algo, quick_chunks):
    name = "eabc" if algo == "eabc" else "rebrac"
    algorithm, config, _ = _case(name)
    data = _data(algorithm.next_actions)
    update = functools.partial(algorithm.update, config=config, max_action=MAX_ACTION)
    period = algorithm.delayed_period(config)
    states = [algorithm.init(jax.random.PRNGKey(s), OBS, ACT, config) for s in (0, 1)]
    keys = [jax.random.PRNGKey(20 + s) for s in (0, 1)]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *states)
    together = chunks.train_chunk_seeds(stacked, jnp.stack(keys), data, update, 8, 6, period)
    for i in (0, 1):
        alone = chunks.train_chunk(states[i], keys[i], data, update, 8, 6, period)
        assert_trees_close(jax.tree.map(lambda x, i=i: x[i], together), alone, 1e-5, 1e-6)
    first, second = (together[0].actor["w0"][i] for i in (0, 1))
    assert not np.allclose(first, second), "the seeds must differ"


def _equations(jaxpr):
    """Every equation of a jaxpr and of the jaxprs inside it (scan bodies, jit calls, branches)."""
    for eqn in jaxpr.eqns:
        yield eqn
        for param in eqn.params.values():
            for inner in param if isinstance(param, (list, tuple)) else (param,):
                if isinstance(inner, jax.extend.core.ClosedJaxpr):
                    yield from _equations(inner.jaxpr)
                elif isinstance(inner, jax.extend.core.Jaxpr):
                    yield from _equations(inner)


@pytest.mark.parametrize("name", ["eabc", "rebrac", "wpc"])
def test_the_seed_vmapped_chunk_has_no_branch_over_the_actor_update(name):
    """The trainer's program for seeds trained together: no ``cond``, and no ``select_n`` that
    picks between two versions of the actor's weights (what a ``cond`` under ``vmap`` becomes:
    the per-step schedule, traced here too, shows that the check sees one)."""
    algorithm, config, _ = _case(name)
    # Widths no other array shares, so that the actor's weights are told by their shapes.
    config = dataclasses.replace(config, hidden_dims=(5, 6, 7)[: len(config.hidden_dims)])
    data = _data(algorithm.next_actions)
    update = functools.partial(algorithm.update, config=config, max_action=MAX_ACTION)
    seeds = 2
    init = functools.partial(algorithm.init, obs_dim=OBS, act_dim=ACT, config=config)
    # Shapes are all a jaxpr needs: the states are never computed (an eager vmap of the init
    # compiled each of its operations anew, 10-20 s).
    states = jax.eval_shape(jax.vmap(init), jax.random.split(jax.random.PRNGKey(0), seeds))
    keys = jax.random.split(jax.random.PRNGKey(1), seeds)
    actor = states.td3bc.actor if isinstance(states, wpc.WPCState) else states.actor
    actor_shapes = {w.shape for name, w in actor.items() if name.startswith("w")}

    def branches(period):
        program = lambda s, k: chunks.train_chunk_seeds(s, k, data, update, 4, 4, period)  # noqa: E731
        eqns = list(_equations(jax.make_jaxpr(program)(states, keys).jaxpr))
        conds = [e for e in eqns if e.primitive.name == "cond"]
        selects = [
            e for e in eqns
            if e.primitive.name == "select_n" and tuple(e.outvars[0].aval.shape) in actor_shapes
        ]  # fmt: skip
        return conds, selects

    assert branches(None) != ([], []), "the per-step schedule branches: the check must see it"
    assert branches(algorithm.delayed_period(config)) == ([], [])


def test_the_trainer_cuts_chunks_anywhere_and_equals_the_step_by_step_loop(
    tmp_path, pendulum_dataset, quick_chunks
):
    """Two seeds trained together in chunks of 3 steps (the actor's period 2 cut at odd steps)
    for 8 steps: each seed's parameters equal the plain loop's from the same start."""
    config = TrainConfig(dataset="pendulum", seed=0, steps=8, log_interval=3, eval_interval=9 * 3,
                         checkpoint_interval=9 * 3, eval_episodes=1, env="Pendulum-v1", batch_size=8)  # fmt: skip
    agent = {"num_critics": 3, "confidence_level": 0.5, "hidden_dims": (8, 8)}
    runs = [
        lifecycle.start(dataclasses.replace(config, seed=s), tmp_path / f"s{s}", agent, dataset=pendulum_dataset)
        for s in (0, 1)
    ]  # fmt: skip
    starts = [(run.state["agent"], run.state["key"]) for run in runs]
    trainer.train_runs(runs, progress=False)
    first = runs[0]
    data = chunks.device_data(first.dataset, first.normalizer)
    for run, (state, key) in zip(runs, starts):
        expected, expected_key, _ = reference_train(
            "eabc", state, key, data, run.agent_config, 8, 8, max_action=run.max_action
        )
        assert int(run.state["agent"].step) == 8
        np.testing.assert_array_equal(run.state["key"], expected_key)
        assert_trees_close(run.state["agent"], expected)
