"""The `jaxstereo` command's Python garbage collector: fewer, cheaper cycle collections.

CPython's cyclic collector runs after every 700 new container objects, and every tenth or hundredth time it walks
older generations too, up to every object alive. A command imports JAX and jaxstereo (about 110,000 objects) and
traces its functions, which allocates objects by the hundred thousand: a fresh `jaxstereo reconstruct` of the
POV-Ray flume's 1728x1152 pair ran 371 collections, 3 of them over everything, for 0.21 s, each holding the GIL
that the threads matching and loading beside it need. With young collections 14 times rarer and full ones 285
times (`THRESHOLDS`), and the modules imported set aside once JAX is loaded (`gc.freeze`, by `cli.main`: they
live as long as the process), it ran 62 young ones for 0.04 s (fresh commands, alternated eight times each with
the default: median 2.85 s against 2.95 s). Cycles are still collected, so a long `jaxstereo batch` does not
grow.

Set by `cli.main` for the `jaxstereo` command only (its process is the command's alone); the library, and a
caller running commands in its own process, keep their collector as it is.
"""

from __future__ import annotations

import gc

THRESHOLDS = (10_000, 20, 100)  # new objects before a young collection; young ones before a middle; middle ones


def collect_garbage_rarely() -> None:
    """Make the cyclic garbage collector's young collections 14 times rarer than CPython's default (700, 10,
    10), its full ones 285 times."""
    gc.set_threshold(*THRESHOLDS)
