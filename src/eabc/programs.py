"""Compiled programs whose XLA options not every jaxlib knows.

A few programs are compiled with options that only shorten their compilation: the ones that run
once (initial parameters) and the test suite's quickly built chunks. XLA adds and removes such
options from one jaxlib release to the next (``xla_cpu_use_fusion_emitters`` is gone from jaxlib
0.11 on, which Python 3.12 installs by default), and it refuses to compile a program that names an
option it does not know. So each option is checked against the installed XLA the first time a
program asks for it, and one it does not know is left out: it changes how long a program takes to
compile, never what the program computes.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping

import jax
import numpy as np

_UNKNOWN = "No such compile option"  # XLA's words for an option it does not have


@functools.cache
def known(name: str, value) -> bool:
    """Whether this jaxlib's XLA accepts the compile option ``name`` set to ``value``: checked once
    per process, by compiling a one-operation program with it."""
    try:
        jax.jit(_probe, compiler_options={name: value}).lower(np.float32(0)).compile()
    except Exception as error:  # XLA's own error class differs between jaxlib releases
        if _UNKNOWN in str(error):
            return False
        raise
    return True


def _probe(x):
    return x + 1


def known_options(options: Mapping) -> dict:
    """``options`` less those this jaxlib's XLA does not know."""
    return {name: value for name, value in options.items() if known(name, value)}


class Program:
    """``jax.jit(fun, compiler_options=..., **jit_options)`` with the options of ``options`` that
    this XLA knows. It is built at its first use, so that importing a module compiles nothing;
    any other attribute is the jitted function's (``lower``, ``_cache_size``, ...)."""

    def __init__(self, fun: Callable, options: Mapping, **jit_options):
        self._fun = fun
        self._options = dict(options)
        self._jit_options = jit_options
        functools.update_wrapper(self, fun)

    @functools.cached_property
    def jitted(self):
        return jax.jit(
            self._fun, compiler_options=known_options(self._options), **self._jit_options
        )

    def __call__(self, *args, **kwargs):
        return self.jitted(*args, **kwargs)

    def __getattr__(self, name: str):
        if name in ("_fun", "_options", "_jit_options", "jitted"):  # not yet set: no recursion
            raise AttributeError(name)
        return getattr(self.jitted, name)
