"""The `jaxstereo reconstruct` command's GIL switch interval: a thread waiting for the GIL gets it sooner.

A fresh `reconstruct` works on several threads at once. Its numpy, OpenCV and XLA steps leave the GIL while an
array operation runs and need it back between operations and chunks; the Python work beside them (drawing the
preview while the points' errors are propagated, tracing while the pair is matched; until round 70 importing
matplotlib for the preview while the points were triangulated) keeps the GIL until CPython's switch interval
forces a switch, 5 ms by default. A step made of many short operations then waits up to that long before each,
with a core idle. At 0.5 ms (`SWITCH_INTERVAL_S`), a fresh command on the development flume's 1728x1152 pair (2
cores) took a median 2.47 s against 2.58 s (12 alternated runs each; 2.475 against 2.53 s in 10 more, and as the
command: 2.46 against 2.54 s in 12 more); 1 ms gained nothing, 0.2 ms no more than 0.5 ms.

Set by `cli.main` for the `jaxstereo reconstruct` command only (its process is the command's alone, and the
other commands were not measured); the library, and a caller running commands in its own process, keep theirs.
"""

from __future__ import annotations

import sys

SWITCH_INTERVAL_S = 0.0005


def switch_threads_often() -> None:
    """Set the interpreter's thread switch interval to `SWITCH_INTERVAL_S` (CPython's default: 5 ms)."""
    sys.setswitchinterval(SWITCH_INTERVAL_S)
