"""A dependency-free progress bar with an estimate of the time left (stderr)."""

from __future__ import annotations

import sys
import time


def format_seconds(seconds: float) -> str:
    """`75.2` -> `"1m15s"`; `3725` -> `"1h02m"`; under a minute `"12.3s"`."""
    if seconds != seconds or seconds < 0:
        return "?"
    if seconds < 60:
        return f"{seconds:.1f}s"
    minutes, secs = divmod(int(round(seconds)), 60)
    if minutes < 60:
        return f"{minutes}m{secs:02d}s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h{minutes:02d}m"


class Progress:
    """Progress over `total` items. `advance(label, worked=True)` after each item; items that were
    skipped (`worked=False`) do not count towards the time per item used for the estimate.

    On a terminal the bar redraws in place; otherwise (logs, CI) each step prints one line.
    """

    def __init__(self, total: int, what: str = "items", stream=None, width: int = 28):
        self.total = total
        self.what = what
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.done = 0
        self.worked = 0
        self.started = time.perf_counter()
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def eta_seconds(self) -> float:
        """Seconds left: the mean wall time per worked item times the items left (NaN before any)."""
        if self.worked == 0:
            return float("nan")
        return (time.perf_counter() - self.started) / self.worked * (self.total - self.done)

    def advance(self, label: str = "", worked: bool = True) -> str:
        """Count one item done; draw and return the line."""
        self.done += 1
        self.worked += int(worked)
        filled = int(round(self.width * self.done / max(self.total, 1)))
        elapsed = time.perf_counter() - self.started
        rate = f"{elapsed / self.worked:.1f} s/{self.what[:-1] if self.what.endswith('s') else self.what}" \
            if self.worked else "-"
        line = (f"[{'#' * filled}{'.' * (self.width - filled)}] {self.done}/{self.total} {self.what}  {rate}  "
                f"elapsed {format_seconds(elapsed)}  left {format_seconds(self.eta_seconds())}  {label}")
        if self.tty:
            self.stream.write("\r" + line[:160].ljust(160))
            if self.done == self.total:
                self.stream.write("\n")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
        return line
