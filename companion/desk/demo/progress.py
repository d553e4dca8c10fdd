"""A run's progress on stderr: one line per run, redrawn in place on a terminal, plain lines every
few seconds otherwise."""

from __future__ import annotations

import math
import sys
import time


class Progress:
    """One line per run, redrawn in place on a terminal; plain lines every few seconds otherwise."""

    def __init__(self, stream=None, every_s: float = 5.0):
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s
        self._last = -math.inf
        self._width = 0

    def update(self, text: str, force: bool = False) -> None:
        now = time.monotonic()
        if self.tty:
            if now - self._last < 0.1 and not force:
                return
            pad = max(0, self._width - len(text))
            self.stream.write("\r" + text + " " * pad)
            self._width = len(text)
        else:
            if now - self._last < self.every_s and not force:
                return
            self.stream.write(text + "\n")
        self._last = now
        self.stream.flush()

    def done(self, text: str) -> None:
        self.update(text, force=True)
        if self.tty:
            self.stream.write("\n")
            self._width = 0
        self.stream.flush()

    def say(self, text: str) -> None:
        if self.tty and self._width:
            self.stream.write("\n")
            self._width = 0
        self.stream.write(text + "\n")
        self.stream.flush()


def progress_line(param: str, laps: int, n_laps: int, t_s: float, alt_m: float, tiles: int, frames: int,
                  dropped: int, engaged: bool | None, wall_s: float, lap_fraction: float = 0.0) -> str:
    """``inverse_depth [#####-----] lap 1/3  t 85 s  alt 15.2 m  tiles 34  frames 1200 (0 dropped)  clear  42 s``."""
    total = max(1, n_laps)
    filled = int(round(20 * min(1.0, (laps + min(lap_fraction, 0.99)) / total)))
    state = "-" if engaged is None else ("ENGAGED" if engaged else "clear")
    return (f"{param:>13} [{'#' * filled}{'-' * (20 - filled)}] lap {min(laps + 1, n_laps) if laps < n_laps else n_laps}/{n_laps}"
            f"  t {t_s:5.0f} s  alt {alt_m:5.1f} m  tiles {tiles:3d}  frames {frames:5d} ({dropped} dropped)"
            f"  {state:7s}  wall {wall_s:4.0f} s")
