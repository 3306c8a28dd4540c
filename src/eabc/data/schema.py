"""What a dataset file must be and hold, checked from its headers before any array is read.

The one place for the rules of dataset files (``.npz`` and D4RL-layout HDF5):

- the path is a regular file (a FIFO would block the reader forever, a device never ends);
- each array a dataset uses (:data:`ARRAYS`) holds numbers: float, int or bool, never objects,
  records (structured), complex numbers or text;
- it has one row per transition: ``[N]`` or ``[N, dim]`` with ``dim >= 1`` (rewards, terminals
  and timeouts ``[N]`` or ``[N, 1]``), never a single value;
- the bytes its header claims are in the file: shape x itemsize against the ``.npz`` member's
  real size (and the zip directory's sizes against the file's), or an HDF5 dataset's storage,
  so that a 2 KB file whose header claims a 60 TB array is refused before anything is allocated;
- all of them together fit in this machine's memory;
- the attributes (:data:`ATTRIBUTES`) have their types: names are text, reference scores and the
  reward offset finite numbers, ``metadata`` a JSON object.

Each refusal is a :class:`~eabc.data.dataset.DatasetError` of one line that names the file, the
key and what to do. What the values must be (equal lengths, no NaN/inf, flags 0 or 1) is the
:class:`~eabc.data.dataset.Dataset`'s own check, the same for every source (files, Minari, the
generator).

The rules are about headers (shape, dtype, bytes), not Python values, so they are a table and one
function (:func:`check`) rather than a pydantic model: a model would need custom array types and
its messages rewritten to name the file.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import stat
import zipfile
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from eabc.data.dataset import DatasetError

ARRAYS = {
    "observations": "rows",
    "actions": "rows",
    "next_observations": "rows",
    "rewards": "column",
    "terminals": "column",
    "timeouts": "column",
}
"""The arrays a dataset file may hold: ``rows`` are ``[N]`` or ``[N, dim]``, ``column`` ``[N]``
or ``[N, 1]``."""
ATTRIBUTES = {"name": str, "env_id": str, "metadata": str, "ref_min_score": float,
              "ref_max_score": float, "reward_offset": float}  # fmt: skip
"""The single values a dataset file may hold beside its arrays, and their types."""
NUMBER_KINDS = {"f": "float", "i": "int", "u": "unsigned int", "b": "bool"}
DEFLATE_RATIO = 1032
"""Deflate (zip, gzip) expands a byte to at most this many: a bound on what compressed data holds."""


@dataclasses.dataclass(frozen=True)
class Header:
    """What a file says about one array or value before it is read."""

    key: str
    shape: tuple[int, ...]
    dtype: np.dtype
    capacity: int | None
    """The most bytes of data the file can hold for it (None where a filter hides that)."""
    where: str = ""
    """The zip member or HDF5 dataset to read it from."""

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


def regular_file(path: Path) -> None:
    """Refuse, in one line, a path that is missing or not a regular file (directory, FIFO,
    device, socket): nothing opens it before this."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise DatasetError(f"dataset file {path} does not exist; check the path") from None
    except OSError as error:
        raise DatasetError(f"{path}: cannot read it ({error.strerror}); check the path") from None
    if stat.S_ISDIR(mode):
        raise DatasetError(f"{path} is a directory, not a dataset file; give the file's path")
    if not stat.S_ISREG(mode):
        kind = (
            "a FIFO" if stat.S_ISFIFO(mode)
            else "a socket" if stat.S_ISSOCK(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "not a regular file"
        )  # fmt: skip
        raise DatasetError(
            f"{path} is {kind}, not a regular file; save the dataset to a file and give its path"
        )


def npz_headers(path: Path, archive: zipfile.ZipFile) -> dict[str, Header]:
    """The headers of the members of an ``.npz`` archive that a dataset uses (``KEY.npy``, or
    ``KEY`` as :func:`numpy.load` also reads it), read without reading their data."""
    names = {info.filename: info for info in archive.infolist()}
    disk = path.stat().st_size
    headers = {}
    for key in (*ARRAYS, *ATTRIBUTES):
        info = names.get(f"{key}.npy") or names.get(key)
        if info is None:
            continue
        with archive.open(info) as member:
            try:
                version = np.lib.format.read_magic(member)
                read = {(1, 0): np.lib.format.read_array_header_1_0,
                        (2, 0): np.lib.format.read_array_header_2_0}.get(version)  # fmt: skip
                if read is None:
                    raise ValueError(f".npy format version {version[0]}.{version[1]}")
                shape, _, dtype = read(member)
            except (ValueError, SyntaxError, EOFError) as error:
                raise DatasetError(
                    f"{path}: member {info.filename} is not a readable .npy array ({_one_line(error)}); "
                    "save the dataset with numpy.savez(path, observations=..., ...)"
                ) from None
            header_size = member.tell()
        if info.compress_type == zipfile.ZIP_STORED:
            expands = 1
        elif info.compress_type == zipfile.ZIP_DEFLATED:
            expands = DEFLATE_RATIO
        else:
            raise DatasetError(
                f"{path}: member {info.filename} uses zip compression method "
                f"{info.compress_type}; save it with numpy.savez or numpy.savez_compressed"
            )
        # The zip directory's sizes are claims too: never more than the file on disk can hold.
        held = min(info.file_size, expands * min(info.compress_size, disk))
        headers[key] = Header(key, tuple(shape), dtype, max(held - header_size, 0), info.filename)
    return headers


def hdf5_headers(path: Path, file) -> dict[str, Header]:
    """The headers of the top-level HDF5 datasets a dataset uses, read without their data."""
    headers = {}
    for key in ARRAYS:
        if key not in file:
            continue
        node = file[key]
        if not isinstance(node, h5py.Dataset):
            raise DatasetError(
                f"{path}: {key!r} is an HDF5 {type(node).__name__.lower()}, not an "
                "array; a dataset needs arrays at the top level (D4RL's layout)"
            )
        try:
            dtype = node.dtype
            if h5py.check_string_dtype(dtype) is not None:
                dtype = np.dtype(str)  # h5py's variable-length text: objects that are text
        except TypeError as error:  # an HDF5 type NumPy has no equivalent of
            raise DatasetError(
                f"{path}: {key} has an HDF5 type NumPy cannot read ({error}); store it as float, "
                "int or bool"
            ) from None
        stored = node.id.get_storage_size()
        if node.is_virtual or node.external or node.scaleoffset is not None:
            capacity = None  # the data is elsewhere or packed: only the memory bound applies
        elif node.compression is None:
            capacity = stored
        elif node.compression == "gzip":
            capacity = DEFLATE_RATIO * stored
        else:
            capacity = None
        headers[key] = Header(key, tuple(node.shape or ()), dtype, capacity, key)
    return headers


def check(path: Path, headers: dict[str, Header]) -> None:
    """Every rule of the module docstring that headers can answer, before any data is read."""
    for key, header in headers.items():
        dtype, shape = header.dtype, header.shape
        if key in ATTRIBUTES:
            _check_attribute_header(path, header)
            continue
        if dtype.kind not in NUMBER_KINDS or dtype.hasobject or dtype.fields is not None:
            what = (
                "objects" if dtype.hasobject
                else "records (a structured dtype)" if dtype.fields is not None or dtype.kind == "V"
                else "complex numbers" if dtype.kind == "c"
                else "text" if dtype.kind in "US"
                else f"values of kind {dtype.kind!r}"
            )  # fmt: skip
            raise DatasetError(
                f"{path}: {key} holds {what} (dtype {dtype}); a dataset's arrays hold numbers "
                "(float, int or bool): convert it, e.g. numpy.asarray(x, numpy.float32)"
            )
        if len(shape) == 0:
            raise DatasetError(
                f"{path}: {key} is a single value, not an array with one row per transition; "
                "save the whole array under that key"
            )
        if any(n < 0 for n in shape):
            raise DatasetError(f"{path}: {key} claims the impossible shape {shape}; make it again")
        allowed = "[N] or [N, dim]" if ARRAYS[key] == "rows" else "[N] or [N, 1]"
        if (
            len(shape) > 2
            or (len(shape) == 2 and ARRAYS[key] == "column" and shape[1] != 1)
            or (len(shape) == 2 and shape[1] == 0)
        ):
            raise DatasetError(
                f"{path}: {key} has shape {shape}; it must be {allowed} (one row per transition): "
                "reshape it before saving"
            )
        if header.capacity is not None and header.nbytes > header.capacity:
            raise DatasetError(
                f"{path}: {key} claims shape {shape} of {dtype} ({_size(header.nbytes)}) but the "
                f"file holds at most {_size(header.capacity)} for it; the file is truncated or "
                "its header is corrupt: make or copy it again"
            )
    total = sum(h.nbytes for h in headers.values())
    memory = _memory()
    if memory is not None and total > memory:
        raise DatasetError(
            f"{path}: its arrays claim {_size(total)}, more than this machine's "
            f"{_size(memory)} of memory; use a smaller dataset or a larger machine"
        )


def _check_attribute_header(path: Path, header: Header) -> None:
    kind = ATTRIBUTES[header.key]
    text = kind is str and header.dtype.kind in "US"
    number = kind is float and header.dtype.kind in "fiu"
    if header.shape != () or not (text or number):
        want = "text" if kind is str else "a number"
        raise DatasetError(
            f"{path}: {header.key} must be a single value ({want}), got shape {header.shape} of "
            f"{header.dtype}; save it as numpy.asarray(value) or leave it out"
        )
    if header.capacity is not None and header.nbytes > header.capacity:
        raise DatasetError(
            f"{path}: {header.key} claims {_size(header.nbytes)} but the file holds at most "
            f"{_size(header.capacity)} for it; the file is truncated or corrupt: make it again"
        )


def attributes(path: Path, raw: dict[str, Any]) -> dict[str, Any]:
    """The attributes a dataset uses from ``raw`` (NumPy values or HDF5 attributes), typed:
    names as text, reference scores as finite floats, ``metadata`` as JSON text of an object."""
    out = {}
    for key, kind in ATTRIBUTES.items():
        if key not in raw:
            continue
        value = raw[key]
        if isinstance(value, np.ndarray) and value.size == 1:
            value = value.reshape(()).item()
        elif isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, bytes):
            try:
                value = value.decode()
            except UnicodeDecodeError:
                value = None  # refused below, with the other wrong types
        if kind is str and isinstance(value, str):
            out[key] = value
        elif kind is float and isinstance(value, int | float) and not isinstance(value, bool):
            out[key] = float(value)
        else:
            want = "text" if kind is str else "a number"
            raise DatasetError(
                f"{path}: attribute {key} must be {want}, got {_short(value)}; fix or remove it"
            )
        if kind is float and not math.isfinite(out[key]):
            raise DatasetError(
                f"{path}: attribute {key} is {out[key]}; it must be a finite number: "
                "fix or remove it"
            )
    if "metadata" in out:
        try:
            valid = isinstance(json.loads(out["metadata"]), dict)
        except ValueError:
            valid = False
        if not valid:
            raise DatasetError(
                f"{path}: attribute metadata must be a JSON object, got "
                f"{_short(out['metadata'])}; fix or remove it"
            )
    return out


def _memory() -> int | None:
    """This machine's physical memory in bytes (None where the OS does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def _size(nbytes: int) -> str:
    for unit in ("bytes", "KB", "MB", "GB", "TB", "PB"):
        if nbytes < 1000 or unit == "PB":
            return f"{nbytes:.0f} {unit}" if unit == "bytes" else f"{nbytes:.1f} {unit}"
        nbytes /= 1000
    raise AssertionError  # unreachable


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split())[:200]
