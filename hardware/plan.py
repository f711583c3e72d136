"""Capture plans: what to shoot, as data (a TOML file), and what it will cost in time.

Thesis 4.2.3 ("Full Process"): for one sample, first the calibration image with all
LEDs on (thesis 4.2.1, table 4.1: f/11, ISO 3200, 30 s), then for each chosen LED
(the thesis used the eight of the middle row) several LDR sequences (three) of the 18
exposures of table 4.1 (f/11, ISO 320, 1/4000 s .. 30 s). Rotating the sample on the
cylinder (thesis 6.2: -45, 0, 45 and 90 degrees) repeats all of that per rotation.

The plan file's format is :data:`PLAN_FORMAT` (also printed by ``glossrig capture --help``).
Its optional ``[led_exposures_s]`` table gives LEDs their own exposure sequences (an
extension of the thesis's one table for all, written by ``glossrig design exposures``,
:mod:`glossrig.core.radiometry.exposure_plan`); every other LED uses ``exposures_s``.

Time. The physical floor of a plan is the sum of its exposure times. The thesis
measured "on average 4 minutes" per 18-exposure sequence (4.2.3); those 18 exposures
add up to 61.0 s, so every shot cost about (240 - 61.0) / 18 = 9.94 s beyond its
exposure (setting the camera over USB, the shutter and mirror cycle, downloading a
~25 MB NEF to the Raspberry Pi). :data:`THESIS_OVERHEAD_S` is that figure and the
default ``overhead_s_per_shot``; measure your own set-up and put it in the plan.
Note: the thesis's "120 minutes (8 LEDs x 3 sequences x 4 minutes) per material" is
96 minutes by its own factors; at 4 min per sequence this module's estimate for one
rotation of the thesis plan is about 97 minutes (96 + the calibration image).
"""
from __future__ import annotations

import hashlib
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from glossrig.core.capture import check_rotation_tags, image_stem
from glossrig.core.errors import InputError
from glossrig.core.resources import resolve_input
from glossrig.core.rig import Rig, load_rig
from glossrig.core.toml_input import check_number

#: Thesis table 4.1 exposure sequence (s) and its sum (61.00725 s).
THESIS_SEQUENCE_S = (0.00025, 0.0005, 0.001, 0.002, 0.004, 0.008, 0.0166, 0.0333, 0.0666, 0.125, 0.25, 0.5,
                     1.0, 2.0, 4.0, 8.0, 15.0, 30.0)
#: Thesis 4.2.3: 4 minutes per 18-exposure sequence -> overhead per shot beyond its exposure (about 9.94 s).
THESIS_OVERHEAD_S = (240.0 - sum(THESIS_SEQUENCE_S)) / len(THESIS_SEQUENCE_S)

#: The capture plan file, as documented to users (``glossrig capture --help``).
PLAN_FORMAT = """\
rig = "scenes/thesis_rig.toml"   # relative to the plan file, the working folder or the repository
sample = "brushed aluminium"     # the material label written to the manifest
rotations = [0]                  # degrees; default: the rig's sample_rotations
leds = [1, 2]                    # ids, or "middle" / "upper" / "lower" / "all"
repeats = 2                      # LDR sequences per LED (thesis m#); default: the rig's sequences_per_led
exposures_s = [0.01, 0.02]       # or "rig" for the rig's table (thesis table 4.1)
                                 # [led_exposures_s] below: per-LED exposures instead
calibration = true               # the all-LEDs calibration image first, per rotation
iso = 320                        # sequence ISO / f-number; default: the rig's
aperture = 11.0
calibration_exposure_s = 30.0    # calibration image settings; default: the rig's
calibration_iso = 3200
calibration_aperture = 11.0
overhead_s_per_shot = 9.94       # measured time per shot beyond the exposure itself
settle_s = 0.0                   # wait after switching LEDs before the next shot

[led_exposures_s]                # optional: these LEDs' sequences use their own exposures
2 = [0.5, 4.0]                   # (glossrig design exposures writes this); the others exposures_s

[checkerboard]                   # optional camera-calibration views, taken first
views = 0                        # the operator is asked to place the board for each
leds = "all"
exposure_s = 30.0                # default: the calibration image's settings
iso = 3200
aperture = 11.0

[twin]                           # only read by the twin backends
material = "lambert:0.8"         # required: ward:..., lambert:ALBEDO, measured:PATH or a scenes/materials
                                 # name; where `sample` names a material too, they must agree
scale = 0.1                      # image scale of the 6032 x 4032 sensor (0.01..1)
seed = 1
effects = "led_drift=0.02"       # named non-idealities, as glossrig simulate --effects;
                                 # default: the thesis's LED fluctuations (led_jitter, led_drift)
ideal = false                    # true: none of the default fluctuations
spp = 4                          # Mitsuba samples per pixel
"""

ROLE_ORDER = ("checkerboard", "calibration", "sequence")
_TOP_KEYS = {"rig", "sample", "rotations", "leds", "repeats", "exposures_s", "calibration", "iso", "aperture",
             "calibration_exposure_s", "calibration_iso", "calibration_aperture", "overhead_s_per_shot",
             "settle_s", "checkerboard", "twin", "led_exposures_s"}
_CHECKER_KEYS = {"views", "leds", "exposure_s", "iso", "aperture"}
_TWIN_KEYS = {"material", "scale", "seed", "effects", "ideal", "spp"}


@dataclass(frozen=True)
class Shot:
    """One planned raw file."""

    index: int
    role: str
    leds: tuple[int, ...]
    rotation: float
    repeat: int
    exposure_s: float
    iso: int
    aperture: float
    exposure_index: int = 0
    view: int | None = None

    @property
    def key(self) -> tuple:
        """Same identity as :meth:`glossrig.core.capture.ImageEntry.key` (used for resume)."""
        return (self.role, tuple(self.leds), float(self.rotation), int(self.repeat), float(self.exposure_s),
                self.view)

    @property
    def stem(self) -> str:
        """File name without extension, unique within a plan (:func:`glossrig.core.capture.image_stem`,
        the one naming scheme ``glossrig simulate`` uses too)."""
        return image_stem(self.role, rotation=self.rotation, leds=self.leds, repeat=self.repeat,
                          exposure_index=self.exposure_index, view=self.view)

    def settings(self) -> tuple[float, int, float]:
        return (self.exposure_s, self.iso, self.aperture)


@dataclass(frozen=True)
class CapturePlan:
    """A validated plan (module docstring); :meth:`shots` lists what it takes."""

    path: str
    text_sha256: str
    rig: Rig
    rig_path: Path
    sample: str
    rotations: tuple[float, ...]
    leds: tuple[int, ...]
    repeats: int
    exposures_s: tuple[float, ...]
    iso: int
    aperture: float
    calibration: bool
    calibration_exposure_s: float
    calibration_iso: int
    calibration_aperture: float
    checkerboard_views: int
    checkerboard_leds: tuple[int, ...]
    checkerboard_exposure_s: float
    checkerboard_iso: int
    checkerboard_aperture: float
    overhead_s_per_shot: float
    settle_s: float
    twin: dict = field(default_factory=dict)
    raw: dict = field(default_factory=dict, repr=False)
    led_exposures_s: dict = field(default_factory=dict)    # LED id -> its own exposures

    def exposures_for(self, led: int) -> tuple[float, ...]:
        """The exposure sequence of one LED: its ``[led_exposures_s]`` entry, else ``exposures_s``."""
        return self.led_exposures_s.get(led, self.exposures_s)

    def shots(self) -> list[Shot]:
        """In capture order (thesis 4.2.3): checkerboard views, then per rotation the
        calibration image and, LED by LED, ``repeats`` sequences of increasing exposure."""
        out: list[Shot] = []

        def add(**kw):
            out.append(Shot(index=len(out), **kw))

        for v in range(self.checkerboard_views):
            add(role="checkerboard", leds=self.checkerboard_leds, rotation=0.0, repeat=0,
                exposure_s=self.checkerboard_exposure_s, iso=self.checkerboard_iso,
                aperture=self.checkerboard_aperture, view=v)
        all_leds = tuple(self.rig.led_ids())
        for rot in self.rotations:
            if self.calibration:
                add(role="calibration", leds=all_leds, rotation=rot, repeat=0,
                    exposure_s=self.calibration_exposure_s, iso=self.calibration_iso,
                    aperture=self.calibration_aperture)
            for led in self.leds:
                for rep in range(self.repeats):
                    for k, t in enumerate(self.exposures_for(led)):
                        add(role="sequence", leds=(led,), rotation=rot, repeat=rep, exposure_s=t, iso=self.iso,
                            aperture=self.aperture, exposure_index=k)
        return out

    def estimate(self, shots: list[Shot] | None = None) -> TimeEstimate:
        shots = self.shots() if shots is None else shots
        floor = sum(s.exposure_s for s in shots)
        return TimeEstimate(shots=len(shots), exposure_s=floor,
                            estimate_s=floor + len(shots) * self.overhead_s_per_shot + self.settle_s * _switches(shots),
                            overhead_s_per_shot=self.overhead_s_per_shot)

    def shot_cost_s(self, shot: Shot) -> float:
        """Expected wall time of one shot (exposure + measured overhead)."""
        return shot.exposure_s + self.overhead_s_per_shot

    def meta(self) -> dict:
        """What the manifest records about the plan."""
        return {"path": self.path, "sha256": self.text_sha256, "sample": self.sample,
                "rotations": list(self.rotations), "leds": list(self.leds), "repeats": self.repeats,
                "exposures_s": list(self.exposures_s),
                "led_exposures_s": {str(k): list(v) for k, v in self.led_exposures_s.items()}, "iso": self.iso, "aperture": self.aperture,
                "calibration": self.calibration, "checkerboard_views": self.checkerboard_views,
                "overhead_s_per_shot": self.overhead_s_per_shot, "planned_images": len(self.shots())}


def _switches(shots: list[Shot]) -> int:
    n, last = 0, None
    for s in shots:
        if s.leds != last:
            n += 1
            last = s.leds
    return n


@dataclass(frozen=True)
class TimeEstimate:
    shots: int
    exposure_s: float        # the physical floor: the sum of exposure times
    estimate_s: float        # with the measured per-shot overhead
    overhead_s_per_shot: float


def format_duration(s: float) -> str:
    s = float(s)
    if s < 60:
        return f"{s:.1f} s"
    m, sec = divmod(int(round(s)), 60)
    if m < 60:
        return f"{m} min {sec:02d} s"
    h, m = divmod(m, 60)
    return f"{h} h {m:02d} min"


# ------------------------------------------------------------------ loading

def _fail(msg: str, path) -> InputError:
    return InputError(msg, path=path)


def _number(d: dict, key: str, path, *, lo: float = 0.0, lo_open: bool = True, hi: float = math.inf,
            where: str = "") -> float:
    return check_number(d[key], where + key, path, lo=lo, lo_open=lo_open, hi=hi)


def _integer(d: dict, key: str, path, *, lo: int, where: str = "") -> int:
    return check_number(d[key], where + key, path, lo=lo, integer=True)


def _exposures(v, path, key: str) -> tuple[float, ...]:
    if not isinstance(v, list) or not v:
        raise _fail(f"{key} must be a non-empty list of exposure times in seconds (or \"rig\"), got {v!r}", path)
    out = []
    for i, t in enumerate(v):
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t <= 0:
            raise _fail(f"{key}[{i}] must be a positive number of seconds, got {t!r}", path)
        out.append(float(t))
    if len(set(out)) != len(out):
        raise _fail(f"{key} lists an exposure time twice", path)
    return tuple(out)


def _leds(rig: Rig, spec, path, key: str) -> tuple[int, ...]:
    if isinstance(spec, list) and not all(isinstance(x, int) and not isinstance(x, bool) for x in spec):
        raise _fail(f"{key} must be LED ids (integers) or \"middle\" / \"upper\" / \"lower\" / \"all\", got {spec!r}",
                    path)
    if not isinstance(spec, (list, str)):
        raise _fail(f"{key} must be a list of LED ids or a row name, got {spec!r}", path)
    try:
        return tuple(rig.select_leds(spec))
    except InputError as e:
        raise _fail(f"{key}: {e}", path) from None


def resolve_rig_path(value: str, plan_path: Path) -> Path:
    """A plan's ``rig``: absolute, or relative to the plan file, the working folder or
    the packaged scenes (:func:`glossrig.core.resources.resolve_input`, so
    ``scenes/thesis_rig.toml`` works from anywhere, installed or not)."""
    return resolve_input(value, f"rig file {value!r}", first=[plan_path.parent], named=plan_path)


def load_plan(path: str | Path) -> CapturePlan:
    """Read and check a capture plan; every error names the plan file and the key. A
    relative ``path`` is looked for in the current folder, then among the packaged scenes
    (``scenes/plans/twin_small.toml`` and ``plans/twin_small.toml`` work from anywhere)."""
    path = resolve_input(path, "capture plan")
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise _fail("capture plan not found", path) from None
    except OSError as e:
        raise _fail(f"cannot read the capture plan: {e}", path) from None
    try:
        raw = tomllib.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise _fail(f"not valid TOML: {e}", path) from None
    unknown = sorted(set(raw) - _TOP_KEYS)
    if unknown:
        raise _fail(f"unknown key(s) {unknown} (known: {sorted(_TOP_KEYS)})", path)
    for key in ("rig", "sample"):
        if key not in raw:
            raise _fail(f"missing key {key!r}", path)
    if not isinstance(raw["rig"], str):
        raise _fail(f"rig must be the path of a rig file, got {raw['rig']!r}", path)
    rig_path = resolve_rig_path(raw["rig"], path)
    rig = load_rig(rig_path)
    sample = raw["sample"]
    if not isinstance(sample, str) or not sample.strip():
        raise _fail(f"sample must be a non-empty label, got {sample!r}", path)

    rots = raw.get("rotations", list(rig.sample_rotations))
    if not isinstance(rots, list) or not rots or not all(
            isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r) and -360 <= r <= 360
            for r in rots):
        raise _fail(f"rotations must be a non-empty list of angles in degrees (-360..360), got {rots!r}", path)
    rots = tuple(float(r) for r in rots)
    if len(set(rots)) != len(rots):
        raise _fail("rotations lists an angle twice", path)
    check_rotation_tags(rots, where=path)

    leds = _leds(rig, raw.get("leds", "middle"), path, "leds")
    repeats = _integer({"repeats": raw.get("repeats", rig.sequences_per_led)}, "repeats", path, lo=1)
    ex = raw.get("exposures_s", "rig")
    exposures = tuple(rig.exposure_times_s) if ex == "rig" else _exposures(ex, path, "exposures_s")
    per_led = raw.get("led_exposures_s", {})
    if not isinstance(per_led, dict):
        raise _fail("[led_exposures_s] must be a table of LED id = [exposure times]", path)
    led_exposures = {}
    for k, v in per_led.items():
        if not k.strip().isdigit() or int(k) not in leds:
            raise _fail(f"[led_exposures_s] key {k!r} is not one of the plan's LEDs {list(leds)}", path)
        led_exposures[int(k)] = _exposures(v, path, f"led_exposures_s.{k}")

    def num(key, default, **kw):
        return _number({key: raw.get(key, default)}, key, path, **kw)

    iso = int(num("iso", rig.sequence_iso, lo=1))
    aperture = num("aperture", rig.sequence_aperture, hi=128)
    calib = raw.get("calibration", True)
    if not isinstance(calib, bool):
        raise _fail(f"calibration must be true or false, got {calib!r}", path)
    cal_exp = num("calibration_exposure_s", rig.calibration_time_s)
    cal_iso = int(num("calibration_iso", rig.calibration_iso, lo=1))
    cal_ap = num("calibration_aperture", rig.calibration_aperture, hi=128)
    rig_overhead = rig.capture.overhead_s_per_shot
    overhead = num("overhead_s_per_shot", THESIS_OVERHEAD_S if rig_overhead is None else rig_overhead,
                   lo=0.0, lo_open=False)
    settle = num("settle_s", 0.0, lo=0.0, lo_open=False, hi=600)

    cb = raw.get("checkerboard", {})
    if not isinstance(cb, dict):
        raise _fail("[checkerboard] must be a table", path)
    unknown = sorted(set(cb) - _CHECKER_KEYS)
    if unknown:
        raise _fail(f"[checkerboard] unknown key(s) {unknown} (known: {sorted(_CHECKER_KEYS)})", path)
    views = _integer({"views": cb.get("views", 0)}, "views", path, lo=0, where="checkerboard.")
    cb_leds = _leds(rig, cb.get("leds", "all"), path, "checkerboard.leds")
    cb_exp = _number({"exposure_s": cb.get("exposure_s", cal_exp)}, "exposure_s", path, where="checkerboard.")
    cb_iso = int(_number({"iso": cb.get("iso", cal_iso)}, "iso", path, lo=1, where="checkerboard."))
    cb_ap = _number({"aperture": cb.get("aperture", cal_ap)}, "aperture", path, hi=128, where="checkerboard.")

    twin = raw.get("twin", {})
    if not isinstance(twin, dict):
        raise _fail("[twin] must be a table", path)
    unknown = sorted(set(twin) - _TWIN_KEYS)
    if unknown:
        raise _fail(f"[twin] unknown key(s) {unknown} (known: {sorted(_TWIN_KEYS)})", path)
    if "material" in twin and not isinstance(twin["material"], str):
        raise _fail(f"twin.material must be a string, got {twin['material']!r}", path)
    if "scale" in twin:
        _number(twin, "scale", path, hi=1.0, where="twin.")
    if "seed" in twin:
        _integer(twin, "seed", path, lo=0, where="twin.")
    if "spp" in twin:
        _integer(twin, "spp", path, lo=1, where="twin.")
    if "ideal" in twin and not isinstance(twin["ideal"], bool):
        raise _fail(f"twin.ideal must be true or false, got {twin['ideal']!r}", path)
    if "effects" in twin and not isinstance(twin["effects"], str):
        raise _fail(f"twin.effects must be a string \"name=value,name=value\", got {twin['effects']!r}", path)

    return CapturePlan(
        path=str(path), text_sha256=hashlib.sha256(text).hexdigest(), rig=rig, rig_path=rig_path,
        sample=sample.strip(), rotations=rots, leds=leds, repeats=repeats, exposures_s=exposures,
        led_exposures_s=led_exposures, iso=iso,
        aperture=aperture, calibration=calib, calibration_exposure_s=cal_exp, calibration_iso=cal_iso,
        calibration_aperture=cal_ap, checkerboard_views=views, checkerboard_leds=cb_leds,
        checkerboard_exposure_s=cb_exp, checkerboard_iso=cb_iso, checkerboard_aperture=cb_ap,
        overhead_s_per_shot=overhead, settle_s=settle, twin=dict(twin), raw=raw)


def describe(plan: CapturePlan, remaining: list[Shot] | None = None) -> str:
    """The plan and its time, as ``--dry-run`` prints it."""
    shots = plan.shots()
    est = plan.estimate(shots)
    by_role = {r: sum(1 for s in shots if s.role == r) for r in ROLE_ORDER}
    lines = [
        f"plan      {plan.path}",
        f"rig       {plan.rig_path} ({plan.rig.name})",
        f"sample    {plan.sample}",
        f"rotations {', '.join(f'{r:g}' for r in plan.rotations)} deg",
        f"LEDs      {', '.join(str(i) for i in plan.leds)}  x {plan.repeats} sequence(s) each",
        f"exposures {len(plan.exposures_s)} per sequence: "
        + ", ".join(f"{t:g}" for t in plan.exposures_s) + f" s at ISO {plan.iso}, f/{plan.aperture:g}",
    ]
    for led, times in sorted(plan.led_exposures_s.items()):
        lines.append(f"  LED {led:2d}: {len(times)} exposure(s): " + ", ".join(f"{t:g}" for t in times) + " s")
    if plan.calibration:
        lines.append(f"calibration image per rotation: all LEDs, {plan.calibration_exposure_s:g} s at ISO "
                     f"{plan.calibration_iso}, f/{plan.calibration_aperture:g}")
    if plan.checkerboard_views:
        lines.append(f"checkerboard views: {plan.checkerboard_views} ({plan.checkerboard_exposure_s:g} s at ISO "
                     f"{plan.checkerboard_iso}, f/{plan.checkerboard_aperture:g}), the operator places the board")
    lines.append(f"images    {len(shots)} (" + ", ".join(f"{n} {r}" for r, n in by_role.items() if n) + ")")
    if len(plan.rotations) > 1:
        lines.append(f"operator  rotates the sample {len(plan.rotations) - 1} time(s) during the capture")
    lines.append(f"time      exposures alone (physical floor): {format_duration(est.exposure_s)}")
    lines.append(f"          estimate with {est.overhead_s_per_shot:.2f} s overhead per shot: "
                 f"{format_duration(est.estimate_s)}")
    seq = sum(plan.exposures_s) + len(plan.exposures_s) * plan.overhead_s_per_shot
    per_rot = plan.estimate([s for s in shots if s.rotation == plan.rotations[0] and s.role != "checkerboard"])
    lines.append(f"          per {len(plan.exposures_s)}-exposure sequence {format_duration(seq)}, per rotation "
                 f"{format_duration(per_rot.estimate_s)} (thesis 4.2.3: 4 min per 18-exposure sequence)")
    if remaining is not None:
        rest = plan.estimate(remaining)
        lines.append(f"resume    {len(remaining)} of {len(shots)} images still to take: "
                     f"{format_duration(rest.estimate_s)} (floor {format_duration(rest.exposure_s)})")
    return "\n".join(lines)
