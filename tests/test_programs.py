"""Compile options the installed XLA does not know are left out, never fatal: jaxlib 0.11 dropped
one that the initial parameters' programs asked for, and every run failed at its start."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from eabc import networks, programs
from eabc.training import chunks, lifecycle

UNKNOWN = "xla_an_option_no_xla_has"


def test_an_unknown_option_is_left_out_and_a_known_one_kept():
    options = {"xla_backend_optimization_level": 1, UNKNOWN: True}
    assert programs.known_options(options) == {"xla_backend_optimization_level": 1}


def test_any_other_refusal_of_an_option_is_raised():
    with pytest.raises(Exception, match="not a valid int32"):
        programs.known("xla_backend_optimization_level", "fast")


def test_a_program_asking_for_an_unknown_option_computes_what_plain_jit_does():
    def f(x):
        return jnp.tanh(x) @ x.T

    program = programs.Program(f, {UNKNOWN: True, "xla_backend_optimization_level": 1})
    assert "jitted" not in vars(program)  # nothing built or probed before its first call
    x = np.linspace(-1.0, 1.0, 12, dtype=np.float32).reshape(3, 4)
    np.testing.assert_array_equal(np.asarray(program(x)), np.asarray(jax.jit(f)(x)))
    assert program._cache_size() == 1  # the jitted function's own attributes pass through
    assert program.__name__ == "f"


def test_the_packages_programs_check_their_options():
    """The programs that ask for options (initial parameters, the quickly built chunks) check
    them: the initial parameters' program with an option no XLA has draws the same bits."""
    assert isinstance(networks._draw_mlp_compiled, programs.Program)
    assert isinstance(lifecycle.init_agent, programs.Program)
    assert all(isinstance(program, programs.Program) for program in chunks._PROGRAMS[True])
    static = ((3, 8, 2), 4, False, None, None)
    odd = programs.Program(
        networks._draw_mlp,
        {**networks.INIT_COMPILE_OPTIONS, UNKNOWN: True},
        static_argnums=(1, 2, 3, 4, 5),
    )
    key = jax.random.PRNGKey(0)
    ours, theirs = networks._draw_mlp_compiled(key, *static), odd(key, *static)
    assert ours.keys() == theirs.keys() == {"w0", "b0", "w1", "b1"}
    for name in ours:
        np.testing.assert_array_equal(np.asarray(ours[name]), np.asarray(theirs[name]))
