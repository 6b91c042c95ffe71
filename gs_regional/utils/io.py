"""File-writing helpers: atomic writes and protection of input files."""
from __future__ import annotations

import json
import os
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator, Optional, Union

PathLike = Union[str, "os.PathLike[str]"]


class OverwriteError(ValueError):
    """Writing to the requested path would destroy one of the inputs."""


@contextmanager
def atomic_write(path: PathLike) -> Iterator[str]:
    """Yield a temporary path beside `path`; move it onto `path` only if the block succeeds.

    A crash or an exception never leaves a half-written file at `path` (readers see the old
    file or the new one) and the temporary file is removed. Parent directories are created.
    The temporary lives in the same directory so that `os.replace` is an atomic rename.
    """
    path = os.fspath(path)
    parent = os.path.dirname(os.path.abspath(path))
    os.makedirs(parent, exist_ok=True)
    # Only a name: the writer creates the file itself, so it gets the usual permissions.
    tmp = os.path.join(parent, f".{os.path.basename(path)}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        yield tmp
        if not os.path.exists(tmp):
            raise FileNotFoundError(f"atomic_write: nothing was written for {path}")
        os.replace(tmp, path)
    except BaseException:
        try:
            os.remove(tmp)
        except FileNotFoundError:
            pass
        raise


def _same_file(a: str, b: str) -> bool:
    if os.path.exists(a) and os.path.exists(b):
        try:
            return os.path.samefile(a, b)  # also catches hard links
        except OSError:
            pass
    return os.path.realpath(a) == os.path.realpath(b)


def check_not_overwriting(out_path: PathLike, protected_paths: Iterable[Optional[PathLike]]) -> None:
    """Raise OverwriteError if `out_path` is (the same file as) any of `protected_paths`.

    `None` entries are ignored so callers can pass optional inputs directly.
    """
    out = os.fspath(out_path)
    for p in protected_paths:
        if p is None:
            continue
        p = os.fspath(p)
        if _same_file(out, p):
            raise OverwriteError(
                f"refusing to write {out}: it is the input file {p}, which would be overwritten; "
                f"choose a different output path"
            )


def _json_default(obj: Any) -> Any:
    """Make numpy/torch scalars and arrays, and paths, JSON-serialisable."""
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "tolist"):  # numpy arrays/scalars, torch tensors
        return obj.tolist()
    if hasattr(obj, "item"):
        return obj.item()
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")


def write_json_atomic(path: PathLike, obj: Any, indent: int = 2) -> None:
    """Write `obj` as JSON to `path` atomically (numpy/torch values are converted)."""
    with atomic_write(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(obj, f, indent=indent, default=_json_default)
            f.write("\n")
