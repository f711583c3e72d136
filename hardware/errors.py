"""Errors of the hardware layer: every one names the device (or file) and what went wrong.

All derive from :class:`glossrig.core.errors.GlossrigError`, so the CLI reports them
as a one-line message (exit code 2) instead of a traceback.
"""
from __future__ import annotations

from glossrig.core.errors import GlossrigError


class DeviceError(GlossrigError):
    """A device misbehaved: no reply, a reply that makes no sense, a state that
    does not match what was commanded. ``device`` names it (port, pin, model)."""

    def __init__(self, message: str, device: str | None = None):
        self.device = device
        super().__init__(f"{device}: {message}" if device else message)


class LightsError(DeviceError):
    """The LEDs could not be switched as commanded (or not confirmed)."""


class CameraError(DeviceError):
    """The camera refused a setting, delivered no file, or shot something else
    than what was requested (checked from the file's own metadata)."""


class CameraDisconnected(CameraError):
    """The camera vanished from USB and did not come back within the retries."""


class EngraverError(DeviceError):
    """The engraver rejected a line, raised an alarm, or stopped answering."""


class CaptureError(GlossrigError):
    """The capture run had to stop (the message says why and how to resume)."""
