"""A minimal text progress bar (stderr), updated between jitted chunks, never inside jit.

On a terminal the bar redraws itself in place (carriage returns). Anywhere else (a CI log,
``2> fit.log``, a notebook's captured stderr) redraws would pile up on one line, so it writes
plain lines instead: one at most every :data:`LOG_INTERVAL` seconds while it runs, and always
the final line, so a stage that takes less than that leaves exactly one line.
"""

from __future__ import annotations

import sys
import time

#: Seconds between two progress lines when the stream is not a terminal.
LOG_INTERVAL = 10.0
_clock = time.perf_counter


def _is_terminal(stream):
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):     # no isatty, or a closed stream
        return False


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

    def __init__(self, total, label="", enabled=True, stream=None, unit="steps", interactive=None,
                 interval=None, compiles=False):
        """``interactive``: redraw in place; by default when the stream is a terminal.
        ``interval``: seconds between plain lines when not interactive (:data:`LOG_INTERVAL`).
        ``compiles``: the final line also says how much of the elapsed time went to XLA compiles
        and how many programs were compiled (:mod:`jaxplush.compilestats`)."""
        self.total = max(int(total), 1)
        self.label = label
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.unit = unit
        self.done = 0
        self.t0 = _clock()
        self.extra = ""
        self.outcome = None
        self.interactive = _is_terminal(self.stream) if interactive is None else bool(interactive)
        self.interval = LOG_INTERVAL if interval is None else float(interval)
        self._last_line = self.t0
        self.clock = None
        if compiles and enabled:
            from jaxplush.compilestats import compile_clock
            self.clock = compile_clock()

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

    def _draw(self):
        if not self.enabled:
            return
        now = _clock()
        if not self.interactive:
            if now - self._last_line < self.interval:
                return
            self._last_line = now
        frac = self.done / self.total
        el = now - self.t0
        rate = self.done / el if el > 0 and self.done else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else float("nan")
        eta_s = f"{eta:5.1f}s" if eta == eta else "  ?  "
        msg = (f"{self.label} [{self._bar(frac)}] {100 * frac:5.1f}% {self.done}/{self.total} {self.unit}"
               f" {_rate(rate)}/s eta {eta_s} {self.extra}")
        self.stream.write(("\r" + msg) if self.interactive else (msg.rstrip() + "\n"))
        self.stream.flush()

    def _draw_final(self):
        el = _clock() - self.t0
        rate = self.done / el if el > 0 else 0.0
        if self.done >= self.total:
            what = f"{self.done} {self.unit} in {el:.1f} s ({_rate(rate)}/s)"
            bar = self._bar(1.0)
        else:
            what = f"stopped at {self.done}/{self.total} {self.unit} after {el:.1f} s"
            bar = self._bar(self.done / self.total)
        why = f": {self.outcome}" if self.outcome else ""
        tail = f" {self.extra}" if self.extra else ""
        if self.clock is not None:
            t = self.clock.stop()
            what += (f", XLA compiles {t.compile_s:.1f} s ({t.programs} program{'' if t.programs == 1 else 's'})"
                     if t.programs else ", no XLA compiles")
        line = f"{self.label} [{bar}] {what}{why}{tail}"
        # on a terminal, pad so that the final line covers the longer running line it replaces
        self.stream.write(("\r" + line.ljust(99)) if self.interactive else line)
        self.stream.write("\n")
        self.stream.flush()

    def __exit__(self, *exc):
        if self.enabled:
            self._draw_final()
        return False
