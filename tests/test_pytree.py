"""eabc.pytree: the agents' state dataclasses and the checkpoint's msgpack layout, without flax."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import jax
import jax.numpy as jnp
import msgpack
import numpy as np
import optax
import pytest

from eabc import pytree
from eabc.agents import get_algorithm, sac


@pytree.dataclass
class _State:
    params: dict
    opt: optax.OptState
    step: jax.Array
    name: str = pytree.field(static=True, default="x")


def _state() -> _State:
    params = {"w0": jnp.arange(6.0).reshape(2, 3), "b0": jnp.zeros(3)}
    return _State(params, optax.adam(1e-3).init(params), jnp.asarray(5, jnp.int32))


def test_a_state_is_a_pytree_with_its_static_fields_out_of_the_leaves():
    state = _state()
    leaves, tree = jax.tree.flatten(state)
    assert len(leaves) == 2 + 1 + 2 + 2 + 1  # params, adam count/mu/nu, step
    doubled = jax.tree.map(lambda x: x * 2, state)
    assert doubled.name == "x" and int(doubled.step) == 10
    assert jax.tree.unflatten(tree, leaves).replace(name="y").name == "y"
    with pytest.raises(AttributeError):
        state.step = 1  # frozen
    real = sac.init(jax.random.PRNGKey(0), 3, 1, sac.SACConfig(hidden_dims=(8,)))
    assert "target_entropy" not in pytree.to_state_dict(real)  # SAC's static setting
    jit_step = jax.jit(lambda s: s.replace(step=s.step + 1))
    assert int(jit_step(state).step) == 6


def test_state_dict_names_fields_and_positions_and_restores_into_the_template():
    state = _state()
    flat = pytree.to_state_dict(state)
    assert set(flat) == {"params", "opt", "step"}  # the static name is not saved
    assert set(flat["opt"]) == {"0", "1"}  # optax's chain by position
    assert set(flat["opt"]["0"]) == {"count", "mu", "nu"}  # its named tuple by field
    restored = pytree.from_state_dict(state, pytree.loads(pytree.dumps(flat)))
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(restored), strict=True):
        np.testing.assert_array_equal(np.asarray(a), b)
        assert np.asarray(a).dtype == b.dtype
    assert jax.tree.structure(restored) == jax.tree.structure(state)
    with pytest.raises(ValueError, match="lacks"):
        pytree.from_state_dict(state, {"params": flat["params"], "step": flat["step"]})


@pytest.mark.parametrize(("algo", "base"), [("td3bc", None), ("wpc", "td3bc"), ("cql", "sac"),
                                          ("uwac", "bear"), ("mopo", "sac"), ("morel", "sac")])  # fmt: skip
def test_find_reads_actor_and_step_wherever_the_state_keeps_them(algo, base):
    """A state that holds its base algorithm's state keeps ``actor`` and ``step`` there: the
    object delegates to it, and :func:`pytree.find` reaches them in the state dict."""
    algorithm = get_algorithm(algo)
    config = dataclasses.replace(algorithm.preset, hidden_dims=(4,))
    state = algorithm.init(jax.random.PRNGKey(0), 3, 2, config)
    flat = pytree.to_state_dict(state)
    assert ("actor" in flat) == (base is None)
    if base is not None:  # nested: a checkpoint of layout 2 and more
        assert algorithm.state_layout >= 2 and set(flat[base]) >= {"actor", "step"}
        assert getattr(state, base).actor is state.actor and getattr(state, base).step is state.step
    actor = pytree.find(flat, "actor")
    assert sorted(actor) == sorted(state.actor)
    for name in state.actor:
        np.testing.assert_array_equal(actor[name], state.actor[name])
    assert int(pytree.find(flat, "step")) == int(state.step) == 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        state.step = 1  # read-only on every state


def test_find_refuses_a_missing_or_ambiguous_entry():
    nested = {"value": {"w0": 1}, "outer": {"inner": {"actor": 2, "step": 3}}}
    assert pytree.find(nested, "actor") == 2 and pytree.find(nested, "step") == 3
    with pytest.raises(KeyError, match="nothing holds it"):
        pytree.find(nested, "critic")
    with pytest.raises(KeyError, match="both 'a' and 'b' hold it"):
        pytree.find({"a": {"actor": 1}, "b": {"x": {"actor": 2}}}, "actor")


def test_the_bytes_are_flax_msgpack_layout_so_old_checkpoints_load():
    """Arrays as extension type 1 ``(shape, dtype name, bytes)``, NumPy scalars as type 3, keys
    sorted: what flax's msgpack_serialize wrote, built here by hand."""
    array = np.arange(4, dtype=np.float32).reshape(2, 2)
    scalar = np.float64(2.5)

    def ext(code, fields):
        return msgpack.ExtType(code, msgpack.packb(fields, use_bin_type=True))

    expected = msgpack.packb(
        {"a": ext(1, ((2, 2), "float32", array.tobytes())), "f": 1.5, "n": None,
         "s": ext(3, ("float64", scalar.tobytes()))},
        use_bin_type=True,
    )  # fmt: skip
    ours = pytree.dumps({"s": scalar, "a": jnp.asarray(array), "n": None, "f": 1.5})
    assert ours == expected
    back = pytree.loads(expected)
    np.testing.assert_array_equal(back["a"], array)
    assert back["a"].dtype == np.float32 and back["s"] == 2.5 and back["n"] is None
    with pytest.raises(TypeError, match="cannot write"):
        pytree.dumps({"x": object()})


def test_nothing_imports_flax():
    code = (
        "import sys; import eabc.cli, eabc.training.trainer, eabc.training.online, "
        "eabc.experiments.report, eabc.policy; from eabc.agents import ALGORITHMS; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'flax'))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout
