"""Progress of long work: each stage logged and timed, a tqdm bar on a terminal, plain log lines in a batch log."""
from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

from tqdm import tqdm

log = logging.getLogger(__name__)


@contextmanager
def stage(name: str, timings: dict) -> Iterator[None]:
    """Log the start and duration of a stage and record its seconds in ``timings[name]``."""
    log.info("%s ...", name)
    t0 = time.perf_counter()
    yield
    timings[name] = time.perf_counter() - t0
    log.info("%s: %.2f s", name, timings[name])


class Progress:
    """Count work units of one stage.

    On a terminal this is a tqdm bar. Elsewhere (cluster batch logs, CI) it writes a log line at most
    every ``interval`` seconds and one at the end, so that the log reads as a sequence of sentences.

    Parameters
    ----------
    desc : str
        What is being counted.
    total : int, optional
        Expected units (None: unknown).
    unit : str
    enabled : bool or None
        Force on/off; None decides by whether stderr is a terminal.
    interval : float
        Seconds between log lines when not on a terminal.
    """

    def __init__(self, desc: str, total: int | None = None, *, unit: str = "it", enabled: bool | None = None,
                 interval: float = 10.0):
        self.desc, self.total, self.unit, self.interval = desc, total, unit, interval
        self.n, self.start, self.last = 0, time.monotonic(), time.monotonic()
        self.postfix = ""
        tty = sys.stderr.isatty() if enabled is None else enabled
        self.bar = tqdm(total=total, desc=desc, unit=unit, leave=False, file=sys.stderr) if tty else None

    def update(self, n: int = 1, *, status: str | None = None) -> None:
        """Add ``n`` units; ``status`` is a short text shown beside the count."""
        self.n += n
        if status is not None:
            self.postfix = status
        if self.bar is not None:
            self.bar.update(n)
            if status is not None:
                self.bar.set_postfix_str(status, refresh=False)
        elif time.monotonic() - self.last >= self.interval:
            self.last = time.monotonic()
            log.info("%s: %s", self.desc, self._text())

    def _text(self) -> str:
        of = f"/{self.total}" if self.total else ""
        extra = f", {self.postfix}" if self.postfix else ""
        return f"{self.n}{of} {self.unit} in {time.monotonic() - self.start:.1f} s{extra}"

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        log.info("%s: done, %s", self.desc, self._text())

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
