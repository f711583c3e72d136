"""The camera: set ISO, aperture and exposure; capture one raw file to a given path;
confirm what was shot from the file's own metadata.

Thesis 4.1.2 and 4.2: a Nikon D750 on USB, driven by the Raspberry Pi, shooting raw
(14-bit NEF) at the settings of table 4.1. The thesis's own script built ``gphoto2``
shell commands by string concatenation and overwrote one temporary file per shot;
here the camera is driven through the python-gphoto2 binding (no shell at all) and
every shot goes to the path the orchestrator names.

Confirmation (:func:`confirm_shot`): whatever the driver believes it set, the file is
read back with the pipeline's own reader (:func:`glossrig.core.calibration.raw.read_exif`, plus
LibRaw must be able to open it) and its exposure time, ISO and f-number are compared
with the request. A camera whose mode dial was left on "A", a shutter-speed table
without the requested value, or a file from the wrong shot all stop the capture
instead of silently entering the HDR merge (thesis 4.3.4) with a wrong exposure.
Tolerances: exposure and f-number within 10 %, the tolerance with which the pipeline
cross-checks manifest and file (:func:`glossrig.core.calibration.raw.read_raw`), so every shot
accepted here is accepted there (the thesis's 0.0166 s is the camera's 1/60 s, 0.4 %
apart); ISO within 1 %. The same tolerances decide, before anything is shot, whether
the camera offers a setting close enough to the plan's.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

from glossrig.core.errors import InputError

from .errors import CameraDisconnected, CameraError

#: Largest accepted relative deviation between requested and recorded exposure / f-number
#: (that of glossrig.core.calibration.raw.read_raw's cross-check) and ISO.
REL_TOLERANCE = 0.10
ISO_TOLERANCE = 0.01


@dataclass(frozen=True)
class ShotInfo:
    """What a raw file says about itself (EXIF), as confirmed after a capture."""

    exposure_s: float
    iso: float
    aperture: float
    camera: str | None = None
    time: str | None = None    # ISO 8601 capture time when the camera keeps its own clock (the twin's)


@runtime_checkable
class Camera(Protocol):
    """What the capture orchestrator needs from a camera (thesis 4.2)."""

    #: File name extension of the raw files this camera writes (".nef", ".dng").
    extension: str

    def configure(self, *, exposure_s: float, iso: int, aperture: float) -> None:
        """Set exposure time (s), ISO and f-number for the following captures."""

    def capture(self, path: Path) -> ShotInfo:
        """Take one picture and write its raw file to ``path`` (which must not
        exist); return what the file's metadata say was shot."""

    def close(self) -> None:
        """Release the camera."""

    # Optional (not part of the checked protocol): ``next_shot(shot, at_s)`` - the
    # orchestrator names the planned shot (:class:`glossrig.hardware.plan.Shot`) the next
    # ``capture`` takes and its time on the plan's schedule (s from the start). A real
    # camera has no use for it; the twin's camera keys the image's random stream and
    # timestamp by it, so a resumed simulated capture is byte-identical to an
    # uninterrupted one.


def _rel(a: float, b: float) -> float:
    """Relative difference, as read_raw measures it."""
    return abs(a - b) / max(abs(a), abs(b))


def format_exposure(t: float) -> str:
    """1/60 s style for short exposures, seconds otherwise."""
    if t < 0.3:
        return f"1/{round(1 / t):d} s"
    return f"{t:g} s"


def confirm_shot(path: str | Path, *, exposure_s: float, iso: float, aperture: float) -> ShotInfo:
    """Read ``path``'s own metadata and check it against the requested settings.

    Raises :class:`CameraError` naming the file if LibRaw cannot open it, if a
    field is missing, or if exposure / f-number differ by more than 10 % or ISO
    by more than 1 %.
    """
    import rawpy
    from glossrig.core.calibration.raw import read_exif

    path = Path(path)
    try:
        info = read_exif(path)
    except InputError as e:
        raise CameraError(f"the camera's file is unreadable: {e}") from None
    try:
        with rawpy.imread(str(path)) as raw:
            _ = raw.sizes
    except (rawpy.LibRawError, OSError) as e:
        raise CameraError(f"LibRaw cannot open the camera's file ({e}); not a raw file?", device=str(path)) from None
    missing = [n for n, v in (("exposure time", info.exposure_s), ("ISO", info.iso), ("f-number", info.aperture))
               if v is None]
    if missing:
        raise CameraError(f"the file records no {', '.join(missing)}; cannot confirm what was shot", device=str(path))
    wrong = []
    if _rel(info.exposure_s, exposure_s) > REL_TOLERANCE:
        wrong.append(f"exposure {format_exposure(info.exposure_s)} instead of {format_exposure(exposure_s)}")
    if abs(info.iso / iso - 1) > ISO_TOLERANCE:
        wrong.append(f"ISO {info.iso:g} instead of {iso:g}")
    if _rel(info.aperture, aperture) > REL_TOLERANCE:
        wrong.append(f"f/{info.aperture:g} instead of f/{aperture:g}")
    if wrong:
        raise CameraError("the camera shot " + ", ".join(wrong) + " (is the mode dial on M and the lens's aperture "
                          "ring locked at its minimum?)", device=str(path))
    return ShotInfo(exposure_s=info.exposure_s, iso=info.iso, aperture=info.aperture, camera=info.camera)


# ----------------------------------------------------------------- gphoto2

def parse_choice(text: str) -> float | None:
    """A camera's setting choice as a number: "1/4000", "0.0002s", "30", "2.5s",
    "f/11", "f/5.6", "320". Non-numeric choices ("Bulb", "Auto") give None."""
    s = str(text).strip().lower()
    if s.startswith("f/"):
        s = s[2:]
    s = s.rstrip("s").strip()
    try:
        if "/" in s:
            num, den = s.split("/", 1)
            v = float(num) / float(den)
        else:
            v = float(s)
    except (ValueError, ZeroDivisionError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def nearest_choice(choices: list[str], value: float, *, what: str, tolerance: float, device: str) -> str:
    """The choice closest to ``value``; CameraError if none lies within the
    relative ``tolerance``."""
    best, best_d = None, math.inf
    for c in choices:
        v = parse_choice(c)
        if v is None:
            continue
        d = _rel(v, value)
        if d < best_d:
            best, best_d = c, d
    if best is None or best_d > tolerance:
        shown = ", ".join(choices[:40]) + (" ..." if len(choices) > 40 else "")
        raise CameraError(f"no {what} setting near {value:g} (the camera offers: {shown})", device=device)
    return best


#: Config widget names that hold each setting, in the order tried (Nikon first, then Canon and others).
WIDGET_NAMES = {
    "iso": ("iso", "isospeed"),
    "aperture": ("f-number", "aperture"),
    "exposure": ("shutterspeed", "shutterspeed2", "exposuretime"),
    "quality": ("imagequality", "imageformat"),
    "target": ("capturetarget",),
}
#: libgphoto2 result codes that mean "the camera is gone or stuck on USB".
DISCONNECT_CODES = {
    "GP_ERROR": -1, "GP_ERROR_IO": -7, "GP_ERROR_TIMEOUT": -10, "GP_ERROR_IO_INIT": -31,
    "GP_ERROR_IO_READ": -34, "GP_ERROR_IO_WRITE": -35, "GP_ERROR_IO_UPDATE": -37,
    "GP_ERROR_IO_USB_CLEAR_HALT": -51, "GP_ERROR_IO_USB_FIND": -52, "GP_ERROR_IO_USB_CLAIM": -53,
    "GP_ERROR_MODEL_NOT_FOUND": -105, "GP_ERROR_CAMERA_BUSY": -110,
}


def import_gphoto2():
    """The python-gphoto2 binding, or a clear error saying how to install it."""
    try:
        import gphoto2
    except ImportError:
        raise CameraError("the python-gphoto2 binding is not installed: install libgphoto2 (apt install "
                          "libgphoto2-dev) and then `pip install 'glossrig[camera]'`", device="gphoto2") from None
    return gphoto2


def _is_raw_quality(choice: str) -> bool:
    c = choice.lower()
    return ("raw" in c or "nef" in c) and "+" not in c and "jpeg" not in c and "fine" not in c


class Gphoto2Camera:
    """A tethered camera through libgphoto2's Python binding (thesis 4.1.2, 4.2).

    ``binding``: the ``gphoto2`` module (default: imported lazily; the tests pass a
    fake with the same surface, :mod:`glossrig.hardware.fakes`). ``extension``: the
    raw files' extension (Nikon: ``.nef``); a capture delivering anything else (a
    JPEG because the quality setting was changed) is refused.

    On connection the driver selects raw-only image quality and, where the camera
    has the setting, ``capture_target`` (default the camera's internal RAM, so the
    card does not fill up over a night). If a libgphoto2 call fails with a USB /
    I/O error (:data:`DISCONNECT_CODES`) the driver closes the camera, waits
    ``reconnect_wait_s`` and reconnects, up to ``reconnect_attempts`` times, then
    re-applies the settings and retakes the shot once; if the camera stays away it
    raises :class:`CameraDisconnected` and the orchestrator stops with the
    capture resumable.
    """

    def __init__(self, binding=None, *, extension: str = ".nef", capture_target: str | None = "Internal RAM",
                 reconnect_attempts: int = 5, reconnect_wait_s: float = 3.0, sleep=time.sleep):
        self.gp = binding if binding is not None else import_gphoto2()
        self.extension = extension.lower()
        self.capture_target = capture_target
        self.reconnect_attempts = reconnect_attempts
        self.reconnect_wait_s = reconnect_wait_s
        self._sleep = sleep
        self._settings: dict | None = None
        self._cam = None
        self.model = "camera"
        self.reconnects = 0
        self._connect()

    # -- connection
    @property
    def name(self) -> str:
        return f"gphoto2 camera {self.model}"

    def _code(self, e) -> int | None:
        return getattr(e, "code", None)

    def _is_disconnect(self, e) -> bool:
        codes = {getattr(self.gp, n, v) for n, v in DISCONNECT_CODES.items()}
        return isinstance(e, self.gp.GPhoto2Error) and self._code(e) in codes

    def _connect(self) -> None:
        gp = self.gp
        cam = gp.Camera()
        try:
            cam.init()
        except gp.GPhoto2Error as e:
            raise CameraDisconnected(f"no camera found on USB ({e}); is it switched on, connected, and not "
                                     "claimed by another program (gvfs, a file manager)?", device="gphoto2") from None
        self._cam = cam
        try:
            summary = str(cam.get_summary())
            for line in summary.splitlines():
                if line.strip().lower().startswith("model:"):
                    self.model = line.split(":", 1)[1].strip()
                    break
        except gp.GPhoto2Error:
            pass
        self._prepare()
        if self._settings is not None:
            self._apply(**self._settings)

    def _reconnect(self, cause) -> None:
        try:
            self._cam.exit()
        except Exception:   # noqa: BLE001 - the camera is already gone
            pass
        self._cam = None
        for _attempt in range(1, self.reconnect_attempts + 1):
            self._sleep(self.reconnect_wait_s)
            try:
                self._connect()
                self.reconnects += 1
                return
            except CameraDisconnected:
                continue
        raise CameraDisconnected(f"the camera dropped off USB ({cause}) and did not come back after "
                                 f"{self.reconnect_attempts} attempts over "
                                 f"{self.reconnect_attempts * self.reconnect_wait_s:g} s", device=self.name)

    def _widget(self, config, key: str):
        for name in WIDGET_NAMES[key]:
            try:
                return config.get_child_by_name(name)
            except self.gp.GPhoto2Error:
                continue
        return None

    def _choices(self, widget) -> list[str]:
        return [str(widget.get_choice(i)) for i in range(widget.count_choices())]

    def _prepare(self) -> None:
        """Raw-only image quality and the capture target, where the camera has them."""
        config = self._cam.get_config()
        changed = False
        quality = self._widget(config, "quality")
        if quality is not None and not _is_raw_quality(str(quality.get_value())):
            raw = [c for c in self._choices(quality) if _is_raw_quality(c)]
            if not raw:
                raise CameraError(f"cannot select raw-only image quality (choices: {self._choices(quality)})",
                                  device=self.name)
            quality.set_value(raw[0])
            changed = True
        target = self._widget(config, "target") if self.capture_target else None
        if target is not None and str(target.get_value()) != self.capture_target:
            if self.capture_target in self._choices(target):
                target.set_value(self.capture_target)
                changed = True
        if changed:
            self._cam.set_config(config)

    def _apply(self, *, exposure_s: float, iso: int, aperture: float) -> None:
        config = self._cam.get_config()
        for key, value, what, tol in (("exposure", exposure_s, "shutter speed", REL_TOLERANCE),
                                      ("iso", iso, "ISO", ISO_TOLERANCE),
                                      ("aperture", aperture, "f-number", REL_TOLERANCE)):
            widget = self._widget(config, key)
            if widget is None:
                raise CameraError(f"the camera exposes no {what} setting ({'/'.join(WIDGET_NAMES[key])}); "
                                  "is it in manual (M) mode?", device=self.name)
            widget.set_value(nearest_choice(self._choices(widget), float(value), what=what, tolerance=tol,
                                            device=self.name))
        self._cam.set_config(config)

    def _retrying(self, fn):
        try:
            return fn()
        except self.gp.GPhoto2Error as e:
            if not self._is_disconnect(e):
                raise CameraError(f"libgphoto2 error: {e}", device=self.name) from None
            self._reconnect(e)
        try:
            return fn()
        except self.gp.GPhoto2Error as e:
            if self._is_disconnect(e):
                raise CameraDisconnected(f"the camera failed again right after reconnecting ({e})",
                                         device=self.name) from None
            raise CameraError(f"libgphoto2 error: {e}", device=self.name) from None

    # -- the protocol
    def configure(self, *, exposure_s: float, iso: int, aperture: float) -> None:
        settings = dict(exposure_s=float(exposure_s), iso=int(iso), aperture=float(aperture))
        self._retrying(lambda: self._apply(**settings))
        self._settings = settings

    def capture(self, path: Path) -> ShotInfo:
        if self._settings is None:
            raise CameraError("capture() before configure()", device=self.name)
        path = Path(path)
        self._retrying(lambda: self._capture_to(path))
        return confirm_shot(path, **self._settings)

    def _capture_to(self, path: Path) -> None:
        gp = self.gp
        where = self._cam.capture(gp.GP_CAPTURE_IMAGE)
        folder, name = where.folder, where.name
        if not name.lower().endswith(self.extension):
            raise CameraError(f"the camera delivered {name!r}, not a {self.extension} raw file; set the image "
                              "quality to raw only", device=self.name)
        size = None
        try:
            size = int(self._cam.file_get_info(folder, name).file.size)
        except (gp.GPhoto2Error, AttributeError):
            pass
        cfile = self._cam.file_get(folder, name, gp.GP_FILE_TYPE_NORMAL)
        data = memoryview(cfile.get_data_and_size())
        # Written here rather than with CameraFile.save so that a full disk is an
        # OSError (ENOSPC) and not an anonymous libgphoto2 I/O error.
        with open(path, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        got = path.stat().st_size
        if size is not None and size > 0 and got != size:
            raise CameraError(f"download of {name} is incomplete: {got} of {size} bytes", device=self.name)
        try:
            self._cam.file_delete(folder, name)
        except gp.GPhoto2Error:
            pass   # RAM captures vanish on their own; a card keeps the spare copy

    def close(self) -> None:
        if self._cam is not None:
            try:
                self._cam.exit()
            except Exception:   # noqa: BLE001 - closing a vanished camera
                pass
            self._cam = None
