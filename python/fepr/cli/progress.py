"""The progress bar every long command shows: tqdm, on stderr (tables on stdout stay clean), with a rate and an
ETA, shown only after about two seconds (short tasks print nothing), silent when ``quiet``::

    with progress_bar(total=300, desc="seed_demo3 FEPR on", unit="step", quiet=False) as bar:
        for _ in range(300):
            sim.step()
            bar.update(1)
"""

from __future__ import annotations

import sys
from typing import Optional

from tqdm.auto import tqdm

__all__ = ["DELAY_S", "progress_bar"]

#: Seconds a task runs before its bar appears (short tasks print nothing).
DELAY_S = 2.0


def progress_bar(total: int, *, desc: str = "", unit: str = "it", quiet: bool = False, leave: Optional[bool] = None):
    """A progress bar for ``total`` units of work (a tqdm bar: a context manager with ``update(n)``).

    Parameters
    ----------
    total : int
        Units of work (steps, frames).
    desc : str
        Label in front of the bar.
    unit : str
        Name of one unit.
    quiet : bool
        Show nothing (the bar still counts).
    leave : bool, optional
        Keep the finished bar on screen (tqdm's default: yes).
    """
    kwargs = {} if leave is None else {"leave": leave}
    return tqdm(
        total=total, desc=desc, unit=unit, delay=DELAY_S, file=sys.stderr, dynamic_ncols=True, disable=quiet, **kwargs
    )
