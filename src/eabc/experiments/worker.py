"""``python -m eabc.experiments.worker ROOT JOB_JSON``: one sweep job in a fresh process.

A worker never outlives its sweep: on Linux the kernel sends it SIGTERM when the parent dies
(``PR_SET_PDEATHSIG``, also after a SIGKILL of the parent), and a watcher thread checks the
parent's pid every second everywhere else. The runs resume from their checkpoints next time.
"""

from __future__ import annotations

import ctypes
import json
import os
import signal
import sys
import threading
import time

PARENT = "EABC_SWEEP_PARENT"
"""The sweep's pid, set by the sweep for its workers."""
_PR_SET_PDEATHSIG = 1


def watch_parent(parent: int) -> None:
    """Exit when ``parent`` is no longer this process's parent."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
        except (OSError, AttributeError):
            pass

    def poll() -> None:
        while True:
            if os.getppid() != parent:
                os._exit(143)  # the sweep is gone: stop training, as SIGTERM would
            time.sleep(1.0)

    if os.getppid() != parent:  # died before the line above could arm the signal
        os._exit(143)
    threading.Thread(target=poll, daemon=True, name="watch-sweep").start()


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if os.environ.get(PARENT):
        watch_parent(int(os.environ[PARENT]))
        # Ctrl-C reaches the whole process group: the sweep stops its workers itself (SIGTERM),
        # so a worker does not die of it mid-run with a traceback in its log.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    from eabc.experiments.job_process import execute  # noqa: PLC0415 (after the watch is armed)

    root, payload = argv
    try:
        summaries = execute(json.loads(payload), root)
    except (ValueError, OSError, RuntimeError) as error:  # one line in the job's log, no traceback
        sys.exit(f"error: {error}")
    for summary in summaries:
        print(json.dumps(summary), flush=True)


if __name__ == "__main__":
    main()
