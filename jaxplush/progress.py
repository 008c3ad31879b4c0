"""A minimal text progress bar (stderr), updated between jitted chunks, never inside jit."""

from __future__ import annotations

import sys
import time


class Progress:
    """``with Progress(total, "simulate") as p: p.update(n)``; silent when ``enabled`` is False."""

    def __init__(self, total, label="", enabled=True, stream=None, unit="steps"):
        self.total = max(int(total), 1)
        self.label = label
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.unit = unit
        self.done = 0
        self.t0 = time.perf_counter()
        self.extra = ""

    def __enter__(self):
        self._draw()
        return self

    def update(self, n, extra=""):
        self.done = min(self.done + int(n), self.total)
        self.extra = extra
        self._draw()

    def _draw(self, end=""):
        if not self.enabled:
            return
        frac = self.done / self.total
        width = 30
        bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
        el = time.perf_counter() - self.t0
        rate = self.done / el if el > 0 and self.done else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else float("nan")
        eta_s = f"{eta:5.1f}s" if eta == eta else "  ?  "
        msg = (f"\r{self.label} [{bar}] {100 * frac:5.1f}% {self.done}/{self.total} {self.unit}"
               f" {rate:,.0f}/s eta {eta_s} {self.extra}")
        self.stream.write(msg + end)
        self.stream.flush()

    def __exit__(self, *exc):
        if self.enabled:
            self._draw(end="\n")
        return False
