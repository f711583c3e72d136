"""When progress bars are shown: one rule for every tqdm bar of glossrig.

A bar is drawn only when the caller asked for one, the ``glossrig`` logger is not
quietened (``glossrig VERB -q`` sets it to WARNING) and stderr is a terminal: a bar
redirected into a log file or a pipe is a few hundred carriage-return-separated
copies of itself, which is noise, not progress (issue #16, "Conventions a user
expects").
"""
from __future__ import annotations

import logging
import sys


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
