"""Shared helpers for the experiments: output folders, tables, progress lines."""

from __future__ import annotations

import csv
import io
import time
from pathlib import Path

from jaxstereo._app.io import write_text_atomic


class Output:
    """An experiment's output folder, with helpers to write its table and log progress."""

    def __init__(self, root, name: str):
        self.dir = Path(root) / name
        self.dir.mkdir(parents=True, exist_ok=True)
        self.name = name
        self.started = time.perf_counter()

    def log(self, message: str) -> None:
        print(f"[{self.name} {time.perf_counter() - self.started:6.1f} s] {message}", flush=True)

    def table(self, header: list[str], rows: list[list], title: str, notes: str = "", name: str = "table") -> str:
        """Write `<name>.md` and `<name>.csv`; returns the Markdown."""
        md = [f"**{title}**", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        md += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
        if notes:
            md += ["", notes]
        text = "\n".join(md) + "\n"
        write_text_atomic(self.dir / f"{name}.md", text)
        buf = io.StringIO()
        writer = csv.writer(buf)
        writer.writerow(header)
        writer.writerows(rows)
        write_text_atomic(self.dir / f"{name}.csv", buf.getvalue())
        return text
