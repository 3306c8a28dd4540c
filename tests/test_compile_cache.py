"""The on-disk compilation cache: a second process reuses the first one's programs."""

from __future__ import annotations

import json
import os
import subprocess
import sys

SCRIPT = """
import json, sys
import jax, jax.numpy as jnp
from eabc import compile_cache

events = []
jax.monitoring.register_event_listener(lambda name, **_: events.append(name))
where = compile_cache.enable()
jax.block_until_ready(jax.jit(lambda x: jnp.tanh(x @ x.T).sum())(jnp.ones((8, 8))))
print(json.dumps({
    "dir": None if where is None else str(where),
    "jax_dir": jax.config.jax_compilation_cache_dir,
    "hits": events.count("/jax/compilation_cache/cache_hits"),
    "misses": events.count("/jax/compilation_cache/cache_misses"),
}))
"""


def _run(extra: dict[str, str]) -> dict:
    """The script in a fresh process, its cache settings only those in ``extra``."""
    keep = {
        k: v
        for k, v in os.environ.items()
        if k not in ("EABC_COMPILE_CACHE", "JAX_COMPILATION_CACHE_DIR")
    }
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=keep | extra, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.splitlines()[-1])


def test_second_process_loads_the_programs_the_first_compiled(tmp_path):
    env = {"EABC_COMPILE_CACHE": str(tmp_path / "xla")}
    first, second = _run(env), _run(env)
    assert first["dir"] == second["dir"] == str(tmp_path / "xla")
    assert first["hits"] == 0 and first["misses"] >= 1
    assert second["hits"] >= 1 and second["misses"] == 0
    assert any((tmp_path / "xla").iterdir())


def test_default_location_and_switching_it_off(tmp_path):
    default = _run({"EABC_CACHE_DIR": str(tmp_path)})
    assert default["dir"] == default["jax_dir"] == str(tmp_path / "xla")
    assert any((tmp_path / "xla").iterdir())
    off = _run({"EABC_COMPILE_CACHE": "off", "EABC_CACHE_DIR": str(tmp_path / "other")})
    assert off["dir"] is None and off["jax_dir"] is None and off["hits"] == 0
    assert not (tmp_path / "other").exists()
