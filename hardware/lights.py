"""The lights: switch exactly a given set of LEDs, all on, all off; report the state.

Thesis 4.1.1 and fig. 4.4: a Raspberry Pi drives a 16-channel relay module whose
relays put the LED supply on the chosen LEDs; several may be on at once (the
calibration image of thesis 4.2.1 needs all of them). The rig description gives
each LED's relay channel (1-based) and, for the Pi, its GPIO pin (BCM numbering;
``scenes/thesis_rig.toml``, taken from the original capture code).

Two real drivers share one behaviour, :class:`RelayLights`: after every switch
they read the state back and raise :class:`~glossrig.hardware.errors.LightsError`
if it differs from what was commanded, naming the LEDs that did not follow.

* :class:`GpioRelayLights` - the thesis set-up: one gpiozero ``OutputDevice`` per
  LED, **active-low** (the relay is energised when the pin is pulled low, as on
  the common opto-isolated relay modules). Read-back is the pin level, which
  catches a pin that another process holds or that is shorted; it cannot see a
  relay contact that has welded or a coil that has died.
* :class:`NumatoRelayLights` - a USB/serial relay board speaking the Numato Lab
  ASCII protocol (their 8/16/32-channel USB relay modules appear as a CDC-ACM
  serial port; other vendors' boards copy it). The protocol, as the driver uses it:

  ===========================  ==================================================
  host sends (ASCII, ``\\r``)   board replies
  ===========================  ==================================================
  ``relay writeall 00f0``      echo of the command, ``\\n\\r``, prompt ``>``
  ``relay readall``            echo, ``\\n\\r``, the relay mask in hex, ``\\n\\r>``
  ``ver``                      echo, ``\\n\\r``, firmware version, ``\\n\\r>``
  ===========================  ==================================================

  Bit *i* of the mask is relay *i* (numbered from 0; relay 0 is rig channel 1);
  the mask has ``channels / 4`` hex digits. The prompt ``>`` ends every reply,
  so a missing prompt within the timeout is a serial timeout: the command is
  sent again (``retries`` times; writeall/readall are idempotent) before the
  driver gives up. Read-back (``readall``) is the board's own relay register.

The virtual lights of the twin live in :mod:`glossrig.hardware.backends_twin`.
"""
from __future__ import annotations

import time
from collections.abc import Iterable
from typing import Protocol, runtime_checkable

from glossrig.core.errors import InputError
from glossrig.core.rig import Rig

from .errors import LightsError
from .serial_port import open_port, port_name


@runtime_checkable
class Lights(Protocol):
    """What the capture orchestrator needs from the lights (thesis 4.2.3)."""

    def switch(self, led_ids: Iterable[int]) -> None:
        """Switch on exactly ``led_ids`` (every other LED off)."""

    def all_on(self) -> None:
        """All LEDs on (the calibration image, thesis 4.2.1)."""

    def all_off(self) -> None:
        """All LEDs off."""

    def state(self) -> frozenset[int]:
        """The ids of the LEDs that are on now."""

    def close(self) -> None:
        """Switch everything off and release the device."""


class RelayLights:
    """Common logic of the relay drivers: id checks, switching, read-back check.

    Subclasses implement ``_apply(ids)`` (make exactly ``ids`` on) and
    ``_read()`` (the set that is on, as the device reports it).
    """

    name = "relay board"

    def __init__(self, rig: Rig):
        self.rig = rig
        self._ids = frozenset(rig.led_ids())

    # -- to implement
    def _apply(self, ids: frozenset[int]) -> None:
        raise NotImplementedError

    def _read(self) -> frozenset[int]:
        raise NotImplementedError

    # -- the protocol
    def _check_ids(self, led_ids: Iterable[int]) -> frozenset[int]:
        ids = frozenset(int(i) for i in led_ids)
        unknown = sorted(ids - self._ids)
        if unknown:
            raise InputError(f"LED ids {unknown} are not in rig {self.rig.name!r} (ids {sorted(self._ids)})",
                             path=self.rig.path)
        return ids

    def switch(self, led_ids: Iterable[int]) -> None:
        want = self._check_ids(led_ids)
        self._apply(want)
        got = self._read()
        if got != want:
            problems = []
            for i in sorted(want - got):
                problems.append(f"LED {i} ({self._describe(i)}) did not switch on")
            for i in sorted(got - want):
                problems.append(f"LED {i} ({self._describe(i)}) did not switch off")
            raise LightsError("; ".join(problems), device=self.name)

    def all_on(self) -> None:
        self.switch(self._ids)

    def all_off(self) -> None:
        self.switch(())

    def state(self) -> frozenset[int]:
        return self._read()

    def _describe(self, led_id: int) -> str:
        led = self.rig.led(led_id)
        return f"{led.name}, relay channel {led.channel}"

    def close(self) -> None:
        self.all_off()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class GpioRelayLights(RelayLights):
    """LEDs on an active-low relay module driven from Raspberry Pi GPIO (thesis 4.1.1, fig. 4.4).

    ``pin_factory`` is a gpiozero pin factory (``None``: gpiozero's default,
    i.e. the Pi's own GPIO; the tests pass ``gpiozero.pins.mock.MockFactory``).
    ``active_high=False`` is the thesis board; set it for a board whose relays
    close on a high pin. Every relay is switched off as the driver starts.
    """

    def __init__(self, rig: Rig, *, pin_factory=None, active_high: bool = False):
        super().__init__(rig)
        try:
            from gpiozero import OutputDevice
            from gpiozero.exc import GPIOZeroError
        except ImportError as e:   # a dependency of glossrig, but report it plainly
            raise LightsError(f"gpiozero is not installed ({e})", device="GPIO") from None
        pins = {}
        for led in rig.leds:
            if led.gpio < 0:
                raise InputError(f"LED {led.id} ({led.name}) has no gpio pin in leds.table", path=rig.path)
            if led.gpio in pins:
                raise InputError(f"LEDs {pins[led.gpio]} and {led.id} share GPIO pin {led.gpio}", path=rig.path)
            pins[led.gpio] = led.id
        self.name = "GPIO relay board"
        self._dev = {}
        try:
            for led in rig.leds:
                self._dev[led.id] = OutputDevice(led.gpio, active_high=active_high, initial_value=False,
                                                 pin_factory=pin_factory)
        except (GPIOZeroError, OSError, RuntimeError) as e:
            self._release()
            raise LightsError(f"cannot claim GPIO pins for the relays: {e}", device="GPIO") from None

    def _apply(self, ids: frozenset[int]) -> None:
        # Off first, then on: never more LEDs lit than either the old or the new set.
        for i, dev in self._dev.items():
            if i not in ids:
                dev.off()
        for i in ids:
            self._dev[i].on()

    def _read(self) -> frozenset[int]:
        return frozenset(i for i, dev in self._dev.items() if dev.value)

    def _describe(self, led_id: int) -> str:
        led = self.rig.led(led_id)
        return f"{led.name}, relay channel {led.channel}, GPIO{led.gpio}"

    def _release(self) -> None:
        for dev in self._dev.values():
            try:
                dev.close()
            except Exception:   # noqa: BLE001 - releasing pins must not mask the real error
                pass
        self._dev = {}

    def close(self) -> None:
        """All relays off, then release the pins (gpiozero makes them inputs; the
        module's input pull-ups then keep active-low relays off)."""
        try:
            if self._dev:
                self.all_off()
        finally:
            self._release()


class NumatoRelayLights(RelayLights):
    """LEDs on a USB/serial relay board speaking the Numato Lab ASCII protocol
    (module docstring). ``port``: device name or pyserial URL, or an open
    serial object. ``channels``: relays on the board (8, 16 or 32); the rig's
    relay channel *c* is board relay *c - 1*."""

    def __init__(self, rig: Rig, port, *, channels: int = 16, baudrate: int = 19200,
                 timeout_s: float = 1.0, retries: int = 2):
        super().__init__(rig)
        if channels not in (8, 16, 32, 64):
            raise InputError(f"relay board channels must be 8, 16, 32 or 64, got {channels}")
        for led in rig.leds:
            if not 1 <= led.channel <= channels:
                raise InputError(f"LED {led.id} ({led.name}) is on relay channel {led.channel}, but the board has "
                                 f"channels 1..{channels}", path=rig.path)
        self.channels = channels
        self.timeout_s = timeout_s
        self.retries = retries
        self.name = f"relay board on {port_name(port)}"
        self._port = open_port(port, baudrate=baudrate, timeout=timeout_s, error=LightsError)
        self._bit = {led.id: led.channel - 1 for led in rig.leds}
        try:
            self._command("ver")     # a board that does not speak the protocol fails here, not mid-capture
            self.all_off()
        except BaseException:
            self._port.close()
            raise

    def _command(self, cmd: str) -> list[str]:
        """Send one command; return the reply's lines after the echo."""
        data = (cmd + "\r").encode("ascii")
        last = ""
        for _ in range(self.retries + 1):
            self._port.reset_input_buffer()
            self._port.write(data)
            self._port.flush()
            deadline = time.monotonic() + self.timeout_s
            buf = b""
            while time.monotonic() < deadline:
                buf += self._port.read_until(b">")
                if not buf.endswith(b">"):
                    continue
                lines = [s.strip() for s in buf[:-1].decode("ascii", "replace").replace("\r", "\n").split("\n")]
                lines = [s for s in lines if s]
                if lines and lines[0] == cmd:
                    return lines[1:]
                if lines and (lines[0].startswith("relay ") or lines[0] == "ver"):
                    buf = b""          # a late reply to an earlier attempt: skip it
                    continue
                return lines           # a board that does not echo
            last = repr(buf.decode("ascii", "replace"))
        raise LightsError(f"no reply to {cmd!r} within {self.timeout_s:g} s after {self.retries + 1} attempts "
                          f"(received {last or 'nothing'}); is the board powered and on this port?",
                          device=self.name)

    def _mask(self, ids: frozenset[int]) -> int:
        m = 0
        for i in ids:
            m |= 1 << self._bit[i]
        return m

    def _apply(self, ids: frozenset[int]) -> None:
        self._command(f"relay writeall {self._mask(ids):0{self.channels // 4}x}")

    def _read(self) -> frozenset[int]:
        lines = self._command("relay readall")
        try:
            mask = int(lines[-1], 16)
        except (IndexError, ValueError):
            raise LightsError(f"unexpected reply to 'relay readall': {lines!r}", device=self.name) from None
        return frozenset(i for i, b in self._bit.items() if mask >> b & 1)

    def close(self) -> None:
        try:
            self.all_off()
        finally:
            self._port.close()
