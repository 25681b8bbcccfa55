"""Progress bars for long runs: shown only after about two seconds, silent when ``quiet``.

:func:`progress_bar` wraps ``tqdm`` (written to stderr, so tables on stdout stay clean) when it is installed
and falls back to a plain line every few seconds otherwise::

    with progress_bar(total=300, desc="seed_demo3 FEPR on", unit="step", quiet=False) as bar:
        for _ in range(300):
            sim.step()
            bar.update(1)
"""

from __future__ import annotations

import sys
import time
from typing import Optional

__all__ = ["DELAY_S", "progress_bar"]

#: Seconds a task runs before its bar appears (short tasks print nothing).
DELAY_S = 2.0


class _Silent:
    """A progress bar that shows nothing."""

    def update(self, n: int = 1) -> None:
        pass

    def set_description(self, desc: str) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Plain(_Silent):
    """Fallback without tqdm: one line on stderr at most every five seconds, after :data:`DELAY_S`."""

    def __init__(self, total: int, desc: str, unit: str):
        self.total, self.desc, self.unit = total, desc, unit
        self.done = 0
        self.start = time.perf_counter()
        self.last = self.start + DELAY_S - 5.0

    def update(self, n: int = 1) -> None:
        self.done += n
        now = time.perf_counter()
        if now - self.start >= DELAY_S and now - self.last >= 5.0:
            self.last = now
            print(f"  {self.desc}: {self.done}/{self.total} {self.unit}s", file=sys.stderr, flush=True)

    def set_description(self, desc: str) -> None:
        self.desc = desc


def progress_bar(total: int, *, desc: str = "", unit: str = "it", quiet: bool = False, leave: Optional[bool] = None):
    """A progress bar for ``total`` units of work (a context manager with ``update(n)``).

    Parameters
    ----------
    total : int
        Units of work (steps, frames).
    desc : str
        Label in front of the bar.
    unit : str
        Name of one unit.
    quiet : bool
        Show nothing.
    leave : bool, optional
        Keep the finished bar on screen (tqdm's default: yes).
    """
    if quiet:
        return _Silent()
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return _Plain(total, desc, unit)
    kwargs = {} if leave is None else {"leave": leave}
    return tqdm(total=total, desc=desc, unit=unit, delay=DELAY_S, file=sys.stderr, dynamic_ncols=True, **kwargs)
