"""The `jaxstereo reconstruct` command's GIL switch interval (`_app/gil.py`): its own process only."""

import subprocess
import sys

# A command whose handler reports the switch interval as the command found it.
SCRIPT = """
import sys
from jaxstereo._app import cli
report = lambda args: print(sys.getswitchinterval()) or 0
cli._cmd_reconstruct = cli._cmd_grid = report
command = {"reconstruct": ["reconstruct", "l.png", "r.png", "--rig", "rig.json", "-o", "s.npz"],
           "grid": ["grid", "survey.npz", "-o", "dem.npz"]}[sys.argv[2]]
sys.exit(cli.main(command, own_process=sys.argv[1] == "own"))
"""


def _interval(mode: str, command: str) -> float:
    done = subprocess.run([sys.executable, "-c", SCRIPT, mode, command], capture_output=True, text=True, check=True)
    return float(done.stdout.strip())


def test_reconstruct_switches_threads_often_and_a_caller_or_another_command_keeps_the_default():
    from jaxstereo._app.gil import SWITCH_INTERVAL_S

    default = 0.005  # CPython's, in each fresh process
    assert _interval("own", "reconstruct") == SWITCH_INTERVAL_S < default
    assert _interval("library", "reconstruct") == default
    assert _interval("own", "grid") == default
