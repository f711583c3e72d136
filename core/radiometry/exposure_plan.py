"""Exposure planning (issue 8): per LED, the exposures of the camera's table that keep
every pixel's HDR estimate within a noise target at the least capture time.

The thesis shoots the same 18 exposures (table 4.1, 1/4000 s .. 30 s) three times for
every LED and material (4.2.3): 54 shots per LED, whose cost is dominated by the
~9.9 s per-shot overhead of the camera and transfer (4 min per sequence), not by the
61 s of exposure. Most of those shots carry no information for a given material: a
pixel contributes to the HDR estimate only while it is neither saturated nor lost in
read noise (:func:`glossrig.core.radiometry.hdr.hdr_ml`), and each pixel's value is known
beforehand to within the material's class from the rig's geometry alone.

Model. For one LED, the planner ray-casts the nominal camera's pixels onto the
sample (:func:`glossrig.core.design.coverage.pixel_geometry`, thesis 4.3.2), takes the
lamp/camera angles at every sample rotation of the plan
(:func:`glossrig.core.design.coverage.direction_angles`, thesis 4.3.5), the material's BRDF
there (extended Ward, thesis eq. 4.79-4.80, or Lambert) and turns it into the green
channel's photo-electron rate ``r`` with the rig's radiometry
(:meth:`glossrig.core.design.fisher.HdrNoise.electron_rate`: ``k_G (11/N)^2 f I cos / d^2``;
green is the channel that saturates first with the twin's LED spectrum and sensor).
The noise of the HDR merge of an exposure set S is
:meth:`~glossrig.core.design.fisher.HdrNoise.sensor_relative`: inverse-variance weights of
shot, dark, read and quantisation noise over the exposures whose signal stays below
90 % of saturation - the weights :func:`glossrig.core.radiometry.hdr.hdr_ml` uses. A brightness
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
   exposure with at least ``lo`` = 0.002 of the range, :func:`~glossrig.core.radiometry.hdr.hdr_ml`)
   keeps such an exposure, so no BRDF sample of the full table is lost.

Search: exact over subsets of the table. Time is the sum of the exposures plus the
per-shot overhead (the hardware layer's measured figure, thesis 4.2.3: 9.94 s), so
subsets are enumerated by size and the cheapest feasible one is kept, stopping when
``k`` shots cannot beat it. Pixels are grouped into 2 % wide bins of rate with
conservative rates (brightest pixel of a bin for saturation, darkest for noise).
(A greedy "longest usable exposure for the brightest failing pixel" needed up to
twice the time on the Table 9.1 materials.) One sequence per LED is planned (a second
sequence halves the variance of a pixel at the cost of every shot again, while a
longer exposure gains more for less).

3. LED jitter (``jitter`` > 0): the LED's output differs from frame to frame
   (thesis 4.3.3, fig. 4.12; the twin's ``led_jitter``, 0.5 % RMS). That error is
   common to every pixel of a frame, so unlike sensor noise it does not average
   out over the thousands of pixels a fit uses: a plan whose frames keep their own
   gains misses rho_d/rho_s by a few tenths of a per cent per LED
   (validation/design/twin.md) while the full table, whose frames neighbour
   correction ties together, does not. The planner predicts the pipeline's
   neighbour correction (:func:`glossrig.core.radiometry.hdr.neighbour_correct`, thesis
   eq. 4.32-4.38, method "robust") from the predicted values of each sequence
   (:func:`neighbour_links`): the same centre-out chain, the same choice of the
   third image q and of the pixels (q, a and b unsaturated, a and b inside
   :data:`~glossrig.core.radiometry.hdr.NEIGHBOUR_WINDOW`), the same fallbacks (the other
   q, the pair's longer image, earlier anchored images) and the same
   :data:`~glossrig.core.radiometry.hdr.NEIGHBOUR_MIN_PIXELS`,
   counted at the capture's resolution (``pixel_factor``). A linked frame carries
   the reference frame's gain, up to the shot noise of the ratio its link rests
   on (accumulated along the chain); patch normalisation (eq. 4.45-4.50) divides
   the reference's gain out. An unlinked frame keeps its own gain. The gain error
   of a pixel's HDR value is then, with hdr_ml's weights w_k of the frames
   (:func:`gain_relative`)

       sigma_g^2 = j^2 (sum_u w_k^2 + (sum_u w_k)^2) + (sum_l w_k s_k)^2

   over unlinked frames u (own gain minus the reference's, jitter j each) and
   linked frames l (chain error s_k, summed as if fully correlated: a bound).
   Requirement: sigma_g <= max(``gain_target``, ``gain_tail`` x the full table's) on
   every measured pixel. The white patch is assumed to lie in linked frames (its
   exposure is that of a bright diffuse surface, the middle of the sequence where
   the reference frame is). Slow drift is a gain per frame as well and is treated
   by the pipeline the same way; only the jitter is modelled.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from collections.abc import Sequence

import numpy as np

from glossrig.core.design import coverage as cov
from glossrig.core.errors import InputError
from glossrig.core.design.fisher import HdrNoise
from glossrig.core.radiometry.hdr import NEIGHBOUR_MIN_PIXELS, NEIGHBOUR_WINDOW, _pairs_centre_out
from glossrig.core.models.materials import Material
from glossrig.core.models.ward import ward_from_angles

#: hdr_ml's lower validity limit, as a fraction of the white-black range.
LO_FRACTION = 0.002
#: Where even the full table misses the noise target, a plan may be this much noisier than it.
TAIL = 2.0
#: LED frame-to-frame jitter, relative RMS (thesis 4.3.3, fig. 4.12; the twin's led_jitter).
THESIS_JITTER = 0.005
#: Default target of the gain error common to a frame's pixels (requirement 3).
GAIN_TARGET = 0.001
#: Where the full table misses the gain target, a plan may have this much more gain error than it.
GAIN_TAIL = 2.0


def material_brdf(material: Material, a: dict, rotation_deg: float) -> np.ndarray:
    """BRDF (1/sr) of ``material`` at the angles ``a`` of
    :func:`glossrig.core.design.coverage.direction_angles` (``half=True``) at a sample rotation."""
    if material.kind == "lambert":
        assert material.albedo is not None      # a Lambertian Material has one (materials.lambert)
        return np.full(a["theta_in"].shape, material.albedo / math.pi)
    if material.kind == "ward":
        assert material.ward is not None        # a Ward Material has its parameters
        return ward_from_angles(np.radians(a["theta_in"]), np.radians(a["theta_out"]), np.radians(a["theta_h"]),
                                np.radians(np.mod(a["phi_h"] - rotation_deg, 360.0)), material.ward)
    raise InputError(f"exposure planning needs an extended-Ward or Lambertian material, got {material.kind} "
                     f"({material.label})")


def pixel_rates(rig, material: Material, led: int, rotations: Sequence[float], scale: float,
                noise: HdrNoise, pixels: cov.PixelGeometry | None = None) -> list[np.ndarray]:
    """Green photo-electron rates (e-/s) of every lit pixel of ``led``, one array per
    rotation (each rotation is its own exposure sequence)."""
    px = cov.pixel_geometry(rig, scale) if pixels is None else pixels
    a = cov.direction_angles(px, rig.led(led).position, half=True)
    lit = a["lit"]
    sub = {k: v[lit] for k, v in a.items() if isinstance(v, np.ndarray) and v.shape == lit.shape}
    return [noise.electron_rate(material_brdf(material, sub, r), sub["cos_in"], sub["dist_in"]) for r in rotations]


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
    gain_noise_worst: float = math.nan        # worst predicted frame-gain error (requirement 3) of the plan
    gain_noise_worst_full: float = math.nan   # the same with the full table, one sequence
    unlinked_frames: int = 0                  # planned frames neighbour correction leaves uncorrected (all rotations)
    gain_noise_rms: float = math.nan          # pixel-weighted RMS of the plan's frame-gain error

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


def neighbour_links(times: Sequence[float] | np.ndarray, hi: np.ndarray, lo: np.ndarray, count: np.ndarray, noise: HdrNoise,
                    pixel_factor: float = 1.0, min_pixels: int = NEIGHBOUR_MIN_PIXELS) -> tuple[np.ndarray, np.ndarray]:
    """Predicted neighbour correction of one sequence (requirement 3 of the module docstring).

    ``times`` increasing; pixels as :func:`rate_bins` gives them (``hi``: rate for
    saturation and the window's top, ``lo``: for the window's bottom, ``count``
    pixels each, times ``pixel_factor`` at the capture's resolution). Mirrors
    :func:`glossrig.core.radiometry.hdr.neighbour_correct` (method "robust", reference the
    centre frame): returns ``linked`` (n,) bool, whether each frame ends up carrying
    the reference frame's gain, and ``chain_var`` (n,), the relative variance of its
    correction factor from shot, dark, read and quantisation noise of the ratios on
    its chain (0 for the reference, inf for a frame left uncorrected)."""
    T = np.asarray(times, float)
    n = T.size
    S = noise.saturation_e
    w_lo, w_hi = NEIGHBOUR_WINDOW
    nom = np.sqrt(hi * lo)
    K = noise.conversion_gain
    unsat = [hi * t < S for t in T]
    window = [(lo * t > w_lo * S) & (hi * t < w_hi * S) for t in T]
    ref = n // 2
    linked = np.zeros(n, bool)
    linked[ref] = True
    chain = np.full(n, np.inf)
    chain[ref] = 0.0

    def rel_var(sel, t):          # relative variance of the sum of a frame's values over sel
        e = nom[sel] * t
        v = e + noise.dark_current_e_s * t + noise.read_noise_e ** 2 + K * K / 12.0
        w = count[sel]
        return float(np.sum(w * v) / np.sum(w * e) ** 2) / pixel_factor

    for a, b in _pairs_centre_out(n, ref):
        step = 1 if b > a else -1
        for c in range(a, ref - step, -step):
            if not linked[c]:
                continue
            pair = unsat[c] & unsat[b] & window[c] & window[b]
            qs = [k for k in (c - step, b + step) if 0 <= k < n and k not in (c, b)]
            sel = next((x for x in [pair & unsat[q] for q in qs] + [pair]
                        if count[x].sum() * pixel_factor >= min_pixels), None)
            if sel is not None:
                linked[b] = True
                chain[b] = chain[c] + rel_var(sel, T[b]) + rel_var(sel, T[c])
                break
    return linked, chain


def gain_relative(info: np.ndarray, linked: np.ndarray, chain_var: np.ndarray, jitter: float) -> np.ndarray:
    """Relative error of each pixel's HDR value from the frames' LED gains (requirement 3):
    ``info`` (n_frames, n_pixels) the HDR merge's information per frame (hdr_ml's
    weights), ``linked``/``chain_var`` from :func:`neighbour_links`, ``jitter`` the
    LED's relative RMS per frame (one repeat per frame)."""
    tot = info.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(tot > 0, info / tot, 0.0)
    wu = w[~linked]
    s = np.sqrt(np.where(linked, chain_var, 0.0))[:, None]
    var = jitter ** 2 * ((wu ** 2).sum(axis=0) + wu.sum(axis=0) ** 2) + (w * s).sum(axis=0) ** 2
    return np.where(tot > 0, np.sqrt(var), np.inf)


def plan_led(rates, table: Sequence[float], noise: HdrNoise, target: float, margin: float = 1.1,
             overhead_s: float = 0.0, max_shots: int | None = None, tail: float = TAIL, *, jitter: float = 0.0,
             gain_target: float = GAIN_TARGET, gain_tail: float = GAIN_TAIL,
             pixel_factor: float = 1.0) -> tuple[tuple[float, ...], dict]:
    """The exposure subset of ``table`` of least time (sum of exposures plus
    ``overhead_s`` per shot) that meets the requirements of the module docstring for
    one LED's pixel rates; exact: subsets are enumerated by size until ``k`` shots
    cannot beat the best time found (``k * overhead + the k shortest exposures``).

    ``rates``: one array of pixel rates, or a list of them, one per sequence (sample
    rotation). With ``jitter`` > 0, requirement 3 (LED jitter, neighbour correction
    predicted per sequence with ``pixel_factor`` capture pixels per predicted pixel)
    is checked on the candidates in order of time."""
    from itertools import combinations

    if not (math.isfinite(target) and 0 < target < 1):
        raise InputError(f"noise target must lie in (0, 1), got {target!r}")
    if not (math.isfinite(margin) and margin >= 1):
        raise InputError(f"brightness margin must be >= 1, got {margin!r}")
    if not (math.isfinite(overhead_s) and overhead_s >= 0):
        raise InputError(f"overhead per shot must be >= 0 s, got {overhead_s!r}")
    if not (math.isfinite(jitter) and 0 <= jitter < 1):
        raise InputError(f"LED jitter must lie in [0, 1), got {jitter!r}")
    if jitter > 0 and not (math.isfinite(gain_target) and 0 < gain_target < 1):
        raise InputError(f"gain error target must lie in (0, 1), got {gain_target!r}")
    if not (math.isfinite(pixel_factor) and pixel_factor > 0):
        raise InputError(f"pixel factor must be > 0, got {pixel_factor!r}")
    T = np.array(sorted(set(float(t) for t in table)))
    if T.size == 0 or T[0] <= 0:
        raise InputError("exposure table must hold positive times")
    seqs = [np.asarray(r, float) for r in rates] if isinstance(rates, (list, tuple)) else [np.asarray(rates, float)]
    hi, lo, count = rate_bins(np.concatenate(seqs) if seqs else np.zeros(0), margin)
    cap = noise.usable_fraction * noise.saturation_e
    floor = LO_FRACTION * noise.saturation_e
    K = noise.conversion_gain

    def information(h, l, times):
        t = np.asarray(times, float)[:, None]
        usable = h[None, :] * t < cap
        var = (l[None, :] * t + noise.dark_current_e_s * t + noise.read_noise_e ** 2 + K * K / 12.0) / (t * t)
        return usable, np.where(usable, 1.0 / var, 0.0)

    usable, info = information(hi, lo, T)                             # (n_t, n_bins)
    valid = usable & (lo[None, :] * T[:, None] >= floor)
    full = info.sum(axis=0)
    need = np.minimum((target * lo) ** -2.0, full / tail ** 2)       # information each bin must reach
    domain = (target * lo) ** -2.0 <= full / tail ** 2               # the target itself applies
    measurable = valid.any(axis=0)

    # requirement 3, per sequence: its bins, their information per table exposure and
    # the bound (gain target, or tail x the full table's gain error)
    seq_bins = []
    if jitter > 0:
        for r in seqs:
            h, l, c = rate_bins(r, margin)
            u, inf_ = information(h, l, T)
            m = (u & (l[None, :] * T[:, None] >= floor)).any(axis=0)
            g_full = gain_relative(inf_, *neighbour_links(T, h, l, c, noise, pixel_factor), jitter)
            seq_bins.append((h, l, c, inf_, m, np.maximum(gain_target, gain_tail * g_full), g_full))

    def gain_check(idx, stop: bool = True):
        """(requirement 3 met, worst gain error, worst of the full table, unlinked frames used by a pixel,
        pixel-weighted RMS gain error)."""
        ok, worst, worst_full, unl = True, 0.0, 0.0, 0
        sq, npx = 0.0, 0.0
        t = T[idx]
        for h, l, c, inf_, m, bound, g_full in seq_bins:
            linked, chain = neighbour_links(t, h, l, c, noise, pixel_factor)
            g = gain_relative(inf_[idx], linked, chain, jitter)
            meas = m & ((h[None, :] * t[:, None] < cap) & (l[None, :] * t[:, None] >= floor)).any(axis=0)
            ok = ok and bool(np.all(g[meas] <= bound[meas] * (1 + 1e-9)))
            if stop and not ok:
                break
            worst = max(worst, float(np.max(g[meas], initial=0.0)))
            worst_full = max(worst_full, float(np.max(g_full[m], initial=0.0)))
            unl += int(np.count_nonzero(~linked & (inf_[idx].sum(axis=1) > 0)))
            sq += float(np.sum(c[meas] * g[meas] ** 2))
            npx += float(np.sum(c[meas]))
        return ok, worst, worst_full, unl, math.sqrt(sq / npx) if npx > 0 else math.nan

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
                cand = np.flatnonzero(ok & (cost < best_cost))
                for j in cand[np.argsort(cost[cand], kind="stable")]:
                    if not seq_bins or gain_check(chunk[j])[0]:
                        best, best_cost = chunk[j], float(cost[j])
                        break
    if best is None:
        raise InputError(f"no subset of at most {n_max} exposures meets the noise target {target:g}"
                         + (f" and the gain error target {gain_target:g}" if seq_bins else ""))
    best = np.sort(best)
    chosen = tuple(float(x) for x in T[best])
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

    stats = {
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
    if seq_bins:
        _, worst, worst_full, unl, rms = gain_check(best, stop=False)
        stats.update(gain_noise_worst=worst, gain_noise_worst_full=worst_full, unlinked_frames=unl,
                     gain_noise_rms=rms)
    return chosen, stats


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
    jitter: float = 0.0
    gain_target: float = GAIN_TARGET
    capture_scale: float = 1.0

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
                "noise_model": self.noise_model, "overhead_s": self.overhead_s, "jitter": self.jitter,
                "gain_target": self.gain_target, "capture_scale": self.capture_scale,
                "leds": [e.to_json() for e in self.leds]}


def plan_exposures(rig, material: Material, led_ids: Sequence[int], rotations: Sequence[float],
                   noise_target: float = 0.03, margin: float = 1.1, scale: float = 0.25,
                   table: Sequence[float] | None = None, *, overhead_s: float, jitter: float = THESIS_JITTER,
                   gain_target: float = GAIN_TARGET, capture_scale: float = 1.0) -> ExposurePlan:
    """Per-LED exposures for ``material`` on ``rig`` (module docstring), chosen from
    ``table`` (default: the rig's exposure table, thesis table 4.1); ``overhead_s`` is
    the time per shot beyond its exposure (the hardware layer's measured figure).
    ``jitter`` (0 to leave requirement 3 out) and ``gain_target``: requirement 3;
    ``capture_scale``: the image scale the capture is made at (1 on the rig), for the
    pixel counts of neighbour correction (green pixels only are predicted, so half the
    mosaic's pixels are counted, a conservative choice)."""
    if not (math.isfinite(capture_scale) and capture_scale > 0):
        raise InputError(f"capture scale must be > 0, got {capture_scale!r}")
    noise = HdrNoise.from_rig(rig, led_rel=0.0)
    table = tuple(rig.exposure_times_s if table is None else table)
    px = cov.pixel_geometry(rig, scale)
    factor = 0.5 * (capture_scale / scale) ** 2
    out = []
    for led in led_ids:
        rates = pixel_rates(rig, material, led, rotations, scale, noise, pixels=px)
        times, stats = plan_led(rates, table, noise, noise_target, margin, overhead_s, jitter=jitter,
                                gain_target=gain_target, pixel_factor=factor)
        out.append(LedExposures(led=int(led), exposures_s=times, **stats))
    return ExposurePlan(material=material, leds=out, rotations=tuple(float(r) for r in rotations),
                        table_s=tuple(sorted(table)), noise_target=noise_target, margin=margin, scale=scale,
                        noise_model=noise.describe(), overhead_s=overhead_s, jitter=jitter, gain_target=gain_target,
                        capture_scale=capture_scale)


#: Albedo of the holder marker's white paper (thesis 4.1.4, white paper: the twin renders it
#: at 0.8); a rig file may give its own as ``[holder.marker] white_albedo``.
WHITE_PATCH_ALBEDO = 0.8


@dataclass(frozen=True)
class PatchExposure:
    """The white patch (thesis 4.1.4, eq. 4.45-4.50) under one LED in one planned sequence:
    its brightest pixel's expected green value at the shortest exposure (``peak_dn``, above
    black; saturation at ``saturation_dn``) and the longest exposure that keeps it within
    hdr_ml's usable range (``max_exposure_s``)."""

    led: int
    shortest_s: float
    peak_dn: float
    saturation_dn: float
    max_exposure_s: float

    @property
    def saturated(self) -> bool:
        """True when no exposure of the sequence measures the patch: patch normalisation,
        and so extract, must then refuse the capture."""
        return self.shortest_s > self.max_exposure_s


def white_patch_exposures(rig, exposures_by_led: dict[int, Sequence[float]], iso: float | None = None,
                          aperture: float | None = None) -> list[PatchExposure]:
    """Expected white-patch exposure of each LED's sequence, from the rig description alone:
    the patch (:func:`glossrig.core.calibration.markers.holder_marker_corners`, normal +z of the holder
    frame, Lambertian with albedo :data:`WHITE_PATCH_ALBEDO`) lit by the LED at its rig
    position, turned into green photo-electrons with the rig's radiometry
    (:meth:`glossrig.core.design.fisher.HdrNoise.electron_rate`) at the sequence's f-number and
    into DN at its ISO. The brightest point of the patch's corners and centre counts; a
    sequence whose shortest exposure already passes hdr_ml's usable fraction of
    saturation leaves the patch unmeasured and the capture unusable for extract."""
    from glossrig.core.calibration.markers import holder_marker_corners

    noise = HdrNoise.from_rig(rig, led_rel=0.0)
    iso = float(rig.sequence_iso if iso is None else iso)
    aperture = float(rig.sequence_aperture if aperture is None else aperture)
    if not (iso > 0 and aperture > 0):
        raise InputError(f"ISO and f-number must be > 0, got {iso}, {aperture}")
    e_per_dn = rig.sensor.electrons_per_dn_iso100 * 100.0 / iso
    span_dn = rig.camera.white_level - max(rig.camera.black_level)
    sat_e = min(rig.sensor.full_well_e, span_dn * e_per_dn)
    albedo = rig.holder.marker.white_albedo
    if albedo is None:
        albedo = WHITE_PATCH_ALBEDO
    corners = holder_marker_corners(rig, inner=True)
    pts = np.vstack([corners, corners.mean(axis=0)])
    # electron_rate is at the rig's sequence f-number; scale to the plan's
    k_ap = (rig.sequence_aperture / aperture) ** 2
    out = []
    for led, times in sorted(exposures_by_led.items()):
        if not times:
            continue
        L = np.asarray(rig.led(int(led)).position, float)
        d = L - pts
        dist = np.linalg.norm(d, axis=1)
        rate = float(np.max(noise.electron_rate(albedo / np.pi, d[:, 2] / dist, dist))) * k_ap
        t0 = float(min(times))
        out.append(PatchExposure(led=int(led), shortest_s=t0, peak_dn=min(rate * t0, sat_e) / e_per_dn,
                                 saturation_dn=sat_e / e_per_dn,
                                 max_exposure_s=noise.usable_fraction * sat_e / rate if rate > 0 else math.inf))
    return out


def white_patch_warnings(rig, exposures_by_led: dict[int, Sequence[float]], iso: float | None = None,
                         aperture: float | None = None, where: str = "the plan") -> list[str]:
    """One message per LED whose planned sequence saturates the white patch at every
    exposure (:func:`white_patch_exposures`): such a capture is refused by extract."""
    msgs = []
    for p in white_patch_exposures(rig, exposures_by_led, iso, aperture):
        if p.saturated:
            msgs.append(f"{where}: LED {p.led}: the white patch saturates at every exposure (expected "
                        f"{p.peak_dn:.0f} DN above black at the shortest, {p.shortest_s:g} s, saturation "
                        f"{p.saturation_dn:.0f} DN); extract will refuse this capture: add an exposure of at most "
                        f"{p.max_exposure_s:.3g} s")
    return msgs
