"""A small progress reporter: a text bar on a terminal (or plain lines in logs), and an optional
callback so that Blender's UI (or anything else) can show the same progress."""
from __future__ import annotations

import sys
import time
from typing import Callable, Optional


class Progress:
    """Usage: ``with Progress(total, "fit") as bar: bar.update(1, psnr=31.2)``."""

    def __init__(self, total: int, desc: str = "", callback: Optional[Callable[[float, str], None]] = None,
                 stream=None, enabled: bool = True, min_interval: float = 0.5):
        self.total = max(int(total), 1)
        self.desc = desc
        self.callback = callback
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.min_interval = min_interval
        self.n = 0
        self.start = time.perf_counter()
        self._last = 0.0
        self.info = ""
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        if not self._tty:  # a log file: a line every few seconds, not a redraw every half second
            self.min_interval = max(min_interval, 10.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def set_fraction(self, frac: float, **info) -> None:
        """Time-budgeted work: report progress as a fraction of the budget instead of counted items."""
        self.update(max(int(frac * self.total) - self.n, 0), **info)

    def update(self, n: int = 1, **info) -> None:
        self.n = min(self.n + n, self.total)
        if info:
            self.info = "  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in info.items())
        now = time.perf_counter()
        if self.callback is not None:
            self.callback(self.n / self.total, self.info)
        if self.enabled and (now - self._last >= self.min_interval or self.n == self.total):
            self._last = now
            self._draw()

    def _draw(self, end: str = "") -> None:
        frac = self.n / self.total
        el = self.elapsed
        eta = el / frac - el if frac > 0 else float("nan")
        width = 24
        bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
        line = f"{self.desc} [{bar}] {self.n}/{self.total} {el:6.1f}s eta {eta:5.0f}s {self.info}"
        if self._tty:
            self.stream.write("\r" + line[:160] + end)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self._tty:
            self._draw(end="\n")
