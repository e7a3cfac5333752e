"""The command line's one malloc arena (`_app/allocator.py`), seen through glibc's own statistics."""

import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="a glibc setting")

# Four threads allocate and keep arrays below the mmap threshold (from their arenas); glibc's `malloc_stats` then
# prints one "Arena N:" block per arena in use, on stderr.
SCRIPT = """
import ctypes, sys, threading
import numpy as np
if sys.argv[1] == "one":
    from jaxstereo._app.allocator import use_one_malloc_arena
    print(use_one_malloc_arena())
kept = []
threads = [threading.Thread(target=lambda: kept.append([np.ones(8192) for _ in range(10)])) for _ in range(4)]
for t in threads:
    t.start()
for t in threads:
    t.join()
ctypes.CDLL(None).malloc_stats()
"""


def _arenas(mode: str) -> tuple[str, int]:
    done = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, check=True)
    return done.stdout.strip(), sum(line.startswith("Arena ") for line in done.stderr.splitlines())


def test_threads_share_one_arena_once_asked():
    _, default = _arenas("default")
    taken, one = _arenas("one")
    assert default >= 2  # without the setting the threads allocate from arenas of their own
    assert (taken, one) == ("True", 1)


def test_the_command_line_takes_it_before_main(monkeypatch):
    import logging

    from jaxstereo._app import allocator, cli

    calls = []
    monkeypatch.setattr(allocator, "use_one_malloc_arena", lambda: calls.append("arena"))
    monkeypatch.setattr(cli, "main", lambda: calls.append("main") or 0)
    monkeypatch.setattr(logging, "shutdown", lambda: None)  # pytest's own handlers stay open
    monkeypatch.setattr(cli.os, "_exit", lambda status: calls.append(("exit", status)))
    monkeypatch.setattr(sys, "stdout", sys.stdout)
    monkeypatch.setattr(sys, "stderr", sys.stderr)
    cli.run()
    assert calls == ["arena", "main", ("exit", 0)]
