"""One writer per run directory: an OS file lock (``filelock``) plus a note of who holds it.

The lock is ``RUN_DIR/.lock`` (``flock``: the kernel drops it when its process dies, so a killed
run never leaves a stale lock); ``RUN_DIR/.lock.owner`` says which process holds it, so that a
second writer is told whom to wait for or stop.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from pathlib import Path

import filelock

from eabc import paths

LOCK = ".lock"
OWNER = ".lock.owner"


class RunLockedError(RuntimeError):
    """Another process is writing to this run directory."""


class RunLock:
    """Holds ``run_dir``'s lock from :meth:`acquire` until :meth:`release` (or process exit)."""

    def __init__(self, run_dir: str | Path):
        self.run_dir = Path(run_dir)
        self._lock = filelock.FileLock(self.run_dir / LOCK, timeout=0)

    def acquire(self) -> RunLock:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        try:
            self._lock.acquire()
        except filelock.Timeout:
            raise RunLockedError(
                f"{self.run_dir} is in use by {holder(self.run_dir)}; wait for it to finish or "
                "stop that process, then try again"
            ) from None
        owner = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "since": time.strftime("%Y-%m-%d %H:%M:%S"),
            "command": " ".join(sys.argv),
        }
        (self.run_dir / OWNER).write_text(json.dumps(owner))
        return self

    def release(self) -> None:
        if self._lock.is_locked:
            (self.run_dir / OWNER).unlink(missing_ok=True)
            self._lock.release()

    @property
    def held(self) -> bool:
        return self._lock.is_locked

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def in_use(run_dir: str | Path) -> bool:
    """Whether a live process holds ``run_dir``'s lock, read from its owner note without taking
    the lock (a probe that took it could make a run starting that instant fail). A note left by
    a killed process on this host does not count; one from another host (a shared filesystem)
    does, as its process cannot be checked from here."""
    try:
        owner = json.loads(paths.read_file(Path(run_dir) / OWNER).decode())
        pid, host = int(owner["pid"]), owner["host"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    if host != socket.gethostname():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def holder(run_dir: Path) -> str:
    """Who holds ``run_dir``'s lock, in words."""
    try:
        owner = json.loads(paths.read_file(Path(run_dir) / OWNER).decode())
        return (
            f"process {owner['pid']} on {owner['host']} (since {owner['since']}: "
            f"{owner['command']})"
        )
    except (OSError, ValueError, KeyError):
        return "another process"
