"""Progress bars for long commands (reconstruct, eval, data synth, training): one interface over
tqdm, counting items and, where there are any, frames (shown as a frames/s rate)."""

from __future__ import annotations

import sys
import time

from tqdm import tqdm


class Progress:
    """A progress bar on stderr: ``update(items, frames)``, ``set_label(text)``, ``close()``.
    Disabled (``enabled=False``) it draws nothing and still counts."""

    def __init__(self, total: int, label: str = "", enabled: bool = True, stream=None, *, unit: str = "clip"):
        self.total = max(int(total), 0)
        self.n = 0
        self.frames = 0
        self.t0 = time.perf_counter()
        self._bar = tqdm(total=self.total, desc=label, unit=unit, disable=not enabled, file=stream or sys.stderr,
                         mininterval=0.2, dynamic_ncols=True)

    def update(self, n: int = 1, frames: int = 0) -> None:
        self.n += n
        self.frames += frames
        if self.frames:
            el = max(time.perf_counter() - self.t0, 1e-9)
            self._bar.set_postfix_str(f"{self.frames} frames, {self.frames / el:.0f} frames/s", refresh=False)
        self._bar.update(n)

    def set_label(self, text: str) -> None:
        self._bar.set_description(text)

    def close(self) -> None:
        self._bar.close()


def progress_bar(label: str = "reconstruct", enabled: bool = True, *, unit: str = "clip"):
    """A factory ``total -> Progress`` (what batch runs take as ``progress``)."""
    return lambda total: Progress(total, label, enabled=enabled, unit=unit)


__all__ = ["Progress", "progress_bar"]
