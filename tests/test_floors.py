"""The dependency floors in pyproject.toml and the pins of the lowest-versions job (.ci/lowest.txt) agree."""

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _floors() -> dict[str, str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    specs = project["dependencies"] + project["optional-dependencies"]["test"]
    floors = {}
    for spec in specs:
        m = re.fullmatch(r"([A-Za-z0-9_.-]+)(\[[^\]]*\])?>=([0-9][0-9.]*)", spec.replace(" ", ""))
        assert m, f"dependency without a floor: {spec!r}"
        floors[m.group(1).lower()] = m.group(3)
    return floors


def _pins() -> dict[str, str]:
    pins = {}
    for line in (ROOT / ".ci" / "lowest.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, version = line.split("==")
            pins[name.lower()] = version
    return pins


def _release(version: str) -> tuple[int, ...]:
    return tuple(int(p) for p in version.split(".") if p.isdigit())


def test_every_runtime_dependency_is_pinned_at_its_floor():
    floors, pins = _floors(), _pins()
    runtime = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    for spec in runtime:
        name = re.match(r"[A-Za-z0-9_.-]+", spec).group(0).lower()
        assert name in pins, f"{name} is not pinned in .ci/lowest.txt"
        floor, pin = _release(floors[name]), _release(pins[name])
        assert pin[: len(floor)] == floor, f"{name}: floor {floors[name]} but .ci/lowest.txt pins {pins[name]}"


def test_the_readme_test_command_runs_the_lowest_job_and_ci_runs_the_readme():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    command = ci.strip().splitlines()[-1]
    assert command in readme
    assert ".ci/lowest" in command
