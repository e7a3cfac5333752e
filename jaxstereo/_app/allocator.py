"""The `jaxstereo reconstruct` command's memory settings: one glibc malloc arena for a repeated command, numpy's
arrays on the kernel's small pages, and freed memory kept for the next allocation.

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

numpy asks the kernel for transparent huge pages (2 MB, `madvise`) for each array of 4 MB or more. On a kernel
that grants them on request only (`/sys/kernel/mm/transparent_hugepage/enabled` "madvise", as here), each first
touch of such an array then clears a whole 2 MB page and may first compact memory to find one. A survey's arrays
are mostly freed and reused within the command, so small pages serve it better: a fresh `reconstruct` of the
development flume's pair (2 cores) took a median 2.29 s against 2.37 s, 3.95 CPU-s against 4.11 (12 alternated
runs each). Through numpy's `NUMPY_MADVISE_HUGEPAGE=0`, before this setting: 2.335 against 2.43 s, system time
0.43 against 0.60 s, 179,000 small pages faulted in instead of 134,000 pages of both sizes (10 runs each).
A command that compiles (empty caches) took 6.8-7.2 s against 6.6-7.3 s (3 runs each): no change there. Set by
`cli.main` for the `reconstruct` command's own process, compiling or not; a kernel that grants huge pages always,
or never, is not affected.

On small pages, the page faults are counted one per 4 KB: a fresh command faulted in 190,000 (750 MB), for a peak
of 650 MB. glibc serves a block of more than its mmap threshold from new pages of the kernel (mmap) and gives them
back when it is freed; the threshold starts at 128 KB and rises to each such block freed, so an image-sized array
allocated again at the same size is mapped afresh. And it hands its heap's freed top back once that exceeds twice
the threshold. With the threshold at its largest, 32 MB (`LARGEST_HEAP_BLOCK`), and the heap never trimmed
(`keep_freed_memory`), the command faulted in 144,000 pages, its system time 0.46 -> 0.37 s, its median 2.29 ->
2.24 s (10 alternated runs each, through glibc's `GLIBC_TUNABLES`; 2.30 -> 2.24 s, CPU 3.86 -> 3.75 s in 12 more
as `cli.main` sets it). The threshold alone, which leaves the heap trimmed at every 128 KB, faulted in 279,000
pages (2.375 s). A compiling command: 6.3-6.6 s against 6.3-6.8 s (3 runs each). The memory is the process's until
it ends, a second later: its peak does not change. Set by `cli.main` for the `reconstruct` command's own process,
compiling or not.
"""

from __future__ import annotations

import ctypes
import sys

M_ARENA_MAX, M_MMAP_THRESHOLD, M_TRIM_THRESHOLD = -8, -3, -1  # glibc's <malloc.h>
LARGEST_HEAP_BLOCK = 32 << 20  # glibc's largest mmap threshold on 64-bit systems (bytes)
NEVER_TRIM = 2**31 - 1  # bytes: more than a survey's heap ever frees at its top


def use_one_malloc_arena() -> bool:
    """Ask glibc's malloc for a single arena; True when it took the setting, False where there is no glibc
    (macOS, Windows, musl: their allocators are left as they are)."""
    return _mallopt(M_ARENA_MAX, 1)


def keep_freed_memory() -> bool:
    """Ask glibc's malloc to serve blocks up to `LARGEST_HEAP_BLOCK` from its heap and never to hand the heap's
    freed top back to the kernel (see the module's text); True when it took both settings, False where there is
    no glibc."""
    return _mallopt(M_MMAP_THRESHOLD, LARGEST_HEAP_BLOCK) and _mallopt(M_TRIM_THRESHOLD, NEVER_TRIM)


def _mallopt(parameter: int, value: int) -> bool:
    """glibc's `mallopt(parameter, value)`; True when it took the setting, False where there is no glibc."""
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
    return mallopt(parameter, value) == 1


def keep_arrays_on_small_pages() -> bool:
    """Stop numpy from asking for transparent huge pages for its large arrays (see the module's text); True when
    the setting was taken, False where this numpy has no such switch."""
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:
        return False
    _set_madvise_hugepage(False)
    return True
