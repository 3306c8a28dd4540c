"""XLA's compiled programs kept on disk, so that a new process does not compile them again.

Every ``eabc`` command (and every sweep worker) turns this on. A run's programs (agent
initialisation, the training chunk) take 5-10 s to compile on a 2-core CPU; with the cache a second
run of the same shapes starts that much sooner, and a sweep compiles each shape once.

Where: ``$EABC_COMPILE_CACHE`` if set (``off`` disables it); otherwise a directory chosen through
JAX's own ``JAX_COMPILATION_CACHE_DIR`` if any, else ``xla/`` in the eabc cache directory
(``$EABC_CACHE_DIR`` or ``~/.cache/eabc``). Entries are keyed by the program, the JAX version and
the compile options; XLA refuses an entry compiled for other CPU features and compiles afresh, so
one directory can be shared by machines. Deleting the directory is always safe.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

from eabc.paths import cache_dir

OFF = ("0", "off", "false", "no", "none")


def enable(
    path: str | os.PathLike | None = None, cache_root: str | os.PathLike | None = None
) -> Path | None:
    """Turn on JAX's persistent compilation cache; returns its directory (None when disabled).

    ``path`` overrides ``$EABC_COMPILE_CACHE``; ``cache_root`` replaces the eabc cache directory
    in the default ``CACHE_ROOT/xla``. Call it before the first compilation of a process.
    """
    setting = str(path) if path is not None else os.environ.get("EABC_COMPILE_CACHE", "")
    if setting.strip().lower() in OFF:
        return None
    if not setting and jax.config.jax_compilation_cache_dir:  # the user's own JAX setting
        return Path(jax.config.jax_compilation_cache_dir)
    if not setting:
        setting = str(cache_dir(cache_root) / "xla")
    jax.config.update("jax_compilation_cache_dir", setting)
    # Every program, however quick to compile: one run makes a few dozen, ~1 MB in all.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return Path(setting)
