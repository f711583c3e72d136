"""Simulated serial devices on pseudo-terminal pairs, speaking the real protocols.

The drivers of :mod:`glossrig.hardware.lights` and :mod:`glossrig.hardware.engraver`
open ``sim.port`` (the pty's slave side, e.g. ``/dev/pts/7``) exactly as they open a
USB serial device; a thread on the master side answers as the device would. This is
how the test suite exercises the drivers at the protocol boundary, and how a driver
can be tried without hardware. **Not for production runs.** POSIX only (``os.openpty``).

* :class:`NumatoRelaySim` - a Numato Lab USB relay module (``relay writeall`` /
  ``relay readall`` / ``ver``; echo, ``\\n\\r``, prompt ``>``). Faults: relays stuck in
  one position, a window of commands whose replies are lost (a serial timeout).
* :class:`GrblSim` - GRBL 1.1 on an Arduino: a 128-byte serial RX buffer and a
  16-block planner, ``ok`` per line once it is planned, real-time ``?`` ``!`` ``~``
  and Ctrl-X, ``<Idle|MPos:...>`` status reports, ``error:N`` and ``ALARM:N``. It flags
  an RX-buffer overflow (data a real GRBL would lose). Faults: an error at line *n*,
  going silent after *n* lines, starting in alarm.
* :class:`RolandSim` - a Roland engraver taking RML-1 into a fixed-size buffer,
  answering the HP-GL/RML device-control queries ``ESC.B`` (free buffer bytes),
  ``ESC.O`` (status: 0 busy, 8 buffer empty) and ``ESC.K`` (abort: clear the buffer).
  It flags a buffer overflow. Fault: going silent.
"""
from __future__ import annotations

import os
import re
import select
import threading
import time
import tty
from collections import deque


class PtyDevice:
    """A device behind a pty pair: ``port`` is what the driver opens."""

    tick_s = 0.002

    def __init__(self):
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self.received = bytearray()
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=type(self).__name__, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], self.tick_s)
            except (OSError, ValueError):
                return
            if ready:
                try:
                    data = os.read(self._master, 4096)
                except OSError:
                    data = b""
                if data:
                    with self._lock:
                        self.received += data
                        self.on_bytes(data)
            with self._lock:
                self.on_tick(time.monotonic())

    def send(self, data: bytes) -> None:
        os.write(self._master, data)

    def on_bytes(self, data: bytes) -> None:
        raise NotImplementedError

    def on_tick(self, now: float) -> None:
        pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class NumatoRelaySim(PtyDevice):
    """A Numato Lab USB relay module with ``channels`` relays.

    ``stuck``: relay index -> state it is stuck in. ``mute_after`` / ``mute_count``:
    after that many commands, the replies to the next ``mute_count`` commands are
    lost (the board still acts on them)."""

    def __init__(self, channels: int = 16, *, stuck: dict | None = None, mute_after: int | None = None,
                 mute_count: int = 0):
        self.channels = channels
        self.mask = 0
        self.stuck = dict(stuck or {})
        self.commands: list[str] = []
        self.mute_after, self.mute_count = mute_after, mute_count
        self._buf = b""
        super().__init__()

    def _effective(self) -> int:
        m = self.mask
        for relay, on in self.stuck.items():
            m = m | (1 << relay) if on else m & ~(1 << relay)
        return m

    def on_bytes(self, data: bytes) -> None:
        self._buf += data
        while b"\r" in self._buf:
            line, self._buf = self._buf.split(b"\r", 1)
            cmd = line.decode("ascii", "replace").strip()
            if cmd:
                self._command(cmd)

    def _command(self, cmd: str) -> None:
        self.commands.append(cmd)
        parts = cmd.split()
        payload = None
        if parts == ["ver"]:
            payload = "00000008"
        elif parts[:2] == ["relay", "readall"]:
            payload = f"{self._effective():0{self.channels // 4}x}"
        elif parts[:2] == ["relay", "writeall"] and len(parts) == 3:
            self.mask = int(parts[2], 16) & ((1 << self.channels) - 1)
        elif parts[:1] == ["relay"] and len(parts) == 3 and parts[1] in ("on", "off", "read"):
            i = int(parts[2], 36)
            if parts[1] == "on":
                self.mask |= 1 << i
            elif parts[1] == "off":
                self.mask &= ~(1 << i)
            else:
                payload = "on" if self._effective() >> i & 1 else "off"
        n = len(self.commands)
        if self.mute_after is not None and self.mute_after < n <= self.mute_after + self.mute_count:
            return
        reply = cmd.encode() + b"\n\r" + ((payload.encode() + b"\n\r") if payload is not None else b"") + b">"
        self.send(reply)

    def on_relays(self) -> set[int]:
        m = self._effective()
        return {i for i in range(self.channels) if m >> i & 1}


_GWORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")


class GrblSim(PtyDevice):
    """GRBL 1.1 (see the module docstring). ``block_s``: time each motion block takes."""

    BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"

    def __init__(self, *, rx_buffer: int = 128, planner: int = 16, block_s: float = 0.0,
                 error_at_line: int | None = None, mute_after_lines: int | None = None, alarm: bool = False):
        self.rx_size, self.planner_size, self.block_s = rx_buffer, planner, block_s
        self.error_at_line, self.mute_after_lines = error_at_line, mute_after_lines
        self.state = "Alarm" if alarm else "Idle"
        self.lines: list[str] = []          # every line taken from the RX buffer, in order
        self.realtime: list[bytes] = []     # ? ! ~ and Ctrl-X, in order
        self.overflow = False
        self.max_rx = 0
        self.mpos = [0.0, 0.0, 0.0]
        self.path: list[tuple[float, float, float]] = []   # executed block targets
        self._rx = bytearray()
        self._planner: deque = deque()
        self._block_end = None
        self._absolute = True
        self._motion = 0
        self._muted = False
        super().__init__()

    def on_bytes(self, data: bytes) -> None:
        for b in data:
            c = bytes([b])
            if c in (b"?", b"!", b"~", b"\x18"):
                self.realtime.append(c)
                self._realtime(c)
            else:
                self._rx += c
        self.max_rx = max(self.max_rx, len(self._rx))
        if len(self._rx) > self.rx_size:
            self.overflow = True

    def _status(self) -> bytes:
        x, y, z = self.mpos
        return f"<{self.state}|MPos:{x:.3f},{y:.3f},{z:.3f}|FS:0,0|WCO:0.000,0.000,0.000>\r\n".encode()

    def _realtime(self, c: bytes) -> None:
        if self._muted:
            return
        if c == b"?":
            self.send(self._status())
        elif c == b"!" and self.state == "Run":
            self.state = "Hold"
        elif c == b"~" and self.state == "Hold":
            self.state = "Run" if self._planner else "Idle"
        elif c == b"\x18":
            moving = bool(self._planner) or self.state in ("Run", "Hold")
            self._rx.clear()
            self._planner.clear()
            self._block_end = None
            if moving:
                self.send(b"ALARM:3\r\n")
            self.send(self.BANNER)
            if moving or self.state == "Alarm":
                self.state = "Alarm"
                self.send(b"[MSG:'$H'|'$X' to unlock]\r\n")
            else:
                self.state = "Idle"

    def _line(self, text: str) -> None:
        self.lines.append(text)
        n = len(self.lines)
        if self.mute_after_lines is not None and n > self.mute_after_lines:
            self._muted = True
            return
        if self.error_at_line == n:
            self.send(b"error:33\r\n")
            return
        if not text:
            self.send(b"ok\r\n")
            return
        if text.startswith("$"):
            if text == "$X" and self.state == "Alarm":
                self.state = "Idle"
                self.send(b"[MSG:Caution: Unlocked]\r\n")
            self.send(b"ok\r\n")
            return
        if self.state == "Alarm":
            self.send(b"error:9\r\n")
            return
        words = _GWORD.findall(text.upper())
        target = list(self._planner[-1] if self._planner else self.mpos)
        moved = False
        for letter, num in words:
            v = float(num)
            if letter == "G":
                if v in (0, 1, 2, 3):
                    self._motion = int(v)
                elif v == 90:
                    self._absolute = True
                elif v == 91:
                    self._absolute = False
            elif letter in "XYZ":
                i = "XYZ".index(letter)
                target[i] = v if self._absolute else target[i] + v
                moved = True
        if moved:
            self._planner.append(tuple(target))
        self.send(b"ok\r\n")

    def on_tick(self, now: float) -> None:
        if self._muted:
            return
        while b"\n" in self._rx and len(self._planner) < self.planner_size and self.state != "Hold":
            i = self._rx.index(b"\n")
            line = bytes(self._rx[:i]).decode("ascii", "replace").strip()
            del self._rx[:i + 1]
            self._line(line)
            if self._muted:
                return
        if self.state in ("Idle", "Run") and self._planner:
            self.state = "Run"
            if self._block_end is None:
                self._block_end = now + self.block_s
            if now >= self._block_end:
                self.mpos = list(self._planner.popleft())
                self.path.append(tuple(self.mpos))
                self._block_end = None
                if not self._planner:
                    self.state = "Idle"


class RolandSim(PtyDevice):
    """A Roland engraver with a ``capacity``-byte command buffer (module docstring).
    ``command_s``: time each RML-1 instruction takes to execute."""

    def __init__(self, *, capacity: int = 256, command_s: float = 0.0, mute: bool = False):
        self.capacity, self.command_s, self.mute = capacity, command_s, mute
        self.buffer = bytearray()
        self.executed: list[str] = []
        self.overflow = False
        self.queries: list[str] = []
        self.aborts = 0
        self._esc = b""
        self._current = None
        super().__init__()

    def on_bytes(self, data: bytes) -> None:
        for b in data:
            c = bytes([b])
            if self._esc or c == b"\x1b":
                self._esc += c
                if len(self._esc) == 3:
                    self._device_control(self._esc[2:3].decode("ascii", "replace"))
                    self._esc = b""
                continue
            if len(self.buffer) >= self.capacity:
                self.overflow = True       # a real machine loses this byte
                continue
            self.buffer += c

    def _device_control(self, letter: str) -> None:
        self.queries.append(letter)
        if letter == "K":
            self.buffer.clear()
            self._current = None
            self.aborts += 1
            return
        if self.mute:
            return
        if letter == "B":
            self.send(f"{self.capacity - len(self.buffer)}\r".encode())
        elif letter == "O":
            self.send(b"8\r" if not self.buffer and self._current is None else b"0\r")
        elif letter == "E":
            self.send(b"0\r")

    def on_tick(self, now: float) -> None:
        if self._current is None:
            if b";" in self.buffer:
                i = self.buffer.index(b";")
                cmd = bytes(self.buffer[:i + 1]).decode("ascii", "replace").strip()
                del self.buffer[:i + 1]
                self._current = (cmd, now + self.command_s)
        elif now >= self._current[1]:
            self.executed.append(self._current[0])
            self._current = None
