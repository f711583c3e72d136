"""When progress bars are shown: one rule for every tqdm bar of glossrig; and the one
spelling of a progress line's elapsed time (:class:`Elapsed`).

A bar is drawn only when the caller asked for one, the ``glossrig`` logger is not
quietened (``glossrig VERB -q`` sets it to WARNING) and stderr is a terminal: a bar
redirected into a log file or a pipe is a few hundred carriage-return-separated
copies of itself, which is noise, not progress (issue #16, "Conventions a user
expects").
"""
from __future__ import annotations

import logging
import sys
import time


class Elapsed:
    """Wall and CPU time since it was made, as a progress line states them: ``str()`` is
    ``"41 s, CPU 6 s"`` (whole seconds). The CPU time is this process's own (worker processes
    are not in it); on a shared machine it is the figure to read, the wall time an upper bound."""

    def __init__(self) -> None:
        self.wall0, self.cpu0 = time.perf_counter(), time.process_time()

    def seconds(self) -> tuple[float, float]:
        """(wall, CPU) seconds since it was made."""
        return time.perf_counter() - self.wall0, time.process_time() - self.cpu0

    def __str__(self) -> str:
        wall, cpu = self.seconds()
        return f"{wall:.0f} s, CPU {cpu:.0f} s"


def progress_enabled(requested: bool = True) -> bool:
    """True when a progress bar should be drawn (see the module docstring).

    ``requested`` is the caller's own wish (``--no-progress`` turns it off). The
    quiet check looks at an explicitly set level only, so library callers that never
    configure logging keep their bars on a terminal.
    """
    if not requested:
        return False
    level = logging.getLogger("glossrig").level
    if level != logging.NOTSET and level > logging.INFO:
        return False
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):     # no stderr, or a closed one
        return False
