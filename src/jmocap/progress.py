"""Text progress bars for long commands (reconstruct, eval, data synth, training)."""

from __future__ import annotations

import sys
import time


class Progress:
    """A small text progress bar on stderr (redrawn at most 5 times a second) counting items
    and frames; ``rates=True`` shows items/s and frames/s (batch reconstruction)."""

    def __init__(self, total: int, label: str = "", enabled: bool = True, stream=None, *, rates: bool = False,
                 unit: str = "clips"):
        self.total = max(int(total), 0)
        self.label = label
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.rates = rates
        self.unit = unit
        self.n = 0
        self.frames = 0
        self.t0 = time.perf_counter()
        self._last = 0.0

    def update(self, n: int = 1, frames: int = 0) -> None:
        self.n += n
        self.frames += frames
        now = time.perf_counter()
        if self.enabled and (now - self._last > 0.2 or self.n >= self.total):
            self._last = now
            self._draw(now)

    def _draw(self, now: float) -> None:
        el = max(now - self.t0, 1e-9)
        width = 24
        frac = self.n / self.total if self.total else 1.0
        bar = "#" * int(round(frac * width))
        eta = el / self.n * (self.total - self.n) if self.n else 0.0
        if self.rates:
            counts = f"{self.n / el:.2f} {self.unit}/s {self.frames / el:.0f} frames/s"
        else:
            counts = f"{self.frames} frames {self.frames / el:.0f} fr/s"
        self.stream.write(f"\r{self.label} {self.n}/{self.total} [{bar:<{width}}] {counts} {el:.0f}s ETA {eta:.0f}s ")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self._draw(time.perf_counter())
            self.stream.write("\n")
            self.stream.flush()


def progress_bar(label: str = "reconstruct", enabled: bool = True, *, rates: bool = True):
    """A factory ``total -> Progress`` (what batch runs take as ``progress``)."""
    return lambda total: Progress(total, label, enabled=enabled, rates=rates)


__all__ = ["Progress", "progress_bar"]
