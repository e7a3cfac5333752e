"""The command line's one malloc arena (`_app/allocator.py`), seen through glibc's own statistics."""

import os
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


def test_a_repeated_reconstruct_takes_it_before_any_thread_and_every_reconstruct_keeps_freed_memory(
        monkeypatch, tmp_path):
    from jaxstereo._app import allocator, cli
    from jaxstereo._app.parser import build_parser

    monkeypatch.setenv("JAXSTEREO_CACHE_DIR", str(tmp_path / "cache"))
    rig = tmp_path / "rig.json"
    rig.write_text("{}")
    argv = ["reconstruct", "L.png", "R.png", "--rig", str(rig), "--water-level", "0.16", "-o", str(tmp_path / "s.npz")]
    calls = []
    monkeypatch.setattr(allocator, "use_one_malloc_arena", lambda: calls.append("arena"))
    monkeypatch.setattr(cli, "_read_images_ahead", lambda args: calls.append("threads") or {})
    monkeypatch.setattr(cli, "_match_ahead", lambda plan, reading, args: None)
    monkeypatch.setattr(cli, "_cmd_reconstruct", lambda args: 0)
    monkeypatch.setattr(cli, "keep_freed_memory", lambda: calls.append("keep"))
    for setting in ("collect_garbage_rarely", "switch_threads_often", "keep_arrays_on_small_pages"):
        monkeypatch.setattr(cli, setting, lambda: None)  # the command's own process's, not pytest's

    def run(own_process: bool) -> list:
        calls.clear()
        assert cli.main(argv, own_process=own_process) == 0
        return list(calls)

    assert run(True) == ["keep", "threads"]  # the first: it compiles, and one arena would slow that down
    plan = cli._match_plan(build_parser().parse_args(argv))
    plan.parent.mkdir(parents=True)
    plan.write_bytes(b"kept by an earlier command")
    assert run(True) == ["keep", "arena", "threads"]
    assert run(False) == ["threads"]  # a caller's own process (these tests) keeps its allocator


# A command whose handler reports whether numpy asks for huge pages as the command found it (numpy's switch
# returns its previous state).
HUGE_PAGES_SCRIPT = """
import sys
from numpy._core.multiarray import _set_madvise_hugepage
from jaxstereo._app import cli
before = _set_madvise_hugepage(True)
report = lambda args: print(before, _set_madvise_hugepage(True)) or 0
cli._cmd_reconstruct = cli._cmd_grid = report
command = {"reconstruct": ["reconstruct", "l.png", "r.png", "--rig", "rig.json", "-o", "s.npz"],
           "grid": ["grid", "survey.npz", "-o", "dem.npz"]}[sys.argv[2]]
sys.exit(cli.main(command, own_process=sys.argv[1] == "own"))
"""


def _huge_pages(mode: str, command: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    env["JAXSTEREO_CACHE_DIR"] = "off"  # no match plan, no disk caches: nothing of the user's is touched
    done = subprocess.run([sys.executable, "-c", HUGE_PAGES_SCRIPT, mode, command], capture_output=True, text=True,
                          check=True, env=env)
    return done.stdout.strip()


def test_the_reconstruct_commands_own_process_keeps_numpys_arrays_on_small_pages():
    assert _huge_pages("own", "reconstruct") == "True False"  # asked for by default; no more in the command
    assert _huge_pages("library", "reconstruct") == "True True"  # a caller's process keeps numpy's setting
    assert _huge_pages("own", "grid") == "True True"  # the other commands were not measured


# An 8 MB array allocated, freed and allocated again: glibc serves it from fresh kernel pages each time (mmap: above
# its starting threshold, then equal to the threshold the first one's freeing set) unless the heap keeps it. Prints
# the minor page faults of the second allocation.
REUSE_SCRIPT = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from jaxstereo._app.allocator import keep_freed_memory
    assert keep_freed_memory()
first = np.ones(1 << 20)
del first
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
second = np.ones(1 << 20)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> int:
    env = {**os.environ, "NUMPY_MADVISE_HUGEPAGE": "0"}  # small pages: one fault per 4 KB page
    done = subprocess.run([sys.executable, "-c", REUSE_SCRIPT, mode], capture_output=True, text=True, check=True,
                          env=env)
    return int(done.stdout)


def test_freed_memory_is_kept_for_the_next_allocation():
    pages = (8 << 20) // 4096
    assert _faults("default") > pages // 2  # fresh pages from the kernel, each faulted in (2035 measured)
    assert _faults("keep") < pages // 20  # the heap's own, already faulted in (0 measured)
