"""The progress of a sweep on stderr: a bar redrawn in place on a terminal, one plain line per
finished trial otherwise (logs, CI)."""

from __future__ import annotations

import sys
import time
from typing import Any, TextIO

BAR_WIDTH = 24


class Progress:
    """Running count, failures and ETA of ``total`` trials."""

    def __init__(self, total: int, stream: TextIO | None = None, skipped: int = 0) -> None:
        self.total, self.done, self.failed = total, skipped, 0
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self.start = time.monotonic()
        self.ran = 0
        if skipped:
            self._line(f"{skipped} trial(s) already done (--resume)")
        if self.tty:
            self._draw()

    def update(self, row: dict[str, Any]) -> None:
        """One trial finished."""
        self.done += 1
        self.ran += 1
        self.failed += row["status"] == "failed"
        status = f"{row['name']}: {row['status']}"
        if row["status"] == "failed":
            status += f" ({row.get('error', '')})"
        if self.tty:
            if row["status"] == "failed":
                self.stream.write(f"\r\x1b[2K{status}\n")
            self._draw()
        else:
            self._line(f"{self.summary()}; {status}")

    def _draw(self) -> None:
        filled = round(BAR_WIDTH * self.done / max(self.total, 1))
        bar = "#" * filled + "." * (BAR_WIDTH - filled)
        self.stream.write(f"\r\x1b[2K[{bar}] {self.summary()}")
        self.stream.flush()

    def summary(self) -> str:
        return f"{self.done}/{self.total} trials, {self.failed} failed, ETA {self.eta()}"

    def eta(self) -> str:
        left = self.total - self.done
        if left == 0:
            return "0 s"
        if self.ran == 0:
            return "?"
        seconds = (time.monotonic() - self.start) / self.ran * left
        return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()

    def _line(self, text: str) -> None:
        self.stream.write(f"hil sweep: {text}\n")
        self.stream.flush()
