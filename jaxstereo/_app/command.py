"""The `jaxstereo` console command's entry point (and `python -m jaxstereo`'s): what the command's own process
must set before numpy is loaded, then `cli.run`.

numpy's OpenBLAS starts a thread per core as it loads, and an idle OpenBLAS thread waits for work by spinning
(yielding its core in a loop) for a while before it sleeps. A fresh `jaxstereo reconstruct` makes no BLAS call
that a second thread would speed up (its matrix products are 3 x 3 rotations of point lists), yet on 2 cores one
such thread spun for about 0.1 s of CPU while the images decoded and JAX was imported (`perf record`). With one
OpenBLAS thread (`OPENBLAS_NUM_THREADS=1`, only where the user has not set it), the command on the development
flume's 1728x1152 pair took a median 2.25 s against 2.395 s, 3.80 CPU-s against 4.07 (12 alternated runs each).

Only the command's own process, and only `reconstruct` (the other commands were not measured): the library, and
a caller running commands in its own process, keep OpenBLAS as they set it. No numpy here: it is not loaded yet.
"""

from __future__ import annotations

import os
import sys


def prepare_process(argv: list[str]) -> None:
    """Set what must precede numpy's loading for the command `argv` names (`sys.argv`: program, command, ...)."""
    if len(argv) > 1 and argv[1] == "reconstruct":
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def run() -> None:
    """The `jaxstereo` command: `prepare_process`, then `cli.run` (which ends the process)."""
    prepare_process(sys.argv)
    from .cli import run as run_command

    run_command()
