"""Tables a reconstruction computes from the rig alone, kept on disk between commands.

Before it matches a pair, `reconstruct` computes from the rig, the water level and the height range alone:
the rectification, the coarse grid its remap is interpolated from, the disparity search range, the exact
epipolar curves' row offsets and the shared errors' covariance table. Together they are 0.1-0.3 s of
arithmetic but, in a fresh process, about 2 s more of JAX tracing and loading compiled functions (a
1728x1152 pair, on 2 cores), so a survey campaign (one rig, one level, many pairs) would pay that on every
command. With a folder set (`use_table_cache`; the command line sets one, the library never does), each
table is kept there under the SHA-256 of its inputs' values and of jaxstereo's own source, so that any
change to either computes it again.

A file is written to a temporary name and renamed; one that cannot be read is computed again. The folder
is kept under `MAX_FOLDER_BYTES`, the least recently used files removed first. The command line keeps its match
plans there too (`match_ahead.py`: the remap tables, 32 MB for a 1728x1152 rig).
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

log = logging.getLogger("jaxstereo")

MAX_FOLDER_BYTES = 256 << 20  # about a hundred rig and water-level combinations
_folder: Path | None = None
_source_digest: bytes | None = None


def use_table_cache(folder: str | os.PathLike | None) -> None:
    """Keep the rig's tables in `folder` (created when first written); None computes them every time (the
    library's default)."""
    global _folder
    _folder = Path(folder) if folder is not None else None


def table_cache_folder() -> Path | None:
    """The folder `use_table_cache` set (None: none)."""
    return _folder


def cached_tables(name: str, inputs, compute: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """`compute()` (a dict of numpy arrays), or the same dict read back from the cache folder when the same
    `name` was computed from equal `inputs` (any PyTree of arrays, numbers, strings and `None`) by the same
    jaxstereo source. Without a folder (`use_table_cache`), `compute()`."""
    if _folder is None:
        return compute()
    path = _folder / f"{name.replace(' ', '-')}-{table_key(name, inputs)}.npz"
    try:
        with open(path, "rb") as handle, np.load(handle) as stored:
            tables = {k: stored[k] for k in stored.files}
        os.utime(path)  # recently used: kept longest
        return tables
    except (OSError, ValueError, EOFError, KeyError, TypeError, AttributeError, zipfile.BadZipFile) as err:
        if not isinstance(err, FileNotFoundError):  # unreadable (a truncated zip, a foreign file): computed again
            log.info("rig table %s unreadable (%s): computed again", path.name, err)
    tables = compute()
    try:
        _folder.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=_folder, suffix=".partial")
        with os.fdopen(handle, "wb") as out:
            np.savez(out, **tables)
        os.replace(temporary, path)
        trim_folder(_folder)
    except OSError:
        pass  # a read-only or full disk: the tables were computed, the command goes on without keeping them
    return tables


def table_key(name: str, inputs) -> str:
    """The hex SHA-256 of `name`, jaxstereo's source and the values, dtypes and shapes of `inputs`' leaves
    with the PyTree's structure (static fields such as a rectification's mode and size included).

    Floating-point values (arrays and numbers alike) are hashed to `KEY_BITS` significant bits (`_quantised`), not
    to their last bit: a rectification computed from the same rig can differ in its last bits between processes (on
    a GPU under load, where XLA picks its kernels per process by timing them, it got another key), and its key must
    not."""
    import jax  # here: the module is imported before JAX by the command line (`match_ahead.py`)

    leaves, structure = jax.tree_util.tree_flatten(inputs)
    h = hashlib.sha256(source_digest())
    h.update(name.encode())
    h.update(str(structure).encode())
    for leaf in leaves:
        if isinstance(leaf, (str, bool, int)):
            h.update(repr(leaf).encode())
        else:
            value = np.asarray(leaf)
            h.update(f"{value.dtype.str}{value.shape}".encode())
            floating = np.issubdtype(value.dtype, np.floating)
            h.update(_quantised(value) if floating else np.ascontiguousarray(value).tobytes())
    return h.hexdigest()


KEY_BITS = 32  # a key tells apart values that differ by more than about 1e-10 of themselves or of their array's largest


def _quantised(value: np.ndarray) -> bytes:
    """`value` (any shape, floating point) as bytes: each finite entry rounded to `KEY_BITS` significant bits, those
    smaller than 2**-KEY_BITS of the array's largest finite magnitude made 0 (a computed zero's noise), then the NaN
    and infinite entries as they are. A value and one a few units in its last place away (1.0 and 1 - 4e-16, a
    rotation's 0 and 4e-18) give the same bytes, unless they straddle one of the rounding's midpoints."""
    value = value.astype(np.float64)
    finite = np.isfinite(value)
    largest = float(np.max(np.abs(value[finite]), initial=0.0))
    kept = np.where(finite & (np.abs(value) >= np.ldexp(largest, -KEY_BITS)), value, 0.0)
    mantissa, exponent = np.frexp(kept)
    rounded = np.ldexp(np.rint(np.ldexp(mantissa, KEY_BITS)), exponent - KEY_BITS) + 0.0  # + 0.0: no -0.0
    return rounded.tobytes() + np.where(finite, 0.0, value).tobytes()


def source_digest() -> bytes:
    """The SHA-256 of every Python file of the jaxstereo package (read once per process)."""
    global _source_digest
    if _source_digest is None:
        h = hashlib.sha256()
        root = Path(__file__).resolve().parents[1]
        for path in sorted(root.rglob("*.py")):
            h.update(str(path.relative_to(root)).encode())
            h.update(path.read_bytes())
        _source_digest = h.digest()
    return _source_digest


def trim_folder(folder: Path) -> None:
    """Remove what a killed command left half-written (over an hour old), then the least recently used
    files until the folder holds at most `MAX_FOLDER_BYTES`."""
    files = []
    for entry in os.scandir(folder):
        if entry.is_file() and entry.name.endswith((".npz", ".partial")):
            stat = entry.stat()
            if entry.name.endswith(".partial") and stat.st_mtime > time.time() - 3600:
                continue  # being written by another command
            files.append((stat.st_mtime if entry.name.endswith(".npz") else 0.0, stat.st_size, entry.path))
    total = sum(size for _, size, _ in files)
    for used, size, path in sorted(files):
        if used and total <= MAX_FOLDER_BYTES:
            break
        try:
            os.remove(path)
        except OSError:
            continue
        total -= size
