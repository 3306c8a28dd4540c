"""Where the package keeps what it makes: the bottom layer, importable from anywhere."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path


def cache_dir(override: str | os.PathLike | None = None) -> Path:
    """Where made datasets and compiled programs live: the argument, else ``$EABC_CACHE_DIR``,
    else ``~/.cache/eabc``."""
    root = override or os.environ.get("EABC_CACHE_DIR") or Path.home() / ".cache" / "eabc"
    return expand(root)


def expand(path: str | os.PathLike) -> Path:
    """``path`` with a leading ``~`` or ``~user`` expanded; ``ValueError`` naming it where there
    is no such user or home (``Path.expanduser`` raises ``RuntimeError`` there, read as a crash)."""
    try:
        return Path(path).expanduser()
    except RuntimeError:
        head = str(path).split(os.sep, 1)[0]
        raise ValueError(
            f"{path}: cannot expand {head} (no such user or home directory); give the full path"
        ) from None


def read_file(path: str | os.PathLike) -> bytes:
    """The bytes of ``path`` if it is a regular file; ``OSError`` naming it otherwise. A FIFO
    would block its reader forever and a device (a link to /dev/zero) never end: the file is
    opened without blocking and checked before a byte is read."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = (
                "a directory" if stat.S_ISDIR(mode)
                else "a FIFO" if stat.S_ISFIFO(mode)
                else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
                else "a socket" if stat.S_ISSOCK(mode)
                else "not a file"
            )  # fmt: skip
            raise OSError(errno.EINVAL, f"it is {kind}, not a regular file", str(path))
        with os.fdopen(os.dup(fd), "rb") as f:
            return f.read()
    finally:
        os.close(fd)


def check_directory(path: str | os.PathLike, flag: str) -> None:
    """``ValueError`` naming ``flag`` when ``path`` cannot be a directory: it, or the nearest of
    its parents that exists, is something else (a file). Checked before work whose output goes
    there."""
    given = expand(path)
    where = given
    while not where.exists() and where != where.parent:
        where = where.parent
    if where.exists() and not where.is_dir():
        inside = "" if where == given else f" ({where} is a file)"
        raise ValueError(
            f"{flag} {path} is not a directory{inside}: give a directory (it is made if missing)"
        )
