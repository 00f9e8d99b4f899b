"""Progress of long loops (training, the SDF grid): a live bar on a terminal, and where the output is not a
terminal (a log file, CI) a plain line every few seconds instead of carriage-return redraws.

    with Progress(total=1800, desc="training") as bar:
        for ...:
            bar.set_postfix(loss=0.041)
            bar.update()
"""
from __future__ import annotations

import sys
import time

__all__ = ["Progress"]

DEFAULT_INTERVAL_S = 10.0  # seconds between progress lines when the output is not a terminal


class Progress:
    """Progress toward `total` steps, written to `stream` (default: stderr, as tqdm).

    On a terminal a tqdm bar; otherwise, or when `interval_s` is given, one line every `interval_s` seconds
    (default DEFAULT_INTERVAL_S) and a last one at close (unless the last line showed the final count):
    "desc: done/total unit (pct), rate, time left | postfix".
    enabled=False writes nothing; leave=False clears the bar when done (lines stay).
    """

    def __init__(self, total: int, desc: str, *, unit: str = "it", initial: int = 0, enabled: bool = True,
                 interval_s: float | None = None, leave: bool = True, stream=None, clock=time.monotonic):
        self.total, self.desc, self.unit = int(total), desc, unit
        self.n = int(initial)
        self.enabled = enabled
        self.stream = stream if stream is not None else sys.stderr
        self._clock = clock
        self._postfix = ""
        self._bar = None
        self._closed = False
        is_terminal = bool(getattr(self.stream, "isatty", lambda: False)())
        if enabled and interval_s is None and is_terminal:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, initial=self.n, desc=desc, unit=unit, file=self.stream, dynamic_ncols=True,
                             leave=leave)
        self.interval_s = DEFAULT_INTERVAL_S if interval_s is None else float(interval_s)
        self._t0 = self._last = clock()
        self._n0 = self._n_shown = self.n

    def set_postfix(self, **values) -> None:
        """Values shown after the count (numbers as given: format them first)."""
        if self._bar is not None:
            self._bar.set_postfix(refresh=False, **values)
        self._postfix = " ".join(f"{k} {v}" for k, v in values.items())

    def update(self, n: int = 1) -> None:
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
        elif self.enabled and self._clock() - self._last >= self.interval_s:
            self._line()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()
        elif self.enabled and self.n > self._n_shown:  # the final count, unless the last line showed it
            self._line()

    def _line(self) -> None:
        now = self._clock()
        self._last, self._n_shown = now, self.n
        elapsed = now - self._t0
        rate = (self.n - self._n0) / elapsed if elapsed > 0 else 0.0
        parts = [f"{self.desc}: {self.n}/{self.total} {self.unit} ({self.n / max(self.total, 1):.0%})"]
        if rate > 0:
            parts.append(f"{rate:.3g} {self.unit}/s")
            if self.n < self.total:
                parts.append(f"{_duration((self.total - self.n) / rate)} left")
            else:
                parts.append(f"{_duration(elapsed)} in all")
        line = ", ".join(parts) + (f" | {self._postfix}" if self._postfix else "")
        print(line, file=self.stream, flush=True)

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _duration(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s"
