"""Where and with what a run was trained: its run directory's ``provenance.json``.

Every time training starts on a run (new, resumed or extended) it appends one *segment*: the step
it starts from, when, the host and its CPU (model, widest vector extension), the JAX device, the
package's version with the git commit of the source it ran from (and whether that source had
uncommitted changes), and the versions of the libraries the numbers depend on. A score can then
be traced to the code and machine that made it, and a report that merges runs of several hosts,
sweep roots or checkouts (``--include``) says which came from where; two copies of one run that
disagree can be told apart by what made them.
"""

from __future__ import annotations

import datetime
import functools
import json
import os
import platform
import socket
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

from eabc import paths
from eabc.training import checkpoint

PROVENANCE = "provenance.json"
LIBRARIES = ("jax", "jaxlib", "numpy", "gymnasium", "mujoco")
"""The packages a run's numbers depend on, whose versions each segment records."""


def cpu_model() -> str:
    """The CPU's model name, family and model (from /proc/cpuinfo on Linux)."""
    fields = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                fields.setdefault(key.strip(), value.strip())
    except OSError:
        return platform.processor() or platform.machine()
    name = fields.get("model name", platform.machine())
    family, model = fields.get("cpu family"), fields.get("model")
    return f"{name} (family {family}, model {model})" if family else name


def vector_isa() -> str:
    """The widest x86 vector extension the CPU reports: AVX-512, AVX2 or older."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line.split() for line in f if line.startswith("flags")), [])
    except OSError:
        return "unknown"
    if "avx512f" in flags:
        return "AVX-512" + (" (+BF16)" if "avx512_bf16" in flags else "")
    return "AVX2" if "avx2" in flags else ("AVX" if "avx" in flags else "SSE")


def _git(*args: str, cwd: Path) -> str | None:
    try:
        done = subprocess.run(
            ["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip()


def code_version(source: Path | None = None) -> str:
    """``VERSION (git COMMIT)`` of the package source that is running (``, uncommitted changes``
    when its tracked files differ from the commit); the version alone outside a git checkout."""
    source = source or Path(__file__).resolve().parents[1]
    try:
        version = metadata.version("eabc")
    except metadata.PackageNotFoundError:
        version = "unknown version"
    commit = _git("rev-parse", "--short=12", "HEAD", cwd=source)
    if not commit:
        return version
    changed = _git("status", "--porcelain", "--untracked-files=no", "--", ".", cwd=source)
    return f"{version} (git {commit}{', uncommitted changes' if changed else ''})"


def _library_versions() -> dict[str, str]:
    versions = {}
    for name in LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


@functools.cache
def _this_process() -> dict[str, Any]:
    """What a segment records that does not change while a process runs (its code was read at
    start-up): looked up once, not once per run of a sweep worker or seed of a vmapped group."""
    import jax  # noqa: PLC0415 (the record is made once per start; keeps the import cheap)

    device = jax.devices()[0]
    kind = device.device_kind if device.device_kind != device.platform else ""
    return {
        "host": socket.gethostname(),
        "cpu": cpu_model(),
        "isa": vector_isa(),
        "cores": cores(),
        "device": f"{device.platform} {kind}".strip(),
        "code": code_version(),
        "python": platform.python_version(),
        "libraries": _library_versions(),
    }


def segment(step: int) -> dict[str, Any]:
    """The record of training that starts now at ``step`` on this machine."""
    started = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    return {"from_step": int(step), "started": started, **_this_process()}


def read(run_dir: Path) -> list[dict[str, Any]]:
    """A run's segments, oldest first; [] for a run from before this record (or an unreadable one)."""
    try:
        data = json.loads(paths.read_file(Path(run_dir) / PROVENANCE).decode())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return []
    segments = data.get("segments") if isinstance(data, dict) else None
    return [s for s in segments if isinstance(s, dict)] if isinstance(segments, list) else []


def record(run_dir: Path, step: int) -> dict[str, Any]:
    """Append this machine's segment, starting at ``step``, to ``run_dir``'s record."""
    new = segment(step)
    checkpoint.save_json(Path(run_dir) / PROVENANCE, {"segments": [*read(run_dir), new]})
    return new


def machine_text(segments: list[dict[str, Any]]) -> str:
    """The machines a run was trained on, in order, each once: ``CPU, ISA [+ CPU, ISA]``."""
    return " + ".join(dict.fromkeys(f"{s.get('cpu', '?')}, {s.get('isa', '?')}" for s in segments))


def code_text(segments: list[dict[str, Any]]) -> str:
    """The code a run was trained with, in order, each once."""
    return " + ".join(dict.fromkeys(str(s.get("code", "?")) for s in segments))
