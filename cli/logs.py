"""Messages of the CLI: the ``glossrig`` logger hierarchy, configured once per verb.

Modules log with ``logging.getLogger(__name__)`` (all under ``glossrig``); a verb's
progress and warnings go to stderr as ``glossrig VERB: message`` (warnings as
``glossrig VERB: warning: message``), while what the verb produces (a parameter
table, "N samples written") stays on stdout. ``-v`` shows debug messages, ``-q``
only warnings and errors (and switches progress bars off, see
:mod:`glossrig.core.progress`).
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import sys

ROOT = "glossrig"


class _StderrHandler(logging.Handler):
    """Writes to whatever ``sys.stderr`` is at the time (pytest's capture swaps it)."""

    def __init__(self, verb: str):
        super().__init__()
        self.verb = verb

    def emit(self, record: logging.LogRecord) -> None:
        try:
            msg = record.getMessage()
            tag = "warning: " if record.levelno == logging.WARNING else "error: " if record.levelno >= logging.ERROR else ""
            sys.stderr.write(f"glossrig {self.verb}: {tag}{msg}\n")
            sys.stderr.flush()
        except Exception:   # noqa: BLE001 - logging must never break the verb
            self.handleError(record)


def add_verbosity_options(parser: argparse.ArgumentParser, nested: bool = False) -> None:
    """``-v/--verbose`` and ``-q/--quiet`` on a verb's parser (``nested``: a sub-verb's,
    whose defaults must not override a value given before the sub-verb's name).

    A parser that already has one of the options (a plugin sub-verb) keeps its own.
    """
    have = parser._option_string_actions
    default = argparse.SUPPRESS if nested else False
    v = [o for o in ("-v", "--verbose") if o not in have]
    q = [o for o in ("-q", "--quiet") if o not in have]
    if "--verbose" in v:
        parser.add_argument(*v, dest="verbose", action="store_true", default=default,
                            help="also show debug messages")
    if "--quiet" in q:
        parser.add_argument(*q, dest="quiet", action="store_true", default=default,
                            help="show only warnings and errors; no progress bars")


@contextlib.contextmanager
def configured(verb: str, verbose: bool = False, quiet: bool = False):
    """Route the ``glossrig`` loggers to stderr for one verb; restore the previous
    set-up afterwards (``glossrig demo`` runs other verbs inside itself)."""
    log = logging.getLogger(ROOT)
    saved = (log.level, log.propagate, list(log.handlers))
    handler = _StderrHandler(verb)
    log.handlers = [handler]
    log.propagate = False
    log.setLevel(logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO)
    try:
        yield log
    finally:
        log.setLevel(saved[0])
        log.propagate = saved[1]
        log.handlers = saved[2]


class LogStream:
    """A text stream whose complete lines go to a logger at INFO (for code that
    prints its messages to a stream, such as the capture orchestrator)."""

    def __init__(self, logger: logging.Logger):
        self._log = logger
        self._buf = ""

    def write(self, text: str) -> int:
        self._buf += text
        while "\n" in self._buf:
            line, self._buf = self._buf.split("\n", 1)
            if line.strip():
                self._log.info(line)
        return len(text)

    def flush(self) -> None:
        if self._buf.strip():
            self._log.info(self._buf)
        self._buf = ""
