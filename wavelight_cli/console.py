"""What a run prints: why each stage runs or is skipped, progress on long work, results and warnings.

Progress and notes go to stderr; results go to stdout, even with --quiet. Long work shows its
elapsed time, rate (with its unit) and the time left: on one updating line (tqdm) when stderr is
a terminal, as plain greppable lines, at most one a second, when it is not:

    visibility: casting [3/9] 33 %, 2.1 s, 1.4 steps/s, about 4 s left
"""

from __future__ import annotations

import sys
import time


class Console:
    """Plain, greppable progress on stderr: `stage: message`; results on stdout."""

    def __init__(self, quiet: bool = False, stream=None, out=None):
        self.quiet = quiet
        self.stream = stream or sys.stderr
        self.out = out or sys.stdout
        self._bars: dict = {}

    @property
    def interactive(self) -> bool:
        return not self.quiet and hasattr(self.stream, "isatty") and self.stream.isatty()

    def say(self, message: str) -> None:
        if not self.quiet:
            self._clear_bars()
            print(message, file=self.stream, flush=True)

    def result(self, message: str) -> None:
        """A result line: printed on stdout even with --quiet."""
        self._clear_bars()
        print(message, file=self.out, flush=True)

    def decision(self, d) -> None:
        if d.run:
            self.say(f"{d.stage}: running ({d.reason})")
        elif getattr(d, "redisplay", False):
            self.say(f"{d.stage}: redrawing the previews ({d.reason})")
        else:
            self.say(f"{d.stage}: skipped, {d.reason}")

    def task(self, stage: str, what: str, total: int, unit: str = "items") -> "Task":
        """Progress of one piece of long work: `task.update(done)`, then `task.close()`."""
        return Task(self, stage, what, total, unit)

    def _clear_bars(self) -> None:
        for bar in list(self._bars.values()):
            bar.clear()


class Task:
    def __init__(self, console: Console, stage: str, what: str, total: int, unit: str):
        self.console, self.stage, self.what, self.total, self.unit = console, stage, what, max(int(total), 1), unit
        self.t0 = time.monotonic()
        self._last = 0.0
        self.done = 0
        self._bar = None
        if console.interactive:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=f"{stage}: {what}", unit=f" {unit}", file=console.stream,
                             leave=False, dynamic_ncols=True, mininterval=0.2)
            console._bars[id(self)] = self._bar

    def update(self, done: int, extra: str = "") -> None:
        step = int(done) - self.done
        self.done = int(done)
        if self._bar is not None:
            self._bar.update(step)
            if extra:
                self._bar.set_postfix_str(extra, refresh=False)
            return
        now = time.monotonic()
        if self.console.quiet or (self.done < self.total and now - self._last < 1.0):
            return
        self._last = now
        elapsed = now - self.t0
        rate = self.done / elapsed if elapsed > 0 else 0.0
        left = (self.total - self.done) / rate if rate > 0 else float("nan")
        eta = "" if self.done >= self.total or not left == left else f", about {_duration(left)} left"
        print(f"{self.stage}: {self.what} [{self.done}/{self.total}] {100 * self.done / self.total:.0f} %, "
              f"{_duration(elapsed)}, {_rate(rate)} {self.unit}/s{eta}" + (f", {extra}" if extra else ""),
              file=self.console.stream, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self.console._bars.pop(id(self), None)


def _duration(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.1f} s"
    return f"{int(seconds // 60)} min {seconds % 60:02.0f} s"


def _rate(value: float) -> str:
    if value >= 1e6:
        return f"{value / 1e6:.1f} M"
    if value >= 1e4:
        return f"{value / 1e3:.0f} k"
    return f"{value:.3g}"
