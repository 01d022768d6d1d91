"""A dependency-free progress bar on standard error for long CLI runs."""

from __future__ import annotations

import sys
import time


class ProgressBar:
    """``with ProgressBar(total, "register") as bar: bar.update(1)``; redraws at most 10 times/s.

    On a terminal it redraws one line; elsewhere (logs, CI) it prints a line every 10 %.
    """

    def __init__(self, total: int, label: str, stream=None) -> None:
        self.total, self.label, self.done = max(int(total), 0), label, 0
        self.stream = stream or sys.stderr
        self.tty = getattr(self.stream, "isatty", lambda: False)()
        self.start = time.monotonic()
        self._last_draw = 0.0
        self._last_decile = -1

    def __enter__(self) -> ProgressBar:
        self._draw(force=True)
        return self

    def __exit__(self, *exc) -> None:
        self._draw(force=True)
        if self.tty:
            self.stream.write("\n")
        self.stream.flush()

    def update(self, n: int = 1, note: str = "") -> None:
        self.done += n
        self.note = note
        self._draw()

    def _draw(self, force: bool = False) -> None:
        now = time.monotonic()
        frac = self.done / self.total if self.total else 1.0
        elapsed = now - self.start
        eta = elapsed / frac - elapsed if frac > 0 else float("nan")
        note = getattr(self, "note", "")
        if self.tty:
            if not force and now - self._last_draw < 0.1:
                return
            width = 30
            fill = int(round(frac * width))
            line = (
                f"\r{self.label} [{'#' * fill}{'.' * (width - fill)}] {self.done}/{self.total} "
                f"{elapsed:5.1f}s eta {eta:5.1f}s {note}"
            )
            self.stream.write(line[:200].ljust(80))
        else:
            decile = int(frac * 10)
            if not force and decile == self._last_decile:
                return
            self._last_decile = decile
            self.stream.write(
                f"{self.label}: {self.done}/{self.total} ({100 * frac:.0f}%) {elapsed:.1f}s {note}\n"
            )
        self._last_draw = now
        self.stream.flush()


class LazyProgressBar:
    """A ``progress(done, total)`` callback that opens its bar on the first report (errors
    raised before any work come as one line, with no bar) and closes it when the work is done;
    :meth:`close` (idempotent) closes it early, e.g. in a ``finally``."""

    def __init__(self, label: str, stream=None):
        self.label, self.stream, self.bar = label, stream, None

    def __call__(self, done: int, total: int) -> None:
        if self.bar is None:
            self.bar = ProgressBar(total, self.label, stream=self.stream).__enter__()
        self.bar.update(done - self.bar.done)
        if done >= total:
            self.close()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.__exit__(None, None, None)
            self.bar = None


def human_size(n: float) -> str:
    """Human-readable byte count (B, kB, MB, GB; 1 kB = 1024 B)."""
    if n < 1024:
        return f"{n:.0f} B"
    for unit, k in (("kB", 1), ("MB", 2), ("GB", 3)):
        if n < 1024 ** (k + 1) or unit == "GB":
            return f"{n / 1024**k:.1f} {unit}"
    raise AssertionError("unreachable")
