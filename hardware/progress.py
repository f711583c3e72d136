"""Progress of a capture: a bar over the expected time, with time remaining.

Shots differ by five orders of magnitude in exposure (1/4000 s .. 30 s, thesis table
4.1), so counting images would make the remaining-time estimate useless. The bar
counts *expected seconds of work* instead - each shot's exposure plus the measured
per-shot overhead (:mod:`glossrig.hardware.plan`) - and tqdm's rate over that
quantity turns it into real seconds: if the set-up is slower than the plan's
overhead says, the remaining time grows accordingly.
"""
from __future__ import annotations

import sys

from tqdm import tqdm

from glossrig.core.progress import progress_enabled

from .camera import format_exposure
from .plan import Shot


class Progress:
    """A tqdm bar on ``stream`` (stderr by default); ``disable`` for silence."""

    def __init__(self, total_work_s: float, n_shots: int, *, done_shots: int = 0, stream=None,
                 disable: bool = False):
        self.n_shots = n_shots
        self.done = done_shots
        self._total = round(total_work_s, 3)
        self._counted = 0.0
        self._bar = tqdm(total=self._total, unit="s", unit_scale=False, file=stream or sys.stderr,
                         disable=not progress_enabled(not disable), dynamic_ncols=True, smoothing=0.05,
                         bar_format="{desc} {percentage:3.0f}%|{bar}| [{elapsed} elapsed, {remaining} left]")
        self._set_desc(None)

    def _set_desc(self, shot: Shot | None) -> None:
        head = f"image {min(self.done + 1, self.n_shots)}/{self.n_shots}"
        if shot is not None:
            what = ("calibration (all LEDs)" if shot.role == "calibration" else
                    f"checkerboard view {shot.view + 1}" if shot.role == "checkerboard" else
                    f"LED {','.join(map(str, shot.leds))} seq {shot.repeat + 1}")
            head += f" rot {shot.rotation:g} deg, {what}, {format_exposure(shot.exposure_s)}"
        self._bar.set_description_str(head, refresh=True)

    def start(self, shot: Shot) -> None:
        self._set_desc(shot)

    def finish(self, shot: Shot, work_s: float) -> None:
        self.done += 1
        step = min(round(work_s, 3), self._total - self._counted)
        self._counted += step
        self._bar.update(step)
        self._set_desc(None)

    def write(self, message: str) -> None:
        """A line above the bar (the bar is redrawn below it)."""
        self._bar.write(message, file=self._bar.fp)

    def clear(self) -> None:
        """Take the bar off the screen (before a prompt)."""
        self._bar.clear()

    def refresh(self) -> None:
        self._bar.refresh()

    def close(self) -> None:
        self._bar.close()
