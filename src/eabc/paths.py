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


def check_output_file(
    path: str | os.PathLike, flag: str, protected: str | os.PathLike | None = None,
    ours: bytes | None = None,
) -> None:  # fmt: skip
    """``ValueError`` naming ``flag`` when writing ``path`` could destroy what is not an output
    of the command: something that exists and is not a regular file (a directory, a device such
    as /dev/null, a FIFO, also behind a link), or a file inside the directory ``protected`` (a
    run's checkpoint, config.json, log) unless its first bytes hold ``ours``, the mark of a file
    the command itself wrote there before. Its folder must be one, too."""
    given = expand(path)
    target = given.resolve() if given.is_symlink() or given.exists() else given
    if given.exists() or given.is_symlink():
        if not target.exists() or not stat.S_ISREG(os.stat(target).st_mode):
            kind = _kind(target)
            raise ValueError(
                f"{flag} {path} is {kind}, not a regular file: writing there would replace it; "
                "give the path of a new file or of one written before"
            )
        if protected is not None and target.is_relative_to(expand(protected).resolve()):
            with open(target, "rb") as f:
                head = f.read(64)
            if ours is None or ours not in head:
                raise ValueError(
                    f"{flag} {path} is a file of {protected} that this command did not write "
                    f"({target.name}); write to a new file, e.g. {Path(protected) / 'policy.onnx'}"
                )
    check_directory(given.parent if str(given.parent) else ".", f"{flag} {path}: its folder")


def _kind(path: Path) -> str:
    if not path.exists():
        return "a link to nothing"
    mode = os.stat(path).st_mode
    for test, word in ((stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISSOCK, "a socket")):  # fmt: skip
        if test(mode):
            return word
    return "not a regular file"
