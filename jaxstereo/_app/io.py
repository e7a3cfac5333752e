"""File output helpers: every file is written to a temporary name and renamed, never half-written."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside `path` (`temporary_path`); on success rename it to `path`, on error remove
    it."""
    tmp = temporary_path(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def temporary_path(path) -> str:
    """A new, empty file beside `path` (its folder made if need be) to write `path`'s content into before
    renaming it; its name keeps `path`'s suffix, so that writers choosing a format by extension still work."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    return tmp


def write_text_atomic(path, text: str) -> None:
    """Write `text` to `path` atomically (temporary file, then rename)."""
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def write_bytes_atomic(path, data: bytes) -> None:
    """Write `data` to `path` atomically (temporary file, then rename)."""
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)


def read_npz(path, what: str) -> dict:
    """All arrays of an `.npz` file as a dict; `JaxStereoError` naming `what` and the file if it is missing
    or cannot be read (zero bytes, truncated, not an archive). The file is always closed."""
    import numpy as np

    from .._geometry.errors import JaxStereoError

    path = Path(path)
    if not path.is_file():
        raise JaxStereoError(f"{what} {str(path)!r} does not exist")
    try:
        with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except Exception as err:  # numpy and zipfile raise several types for broken archives
        raise JaxStereoError(f"{what} {str(path)!r} cannot be read as .npz ({err.__class__.__name__})") from None
