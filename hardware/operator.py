"""The person at the rig: rotates the sample on the cylinder and places the checkerboard.

Thesis 4.1.4: the cylinder is pulled out of its holder, the sample turned on it, and
plugged back in; the LEDs are off while the box is open (the orchestrator switches
them off before asking). With the twin the "operator" is the virtual rig itself
(:mod:`glossrig.hardware.backends_twin`).
"""
from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Protocol, runtime_checkable

from .errors import CaptureError


@runtime_checkable
class Operator(Protocol):
    def rotate_to(self, rotation_deg: float) -> None:
        """Return once the sample is mounted at ``rotation_deg``."""

    def place_checkerboard(self, view: int, views: int) -> None:
        """Return once the checkerboard is placed for view ``view`` (0-based) of ``views``."""


class ConsoleOperator:
    """Asks on the terminal and waits for Enter.

    ``sample_ready``: the sample is already mounted at the first rotation the run
    needs, so that one is not asked for (unattended overnight runs of one
    rotation). If input is closed (no terminal) when a question must be asked,
    the capture stops with a :class:`CaptureError` rather than guessing.
    """

    def __init__(self, *, sample_ready: bool = False, ask: Callable[[str], str] | None = None, stream=None):
        self.sample_ready = sample_ready
        self._stream = stream or sys.stderr
        self._ask = ask or self._read_line
        self._first = True

    def _read_line(self, prompt: str) -> str:
        """Prompt on the message stream (stdout stays for results); EOFError if input is closed."""
        print(prompt, end="", file=self._stream, flush=True)
        line = sys.stdin.readline()
        if not line:
            raise EOFError
        return line

    def _prompt(self, headline: str, detail: str) -> None:
        bar = "=" * max(len(headline), len(detail), 40)
        print(f"\a\n{bar}\n{headline}\n{detail}\n{bar}", file=self._stream, flush=True)
        try:
            self._ask("Press Enter when done (Ctrl-C stops the capture; --resume continues it later): ")
        except EOFError:
            raise CaptureError(f"the operator must act now ({headline.lower()}), but the input is closed; run the "
                               "capture from a terminal, or pass --sample-ready if the sample is already in "
                               "place") from None

    def rotate_to(self, rotation_deg: float) -> None:
        first, self._first = self._first, False
        if first and self.sample_ready:
            return
        self._prompt(f"ROTATE THE SAMPLE TO {rotation_deg:g} DEGREES",
                     "The LEDs are off. Take the cylinder out, turn the sample on it to "
                     f"{rotation_deg:g} deg, plug it back in, close the box.")

    def place_checkerboard(self, view: int, views: int) -> None:
        self._prompt(f"CHECKERBOARD VIEW {view + 1} OF {views}",
                     "Place the checkerboard in a new pose in front of the cylinder, filling much of the frame, "
                     "then close the box.")
