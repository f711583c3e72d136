"""The twin's catalogue of named, parameterised non-idealities (issue 2).

Each effect is off unless asked for (``--effects name=value``), is recorded in
truth.json, and has one scalar magnitude with a physical meaning. Later work
hides these in captures and asks the pipeline to find them, so each is
physically plausible and documented here. Where an effect needs random
per-LED or per-pixel detail (directions, phases, which pixels), that detail is
drawn from the capture's seed and recorded in the truth as well.

The rig's own baseline LED fluctuations (thesis 4.3.3, fig. 4.12) are the same
two effects ``led_jitter`` and ``led_drift`` at the magnitudes its rig file states
(:func:`rig_fluctuations`; ``[leds]`` of the rig file, :class:`glossrig.core.rig.Lighting`);
``glossrig simulate`` applies them unless ``--ideal`` is given, and ``--effects``
overrides either. The drift's period is drawn per LED in the rig file's
``drift_period_s`` range whatever the drift's amplitude.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.led_fluctuations import LED_DRIFT_PERIOD_S


@dataclass(frozen=True)
class Effect:
    name: str
    unit: str
    typical: float          # a realistic magnitude (used by tests / blind studies)
    low: float              # accepted range
    high: float
    doc: str


CATALOGUE: dict[str, Effect] = {e.name: e for e in [
    Effect("led_jitter", "relative RMS", 0.005, 0.0, 0.2,
           "High-frequency LED intensity fluctuation (thesis 4.3.3, fig. 4.12): every frame's LED "
           "output is multiplied by an independent N(1, value) factor (supply ripple, thermal noise)."),
    Effect("led_drift", "relative amplitude", 0.01, 0.0, 0.5,
           "Low-frequency LED intensity drift over the capture (thesis fig. 4.12): per LED "
           "1 + value * sin(2 pi t / P + phase), P drawn in 20-60 min (warm-up, temperature)."),
    Effect("led_emission", "cos exponent n", 20.0, 0.0, 500.0,
           "Angular emission pattern remaining after the diffuser (thesis 4.1.3, fig. 4.2): radiant "
           "intensity ~ cos^n of the angle to the LED's optical axis, the axis tilted by 2 degrees in a "
           "random direction per LED; normalised to 1 towards the cylinder axis."),
    Effect("led_position_error", "mm RMS per axis", 2.0, 0.0, 30.0,
           "Each LED sits off its nominal hole by an independent N(0, value) offset per axis "
           "(hand-mounted holders, thesis 4.1.5); the pipeline still assumes the nominal position."),
    Effect("vignetting", "relative fall-off at the corner", 0.1, 0.0, 0.9,
           "Lens vignetting: irradiance at the sensor multiplied by 1 - value * (r / r_corner)^2, r the "
           "distance from the principal point."),
    Effect("sensor_nonlinearity", "relative compression at white", 0.02, 0.0, 0.3,
           "Compressive sensor response: signal above black x -> x (1 - value * x / (white - black))."),
    Effect("black_level_offset", "DN", 5.0, -50.0, 200.0,
           "The true black level differs from the one the raw file states by value DN (all channels); "
           "the DNG keeps the nominal black level."),
    Effect("stray_light", "fraction of the LED's direct irradiance", 0.003, 0.0, 0.2,
           "Light scattered by the box and board (thesis 4.1.5): a uniform radiance "
           "value * I / (pi d^2) added to every pixel while an LED is on (d = LED distance)."),
    Effect("sample_radius_error", "mm", 0.3, -3.0, 3.0,
           "The wrapped sample's outer radius differs from the rig file's by value mm (paper and "
           "sample thickness, thesis 4.1.4)."),
    Effect("sample_rotation_offset", "degrees", 2.0, -20.0, 20.0,
           "The sample is wrapped turned by value degrees from the rotation the capture states."),
    Effect("hot_pixels", "fraction of pixels", 2e-4, 0.0, 0.01,
           "A random fraction of pixels has a dark current of 200 e-/s instead of the nominal one."),
]}



def rig_fluctuations(rig) -> dict[str, float]:
    """The rig's own LED fluctuations as twin effects: ``[leds] jitter`` and ``drift_amplitude`` of its
    file (:class:`glossrig.core.rig.Lighting`; diagnose expects the same of a healthy rig)."""
    return {"led_jitter": rig.lighting.jitter, "led_drift": rig.lighting.drift_amplitude}


HOT_PIXEL_RATE_E_S = 200.0
EMISSION_TILT_DEG = 2.0


def parse_effects(text: str | None) -> dict[str, float]:
    """``name=value,name=value`` -> dict; unknown names and out-of-range values are errors."""
    out: dict[str, float] = {}
    if not text:
        return out
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "=" not in part:
            raise InputError(f"--effects: expected name=value, got {part!r}")
        k, v = (s.strip() for s in part.split("=", 1))
        if k not in CATALOGUE:
            raise InputError(f"--effects: unknown effect {k!r}; known: {', '.join(CATALOGUE)}")
        try:
            x = float(v)
        except ValueError:
            raise InputError(f"--effects: {k}={v!r} is not a number") from None
        e = CATALOGUE[k]
        if not (e.low <= x <= e.high) or not math.isfinite(x):
            raise InputError(f"--effects: {k}={x} outside its plausible range [{e.low}, {e.high}] ({e.unit})")
        out[k] = x
    return out


@dataclass
class EffectState:
    """The effects of one capture with their seeded random detail."""

    values: dict[str, float]
    seed: int
    led_ids: list[int]
    detail: dict = field(default_factory=dict)
    #: the range (s) each LED's drift period is drawn from: the rig file's ``[leds] drift_period_s``
    drift_period_s: tuple[float, float] = LED_DRIFT_PERIOD_S

    def __post_init__(self):
        rng = np.random.default_rng([self.seed, 7])
        n = len(self.led_ids)
        self.detail["drift_period_s"] = dict(zip(self.led_ids, rng.uniform(*self.drift_period_s, n).tolist()))
        self.detail["drift_phase"] = dict(zip(self.led_ids, rng.uniform(0, 2 * np.pi, n).tolist()))
        tilt_dir = rng.uniform(0, 2 * np.pi, n)
        self.detail["emission_tilt_dir"] = dict(zip(self.led_ids, tilt_dir.tolist()))
        sigma = self.get("led_position_error")
        offs = rng.normal(0.0, 1.0, (n, 3)) * sigma
        self.detail["led_offset_mm"] = {i: offs[k].tolist() for k, i in enumerate(self.led_ids)}

    def get(self, name: str) -> float:
        return float(self.values.get(name, 0.0))

    # --- geometry -------------------------------------------------------
    def led_position(self, led) -> tuple[float, float, float]:
        off = self.detail["led_offset_mm"][led.id]
        return tuple(float(p + o) for p, o in zip(led.position, off))

    # --- LED output -------------------------------------------------------
    def led_gain(self, led_id: int, t_s: float, rng: np.random.Generator) -> float:
        g = 1.0
        if self.get("led_jitter") > 0:
            g *= 1.0 + rng.normal(0.0, self.get("led_jitter"))
        if self.get("led_drift") > 0:
            p = self.detail["drift_period_s"][led_id]
            g *= 1.0 + self.get("led_drift") * math.sin(2 * math.pi * t_s / p + self.detail["drift_phase"][led_id])
        return g

    def emission_factor(self, led_id: int, led_pos, points_mm: np.ndarray) -> np.ndarray | None:
        """cos^n pattern about the LED's tilted axis at the scene points (h, w, 3), or None."""
        n = self.get("led_emission")
        if n <= 0:
            return None
        p = np.asarray(led_pos, float)
        axis = -np.array([p[0], 0.0, p[2]])
        axis /= np.linalg.norm(axis)
        up = np.array([0.0, 1.0, 0.0])
        side = np.cross(axis, up)
        tdir = self.detail["emission_tilt_dir"][led_id]
        tilt = math.radians(EMISSION_TILT_DEG)
        a = math.cos(tilt) * axis + math.sin(tilt) * (math.cos(tdir) * up + math.sin(tdir) * side)
        d = points_mm - p
        d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)
        c = np.clip(d @ a, 0.0, 1.0)
        ref = max(float(axis @ a), 1e-6)   # direction to the cylinder axis
        return ((c / ref) ** n).astype(np.float32)

    def vignetting_factor(self, size, K) -> np.ndarray | None:
        k = self.get("vignetting")
        if k <= 0:
            return None
        w, h = size
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = (xx - K[0, 2]) ** 2 + (yy - K[1, 2]) ** 2
        rc2 = max((K[0, 2]) ** 2, (w - 1 - K[0, 2]) ** 2) + max(K[1, 2] ** 2, (h - 1 - K[1, 2]) ** 2)
        return (1.0 - k * r2 / rc2).astype(np.float32)

    def stray_radiance(self, intensity_W_sr: float, distance_mm: float) -> float:
        s = self.get("stray_light")
        if s <= 0:
            return 0.0
        d_m = distance_mm * 1e-3
        return s * intensity_W_sr / (math.pi * d_m * d_m)

    # --- sensor -------------------------------------------------------------
    def hot_pixel_mask(self, size, seed: int) -> np.ndarray | None:
        f = self.get("hot_pixels")
        if f <= 0:
            return None
        w, h = size
        rng = np.random.default_rng([seed, 11])
        return rng.random((h, w)) < f

    def apply_dn(self, dn: np.ndarray, black: np.ndarray, white: int, exposure_s: float, e_per_dn: float,
                 hot: np.ndarray | None) -> np.ndarray:
        """Sensor-level effects on a float DN mosaic (before the final rounding/clipping)."""
        if self.get("sensor_nonlinearity") > 0:
            # compress only within the sensor's range: above white the pixel is saturated
            # anyway (it is clipped afterwards), and the quadratic must not fold back there
            rng = white - black
            x = np.clip(dn - black, 0, rng)
            dn = np.where(dn - black >= rng, dn, black + x * (1.0 - self.get("sensor_nonlinearity") * x / rng))
        if self.get("black_level_offset") != 0:
            dn = dn + self.get("black_level_offset")
        if hot is not None:
            dn = dn + hot * (HOT_PIXEL_RATE_E_S * exposure_s / e_per_dn)
        return dn

    def to_json(self) -> dict:
        return {"values": dict(self.values), "seed": self.seed,
                "detail": {k: {str(i): v for i, v in d.items()} for k, d in self.detail.items()},
                "catalogue": {k: {"unit": e.unit, "doc": e.doc} for k, e in CATALOGUE.items() if k in self.values}}
