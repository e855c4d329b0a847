"""The progress bar of the studies: ``tqdm`` on stderr, silent when switched off or when stderr is
not a terminal (a pipe, a log file, a test runner), so that only an interactive user sees it."""
from __future__ import annotations

import sys

__all__ = ["progress_bar"]


def progress_bar(total: int, desc: str, unit: str, enabled: bool = True):
    """A ``tqdm`` bar over ``total`` units (a context manager; ``update()``, ``set_postfix_str()``).

    Args:
        total: the number of units of work.
        desc: what runs, shown first (e.g. "center-out").
        unit: the unit counted (e.g. "solve").
        enabled: False: no bar at all. True: a bar when stderr is a terminal (tqdm's
            ``disable=None``).
    """
    from tqdm.auto import tqdm
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=None if enabled else True,
                dynamic_ncols=True)
