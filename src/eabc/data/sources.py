"""What a user types after ``--dataset``, resolved: a file path, ``minari:ID`` (or a Minari id that
exists locally), or a built-in name such as ``hopper-random`` that is made on first use.

Which of these a value names is decided once, by :func:`kind`; every command and sweep asks it.
The top of the data layer: it uses the file readers (:mod:`eabc.data.loaders`) and the generator
(:mod:`eabc.data.generate`), neither of which knows about the other's names.
"""

from __future__ import annotations

import os
from typing import Literal

from eabc import paths, timing
from eabc.data import generate, loaders, schema
from eabc.data.dataset import Dataset, DatasetError

MINARI = "minari:"
FILE_SUFFIXES = (".hdf5", ".h5", ".npz")
Kind = Literal["minari", "file", "builtin", "other"]


def kind(source: str | os.PathLike) -> Kind:
    """What a ``--dataset`` value names: ``minari`` (``minari:ID``: the prefix wins over
    anything the rest looks like), ``file`` (a path ending .hdf5, .h5 or .npz, or one that
    exists), ``builtin`` (a name of :func:`eabc.data.generate.builtin_names`, made on first
    use), else ``other``: a Minari id given without its prefix where Minari holds it locally
    (:func:`load_dataset` asks Minari then), or nothing known. Nothing is read or imported."""
    text = str(source)
    if text.startswith(MINARI):
        return "minari"
    path = paths.expand(text)
    if path.suffix in FILE_SUFFIXES or path.exists():
        return "file"
    return "builtin" if text in generate.builtin_names() else "other"


def load_dataset(
    source: str | os.PathLike, cache_dir: str | os.PathLike | None = None, make: bool = True
) -> Dataset:
    """Load a dataset from a path, a Minari id or a built-in name (see module docstring). A
    built-in dataset not in the cache is made first; without ``make`` (commands that only
    describe) it is refused, naming the command that makes it, and a cached one made from an
    older zoo is read as it is."""
    text, named = str(source), kind(source)
    if named == "file":
        return loaders.load_file(paths.expand(text))
    if named == "minari":
        return loaders.load_minari(text.removeprefix(MINARI))
    if named == "builtin" and not make:
        cached = generate.dataset_path(text, cache_dir)
        if not cached.exists():
            speed = timing.host_speed(cache_dir, measure=False)  # a recent probe, if any
            option = f" --cache-dir {cache_dir}" if cache_dir is not None else ""
            raise FileNotFoundError(
                f"{text} is not made yet (no {cached}); `eabc data make {text}{option}` makes "
                f"it, {generate.making_time(text, speed=speed)}"
            )
        return loaders.load_file(cached)
    if named == "builtin":
        return generate.load_or_make(text, cache_dir=cache_dir)
    if "/" in text and loaders.has_minari(text):
        return loaders.load_minari(text)
    raise _unknown(text)


def check_source(source: str | os.PathLike) -> None:
    """Refuse what :func:`load_dataset` would refuse for its name or path alone, loading and
    making nothing: a file that is missing or not a regular file, a name that is none of the
    above, a Minari dataset that is not there or damaged, or Minari's AntMaze data
    (:func:`loaders.check_minari`). A sweep checks every dataset so before its first run starts."""
    text, named = str(source), kind(source)
    if named == "file":
        schema.regular_file(paths.expand(text))
    elif named == "minari":
        loaders.check_minari(text.removeprefix(MINARI))
    elif named == "other" and not ("/" in text and loaders.has_minari(text)):
        raise _unknown(text)


def _unknown(text: str) -> DatasetError:
    return DatasetError(
        f"unknown dataset {text!r}{generate.did_you_mean(text)}: it is not a file, not a local "
        "Minari dataset and not a built-in name. Built-in names: "
        f"{', '.join(generate.builtin_names())}. For a file give its path (.hdf5, .h5 or .npz); "
        "for Minari use minari:ID."
    )
