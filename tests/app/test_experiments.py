"""The experiments run from the command line and write their tables; the README updater splices them."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from experiments.__main__ import main, update_readme  # noqa: E402


def test_incidence_limit_experiment_and_readme_update(tmp_path):
    assert main(["incidence-limit", "--out", str(tmp_path)]) == 0
    table = (tmp_path / "incidence-limit" / "table.md").read_text()
    row = next(line for line in table.splitlines() if line.startswith("| 0.3 |"))
    assert row.split("|")[2].strip() == "0.405"  # the angular error at 20 deg
    assert (tmp_path / "incidence-limit" / "incidence_limit.png").stat().st_size > 0
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\n## Results\n\n<!-- results:start -->\nSTALE-TABLE\n<!-- results:end -->\n\nafter\n")
    update_readme(tmp_path, readme)
    text = readme.read_text()
    assert "STALE-TABLE" not in text and "| 0.3 | 0.405 |" in text and text.endswith("after\n")
