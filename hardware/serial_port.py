"""Opening serial ports for the relay board and the engravers (pyserial).

Every serial driver accepts either a port name / pyserial URL (``/dev/ttyACM0``,
``COM3``, ``loop://``, ``socket://host:port``) or an already open
:class:`serial.SerialBase` (what the tests pass for a pty pair). Failures to open
become a :class:`~glossrig.hardware.errors.DeviceError` naming the port.
"""
from __future__ import annotations

import serial

from .errors import DeviceError


def open_port(port, *, baudrate: int, timeout: float, error=DeviceError, **kw) -> serial.SerialBase:
    """Open ``port`` (name, URL or open serial object) with the given settings.

    ``timeout`` is the read timeout in seconds; ``kw`` passes pyserial options
    such as ``rtscts`` or ``write_timeout``. An open object is returned as it
    is, with its timeouts set, so the caller's port settings are kept.
    """
    if isinstance(port, serial.SerialBase):
        port.timeout = timeout
        if "write_timeout" in kw:
            port.write_timeout = kw["write_timeout"]
        return port
    try:
        return serial.serial_for_url(str(port), baudrate=baudrate, timeout=timeout, **kw)
    except (serial.SerialException, ValueError, OSError) as e:
        raise error(f"cannot open serial port: {e}", device=str(port)) from None


def port_name(port) -> str:
    """A readable name of ``port`` for messages."""
    if isinstance(port, serial.SerialBase):
        return str(port.name or port.port or "serial port")
    return str(port)
