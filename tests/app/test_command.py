"""The `jaxstereo` command's entry point (`_app/command.py`): one OpenBLAS thread for `reconstruct`'s own process."""

import os
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import pytest

import jaxstereo

# Prepares the process for the command named in argv[1], loads numpy, and reports the setting and the process's
# native threads (Linux: /proc/self/task), numpy's OpenBLAS threads among them.
SCRIPT = """
import os, sys
from jaxstereo._app.command import prepare_process
assert "numpy" not in sys.modules  # the entry point itself loads no numpy
prepare_process(["jaxstereo", sys.argv[1]])
import numpy
print(os.environ.get("OPENBLAS_NUM_THREADS"), len(os.listdir("/proc/self/task")))
"""


def _prepared(command: str, **env) -> tuple[str, int]:
    environment = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    done = subprocess.run([sys.executable, "-c", SCRIPT, command], capture_output=True, text=True, check=True,
                          env={**environment, **env})
    setting, threads = done.stdout.split()
    return setting, int(threads)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="counts threads in /proc")
def test_reconstruct_loads_numpy_with_one_openblas_thread_and_the_user_setting_stands():
    assert _prepared("reconstruct") == ("1", 1)  # the main thread alone
    other, default_threads = _prepared("grid")
    assert other == "None"  # the other commands leave OpenBLAS as it is
    if os.cpu_count() > 1:
        assert default_threads > 1  # numpy's OpenBLAS threads, which reconstruct does without
    assert _prepared("reconstruct", OPENBLAS_NUM_THREADS="2")[0] == "2"


def test_the_console_command_and_python_m_enter_there():
    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "jaxstereo"]
    assert script.value == "jaxstereo._app.command:run"
    assert "from ._app.command import run" in (Path(jaxstereo.__file__).parent / "__main__.py").read_text()


def test_version_names_jaxstereo_and_the_packages_it_runs_on():
    import tomllib
    from importlib import metadata

    done = subprocess.run([sys.executable, "-m", "jaxstereo", "--version"], capture_output=True, text=True, check=True)
    lines = done.stdout.splitlines()
    project = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())["project"]
    assert jaxstereo.__version__ == project["version"] == metadata.version("jaxstereo")
    assert lines[0] == f"jaxstereo {jaxstereo.__version__}"
    # each dependency pyproject names, at the version installed
    for requirement in project["dependencies"]:
        name = requirement.split(">")[0].split("=")[0].split("<")[0].strip()
        assert f"  {name} {metadata.version(name)}" in lines, (name, lines)
