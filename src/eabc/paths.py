"""Where the package keeps what it makes: the bottom layer, importable from anywhere."""

from __future__ import annotations

import os
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
