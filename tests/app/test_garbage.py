"""The `jaxstereo` command's garbage collector setting (`_app/garbage.py`): its own process only."""

import subprocess
import sys

# A command whose handler reports the collector's state as the command found it, after the state the process
# started with.
SCRIPT = """
import gc, sys
print(gc.get_threshold(), gc.get_freeze_count())
from jaxstereo._app import cli
cli._cmd_grid = lambda args: print(gc.get_threshold(), gc.get_freeze_count()) or 0
sys.exit(cli.main(["grid", "survey.npz", "-o", "dem.npz"], own_process=sys.argv[1] == "own"))
"""


def _collector(mode: str) -> list[tuple[tuple[int, ...], int]]:
    """(threshold, objects frozen) at the process's start, then in the command's handler."""
    done = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, check=True)
    states = []
    for line in done.stdout.strip().splitlines():
        threshold, frozen = line.rsplit(" ", 1)
        states.append((tuple(int(k) for k in threshold.strip("()").split(",")), int(frozen)))
    return states


def test_the_command_collects_rarely_with_jax_set_aside_and_a_caller_keeps_its_own_collector():
    from jaxstereo._app.garbage import THRESHOLDS

    (default, at_start), (threshold, frozen) = _collector("own")
    assert default != THRESHOLDS and threshold == THRESHOLDS  # the interpreter's default: (700, 10, 10) in 3.11
    # JAX's modules and jaxstereo's: about 90,000 objects after importing JAX. An interpreter may start with some
    # frozen already (the Python 3.12 of an H100 machine's image: 375, even with `-S`).
    assert frozen - at_start > 50_000
    assert _collector("library") == [(default, at_start)] * 2  # as the process started: nothing set, nothing frozen
