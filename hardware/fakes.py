"""Test doubles at the device boundary - for the test suite and for trying the
capture command without hardware. **Not for measurements.**

* :class:`FakeGphoto2` has the surface of the python-gphoto2 module that
  :class:`~glossrig.hardware.camera.Gphoto2Camera` uses (``Camera``, config widgets,
  ``capture``, ``file_get``, ``GPhoto2Error`` with libgphoto2's result codes). Behind
  it a :class:`FakeCameraBody` plays the physical camera: a Nikon-like table of
  shutter speeds / ISOs / f-numbers, a JPEG image-quality default the driver has to
  change, and small but real DNG files (written by the twin's DNG writer) carrying
  the settings the body really used in their EXIF. Faults: a USB drop after *n*
  captures that heals after *k* reconnection attempts (or never), a body that
  ignores exposure settings (mode dial not on M), a slow shutter.
* :class:`DeadRelayPin` is a gpiozero mock pin whose relay never energises.

``glossrig capture --camera fake --lights fake`` (test-only choices) runs the real
gphoto2 and GPIO drivers on these doubles; faults come from the environment
variables ``GLOSSRIG_FAKE_CAMERA`` (``delay_s=0.1,disconnect_after=5,
reconnect_after=2,ignore_settings=1``) and ``GLOSSRIG_FAKE_LIGHTS`` (``dead=5+7``).
"""
from __future__ import annotations

import os
import tempfile
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from gpiozero.pins.mock import MockPin

from glossrig.core.errors import InputError

# libgphoto2 result codes (gphoto2-port-result.h, gphoto2-result.h)
GP_OK = 0
GP_ERROR = -1
GP_ERROR_BAD_PARAMETERS = -2
GP_ERROR_IO = -7
GP_ERROR_IO_USB_FIND = -52
GP_ERROR_MODEL_NOT_FOUND = -105

#: Nikon D750 shutter speeds as gphoto2 lists them (1/3-stop scale, 1/4000 .. 30 s).
NIKON_SHUTTER = ["1/4000", "1/3200", "1/2500", "1/2000", "1/1600", "1/1250", "1/1000", "1/800", "1/640", "1/500",
                 "1/400", "1/320", "1/250", "1/200", "1/160", "1/125", "1/100", "1/80", "1/60", "1/50", "1/40",
                 "1/30", "1/25", "1/20", "1/15", "1/13", "1/10", "1/8", "1/6", "1/5", "1/4", "1/3", "10/25", "1/2",
                 "10/16", "10/13", "1", "13/10", "16/10", "2", "25/10", "3", "4", "5", "6", "8", "10", "13", "15",
                 "20", "25", "30", "Bulb"]
NIKON_ISO = ["100", "125", "160", "200", "250", "320", "400", "500", "640", "800", "1000", "1250", "1600", "2000",
             "2500", "3200", "4000", "5000", "6400", "8000", "10000", "12800"]
LENS_FNUMBER = ["f/4", "f/4.5", "f/5", "f/5.6", "f/6.3", "f/7.1", "f/8", "f/9", "f/10", "f/11", "f/13", "f/14",
                "f/16", "f/18", "f/20", "f/22"]
QUALITY = ["JPEG Basic", "JPEG Normal", "JPEG Fine", "NEF (Raw)", "NEF+Basic", "NEF+Normal", "NEF+Fine"]
TARGET = ["Internal RAM", "Memory card"]


class FakeGPhoto2Error(Exception):
    """Stands for ``gphoto2.GPhoto2Error``: carries libgphoto2's result ``code``."""

    def __init__(self, code: int, string: str = ""):
        self.code = code
        self.string = string or f"libgphoto2 error {code}"
        super().__init__(f"[{code}] {self.string}")


def _parse_value(s: str):
    s = s.strip()
    if s.lower() in ("true", "yes", "on"):
        return True
    try:
        return int(s)
    except ValueError:
        return float(s)


@dataclass
class FakeCameraBody:
    """The physical camera behind the fake binding (its card, settings and faults)."""

    delay_s: float = 0.0                 # time a capture takes (shutter + download)
    disconnect_after: int | None = None  # drop off USB after this many captures
    reconnect_after: int | None = 1      # comes back on this init attempt (None: never)
    ignore_settings: bool = False        # exposure stays at the body's own value (dial on A)
    size: tuple[int, int] = (48, 32)     # (width, height) of the fake raw files
    settings: dict = field(default_factory=lambda: {
        "shutterspeed": "1/125", "iso": "200", "f-number": "f/8", "imagequality": "JPEG Fine",
        "capturetarget": "Memory card"})
    connected: bool = True
    captures: int = 0
    failed_inits: int = 0
    card: dict = field(default_factory=dict)
    log: list = field(default_factory=list)   # (file name, settings used, observe()) per capture
    observe: object = None                    # optional callable recorded with each capture (e.g. lights.state)
    lock: threading.Lock = field(default_factory=threading.Lock)

    CHOICES = {"shutterspeed": NIKON_SHUTTER, "iso": NIKON_ISO, "f-number": LENS_FNUMBER,
               "imagequality": QUALITY, "capturetarget": TARGET}

    @classmethod
    def from_spec(cls, spec: str | None, where: str = "GLOSSRIG_FAKE_CAMERA") -> FakeCameraBody:
        """``key=value,key=value`` (keys: delay_s, disconnect_after, reconnect_after
        (``none`` = never), ignore_settings)."""
        body = cls()
        if not spec:
            return body
        for item in spec.split(","):
            if not item.strip():
                continue
            key, _, value = item.partition("=")
            key = key.strip()
            if key not in ("delay_s", "disconnect_after", "reconnect_after", "ignore_settings"):
                raise InputError(f"unknown fake-camera option {key!r}", path=where)
            try:
                val = None if value.strip().lower() == "none" else _parse_value(value)
            except ValueError:
                raise InputError(f"fake-camera option {key}={value!r} is not a number", path=where) from None
            setattr(body, key, val)
        return body

    def shoot(self) -> str:
        """Take a picture with the current settings; return its name on the card."""
        from glossrig.twin.dng import write_dng    # the twin's DNG writer makes real, readable files

        from .camera import parse_choice
        if self.delay_s:
            time.sleep(self.delay_s)
        with self.lock:
            if self.disconnect_after is not None and self.captures >= self.disconnect_after:
                self.connected = False
                self.failed_inits = 0
                self.disconnect_after = None     # one drop per configured fault
                raise FakeGPhoto2Error(GP_ERROR_IO, "I/O problem (camera dropped off USB)")
            self.captures += 1
            n = self.captures
        exp = parse_choice(self.settings["shutterspeed"])
        iso = float(self.settings["iso"])
        fnum = parse_choice(self.settings["f-number"])
        w, h = self.size
        rng = np.random.default_rng(n)
        level = 600 + min(14000.0, 2.0e5 * exp * iso / 320.0)
        mosaic = np.clip(rng.normal(level, 5.0, size=(h, w)), 0, 15520).astype(np.uint16)
        ext = ".DNG" if self.settings["imagequality"].startswith("NEF") and "+" not in self.settings["imagequality"] \
            else ".JPG"
        name = f"DSC_{n:04d}{ext}"
        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / "shot.dng"
            write_dng(p, mosaic, black_level=(600, 600, 600, 600), white_level=15520, exposure_s=exp, iso=iso,
                      aperture=fnum, time=datetime.now(timezone.utc), make="Nikon", model="D750 (glossrig fake)")
            self.card[name] = p.read_bytes()
        self.log.append((name, dict(self.settings), self.observe() if callable(self.observe) else None))
        return name


class _Widget:
    def __init__(self, name: str, value: str, choices: list[str]):
        self.name, self._value, self._choices = name, value, choices

    def get_value(self):
        return self._value

    def set_value(self, value):
        if value not in self._choices:
            raise FakeGPhoto2Error(GP_ERROR_BAD_PARAMETERS, f"{value!r} is not a choice of {self.name}")
        self._value = value

    def count_choices(self):
        return len(self._choices)

    def get_choice(self, i):
        return self._choices[i]


class _Config:
    def __init__(self, settings: dict):
        self.children = {k: _Widget(k, v, FakeCameraBody.CHOICES[k]) for k, v in settings.items()}

    def get_child_by_name(self, name):
        try:
            return self.children[name]
        except KeyError:
            raise FakeGPhoto2Error(GP_ERROR_BAD_PARAMETERS, f"no widget {name!r}") from None


class _Path:
    def __init__(self, folder, name):
        self.folder, self.name = folder, name


class _Info:
    class _File:
        def __init__(self, size):
            self.size = size

    def __init__(self, size):
        self.file = self._File(size)


class _File:
    def __init__(self, data: bytes):
        self._data = data

    def get_data_and_size(self):
        return memoryview(self._data)


class _Camera:
    FOLDER = "/store_00010001/DCIM/100D750_"

    def __init__(self, body: FakeCameraBody):
        self.body = body
        self._open = False

    def _check(self):
        if not self._open:
            raise FakeGPhoto2Error(GP_ERROR, "camera not initialised")
        if not self.body.connected:
            raise FakeGPhoto2Error(GP_ERROR_IO_USB_FIND, "could not find the requested device on the USB port")

    def init(self):
        b = self.body
        if not b.connected:
            b.failed_inits += 1
            if b.reconnect_after is not None and b.failed_inits >= b.reconnect_after:
                b.connected = True
            else:
                raise FakeGPhoto2Error(GP_ERROR_MODEL_NOT_FOUND, "unknown model")
        self._open = True

    def exit(self):
        self._open = False

    def get_summary(self):
        self._check()
        return "Manufacturer: Nikon Corporation\nModel: D750 (glossrig fake)\n"

    def get_config(self):
        self._check()
        return _Config(self.body.settings)

    def set_config(self, config: _Config):
        self._check()
        for k, w in config.children.items():
            if k == "shutterspeed" and self.body.ignore_settings:
                continue
            self.body.settings[k] = w.get_value()

    def capture(self, kind):
        self._check()
        return _Path(self.FOLDER, self.body.shoot())

    def file_get_info(self, folder, name):
        self._check()
        return _Info(len(self.body.card[name]))

    def file_get(self, folder, name, kind):
        self._check()
        return _File(self.body.card[name])

    def file_delete(self, folder, name):
        self._check()
        self.body.card.pop(name, None)


class FakeGphoto2:
    """Module-like stand-in for ``import gphoto2`` bound to one :class:`FakeCameraBody`."""

    GPhoto2Error = FakeGPhoto2Error
    GP_CAPTURE_IMAGE = 0
    GP_FILE_TYPE_NORMAL = 1
    GP_OK = GP_OK
    GP_ERROR = GP_ERROR
    GP_ERROR_IO = GP_ERROR_IO
    GP_ERROR_IO_USB_FIND = GP_ERROR_IO_USB_FIND
    GP_ERROR_MODEL_NOT_FOUND = GP_ERROR_MODEL_NOT_FOUND

    def __init__(self, body: FakeCameraBody | None = None):
        self.body = body if body is not None else FakeCameraBody()

    def Camera(self):   # noqa: N802 - the binding's name
        return _Camera(self.body)


class DeadRelayPin(MockPin):
    """A gpiozero mock pin wired to a relay that never energises: whatever is
    written, the pin reads high (an active-low relay's "off")."""

    def _set_state(self, value):
        super()._set_state(1)


def fake_lights_spec(spec: str | None, where: str = "GLOSSRIG_FAKE_LIGHTS") -> set[int]:
    """LED ids whose relay is dead, from ``dead=5+7``."""
    dead: set[int] = set()
    if not spec:
        return dead
    for item in spec.split(","):
        key, _, value = item.partition("=")
        if key.strip() != "dead":
            raise InputError(f"unknown fake-lights option {key.strip()!r}", path=where)
        try:
            dead |= {int(v) for v in value.split("+") if v.strip()}
        except ValueError:
            raise InputError(f"fake-lights option dead={value!r}: expected LED ids joined by '+'", path=where) from None
    return dead


def env_spec(name: str) -> str | None:
    return os.environ.get(name) or None
