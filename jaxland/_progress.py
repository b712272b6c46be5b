"""Progress lines on stderr, one writer for every long job (Monte Carlo chunks, design and fit
iterations)."""

from __future__ import annotations

import sys


class ProgressLine:
    """``line(text)`` prints ``"<label> <text>"`` to stderr. ``in_place``: a counter that
    rewrites its line on a terminal (one line per update into a log file, so CI logs stay
    readable); otherwise one line per update. ``quiet`` prints nothing."""

    def __init__(self, label: str, *, quiet: bool = False, in_place: bool = False,
                 stream=None):
        self.label, self.quiet = label, quiet
        self.stream = sys.stderr if stream is None else stream
        self.in_place = in_place and self.stream.isatty()
        self._open = False

    def __call__(self, text: str) -> None:
        if self.quiet:
            return
        if self.in_place:
            print(f"\r{self.label} {text}", end="", file=self.stream, flush=True)
            self._open = True
        else:
            print(f"{self.label} {text}", file=self.stream, flush=True)

    def close(self) -> None:
        """End an in-place line."""
        if self._open:
            print(file=self.stream, flush=True)
            self._open = False
