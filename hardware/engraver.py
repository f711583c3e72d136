"""The engraver: stream a toolpath with flow control, report position and state, stop at once.

Thesis 5.1.1: a 3-axis Roland CNC engraving machine (10 um resolution; 100 mm/s in x
and z, 50 mm/s in y) controlled through its proprietary machine language, RML-1; the
same scratch toolpaths can run on a GRBL machine as G-code. Every driver first parses
and checks the whole toolpath (:mod:`glossrig.hardware.toolpath_check`: bed, safe
depth, axis speeds) and refuses it before a single byte is sent.

* :class:`GrblEngraver` - GRBL 1.1 over serial (115200 baud). Flow control is GRBL's
  *character counting* protocol: the driver keeps the bytes of every line not yet
  acknowledged by ``ok`` and never lets them exceed GRBL's 128-byte receive buffer, so
  the planner stays full without a byte being lost. ``error:N`` or ``ALARM:N`` stop
  the stream (feed hold + soft reset) and raise, naming the file line. While waiting
  it polls the real-time status (``?``); if GRBL answers nothing at all for
  ``timeout_s`` - not even status - the stream stops with a serial-timeout error.
  ``stop()`` sends feed hold ``!`` then soft reset Ctrl-X: motion decelerates at once,
  buffers are flushed and the spindle stops (GRBL then asks for re-homing).
* :class:`RolandEngraver` - RML-1 over serial (Roland's default 9600 baud, 8N1,
  hardware handshake). Flow control uses the HP-GL/RML device-control query ``ESC.B``
  (bytes free in the machine's buffer) before each chunk, on top of the RTS/CTS
  handshake; ``ESC.O`` gives the state (0: data in buffer, 8: buffer empty, 16/24:
  paused). The machine reports no position over the serial line, so ``position()`` is
  the end point of the last instruction the machine has taken from its buffer
  (sent bytes minus bytes still buffered): the move it is executing or has finished.
  ``stop()`` stops sending and sends ``ESC.K`` (abort: the machine discards its buffer)
  then ``!MC0;`` (spindle off). Check on your machine that ESC.K is honoured; its own
  stop button remains the emergency stop.
* :class:`SimulatedEngraver` - the virtual machine: checks like the others, then
  "executes" the moves, recording the path it was sent (``path``, ``received``).
"""
from __future__ import annotations

import re
import threading
import time
from collections import deque
from dataclasses import dataclass
from collections.abc import Callable
from typing import Protocol, runtime_checkable

from .errors import EngraverError
from .serial_port import open_port, port_name
from .toolpath_check import MachineLimits, Move, Toolpath, ToolpathError, check_toolpath, read_toolpath

#: GRBL 1.1 error and alarm codes the driver names in its messages.
GRBL_ERRORS = {
    1: "G-code words consist of a letter and a value; letter not found",
    2: "numeric value format is not valid or missing",
    3: "'$' system command not recognised",
    9: "G-code locked out during alarm or jog state",
    15: "jog target exceeds machine travel",
    20: "unsupported or invalid G-code command",
    22: "feed rate has not yet been set",
    24: "two G-code commands that both need the XYZ axis words",
    33: "the motion command has an invalid target",
}
GRBL_ALARMS = {1: "hard limit triggered", 2: "soft limit: motion target exceeds machine travel",
               3: "reset while in motion", 4: "probe fail", 5: "probe fail", 6: "homing fail", 7: "homing fail",
               8: "homing fail", 9: "homing fail"}
_STATES = {"idle": "idle", "run": "running", "jog": "running", "home": "running", "hold": "paused",
           "door": "paused", "alarm": "alarm", "check": "idle", "sleep": "idle"}


class EngraverStopped(EngraverError):
    """``stop()`` was called while streaming."""


@dataclass
class StreamReport:
    commands: int
    seconds: float
    position: tuple[float | None, float | None, float | None]


@runtime_checkable
class Engraver(Protocol):
    limits: MachineLimits

    def stream(self, toolpath, *, progress: Callable[[int, int], None] | None = None) -> StreamReport:
        """Check ``toolpath`` (file, text or lines) and send it, with flow control."""

    def position(self) -> tuple[float | None, float | None, float | None]:
        """Tool position in work coordinates, mm (None where unknown)."""

    def state(self) -> str:
        """"idle", "running", "paused", "alarm", "stopped" or "disconnected"."""

    def stop(self) -> None:
        """Stop motion at once and discard what is buffered."""

    def close(self) -> None:
        """Release the port."""


# ------------------------------------------------------------------ GRBL

class GrblEngraver:
    """GRBL 1.1 over a serial port (module docstring)."""

    def __init__(self, port, limits: MachineLimits, *, baudrate: int = 115200, rx_buffer: int = 128,
                 timeout_s: float = 5.0, poll_s: float = 0.2, startup_s: float = 3.0, reset_on_connect: bool = True):
        self.limits = limits
        self.rx_buffer = rx_buffer
        self.timeout_s, self.poll_s = timeout_s, poll_s
        self.name = f"GRBL on {port_name(port)}"
        self._port = open_port(port, baudrate=baudrate, timeout=min(poll_s, 0.05), error=EngraverError)
        self._wlock = threading.Lock()
        self._stop = threading.Event()
        self._streaming = False
        self._state = "disconnected"
        self._mpos = None
        self._wco = (0.0, 0.0, 0.0)
        self._wpos = None
        self._partial = b""
        self._last_rx = time.monotonic()
        try:
            if reset_on_connect:
                self._write(b"\x18")
                deadline = time.monotonic() + startup_s
                banner = False
                while time.monotonic() < deadline and not banner:
                    line = self._readline()
                    banner = line is not None and line.startswith("Grbl")
                if not banner:
                    raise EngraverError(f"no GRBL start-up banner within {startup_s:g} s after a reset; is this a "
                                        "GRBL controller at this baud rate?", device=self.name)
            self._query_status()
        except BaseException:
            self._port.close()
            raise

    # -- low level
    def _write(self, data: bytes) -> None:
        with self._wlock:
            try:
                self._port.write(data)
                self._port.flush()
            except Exception as e:   # noqa: BLE001 - serial errors of any flavour
                self._state = "disconnected"
                raise EngraverError(f"write failed: {e}", device=self.name) from None

    def _readline(self) -> str | None:
        """One complete line, or None if none arrived within the port's read timeout."""
        try:
            chunk = self._port.readline()
        except Exception as e:   # noqa: BLE001
            self._state = "disconnected"
            raise EngraverError(f"read failed: {e}", device=self.name) from None
        if not chunk:
            return None
        self._last_rx = time.monotonic()
        self._partial += chunk
        if not self._partial.endswith(b"\n"):
            return None
        line = self._partial.decode("ascii", "replace").strip()
        self._partial = b""
        if line.startswith("<"):
            self._parse_status(line)
        return line

    def _parse_status(self, line: str) -> None:
        body = line.strip("<>")
        fields = body.split("|") if "|" in body else [body.split(",", 1)[0]] + re.findall(r"\w+Pos:[^A-Z]*", body)
        self._state = _STATES.get(fields[0].split(":")[0].lower(), fields[0].lower())
        for f in fields[1:]:
            key, _, val = f.partition(":")
            try:
                nums = tuple(float(v) for v in val.strip(",").split(",")[:3])
            except ValueError:
                continue
            if key == "MPos":
                self._mpos = nums
            elif key == "WPos":
                self._wpos = nums
            elif key == "WCO":
                self._wco = nums
        if self._mpos is not None:
            self._wpos = tuple(m - o for m, o in zip(self._mpos, self._wco))

    def _query_status(self) -> None:
        self._write(b"?")
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            line = self._readline()
            if line is not None and line.startswith("<"):
                return
        raise EngraverError(f"no status report within {self.timeout_s:g} s (serial timeout)", device=self.name)

    # -- the protocol
    def position(self):
        if not self._streaming:
            self._query_status()
        return self._wpos if self._wpos is not None else (None, None, None)

    def state(self) -> str:
        if not self._streaming and self._state not in ("stopped", "disconnected"):
            self._query_status()
        return self._state

    def stop(self) -> None:
        self._stop.set()
        try:
            self._write(b"!")       # feed hold: decelerate now
            self._write(b"\x18")    # soft reset: flush buffers, spindle off
        finally:
            self._state = "stopped"

    def _fail(self, message: str) -> EngraverError:
        try:
            self.stop()
        except EngraverError:
            pass
        return EngraverError(message, device=self.name)

    def stream(self, toolpath, *, progress=None) -> StreamReport:
        tp = read_toolpath(toolpath, dialect="gcode")
        check_toolpath(tp, self.limits)
        too_long = [(n, t) for n, t in tp.commands if len(t) + 1 > self.rx_buffer - 1]
        if too_long:
            raise ToolpathError(f"line {too_long[0][0]} is longer than GRBL's {self.rx_buffer}-byte receive buffer",
                                path=tp.source)
        self._query_status()
        if self._state == "alarm":
            raise EngraverError("the machine is in ALARM state; home it ($H) or unlock it ($X) and check it, then "
                                "stream again (nothing was sent)", device=self.name)
        self._stop.clear()
        self._streaming = True
        t0 = time.monotonic()
        pending: deque = deque()     # (line number, text, bytes) sent but not yet acknowledged
        in_flight = 0
        self._last_rx = time.monotonic()
        last_poll = 0.0
        done = 0
        try:
            commands = list(tp.commands)
            i = 0
            while i < len(commands) or pending:
                if self._stop.is_set():
                    raise EngraverStopped("stopped on request", device=self.name)
                if i < len(commands):
                    n, text = commands[i]
                    data = (text + "\n").encode("ascii")
                    if in_flight + len(data) <= self.rx_buffer - 1:
                        self._write(data)
                        pending.append((n, text, len(data)))
                        in_flight += len(data)
                        i += 1
                        continue
                line = self._readline()
                if self._stop.is_set():
                    raise EngraverStopped("stopped on request", device=self.name)
                now = time.monotonic()
                if line is None:
                    if now - self._last_rx > self.timeout_s:
                        raise self._fail(f"no reply from GRBL for {self.timeout_s:g} s with {len(pending)} line(s) "
                                         f"unacknowledged (serial timeout); stopped after line "
                                         f"{pending[0][0] if pending else '?'} of {tp.source}")
                    if now - last_poll > self.poll_s:
                        self._write(b"?")
                        last_poll = now
                    continue
                if line == "ok":
                    _, _, nb = pending.popleft()
                    in_flight -= nb
                    done += 1
                    if progress:
                        progress(done, len(commands))
                elif line.startswith("error:"):
                    n, text, _ = pending[0]
                    code = int(line.split(":")[1]) if line.split(":")[1].isdigit() else -1
                    raise self._fail(f"{tp.source} line {n} {text!r} rejected: {line} "
                                     f"({GRBL_ERRORS.get(code, 'see the GRBL error codes')}); stopped")
                elif line.startswith("ALARM:"):
                    code = int(line.split(":")[1]) if line.split(":")[1].isdigit() else -1
                    raise self._fail(f"{line} ({GRBL_ALARMS.get(code, 'alarm')}) while streaming {tp.source}; "
                                     "stopped")
                elif line.startswith("Grbl"):
                    self._state = "alarm"
                    raise EngraverError(f"GRBL reset itself while streaming {tp.source} (power or USB glitch?); "
                                        "the machine must be re-homed", device=self.name)
            # everything acknowledged: wait for the motion to finish
            while True:
                if self._stop.is_set():
                    raise EngraverStopped("stopped on request", device=self.name)
                self._write(b"?")
                deadline = time.monotonic() + self.timeout_s
                got = False
                while time.monotonic() < deadline:
                    line = self._readline()
                    if line is not None and line.startswith("<"):
                        got = True
                        break
                if not got:
                    raise self._fail(f"no status from GRBL for {self.timeout_s:g} s at the end of {tp.source} "
                                     "(serial timeout)")
                if self._state == "idle":
                    break
                if self._state == "alarm":
                    raise EngraverError(f"the machine went into ALARM at the end of {tp.source}", device=self.name)
                time.sleep(self.poll_s)
        except KeyboardInterrupt:
            self.stop()
            raise
        finally:
            self._streaming = False
        return StreamReport(commands=done, seconds=time.monotonic() - t0,
                            position=self._wpos if self._wpos is not None else (None, None, None))

    def close(self) -> None:
        self._port.close()
        if self._state != "stopped":
            self._state = "disconnected"


# ------------------------------------------------------------------ Roland RML-1

class RolandEngraver:
    """A Roland engraver speaking RML-1 over a serial port (module docstring)."""

    _STATUS = {0: "running", 8: "idle", 16: "paused", 24: "paused"}

    def __init__(self, port, limits: MachineLimits, *, baudrate: int = 9600, handshake: str = "rtscts",
                 timeout_s: float = 5.0, poll_s: float = 0.05, margin: int = 16):
        if handshake not in ("rtscts", "dsrdtr", "none"):
            raise ValueError("handshake must be 'rtscts', 'dsrdtr' or 'none'")
        self.limits = limits
        self.timeout_s, self.poll_s, self.margin = timeout_s, poll_s, margin
        self.name = f"Roland engraver on {port_name(port)}"
        self._port = open_port(port, baudrate=baudrate, timeout=poll_s, error=EngraverError,
                               rtscts=handshake == "rtscts", dsrdtr=handshake == "dsrdtr", write_timeout=timeout_s)
        self._wlock = threading.Lock()
        self._stop = threading.Event()
        self._state = "idle"
        self._tp: Toolpath | None = None
        self._ends: list[int] = []        # byte offset just after each command
        self._sent = 0
        self._capacity = None
        self._pos = (None, None, None)
        self._streaming = False
        try:
            self.capacity()      # a machine that does not answer fails here, not mid-stream
        except BaseException:
            self._port.close()
            raise

    def _write(self, data: bytes) -> None:
        with self._wlock:
            try:
                self._port.write(data)
                self._port.flush()
            except Exception as e:   # noqa: BLE001 - pyserial's SerialTimeoutException and friends
                raise EngraverError(f"the machine did not accept data for {self.timeout_s:g} s ({e}); handshake "
                                    "held or cable disconnected", device=self.name) from None

    def _query(self, letter: str) -> int:
        with self._wlock:
            try:
                self._port.reset_input_buffer()
                self._port.write(b"\x1b." + letter.encode())
                self._port.flush()
            except Exception as e:   # noqa: BLE001
                raise EngraverError(f"write failed: {e}", device=self.name) from None
            deadline = time.monotonic() + self.timeout_s
            buf = b""
            while time.monotonic() < deadline:
                buf += self._port.read_until(b"\r")
                if buf.endswith(b"\r"):
                    try:
                        return int(buf.strip())
                    except ValueError:
                        raise EngraverError(f"unexpected reply {buf!r} to ESC.{letter}", device=self.name) from None
        raise EngraverError(f"no reply to ESC.{letter} within {self.timeout_s:g} s (serial timeout)", device=self.name)

    def capacity(self) -> int:
        """Free bytes in the machine's buffer (ESC.B)."""
        free = self._query("B")
        if self._capacity is None or (not self._streaming and free > self._capacity):
            self._capacity = free
        return free

    def _consumed(self, free: int) -> int:
        buffered = max(0, (self._capacity or free) - free)
        return max(0, self._sent - buffered)

    def _track(self, free: int) -> None:
        if self._tp is None:
            return
        consumed = self._consumed(free)
        k = -1
        for i, end in enumerate(self._ends):
            if end <= consumed:
                k = i
            else:
                break
        if k >= 0:
            self._pos = self._tp.position_after(k)

    def position(self):
        if not self._streaming and self._tp is not None:
            self._track(self.capacity())
        return self._pos

    def state(self) -> str:
        if self._state in ("stopped", "disconnected") or self._streaming:
            return self._state
        code = self._query("O")
        return self._STATUS.get(code, f"status {code}")

    def stop(self) -> None:
        self._stop.set()
        try:
            with self._wlock:
                self._port.write(b"\x1b.K")   # abort: the machine discards its buffer
                self._port.write(b"!MC0;")     # spindle off
                self._port.flush()
        except Exception as e:   # noqa: BLE001
            raise EngraverError(f"could not send the stop sequence: {e}", device=self.name) from None
        finally:
            self._state = "stopped"

    def stream(self, toolpath, *, progress=None) -> StreamReport:
        tp = read_toolpath(toolpath, dialect="rml", units_per_mm=self.limits.rml_units_per_mm)
        check_toolpath(tp, self.limits)
        chunks = [t.encode("ascii") for _, t in tp.commands]
        self._stop.clear()
        self._capacity = None
        self.capacity()                       # the empty buffer's size
        self._tp, self._sent, self._ends, self._pos = tp, 0, [], (None, None, None)
        end = 0
        for c in chunks:
            end += len(c)
            self._ends.append(end)
        self._streaming, self._state = True, "running"
        t0 = time.monotonic()
        try:
            i = 0
            while i < len(chunks):
                if self._stop.is_set():
                    raise EngraverStopped("stopped on request", device=self.name)
                free = self._query("B")
                self._track(free)
                room = free - self.margin
                batch = []
                while i < len(chunks) and len(chunks[i]) <= room:
                    batch.append(chunks[i])
                    room -= len(chunks[i])
                    i += 1
                if not batch:
                    if len(chunks[i]) > self._capacity - self.margin:
                        raise EngraverError(f"instruction {tp.commands[i][1]!r} ({tp.source} line "
                                            f"{tp.commands[i][0]}) is longer than the machine's buffer",
                                            device=self.name)
                    time.sleep(self.poll_s)
                    continue
                data = b"".join(batch)
                self._write(data)
                self._sent += len(data)
                if progress:
                    progress(i, len(chunks))
            while True:                      # until the machine has taken everything
                if self._stop.is_set():
                    raise EngraverStopped("stopped on request", device=self.name)
                free = self._query("B")
                self._track(free)
                if free >= self._capacity:
                    break
                time.sleep(self.poll_s)
            while self._query("O") != 8:
                if self._stop.is_set():
                    raise EngraverStopped("stopped on request", device=self.name)
                time.sleep(self.poll_s)
            self._state = "idle"
        except KeyboardInterrupt:
            self.stop()
            raise
        except EngraverStopped:
            raise
        except EngraverError:
            try:
                self.stop()
            except EngraverError:
                pass
            raise
        finally:
            self._streaming = False
        return StreamReport(commands=len(chunks), seconds=time.monotonic() - t0, position=self._pos)

    def close(self) -> None:
        self._port.close()


# ------------------------------------------------------------------ virtual

class SimulatedEngraver:
    """The virtual engraver: refuses what the real ones refuse, then executes the moves
    instantly (or at ``time_scale`` x their duration at the programmed feeds) and
    records them: ``received`` (the commands) and ``path`` (the moves, in mm)."""

    def __init__(self, limits: MachineLimits, *, dialect: str = "gcode", time_scale: float = 0.0,
                 rapid_mm_s: float = 100.0):
        self.limits, self.dialect = limits, dialect
        self.time_scale, self.rapid_mm_s = time_scale, rapid_mm_s
        self.received: list[str] = []
        self.path: list[Move] = []
        self._pos = (None, None, None)
        self._state = "idle"
        self._stop = threading.Event()

    def stream(self, toolpath, *, progress=None) -> StreamReport:
        tp = read_toolpath(toolpath, dialect=self.dialect, units_per_mm=self.limits.rml_units_per_mm)
        check_toolpath(tp, self.limits)
        self._stop.clear()
        self._state = "running"
        t0 = time.monotonic()
        moves_by_cmd: dict[int, list[Move]] = {}
        for m in tp.moves:
            moves_by_cmd.setdefault(m.index, []).append(m)
        try:
            for k, (_, text) in enumerate(tp.commands):
                if self._stop.is_set():
                    raise EngraverStopped("stopped on request", device="simulated engraver")
                self.received.append(text)
                for m in moves_by_cmd.get(k, []):
                    if self._stop.is_set():
                        raise EngraverStopped("stopped on request", device="simulated engraver")
                    if self.time_scale and None not in m.start and None not in m.end:
                        dist = sum((a - b) ** 2 for a, b in zip(m.end, m.start)) ** 0.5
                        time.sleep(self.time_scale * dist / (m.feed_mm_s or self.rapid_mm_s))
                    self.path.append(m)
                    self._pos = m.end
                if progress:
                    progress(k + 1, len(tp.commands))
            self._state = "idle"
        except EngraverStopped:
            self._state = "stopped"
            raise
        return StreamReport(commands=len(self.received), seconds=time.monotonic() - t0, position=self._pos)

    def position(self):
        return self._pos

    def state(self) -> str:
        return self._state

    def stop(self) -> None:
        self._stop.set()
        self._state = "stopped"

    def close(self) -> None:
        pass
