"""The rig description (design.md): one TOML file, millimetres and degrees.

One source for the twin, the pipeline's nominal geometry, the hardware channel
map and the design tools. Frames are documented at the top of
``scenes/thesis_rig.toml``; :func:`load_rig` validates units, ranges and keys
and names the file and key in every error.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.resources import resolve_input, scenes_dir
from glossrig.core.toml_input import read_toml

#: the folder holding core/: the checkout's root, or site-packages/glossrig when installed
REPO_ROOT = Path(__file__).resolve().parent.parent
#: the packaged scenes (glossrig.scenes: the checkout's scenes/ or the installed copy)
SCENES_DIR = scenes_dir()
ROWS = {"upper": 1.0, "middle": 0.0, "lower": -1.0}


@dataclass(frozen=True)
class Led:
    id: int
    row: str
    angle_deg: float
    channel: int
    name: str
    gpio: int
    position: tuple[float, float, float]   # holder frame, mm


@dataclass(frozen=True)
class Camera:
    """Pinhole + OpenCV distortion (k1 k2 p1 p2 k3) at full sensor resolution."""

    model: str
    image_px: tuple[int, int]
    sensor_mm: tuple[float, float]
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...]
    cfa: str
    bits: int
    white_level: int
    black_level: tuple[int, int, int, int]
    distance_to_axis: float
    roll_deg: float

    def matrix(self, scale: float = 1.0) -> np.ndarray:
        """Camera matrix for an image resampled by ``scale`` (pixel centres at
        integer coordinates: c' = (c + 0.5) * s - 0.5)."""
        return np.array([[self.fx * scale, 0, (self.cx + 0.5) * scale - 0.5],
                         [0, self.fy * scale, (self.cy + 0.5) * scale - 0.5],
                         [0, 0, 1.0]])

    def size(self, scale: float = 1.0) -> tuple[int, int]:
        """(width, height) in pixels at ``scale``; even, so the CFA tiles."""
        w, h = self.image_px
        return (max(2, int(round(w * scale / 2)) * 2), max(2, int(round(h * scale / 2)) * 2))

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Nominal world(holder)->camera rotation R and translation t (OpenCV:
        x_cam = R x_holder + t). The camera sits on +z at ``distance_to_axis``
        looking at the axis; rolled so the cylinder axis (+y) runs along -x in
        the image (holder on the right, thesis 4.3.2)."""
        roll = math.radians(self.roll_deg)
        # Unrolled: cam x = holder +x, cam y = holder -y, cam z = holder -z.
        base = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
        c, s = math.cos(roll), math.sin(roll)
        rz = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]])   # clockwise image roll
        R = rz @ base
        centre = np.array([0.0, 0.0, self.distance_to_axis])
        return R, -R @ centre


@dataclass(frozen=True)
class Rig:
    path: str
    name: str
    raw: dict = field(repr=False)
    cylinder_radius: float
    sample_height: float
    leds: tuple[Led, ...]
    camera: Camera
    exposure_times_s: tuple[float, ...]
    sequence_iso: int
    sequence_aperture: float
    calibration_iso: int
    calibration_aperture: float
    calibration_time_s: float
    sample_rotations: tuple[float, ...]

    def led(self, led_id: int) -> Led:
        for led in self.leds:
            if led.id == led_id:
                return led
        raise InputError(f"LED id {led_id} is not in rig {self.name!r} (ids {self.led_ids()})", path=self.path)

    def led_ids(self) -> list[int]:
        return [led.id for led in self.leds]

    def select_leds(self, spec: str | list) -> list[int]:
        """``middle``, ``all``, a row name, a comma-separated list or a list of ids."""
        if isinstance(spec, (list, tuple)):
            ids = [int(x) for x in spec]
        elif spec in ("all",):
            return self.led_ids()
        elif spec in ROWS:
            return [led.id for led in self.leds if led.row == spec]
        else:
            try:
                ids = [int(x) for x in str(spec).split(",") if x.strip()]
            except ValueError:
                raise InputError(f"LEDs: expected 'middle', 'all', a row or comma-separated ids, got {spec!r}") from None
        if not ids:
            raise InputError("LEDs: empty selection")
        for i in ids:
            self.led(i)
        if len(set(ids)) != len(ids):
            raise InputError(f"LEDs: duplicate ids in {spec!r}")
        return ids

    def section(self, name: str) -> dict:
        return _get(self.raw, name, self.path)

    def with_leds(self, leds: list[Led]) -> Rig:
        return replace(self, leds=tuple(leds))


def _get(d: dict, key: str, path, kind=None):
    if key not in d:
        raise InputError(f"missing key {key!r}", path=path)
    v = d[key]
    if kind is not None and not isinstance(v, kind):
        raise InputError(f"key {key!r} must be {getattr(kind, '__name__', kind)}, got {type(v).__name__}", path=path)
    return v


def _num(d: dict, key: str, path, lo=-math.inf, hi=math.inf, where="") -> float:
    v = _get(d, key, path)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"{where}{key} must be a number, got {v!r}", path=path)
    if not (lo <= v <= hi):
        raise InputError(f"{where}{key}={v} outside [{lo}, {hi}]", path=path)
    return float(v)


def led_position(angle_deg: float, row: str, distance: float, row_offset: float) -> tuple[float, float, float]:
    a = math.radians(angle_deg)
    return (distance * math.sin(a), ROWS[row] * row_offset, distance * math.cos(a))


def load_rig(path: str | Path) -> Rig:
    """Load and validate a rig TOML file. A relative ``path`` is looked for in the current
    folder, then among the packaged scenes (:func:`glossrig.core.resources.resolve_input`:
    ``scenes/thesis_rig.toml`` and ``thesis_rig.toml`` load from any folder)."""
    path = resolve_input(path, "rig file")
    raw = read_toml(path, "rig file")
    p = str(path)
    cyl = _get(raw, "cylinder", p, dict)
    radius = _num(cyl, "radius_with_sample", p, 1, 500, "cylinder.")
    height = _num(cyl, "sample_height", p, 1, 1000, "cylinder.")

    leds_sec = _get(raw, "leds", p, dict)
    dist = _num(leds_sec, "distance_from_axis", p, radius + 1, 5000, "leds.")
    row_off = _num(leds_sec, "row_offset", p, 0, 500, "leds.")
    table = _get(leds_sec, "table", p, list)
    leds = []
    for i, e in enumerate(table):
        w = f"leds.table[{i}]."
        for k in ("id", "row", "angle", "channel", "name"):
            _get(e, k, p)
        if e["row"] not in ROWS:
            raise InputError(f"{w}row must be one of {sorted(ROWS)}, got {e['row']!r}", path=p)
        angle = _num(e, "angle", p, -180, 180, w)
        if "distance" in e:
            d = _num(e, "distance", p, radius + 1, 5000, w)
        else:
            d = dist
        pos = led_position(angle, e["row"], d, row_off)
        if "height" in e:
            pos = (pos[0], _num(e, "height", p, -500, 500, w), pos[2])
        leds.append(Led(id=int(e["id"]), row=e["row"], angle_deg=angle, channel=int(e["channel"]),
                        name=str(e["name"]), gpio=int(e.get("gpio", -1)), position=pos))
    ids = [led.id for led in leds]
    if len(set(ids)) != len(ids):
        raise InputError("leds.table: duplicate LED ids", path=p)
    chans = [led.channel for led in leds]
    if len(set(chans)) != len(chans):
        raise InputError("leds.table: duplicate relay channels", path=p)

    cam = _get(raw, "camera", p, dict)
    img = _get(cam, "image_px", p, list)
    dist_coeffs = tuple(float(x) for x in _get(cam, "distortion", p, list))
    if len(dist_coeffs) != 5:
        raise InputError("camera.distortion must hold 5 coefficients (k1 k2 p1 p2 k3)", path=p)
    cfa = str(_get(cam, "cfa", p))
    if sorted(cfa) != sorted("RGGB"):
        raise InputError(f"camera.cfa must be a 2x2 Bayer pattern such as RGGB, got {cfa!r}", path=p)
    bits = int(_num(cam, "bits", p, 8, 16, "camera."))
    white = int(_num(cam, "white_level", p, 1, 2 ** bits - 1, "camera."))
    black = tuple(int(x) for x in _get(cam, "black_level", p, list))
    if len(black) != 4 or any(not (0 <= b < white) for b in black):
        raise InputError("camera.black_level must hold 4 values in [0, white_level)", path=p)
    camera = Camera(
        model=str(cam.get("model", "camera")), image_px=(int(img[0]), int(img[1])),
        sensor_mm=tuple(float(x) for x in _get(cam, "sensor_mm", p, list)),
        fx=_num(cam, "fx", p, 1, 1e6, "camera."), fy=_num(cam, "fy", p, 1, 1e6, "camera."),
        cx=_num(cam, "cx", p, 0, img[0], "camera."), cy=_num(cam, "cy", p, 0, img[1], "camera."),
        distortion=dist_coeffs, cfa=cfa, bits=bits, white_level=white, black_level=black,
        distance_to_axis=_num(cam, "distance_to_axis", p, radius + 1, 1e5, "camera."),
        roll_deg=_num(cam, "roll", p, -180, 180, "camera."))

    ex = _get(raw, "exposures", p, dict)
    times = tuple(float(t) for t in _get(ex, "sequence_times_s", p, list))
    if not times or any(t <= 0 for t in times) or list(times) != sorted(times):
        raise InputError("exposures.sequence_times_s must be positive and increasing", path=p)
    for sec in ("holder", "cylinder_markers", "sensor"):
        _get(raw, sec, p, dict)
    return Rig(
        path=p, name=str(raw.get("name", path.stem)), raw=raw, cylinder_radius=radius, sample_height=height,
        leds=tuple(leds), camera=camera, exposure_times_s=times,
        sequence_iso=int(_num(ex, "sequence_iso", p, 50, 204800, "exposures.")),
        sequence_aperture=_num(ex, "sequence_aperture", p, 0.5, 64, "exposures."),
        calibration_iso=int(_num(ex, "calibration_iso", p, 50, 204800, "exposures.")),
        calibration_aperture=_num(ex, "calibration_aperture", p, 0.5, 64, "exposures."),
        calibration_time_s=_num(ex, "calibration_time_s", p, 1e-5, 3600, "exposures."),
        sample_rotations=tuple(float(r) for r in ex.get("sample_rotations", [0.0])),
    )


def default_rig_path() -> Path:
    """The thesis rig among the packaged scenes (found wherever glossrig is installed)."""
    return SCENES_DIR / "thesis_rig.toml"
