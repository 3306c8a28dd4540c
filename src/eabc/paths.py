"""Where the package keeps what it makes: the bottom layer, importable from anywhere."""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir(override: str | os.PathLike | None = None) -> Path:
    """Where made datasets and compiled programs live: the argument, else ``$EABC_CACHE_DIR``,
    else ``~/.cache/eabc``."""
    root = override or os.environ.get("EABC_CACHE_DIR") or Path.home() / ".cache" / "eabc"
    return Path(root).expanduser()
