"""Progress output on stderr: tqdm bars (rate, ETA) on a terminal, a line every LOG_EVERY seconds
in logs, no bars and no periodic lines in quiet mode (``clrf --quiet``). Messages (one line
per evaluation, pruning) print in every mode: they are the log.

>>> with bar(len(views), "render", "view") as b:
...     for v in views: ...; b.update(1)
"""
from __future__ import annotations

import sys
import time

LOG_EVERY = 30.0   # seconds between progress lines when stderr is not a terminal
QUIET = False      # set by the CLI's --quiet


def set_quiet(quiet: bool):
    global QUIET
    QUIET = bool(quiet)


def _tty() -> bool:
    return hasattr(sys.stderr, "isatty") and sys.stderr.isatty()


def _num(x) -> str:
    return f"{x:.0f}" if float(x).is_integer() else f"{x:.1f}"


class _LogBar:
    """tqdm's interface for logs: one plain line every LOG_EVERY seconds and one at the end."""

    def __init__(self, total, desc, unit):
        self.total, self.desc, self.unit = total, desc, unit
        self.n = 0
        self.postfix = ""
        self.t0 = self.last = time.perf_counter()

    def _line(self):
        dt = time.perf_counter() - self.t0
        rate = self.n / dt if dt > 0 else 0.0
        eta = max(self.total - self.n, 0) / rate if rate > 0 and self.total else 0.0
        tot = f"/{_num(self.total)}" if self.total else ""
        sys.stderr.write(f"{self.desc}: {_num(self.n)}{tot} {self.unit} ({rate:.3g} {self.unit}/s, "
                         f"{dt:.0f} s elapsed, ETA {eta:.0f} s){self.postfix}\n")
        sys.stderr.flush()
        self.last = time.perf_counter()

    def update(self, k=1):
        self.n += k
        if time.perf_counter() - self.last >= LOG_EVERY:
            self._line()

    def set_postfix_str(self, s, refresh=False):
        self.postfix = f"  {s}"

    def close(self):
        if self.n:
            self._line()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _Silent(_LogBar):
    def update(self, k=1):
        self.n += k

    def close(self):
        pass


# tqdm's layout for fractional totals (training seconds): counts with one decimal
FLOAT_FORMAT = ("{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} {unit} "
                "[{elapsed}<{remaining}{postfix}]")


def bar(total, desc: str, unit: str = "it"):
    """A progress bar over ``total`` units: tqdm on a terminal, _LogBar in logs, silent when
    quiet. All three have update(k), set_postfix_str(s), close() and work as context managers."""
    if QUIET:
        return _Silent(total, desc, unit)
    if not _tty():
        return _LogBar(total, desc, unit)
    from tqdm import tqdm
    fmt = None if isinstance(total, int) else FLOAT_FORMAT
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True,
                mininterval=0.2, leave=True, bar_format=fmt)


def message(text: str):
    """One line on stderr (above a tqdm bar on a terminal), in every mode."""
    if _tty() and not QUIET:
        from tqdm import tqdm
        tqdm.write(text, file=sys.stderr)
    else:
        sys.stderr.write(text + "\n")
        sys.stderr.flush()


class TrainProgress:
    """Training: a bar over the time budget in seconds (ETA = remaining budget at the current
    pace), the latest loss/PSNR/rate as its postfix; messages print above it."""

    def __init__(self, total_seconds: float, start_seconds: float = 0.0):
        self.total = float(total_seconds)
        self.bar = bar(self.total, "train", "s")
        self.done = 0.0
        self.advance_to(start_seconds)

    def advance_to(self, seconds: float):
        """Move the bar to ``seconds`` of training (clamped to the budget)."""
        step = min(float(seconds), self.total) - self.done
        if step > 0:
            self.bar.update(step)
            self.done += step

    def update(self, text: str, seconds: float):
        self.bar.set_postfix_str(text, refresh=False)
        self.advance_to(seconds)

    def message(self, text: str):
        message(text)

    def close(self):
        self.bar.close()
