"""The run directory's writer lock: one writer, no stale files, a dead holder taken over."""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import textwrap

import pytest

from eabc.training.lock import LOCK, OWNER, RunLock, RunLockedError


def test_released_lock_leaves_no_files(tmp_path):
    lock = RunLock(tmp_path / "run").acquire()
    assert (tmp_path / "run" / LOCK).exists() and (tmp_path / "run" / OWNER).exists()
    with pytest.raises(RunLockedError, match="in use by process"):
        RunLock(tmp_path / "run").acquire()
    lock.release()
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == []
    with RunLock(tmp_path / "run"):  # taken again after its file is gone
        pass
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == []


def test_a_killed_holders_lock_is_taken_over_silently(tmp_path, capfd):
    run_dir = tmp_path / "run"
    holder = _holder(run_dir)
    with pytest.raises(RunLockedError):
        RunLock(run_dir).acquire()
    holder.kill()  # SIGKILL: nothing of the holder runs, its files stay
    holder.wait()
    assert (run_dir / LOCK).exists()
    capfd.readouterr()
    with RunLock(run_dir):
        pass
    assert capfd.readouterr() == ("", "")
    assert not (run_dir / LOCK).exists() and not (run_dir / OWNER).exists()


def test_sigterm_removes_the_lock_file(tmp_path):
    """``eabc`` turns SIGTERM into an exit that runs the lock's release."""
    run_dir = tmp_path / "run"
    holder = _holder(run_dir, "from eabc.cli import exit_on_sigterm; exit_on_sigterm()")
    holder.send_signal(signal.SIGTERM)
    assert holder.wait(timeout=30) == 128 + signal.SIGTERM
    assert not (run_dir / LOCK).exists() and not (run_dir / OWNER).exists()


def test_a_lock_file_removed_while_being_taken_is_not_shared(tmp_path):
    """A writer that locked a file its owner has just removed locks the new one instead: two
    writers never hold the lock at once."""
    run_dir = tmp_path / "run"
    first = RunLock(run_dir).acquire()
    stale = os.open(run_dir / LOCK, os.O_RDWR)  # opened before the owner lets go
    first.release()
    second = RunLock(run_dir).acquire()
    fcntl.flock(stale, fcntl.LOCK_EX | fcntl.LOCK_NB)  # the old inode: free, but no longer the lock
    with pytest.raises(RunLockedError):
        RunLock(run_dir).acquire()
    os.close(stale)
    second.release()


def _holder(run_dir, setup: str = "") -> subprocess.Popen:
    code = textwrap.dedent(f"""
        import sys, time
        {setup}
        from eabc.training.lock import RunLock
        lock = RunLock(sys.argv[1]).acquire()
        try:
            print("held", flush=True)
            time.sleep(60)
        finally:
            lock.release()
    """)
    process = subprocess.Popen(
        [sys.executable, "-c", code, str(run_dir)], stdout=subprocess.PIPE, text=True
    )
    assert process.stdout.readline().strip() == "held"
    return process
