"""Progress of a sweep on standard error: a tqdm bar on a terminal, a few plain lines elsewhere.

Off a terminal (CI logs, ``> log 2>&1``) a tqdm bar is one huge line of carriage returns, so
the progress is printed as at most ~12 ordinary lines: every 10% of the work, and at least
every ``interval`` seconds. Tasks carry a ``cost`` (relative work, e.g. proportional to the
dataset size), and both the bar and the lines count cost rather than tasks: when the tasks of a
sweep differ by orders of magnitude (the ``rates`` figure grows K from 100 to 100,000), the
remaining-time estimate is then an honest one rather than the count of cheap tasks done first.
"""

from __future__ import annotations

import sys
import time

__all__ = ["SweepProgress"]


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class SweepProgress:
    """Cost-weighted progress of ``n`` tasks whose costs sum to ``total``.

    Parameters
    ----------
    total : float
        Sum of the task costs.
    n : int
        Number of tasks.
    label : str
    enabled : bool
        False: print nothing.
    stream : file, optional
        Default ``sys.stderr``.
    tty : bool, optional
        Force the terminal (tqdm) or plain-line mode; default: ``stream.isatty()``.
    interval : float
        Off a terminal, the longest silence between two lines (seconds).

    Examples
    --------
    >>> import io
    >>> out = io.StringIO()
    >>> p = SweepProgress(total=4.0, n=2, label="demo", stream=out, tty=False)
    >>> p.advance(1.0); p.advance(3.0); p.close()
    >>> print(out.getvalue().count("\\n"), "\\r" in out.getvalue())
    2 False
    >>> out.getvalue().splitlines()[-1].startswith("[demo] 100% (2/2 tasks)")
    True
    """

    def __init__(self, total: float, n: int, label: str, enabled: bool = True, *,
                 stream=None, tty: bool | None = None, interval: float = 60.0):
        self.total = float(total) if total > 0 else 1.0
        self.n = int(n)
        self.label = label
        self.enabled = enabled and n > 0
        self.stream = stream if stream is not None else sys.stderr
        if tty is None:
            isatty = getattr(self.stream, "isatty", None)
            tty = bool(isatty()) if isatty is not None else False
        self.interval = float(interval)
        self.done = 0.0
        self.count = 0
        self.start = time.perf_counter()
        self._last_time = self.start
        self._last_decile = 0
        self._bar = None
        if self.enabled and tty:
            try:
                from tqdm.auto import tqdm
            except ImportError:  # pragma: no cover - tqdm is in the experiments extra
                tty = False
            else:
                self._bar = tqdm(total=self.total, desc=label, file=self.stream, leave=False,
                                 bar_format="{desc}: {percentage:3.0f}%|{bar}| {postfix} "
                                            "[{elapsed}<{remaining}]")
                self._bar.set_postfix_str(f"0/{self.n} tasks", refresh=False)

    def advance(self, cost: float = 1.0) -> None:
        """One task of relative cost ``cost`` finished."""
        if not self.enabled:
            return
        self.done += float(cost)
        self.count += 1
        if self._bar is not None:
            self._bar.set_postfix_str(f"{self.count}/{self.n} tasks", refresh=False)
            self._bar.update(float(cost))
            return
        now = time.perf_counter()
        decile = int(10 * self.done / self.total + 1e-9)
        if self.count == self.n or decile > self._last_decile or \
                now - self._last_time >= self.interval:
            self._last_decile = max(decile, self._last_decile)
            self._last_time = now
            self.stream.write(self.line(now) + "\n")
            self.stream.flush()

    def line(self, now: float | None = None) -> str:
        """``[label] 40% (12/30 tasks), 0:41 elapsed, about 1:02 left``."""
        now = time.perf_counter() if now is None else now
        elapsed = now - self.start
        frac = min(self.done / self.total, 1.0)
        text = (f"[{self.label}] {100 * frac:.0f}% ({self.count}/{self.n} tasks), "
                f"{_clock(elapsed)} elapsed")
        if 0 < frac < 1:
            text += f", about {_clock(elapsed * (1 - frac) / frac)} left"
        return text

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
