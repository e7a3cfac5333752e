"""Image work split into bands of rows, run on threads: the single-threaded numpy and OpenCV steps after
matching use every core. numpy and OpenCV release the GIL inside their array operations."""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

MAX_BANDS = 8  # threads at most
MIN_BAND_HALOS = 4  # a band (without its halo) at least this many halos tall: the halos stay a small share
# A band of at most this many pixels (with `width` given): the sub-pixel step holds about 45 float32 arrays of its
# band at once, so its memory stays near 100 MB a thread whatever the image's size. Memory a process touches for
# the first time costs it a page fault and the page's zeroing: on the development flume's 1728x1152 pair (2 cores)
# four bands of 288 rows instead of two of 576 took the peak memory of a fresh `jaxstereo reconstruct` from 0.96 to
# 0.74 GB and its median time from 2.97 to 2.78 s (seven alternated runs each), though the halos add 10 % of rows.
MAX_BAND_PIXELS = 1 << 19


def available_cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def map_row_bands(fn: Callable[[int, int], tuple], height: int, halo: int, width: int | None = None) -> tuple:
    """`fn(start, stop)` over bands of an image's rows, on threads, stitched into the whole image's result.

    `fn` computes rows `start:stop` of every output (a tuple of arrays (stop - start, ...), or None entries)
    from those rows of its inputs alone, its values exact at least `halo` rows from the band's edges. Each
    band is extended by `halo` rows on both sides (within the image) and only its own rows are kept, so the
    result is the one `fn(0, height)` gives, up to float rounding in sums that run along the columns.
    There is one thread per available core (at most `MAX_BANDS`) and, with the image's `width` (pixels), as many
    bands as that times the fewest that keeps each within `MAX_BAND_PIXELS` (without `width`: one band a
    thread); fewer where a band would be shorter than `MIN_BAND_HALOS` halos.
    """
    threads = min(available_cores(), MAX_BANDS)
    count = threads if width is None else threads * max(1, -(-height * width // (threads * MAX_BAND_PIXELS)))
    count = max(1, min(count, height // max(MIN_BAND_HALOS * halo, 1)))
    if count == 1:
        return fn(0, height)
    edges = [round(height * i / count) for i in range(count + 1)]

    def run(i: int) -> tuple:
        start, stop = max(edges[i] - halo, 0), min(edges[i + 1] + halo, height)
        keep = slice(edges[i] - start, edges[i + 1] - start)
        return tuple(None if part is None else part[keep] for part in fn(start, stop))

    with ThreadPoolExecutor(min(threads, count), thread_name_prefix="row-band") as pool:
        parts = list(pool.map(run, range(count)))
    return tuple(None if first is None else np.concatenate([p[k] for p in parts]) for k, first in enumerate(parts[0]))
