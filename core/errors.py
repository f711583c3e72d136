"""Errors a user sees: each names the file (or input) and what is wrong with it."""
from __future__ import annotations

from pathlib import Path


class GlossrigError(Exception):
    """Base class of every error glossrig reports to a user (CLI exit code 2)."""


class InputError(GlossrigError):
    """Bad input: names the offending file or argument and the problem.

    >>> str(InputError("exposure_s must be > 0", path="capture.json"))
    'capture.json: exposure_s must be > 0'
    """

    def __init__(self, message: str, path: str | Path | None = None):
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)
