"""A repeated `jaxstereo reconstruct`'s memory allocator setting: one glibc malloc arena for the whole process.

glibc gives each thread that allocates its own arena (up to 8 per core) and hands freed memory at an arena's top
back to the kernel. A survey allocates image-sized arrays (4-24 MB) on several threads at once (the row bands of
the sub-pixel stage, the matching ahead, OpenCV's and XLA's pools), so the same memory is returned and faulted
in again, page by page: a fresh `jaxstereo reconstruct` of the POV-Ray flume's 1728x1152 pair spent 1.1-1.7 s of
system time on 2 cores, most of it in page faults of numpy's and OpenCV's outputs (`perf record -e page-faults`).
With one arena the freed blocks are reused: 0.6-0.9 s of system time, the peak memory 10-20 % lower, and the
command 0.2-0.6 s faster (2.95-3.07 s against 3.32-3.80 s, five alternated runs each; 3.22 against 3.42 s median
of five in another hour).

Compiling is another matter: XLA's compiler threads allocate small blocks by the million, and one arena makes
them queue for its lock. A reconstruction that compiles (the first on a machine) took 10.0 s against 8.7 s, the
refinement of the demo's water level 11.3 s against 8.4 s, the demo 62 s against 53 s. So the command line takes
one arena only for a `reconstruct` that repeats an earlier one with the same rig file and settings (its match
plan is on disk: `match_ahead.py`), whose compiled functions come from JAX's persistent cache. Two arenas were
measured too: no cost to compiling, and no gain to the repeat either (3.37 s median).

Set by `cli.main` for the `jaxstereo` command only (its process is the command's alone), before any thread
starts; the library, and a caller running commands in its own process, leave the allocator alone.
"""

from __future__ import annotations

import ctypes
import sys

M_ARENA_MAX = -8  # glibc's <malloc.h>


def use_one_malloc_arena() -> bool:
    """Ask glibc's malloc for a single arena; True when it took the setting, False where there is no glibc
    (macOS, Windows, musl: their allocators are left as they are)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)  # the symbols already loaded, the C library among them
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    if not hasattr(libc, "gnu_get_libc_version"):  # glibc's own symbol: musl has a mallopt that does nothing
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return mallopt(M_ARENA_MAX, 1) == 1
