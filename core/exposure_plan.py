"""Exposure planning (issue 8): per LED, the exposures of the camera's table that keep
every pixel's HDR estimate within a noise target at the least capture time.

The thesis shoots the same 18 exposures (table 4.1, 1/4000 s .. 30 s) three times for
every LED and material (4.2.3): 54 shots per LED, whose cost is dominated by the
~9.9 s per-shot overhead of the camera and transfer (4 min per sequence), not by the
61 s of exposure. Most of those shots carry no information for a given material: a
pixel contributes to the HDR estimate only while it is neither saturated nor lost in
read noise (:func:`glossrig.core.hdr.hdr_ml`), and each pixel's value is known
beforehand to within the material's class from the rig's geometry alone.

Model. For one LED, the planner ray-casts the nominal camera's pixels onto the
sample (:func:`glossrig.core.coverage.pixel_geometry`, thesis 4.3.2), takes the
lamp/camera angles at every sample rotation of the plan
(:func:`glossrig.core.coverage.direction_angles`, thesis 4.3.5), the material's BRDF
there (extended Ward, thesis eq. 4.79-4.80, or Lambert) and turns it into the green
channel's photo-electron rate ``r`` with the rig's radiometry
(:meth:`glossrig.core.fisher.HdrNoise.electron_rate`: ``k_G (11/N)^2 f I cos / d^2``;
green is the channel that saturates first with the twin's LED spectrum and sensor).
The noise of the HDR merge of an exposure set S is
:meth:`~glossrig.core.fisher.HdrNoise.sensor_relative`: inverse-variance weights of
shot, dark, read and quantisation noise over the exposures whose signal stays below
90 % of saturation - the weights :func:`glossrig.core.hdr.hdr_ml` uses. A brightness
``margin`` m makes the plan hold for the material's class, not one exact sample:
saturation is judged at ``m r``, noise at ``r / m``.

Requirements on the plan, per LED over all its rotations and lit pixels:

1. noise: relative standard deviation <= max(``noise``, ``TAIL`` x the full table's)
   on every pixel, the full table being one sequence of every table exposure. So
   the target holds wherever the full table does at least ``TAIL`` = 2 times
   better; pixels too dark for that (grazing light, dark diffuse: the full table
   itself needs its 15 s and 30 s shots for them) may be up to twice as noisy as
   the full table makes them, instead of forcing every long exposure into the plan;
2. coverage: every pixel that the full table measures at all (one unsaturated
   exposure with at least ``lo`` = 0.002 of the range, :func:`~glossrig.core.hdr.hdr_ml`)
   keeps such an exposure, so no BRDF sample of the full table is lost.

Search: exact over subsets of the table. Time is the sum of the exposures plus the
per-shot overhead (the hardware layer's measured figure, thesis 4.2.3: 9.94 s), so
subsets are enumerated by size and the cheapest feasible one is kept, stopping when
``k`` shots cannot beat it. Pixels are grouped into 2 % wide bins of rate with
conservative rates (brightest pixel of a bin for saturation, darkest for noise).
(A greedy "longest usable exposure for the brightest failing pixel" needed up to
twice the time on the Table 9.1 materials.) LED jitter is not a sensor noise and is not
part of the target (the twin adds it; :func:`glossrig.core.hdr.neighbour_correct`
removes the part it can); one sequence per LED is planned (a second sequence
halves the variance of a pixel at the cost of every shot again, while a longer
exposure gains more for less).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from . import coverage as cov
from .errors import InputError
from .fisher import HdrNoise
from .materials import Material
from .ward import ward_from_angles

#: hdr_ml's lower validity limit, as a fraction of the white-black range.
LO_FRACTION = 0.002
#: Where even the full table misses the noise target, a plan may be this much noisier than it.
TAIL = 2.0


def material_brdf(material: Material, a: dict, rotation_deg: float) -> np.ndarray:
    """BRDF (1/sr) of ``material`` at the angles ``a`` of
    :func:`glossrig.core.coverage.direction_angles` (``half=True``) at a sample rotation."""
    if material.kind == "lambert":
        return np.full(a["theta_in"].shape, material.albedo / math.pi)
    if material.kind == "ward":
        return ward_from_angles(np.radians(a["theta_in"]), np.radians(a["theta_out"]), np.radians(a["theta_h"]),
                                np.radians(np.mod(a["phi_h"] - rotation_deg, 360.0)), material.ward)
    raise InputError(f"exposure planning needs an extended-Ward or Lambertian material, got {material.kind} "
                     f"({material.label})")


def pixel_rates(rig, material: Material, led: int, rotations: Sequence[float], scale: float,
                noise: HdrNoise, pixels: cov.PixelGeometry | None = None) -> np.ndarray:
    """Green photo-electron rates (e-/s) of every lit pixel of ``led`` over the rotations."""
    px = cov.pixel_geometry(rig, scale) if pixels is None else pixels
    a = cov.direction_angles(px, rig.led(led).position, half=True)
    lit = a["lit"]
    sub = {k: v[lit] for k, v in a.items() if isinstance(v, np.ndarray) and v.shape == lit.shape}
    rates = [noise.electron_rate(material_brdf(material, sub, r), sub["cos_in"], sub["dist_in"]) for r in rotations]
    return np.concatenate(rates) if rates else np.zeros(0)


@dataclass
class LedExposures:
    """The planned exposures of one LED and how they meet the requirements."""

    led: int
    exposures_s: tuple[float, ...]
    lit_pixels: int
    target_fraction: float        # lit pixels the full table brings within the noise target
    worst_noise: float            # worst planned noise over those pixels (at rate / margin)
    worst_tail_ratio: float       # elsewhere: worst planned noise / the full table's
    median_noise: float           # median planned noise over every measured pixel
    median_noise_full: float      # the same with the full table, one sequence
    unmeasured_fraction: float    # lit pixels with no valid planned exposure
    unmeasured_fraction_full: float

    def to_json(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


def rate_bins(rates: np.ndarray, margin: float, width: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels grouped by log rate (relative bin ``width``), each bin with conservative
    rates: its brightest pixel times ``margin`` for saturation, its darkest divided by
    ``margin`` for noise and the lower limit; returns (sat_rate, noise_rate, count)."""
    r = np.asarray(rates, float)
    r = r[np.isfinite(r) & (r > 0)]
    if r.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
    code = np.floor(np.log(r) / math.log1p(width)).astype(np.int64)
    _, inv, count = np.unique(code, return_inverse=True, return_counts=True)
    hi = np.full(count.size, -np.inf)
    lo = np.full(count.size, np.inf)
    np.maximum.at(hi, inv, r)
    np.minimum.at(lo, inv, r)
    return hi * margin, lo / margin, count


def plan_led(rates: np.ndarray, table: Sequence[float], noise: HdrNoise, target: float, margin: float = 1.1,
             overhead_s: float = 0.0, max_shots: int | None = None, tail: float = TAIL) -> tuple[tuple[float, ...], dict]:
    """The exposure subset of ``table`` of least time (sum of exposures plus
    ``overhead_s`` per shot) that meets the requirements of the module docstring for
    one LED's pixel rates; exact: subsets are enumerated by size until ``k`` shots
    cannot beat the best time found (``k * overhead + the k shortest exposures``)."""
    from itertools import combinations

    if not (math.isfinite(target) and 0 < target < 1):
        raise InputError(f"noise target must lie in (0, 1), got {target!r}")
    if not (math.isfinite(margin) and margin >= 1):
        raise InputError(f"brightness margin must be >= 1, got {margin!r}")
    if not (math.isfinite(overhead_s) and overhead_s >= 0):
        raise InputError(f"overhead per shot must be >= 0 s, got {overhead_s!r}")
    T = np.array(sorted(set(float(t) for t in table)))
    if T.size == 0 or T[0] <= 0:
        raise InputError("exposure table must hold positive times")
    hi, lo, count = rate_bins(rates, margin)
    cap = noise.usable_fraction * noise.saturation_e
    floor = LO_FRACTION * noise.saturation_e
    K = noise.conversion_gain
    t = T[:, None]
    usable = hi[None, :] * t < cap                                    # (n_t, n_bins)
    valid = usable & (lo[None, :] * t >= floor)
    var = (lo[None, :] * t + noise.dark_current_e_s * t + noise.read_noise_e ** 2 + K * K / 12.0) / (t * t)
    info = np.where(usable, 1.0 / var, 0.0)
    full = info.sum(axis=0)
    need = np.minimum((target * lo) ** -2.0, full / tail ** 2)       # information each bin must reach
    domain = (target * lo) ** -2.0 <= full / tail ** 2               # the target itself applies
    measurable = valid.any(axis=0)
    # Shot noise alone gives info <= t / rate per usable exposure, so any feasible
    # subset exposes for at least max(need * rate) seconds: a bound that stops the
    # enumeration as soon as more shots cannot be cheaper.
    t_need = float(np.max(need * lo, initial=0.0))
    best, best_cost = None, math.inf
    n_max = T.size if max_shots is None else min(int(max_shots), T.size)
    for k in range(1, n_max + 1):
        if k * overhead_s + max(T[:k].sum(), t_need) >= best_cost:
            break
        idx = np.array(list(combinations(range(T.size), k)), np.int64)
        for chunk in np.array_split(idx, max(1, idx.shape[0] // 4000)):
            ok = np.all(valid[chunk].any(axis=1)[:, measurable], axis=1)
            if ok.any():
                ok[ok] = np.all(info[chunk[ok]].sum(axis=1) >= need, axis=1)
            if ok.any():
                cost = T[chunk].sum(axis=1) + k * overhead_s
                cost = np.where(ok, cost, np.inf)
                j = int(np.argmin(cost))
                if cost[j] < best_cost:
                    best, best_cost = chunk[j], float(cost[j])
    if best is None:
        raise InputError(f"no subset of at most {n_max} exposures meets the noise target {target:g}")
    chosen = tuple(float(x) for x in T[np.sort(best)])
    tot = info[best].sum(axis=0)
    with np.errstate(divide="ignore"):
        plan_noise = np.where(tot > 0, 1.0 / (np.sqrt(tot) * lo), np.inf)
        full_noise = np.where(info.sum(axis=0) > 0, 1.0 / (np.sqrt(info.sum(axis=0)) * lo), np.inf)
    meas = valid[best].any(axis=0)
    n = max(int(count.sum()), 1)

    def wmedian(x, m):
        x, w = x[m], count[m]
        if x.size == 0:
            return math.nan
        o = np.argsort(x)
        return float(x[o][np.searchsorted(np.cumsum(w[o]), 0.5 * w.sum())])

    return chosen, {
        "lit_pixels": int(count.sum()),
        "target_fraction": float(count[domain].sum() / n),
        "worst_noise": float(plan_noise[domain].max()) if domain.any() else math.nan,
        "worst_tail_ratio": float(np.max(plan_noise[~domain & (full > 0)] / full_noise[~domain & (full > 0)],
                                         initial=0.0)),
        "median_noise": wmedian(plan_noise, meas),
        "median_noise_full": wmedian(full_noise, measurable),
        "unmeasured_fraction": float(count[~meas].sum() / n),
        "unmeasured_fraction_full": float(count[~measurable].sum() / n),
    }


@dataclass
class ExposurePlan:
    """Planned exposures per LED for one material on one rig (at its rotations)."""

    material: Material
    leds: list[LedExposures]
    rotations: tuple[float, ...]
    table_s: tuple[float, ...]
    noise_target: float
    margin: float
    scale: float
    noise_model: str = field(default="")
    overhead_s: float = 0.0

    def time_s_per_rotation(self) -> float:
        """Exposures plus the per-shot overhead of one rotation (one sequence per LED)."""
        return self.exposure_s_per_rotation() + self.shots_per_rotation() * self.overhead_s

    def exposures(self) -> dict[int, tuple[float, ...]]:
        return {e.led: e.exposures_s for e in self.leds}

    def shots_per_rotation(self) -> int:
        return sum(len(e.exposures_s) for e in self.leds)

    def exposure_s_per_rotation(self) -> float:
        return float(sum(sum(e.exposures_s) for e in self.leds))

    def to_json(self) -> dict:
        return {"material": self.material.to_json(), "rotations": list(self.rotations), "table_s": list(self.table_s),
                "noise_target": self.noise_target, "margin": self.margin, "scale": self.scale,
                "noise_model": self.noise_model, "overhead_s": self.overhead_s, "leds": [e.to_json() for e in self.leds]}


def plan_exposures(rig, material: Material, led_ids: Sequence[int], rotations: Sequence[float],
                   noise_target: float = 0.03, margin: float = 1.1, scale: float = 0.25,
                   table: Sequence[float] | None = None, *, overhead_s: float) -> ExposurePlan:
    """Per-LED exposures for ``material`` on ``rig`` (module docstring), chosen from
    ``table`` (default: the rig's exposure table, thesis table 4.1); ``overhead_s`` is
    the time per shot beyond its exposure (the hardware layer's measured figure)."""
    noise = HdrNoise.from_rig(rig, led_rel=0.0)
    table = tuple(rig.exposure_times_s if table is None else table)
    px = cov.pixel_geometry(rig, scale)
    out = []
    for led in led_ids:
        rates = pixel_rates(rig, material, led, rotations, scale, noise, pixels=px)
        times, stats = plan_led(rates, table, noise, noise_target, margin, overhead_s)
        out.append(LedExposures(led=int(led), exposures_s=times, **stats))
    return ExposurePlan(material=material, leds=out, rotations=tuple(float(r) for r in rotations),
                        table_s=tuple(sorted(table)), noise_target=noise_target, margin=margin, scale=scale,
                        noise_model=noise.describe(), overhead_s=overhead_s)
