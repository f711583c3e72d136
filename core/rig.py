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

from glossrig.core import led_fluctuations
from glossrig.core.errors import InputError
from glossrig.core.resources import resolve_input, scenes_dir
from glossrig.core.toml_input import check_number, read_toml

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
    lens: str = ""

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
class Cylinder:
    """``[cylinder]``: the sample cylinder, along the holder frame's y axis (mm)."""

    radius_with_sample: float
    sample_height: float                 # centred on the holder-frame origin
    bottom: float                        # y where the cylinder enters the holder
    top: float
    radius_bare: float | None = None


@dataclass(frozen=True)
class HolderMarker:
    """``[holder.marker]``: the white patch framed by a red square on the holder's front face."""

    outer_width: float
    outer_height: float
    frame: float                         # width of the red frame
    centre_y: float
    #: Lambertian albedo of the white patch; None: the exposure planner's default
    #: (:data:`glossrig.core.radiometry.exposure_plan.WHITE_PATCH_ALBEDO`)
    white_albedo: float | None = None


@dataclass(frozen=True)
class Holder:
    """``[holder]``: the box the cylinder is plugged into (mm); its front face is the marker plane z = depth / 2."""

    width: float                         # along x
    height: float                        # along y
    depth: float                         # along z
    top: float                           # y of the top face
    marker: HolderMarker


@dataclass(frozen=True)
class CylinderMarkers:
    """``[cylinder_markers]``: ``count`` red squares of side ``side`` on a white paper band (mm)."""

    side: float
    count: int
    centre_height: float
    band_bottom: float
    band_top: float
    paper_thickness: float = 0.0


@dataclass(frozen=True)
class Lighting:
    """``[leds]`` apart from its table (which is :attr:`Rig.leds`)."""

    distance_from_axis: float
    row_offset: float
    radiant_intensity_W_sr: float        # twin's and design tools' radiometric scale
    housing_radius: float = 4.0          # LED housing (twin's shadows)
    #: the LEDs' own fluctuations (thesis 4.3.3, fig. 4.12; :mod:`glossrig.core.led_fluctuations`, whose
    #: figures a rig file without these keys gets): relative RMS from frame to frame, the slow drift's
    #: relative amplitude and the range its period (s) is drawn from. The twin simulates them unless
    #: --ideal; diagnose names an LED drift only where it exceeds them (:meth:`drift_slope_rms_per_min`)
    jitter: float = led_fluctuations.LED_JITTER
    drift_amplitude: float = led_fluctuations.LED_DRIFT_AMPLITUDE
    drift_period_s: tuple[float, float] = led_fluctuations.LED_DRIFT_PERIOD_S

    def drift_slope_rms_per_min(self) -> float:
        """RMS relative slope (1/min) of a healthy LED's drift
        (:func:`glossrig.core.led_fluctuations.drift_slope_rms_per_min`)."""
        return led_fluctuations.drift_slope_rms_per_min(self.drift_amplitude, self.drift_period_s)


@dataclass(frozen=True)
class Sensor:
    """``[sensor]``: the photon-transfer figures (twin's sensor, HDR weighting, design noise)."""

    electrons_per_dn_iso100: float       # conversion gain at ISO 100 (e-/DN), scales as 100 / ISO
    read_noise_e: float
    dark_current_e_s: float
    full_well_e: float
    electrons_per_radiance_s_f11: tuple[float, float, float]   # R, G, B at f/11


@dataclass(frozen=True)
class Checkerboard:
    """``[checkerboard]``: the intrinsics target."""

    inner_corners: tuple[int, int]
    square: float                        # mm


@dataclass(frozen=True)
class Reference:
    """``[reference]`` (optional): the diffuse reference sample."""

    material: str
    assumed_albedo: float


@dataclass(frozen=True)
class CaptureTiming:
    """``[capture]`` (optional): timing of a real capture."""

    #: seconds per shot beyond the exposure; None: the capture plan's default
    overhead_s_per_shot: float | None = None


@dataclass(frozen=True)
class Rig:
    """A validated rig file: every section as attributes (read these, not :attr:`raw`)."""

    path: str
    name: str
    #: the parsed file as read, only to compare whole rig files (extract's reference check)
    raw: dict = field(repr=False)
    cylinder: Cylinder
    holder: Holder
    cylinder_markers: CylinderMarkers
    lighting: Lighting
    leds: tuple[Led, ...]
    camera: Camera
    sensor: Sensor
    # [exposures]
    exposure_times_s: tuple[float, ...]
    sequence_iso: int
    sequence_aperture: float
    calibration_iso: int
    calibration_aperture: float
    calibration_time_s: float
    sample_rotations: tuple[float, ...]
    sequences_per_led: int
    checkerboard: Checkerboard
    capture: CaptureTiming
    reference: Reference | None
    description: str = ""

    @property
    def cylinder_radius(self) -> float:
        """Radius of the sample-wrapped cylinder (``cylinder.radius_with_sample``)."""
        return self.cylinder.radius_with_sample

    @property
    def sample_height(self) -> float:
        return self.cylinder.sample_height

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

    def with_leds(self, leds: list[Led]) -> Rig:
        return replace(self, leds=tuple(leds))


_REQUIRED = object()


def _get(d: dict, key: str, path, kind=None, where: str = "", default=_REQUIRED):
    """``d[key]`` (``where``: the section prefix, e.g. ``"camera."``, for the messages);
    ``default`` when given and the key is absent."""
    if key not in d:
        if default is not _REQUIRED:
            return default
        raise InputError(f"missing key {where + key!r}", path=path)
    v = d[key]
    if kind is not None and not isinstance(v, kind):
        raise InputError(f"key {where + key!r} must be {getattr(kind, '__name__', kind)}, got {type(v).__name__}",
                         path=path)
    return v


def _num(d: dict, key: str, path, lo=-math.inf, hi=math.inf, where="", default=_REQUIRED, **kw):
    """The number ``d[key]`` checked by :func:`check_number` (``kw``: its ``lo_open``,
    ``hi_open``, ``integer``); ``default`` when given and the key is absent."""
    if key not in d and default is not _REQUIRED:
        return default
    return check_number(_get(d, key, path, where=where), where + key, path, lo=lo, hi=hi, **kw)


def _nums(d: dict, key: str, path, n: int | None, where: str, what: str = "", **kw) -> tuple:
    """The list ``d[key]`` of ``n`` numbers (any count when None), each checked by :func:`check_number`."""
    v = _get(d, key, path, list, where)
    if n is not None and len(v) != n:
        raise InputError(f"{where}{key} must hold {what or f'{n} values'}, got {v!r}", path=path)
    return tuple(check_number(x, f"{where}{key}[{i}]", path, **kw) for i, x in enumerate(v))


def _str(d: dict, key: str, path, where: str, default=_REQUIRED) -> str:
    v = _get(d, key, path, where=where, default=default)
    if not isinstance(v, str):
        raise InputError(f"{where}{key} must be a string, got {v!r}", path=path)
    return v


def led_position(angle_deg: float, row: str, distance: float, row_offset: float) -> tuple[float, float, float]:
    a = math.radians(angle_deg)
    return (distance * math.sin(a), ROWS[row] * row_offset, distance * math.cos(a))


def _section(raw: dict, name: str, path, optional: bool = False) -> dict:
    """The table ``[name]`` of the rig file (``{}`` when ``optional`` and absent)."""
    return _get(raw, name, path, dict, default={} if optional else _REQUIRED)


def _cylinder(raw: dict, p: str) -> Cylinder:
    cyl, w = _section(raw, "cylinder", p), "cylinder."
    return Cylinder(radius_with_sample=_num(cyl, "radius_with_sample", p, 1, 500, w),
                    sample_height=_num(cyl, "sample_height", p, 1, 1000, w),
                    bottom=_num(cyl, "bottom", p, -1000, 1000, w), top=_num(cyl, "top", p, -1000, 1000, w),
                    radius_bare=_num(cyl, "radius_bare", p, 1, 500, w, default=None))


def _holder(raw: dict, p: str) -> Holder:
    h, w = _section(raw, "holder", p), "holder."
    m, wm = _get(h, "marker", p, dict, w), "holder.marker."
    marker = HolderMarker(outer_width=_num(m, "outer_width", p, 0, 1000, wm, lo_open=True),
                          outer_height=_num(m, "outer_height", p, 0, 1000, wm, lo_open=True),
                          frame=_num(m, "frame", p, 0, 500, wm), centre_y=_num(m, "centre_y", p, -1000, 1000, wm),
                          white_albedo=_num(m, "white_albedo", p, 0, 1, wm, default=None, lo_open=True))
    return Holder(width=_num(h, "width", p, 0, 1000, w, lo_open=True),
                  height=_num(h, "height", p, 0, 1000, w, lo_open=True),
                  depth=_num(h, "depth", p, 0, 1000, w, lo_open=True), top=_num(h, "top", p, -1000, 1000, w),
                  marker=marker)


def _cylinder_markers(raw: dict, p: str) -> CylinderMarkers:
    cm, w = _section(raw, "cylinder_markers", p), "cylinder_markers."
    return CylinderMarkers(side=_num(cm, "side", p, 0, 1000, w, lo_open=True),
                           count=_num(cm, "count", p, 1, 100, w, integer=True),
                           centre_height=_num(cm, "centre_height", p, -1000, 1000, w),
                           band_bottom=_num(cm, "band_bottom", p, -1000, 1000, w),
                           band_top=_num(cm, "band_top", p, -1000, 1000, w),
                           paper_thickness=_num(cm, "paper_thickness", p, 0, 10, w, default=0.0))


def _drift_period(sec: dict, p: str) -> tuple[float, float]:
    """``[leds] drift_period_s = [low, high]``: the range (s) an LED's drift period is drawn from."""
    if "drift_period_s" not in sec:
        return led_fluctuations.LED_DRIFT_PERIOD_S
    lo, hi = _nums(sec, "drift_period_s", p, 2, "leds.", "[low, high] in seconds", lo=1.0, hi=1e6)
    if hi < lo:
        raise InputError(f"leds.drift_period_s must be [low, high] with low <= high, got {[lo, hi]}", path=p)
    return (lo, hi)


def _leds(raw: dict, p: str, radius: float) -> tuple[Lighting, tuple[Led, ...]]:
    sec = _section(raw, "leds", p)
    lighting = Lighting(distance_from_axis=_num(sec, "distance_from_axis", p, radius + 1, 5000, "leds."),
                        row_offset=_num(sec, "row_offset", p, 0, 500, "leds."),
                        radiant_intensity_W_sr=_num(sec, "radiant_intensity_W_sr", p, 0, lo_open=True,
                                                    where="leds."),
                        housing_radius=_num(sec, "housing_radius", p, 0, 100, "leds.", default=4.0, lo_open=True),
                        jitter=_num(sec, "jitter", p, 0, 0.2, "leds.", default=led_fluctuations.LED_JITTER),
                        drift_amplitude=_num(sec, "drift_amplitude", p, 0, 0.5, "leds.",
                                             default=led_fluctuations.LED_DRIFT_AMPLITUDE),
                        drift_period_s=_drift_period(sec, p))
    leds = []
    for i, e in enumerate(_get(sec, "table", p, list, "leds.")):
        w = f"leds.table[{i}]."
        if not isinstance(e, dict):
            raise InputError(f"{w[:-1]} must be a table {{ id = ..., row = ..., ... }}, got {e!r}", path=p)
        row = _get(e, "row", p, where=w)
        if not isinstance(row, str) or row not in ROWS:
            raise InputError(f"{w}row must be one of {sorted(ROWS)}, got {row!r}", path=p)
        angle = _num(e, "angle", p, -180, 180, w)
        d = _num(e, "distance", p, radius + 1, 5000, w, default=lighting.distance_from_axis)
        pos = led_position(angle, row, d, lighting.row_offset)
        if "height" in e:
            pos = (pos[0], _num(e, "height", p, -500, 500, w), pos[2])
        leds.append(Led(id=_num(e, "id", p, 0, where=w, integer=True), row=row, angle_deg=angle,
                        channel=_num(e, "channel", p, 1, where=w, integer=True), name=str(_get(e, "name", p, where=w)),
                        gpio=_num(e, "gpio", p, 0, where=w, integer=True, default=-1), position=pos))
    ids = [led.id for led in leds]
    if len(set(ids)) != len(ids):
        raise InputError("leds.table: duplicate LED ids", path=p)
    chans = [led.channel for led in leds]
    if len(set(chans)) != len(chans):
        raise InputError("leds.table: duplicate relay channels", path=p)
    return lighting, tuple(leds)


def _camera(raw: dict, p: str, radius: float) -> Camera:
    cam, w = _section(raw, "camera", p), "camera."
    img = _nums(cam, "image_px", p, 2, w, "2 values (width, height)", lo=2, integer=True)
    dist_coeffs = _nums(cam, "distortion", p, None, w)
    if len(dist_coeffs) != 5:
        raise InputError("camera.distortion must hold 5 coefficients (k1 k2 p1 p2 k3)", path=p)
    cfa = str(_get(cam, "cfa", p, where=w))
    if sorted(cfa) != sorted("RGGB"):
        raise InputError(f"camera.cfa must be a 2x2 Bayer pattern such as RGGB, got {cfa!r}", path=p)
    bits = int(_num(cam, "bits", p, 8, 16, w))
    white = int(_num(cam, "white_level", p, 1, 2 ** bits - 1, w))
    black = tuple(int(x) for x in _nums(cam, "black_level", p, None, w))
    if len(black) != 4 or any(not (0 <= b < white) for b in black):
        raise InputError("camera.black_level must hold 4 values in [0, white_level)", path=p)
    return Camera(
        model=str(cam.get("model", "camera")), image_px=img,
        sensor_mm=_nums(cam, "sensor_mm", p, 2, w, "2 values (width, height)", lo=0, lo_open=True),
        fx=_num(cam, "fx", p, 1, 1e6, w), fy=_num(cam, "fy", p, 1, 1e6, w),
        cx=_num(cam, "cx", p, 0, img[0], w), cy=_num(cam, "cy", p, 0, img[1], w),
        distortion=dist_coeffs, cfa=cfa, bits=bits, white_level=white, black_level=black,
        distance_to_axis=_num(cam, "distance_to_axis", p, radius + 1, 1e5, w),
        roll_deg=_num(cam, "roll", p, -180, 180, w), lens=str(cam.get("lens", "")))


def _sensor(raw: dict, p: str) -> Sensor:
    sen, w = _section(raw, "sensor", p), "sensor."
    return Sensor(electrons_per_dn_iso100=_num(sen, "electrons_per_dn_iso100", p, 0, where=w, lo_open=True),
                  read_noise_e=_num(sen, "read_noise_e", p, 0, where=w),
                  dark_current_e_s=_num(sen, "dark_current_e_s", p, 0, where=w),
                  full_well_e=_num(sen, "full_well_e", p, 0, where=w, lo_open=True),
                  electrons_per_radiance_s_f11=_nums(sen, "electrons_per_radiance_s_f11", p, 3, w,
                                                     "3 positive numbers (R, G, B)", lo=0, lo_open=True))


def _checkerboard(raw: dict, p: str) -> Checkerboard:
    cb, w = _section(raw, "checkerboard", p), "checkerboard."
    return Checkerboard(inner_corners=_nums(cb, "inner_corners", p, 2, w, "2 counts", lo=2, integer=True),
                        square=_num(cb, "square", p, 0, 1000, w, lo_open=True))


def _reference(raw: dict, p: str) -> Reference | None:
    ref, w = _section(raw, "reference", p, optional=True), "reference."
    if not ref:
        return None
    return Reference(material=_str(ref, "material", p, w),
                     assumed_albedo=_num(ref, "assumed_albedo", p, 0, 1, w, lo_open=True))


def load_rig(path: str | Path) -> Rig:
    """Load and validate a rig TOML file. A relative ``path`` is looked for in the current
    folder, then among the packaged scenes (:func:`glossrig.core.resources.resolve_input`:
    ``scenes/thesis_rig.toml`` and ``thesis_rig.toml`` load from any folder).

    Every section is read and checked here, once (numbers by :func:`check_number`), into
    the attributes of :class:`Rig`; errors name the file and the key."""
    path = resolve_input(path, "rig file")
    raw = read_toml(path, "rig file")
    p = str(path)
    cylinder = _cylinder(raw, p)
    radius = cylinder.radius_with_sample
    lighting, leds = _leds(raw, p, radius)
    camera = _camera(raw, p, radius)

    ex, w = _section(raw, "exposures", p), "exposures."
    times = _nums(ex, "sequence_times_s", p, None, w)
    if not times or any(t <= 0 for t in times) or list(times) != sorted(times):
        raise InputError("exposures.sequence_times_s must be positive and increasing", path=p)
    capture = _section(raw, "capture", p, optional=True)
    return Rig(
        path=p, name=str(raw.get("name", path.stem)), raw=raw, cylinder=cylinder, holder=_holder(raw, p),
        cylinder_markers=_cylinder_markers(raw, p), lighting=lighting, leds=leds, camera=camera,
        sensor=_sensor(raw, p), exposure_times_s=times,
        sequence_iso=int(_num(ex, "sequence_iso", p, 50, 204800, w)),
        sequence_aperture=_num(ex, "sequence_aperture", p, 0.5, 64, w),
        calibration_iso=int(_num(ex, "calibration_iso", p, 50, 204800, w)),
        calibration_aperture=_num(ex, "calibration_aperture", p, 0.5, 64, w),
        calibration_time_s=_num(ex, "calibration_time_s", p, 1e-5, 3600, w),
        sample_rotations=(_nums(ex, "sample_rotations", p, None, w, lo=-360, hi=360)
                          if "sample_rotations" in ex else (0.0,)),
        sequences_per_led=_num(ex, "sequences_per_led", p, 1, where=w, integer=True, default=1),
        checkerboard=_checkerboard(raw, p),
        capture=CaptureTiming(overhead_s_per_shot=_num(capture, "overhead_s_per_shot", p, 0, where="capture.",
                                                       default=None)),
        reference=_reference(raw, p), description=str(raw.get("description", "")),
    )


def default_rig_path() -> Path:
    """The thesis rig among the packaged scenes (found wherever glossrig is installed)."""
    return SCENES_DIR / "thesis_rig.toml"
