"""The `jaxstereo` command's garbage collector setting (`_app/garbage.py`): its own process only."""

import subprocess
import sys

# A command whose handler reports the collector's state as the command found it.
SCRIPT = """
import gc, sys
from jaxstereo._app import cli
cli._cmd_grid = lambda args: print(gc.get_threshold(), gc.get_freeze_count()) or 0
sys.exit(cli.main(["grid", "survey.npz", "-o", "dem.npz"], own_process=sys.argv[1] == "own"))
"""


def _collector(mode: str) -> tuple[tuple[int, ...], int]:
    done = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, check=True)
    threshold, frozen = done.stdout.strip().rsplit(" ", 1)
    return tuple(int(k) for k in threshold.strip("()").split(",")), int(frozen)


def test_the_command_collects_rarely_with_jax_set_aside_and_a_caller_keeps_its_own_collector():
    from jaxstereo._app.garbage import THRESHOLDS

    threshold, frozen = _collector("own")
    assert threshold == THRESHOLDS
    assert frozen > 50_000  # JAX's modules and jaxstereo's: about 90,000 objects after importing JAX
    default, none = _collector("library")
    assert default != THRESHOLDS and none == 0  # the interpreter's default (700, 10, 10 in 3.11), nothing set aside
