"""A minimal text progress bar (stderr), updated between jitted chunks, never inside jit."""

from __future__ import annotations

import sys
import time


def _rate(r):
    """A rate with three significant figures (0.312, 41.7, 54,000)."""
    if r >= 1000:
        return f"{r:,.0f}"
    return f"{r:.3g}"


class Progress:
    """``with Progress(total, "simulate") as p: p.update(n)``; silent when ``enabled`` is False.

    While running it shows the fraction done, the rate and the time left. When the block ends
    it draws a final line with the elapsed time instead of an estimate: all ``total`` units
    done, or where it stopped early (a fit that converged before its iteration limit, a run
    that failed) and, if :meth:`finish` was called, why.
    """

    def __init__(self, total, label="", enabled=True, stream=None, unit="steps"):
        self.total = max(int(total), 1)
        self.label = label
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.unit = unit
        self.done = 0
        self.t0 = time.perf_counter()
        self.extra = ""
        self.outcome = None

    def __enter__(self):
        self._draw()
        return self

    def update(self, n, extra=""):
        self.done = min(self.done + int(n), self.total)
        self.extra = extra
        self._draw()

    def finish(self, outcome):
        """Say how the work ended (shown on the final line), e.g. "converged"."""
        self.outcome = outcome

    def _bar(self, frac):
        width = 30
        return "#" * int(frac * width) + "-" * (width - int(frac * width))

    def _draw(self, end=""):
        if not self.enabled:
            return
        frac = self.done / self.total
        el = time.perf_counter() - self.t0
        rate = self.done / el if el > 0 and self.done else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else float("nan")
        eta_s = f"{eta:5.1f}s" if eta == eta else "  ?  "
        msg = (f"\r{self.label} [{self._bar(frac)}] {100 * frac:5.1f}% {self.done}/{self.total} {self.unit}"
               f" {_rate(rate)}/s eta {eta_s} {self.extra}")
        self.stream.write(msg + end)
        self.stream.flush()

    def _draw_final(self):
        el = time.perf_counter() - self.t0
        rate = self.done / el if el > 0 else 0.0
        if self.done >= self.total:
            what = f"{self.done} {self.unit} in {el:.1f} s ({_rate(rate)}/s)"
            bar = self._bar(1.0)
        else:
            what = f"stopped at {self.done}/{self.total} {self.unit} after {el:.1f} s"
            bar = self._bar(self.done / self.total)
        why = f": {self.outcome}" if self.outcome else ""
        tail = f" {self.extra}" if self.extra else ""
        # pad so that the final line covers the longer running line it replaces
        self.stream.write(f"\r{self.label} [{bar}] {what}{why}{tail}".ljust(100) + "\n")
        self.stream.flush()

    def __exit__(self, *exc):
        if self.enabled:
            self._draw_final()
        return False
