"""One writer per run directory: an OS file lock plus a note of who holds it.

The lock is ``RUN_DIR/.lock``, held with ``flock``: the kernel drops it when its process dies, so
a killed run's ``.lock`` is taken over by the next writer without a word. Its owner removes the
file when it lets go (while still holding it, so that no other writer can be inside); a writer
that locked a file removed meanwhile lets go and tries again on the new one, so two writers never
both hold "the" lock. ``RUN_DIR/.lock.owner`` says which process holds it, so that a second
writer is told whom to wait for or stop. Where ``fcntl`` is missing (Windows) ``filelock`` holds
the lock instead, and its file stays behind.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from pathlib import Path

from eabc import paths

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None

LOCK = ".lock"
OWNER = ".lock.owner"


class RunLockedError(RuntimeError):
    """Another process is writing to this run directory."""


class RunLock:
    """Holds ``run_dir``'s lock from :meth:`acquire` until :meth:`release` (or process exit)."""

    def __init__(self, run_dir: str | Path):
        self.run_dir = Path(run_dir)
        self._fd: int | None = None
        self._fallback = None
        if fcntl is None:
            import filelock  # noqa: PLC0415 (fcntl's fallback, where there is none)

            self._fallback = filelock.FileLock(self.run_dir / LOCK, timeout=0)

    def acquire(self) -> RunLock:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if not self._take():
            raise RunLockedError(
                f"{self.run_dir} is in use by {holder(self.run_dir)}; wait for it to finish or "
                "stop that process, then try again"
            )
        owner = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "since": time.strftime("%Y-%m-%d %H:%M:%S"),
            "command": " ".join(sys.argv),
        }
        (self.run_dir / OWNER).write_text(json.dumps(owner))
        return self

    def _take(self) -> bool:
        """Lock ``.lock`` (made if missing); False if a live process holds it."""
        if self._fallback is not None:
            import filelock  # noqa: PLC0415 (fcntl's fallback, where there is none)

            try:
                self._fallback.acquire()
            except filelock.Timeout:
                return False
            return True
        path = self.run_dir / LOCK
        while True:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:  # held by a live process
                os.close(fd)
                return False
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:  # its owner removed it as we locked it
                same = False
            if same:
                self._fd = fd
                return True
            os.close(fd)  # a file no longer at the path: lock the one there now

    def release(self) -> None:
        if not self.held:
            return
        (self.run_dir / OWNER).unlink(missing_ok=True)
        if self._fallback is not None:
            self._fallback.release()
            return
        (self.run_dir / LOCK).unlink(missing_ok=True)  # still held: no writer is inside
        os.close(self._fd)
        self._fd = None

    @property
    def held(self) -> bool:
        if self._fallback is not None:
            return self._fallback.is_locked
        return self._fd is not None

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
