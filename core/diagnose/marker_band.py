"""The cylinder's white marker band as a witness of the LED positions (issue 14, items 3 and 5).

Why. An LED that sits off the position the lamp calibration gives (hand-mounted holders, thesis
4.1.5; the catalogue's ``led_position_error``) lights the sample from another direction and
distance: in BRDF space a per-LED change of the angles and the irradiance that a real material's
departure from its model takes up (on the blind study's satin_rosaline and ilm_l3_37_matte captures
the per-LED offsets bend to each half's misfit and run to their bounds).

The signature no material produces. The marker band above the sample is white paper wrapped on the
same cylinder, the same surface in the sample capture and in the reference capture (only the sample
is swapped), seen by the same pixels. On a curved matte surface the shading is the LED's geometry
itself: the irradiance ``cos(theta_in) / d^2`` changes around the circumference from full to grazing,
so a change of the LED's position between the captures tilts the ratio of the two captures' rates
over the band in a pattern fixed by the offset - ``log(R_s / R_r) = a_(colour) + log(E(P + delta) /
E(P))`` per LED, ``E`` the irradiance at each band pixel's point (its ray met with the band's
cylinder, the calibrated poses), ``a`` the LED's output in the two captures. Fitted per LED (three
offsets, three colour offsets; robust loss, the printed markers left out by their albedo in the
reference capture) the offsets come out to a few tenths of a millimetre: on the blind study's
captures LED 9 moved by (1.15, 6.00, 8.00) mm read (1.18, 6.22, 8.07) +- (0.07, 0.35, 0.20), LED 6
moved by (2.26, -0.98, 0.75) read (2.36, -0.90, 0.64) +- 0.3-0.4; on null captures within 0.6 mm.

What else shades the band. Every change of the light or the sensor between the captures bends the
ratio too, and read as moved LEDs it gives offsets of 2-120 mm (measured: vignetting 0.135, stray
light 0.008, an LED emission pattern n = 25, a sensor non-linearity of 4.5 %, a channel response
error, a black level 14 DN off): where such a cause is found (``bent_by``: a significant sensor
cause in the frames, stray light in the frames' dark pixels, vignetting or an emission pattern on
the white patch) the band is not read. Hot pixels (left out by the robust loss) and LED drift (one
output per LED and capture) do not bend it. Where no such cause is found but one acts unseen, the
fit says so: the ratio is then no moved LED's pattern and its residual exceeds the noise
(an emission pattern left 0.06-0.10 of log residual against 0.014) - the fit must describe the
band to within FIT_CHI2 times its noise.

Test. Per LED, held out on the band's two halves around the circumference (the offsets from one
half predict the other; the gain of its chi^2 over no offset); significant where the offsets lie
beyond the BAND_Z-sigma bound of no move (:func:`band_moved`): one LED's (its chi^2 over the three
components at that tail, BAND_Z3 = 4.70), or all LEDs' together (the sum of their chi^2 at the same
tail of chi^2 with 3 x LEDs degrees of freedom: 60.0 for eight LEDs, 28.9 for two). The first finds
one LED knocked out of place, the second every hand-mounted holder a little off (the catalogue's
``led_position_error`` moves each LED by its own random offset): on the eight-LED blind study's
trial 48 (LED moves of 1.66 mm RMS per axis beside hot pixels) no LED's offset passed 4.70 but
their sum of chi^2 was 65.1, where the 26 captures of that study read without a moved LED summed to
at most 4.1 (the floor below makes the null sums small). Each test at the 4-sigma tail (6.3e-5):
on offsets that are noise alone the sum adds at most that to the LEDs' own tests, (LEDs + 1) x 6.3e-5
in all (5.7e-4 on eight LEDs; tests/test_marker_band.py draws it). Each component's standard error
(the fit's, scaled by its residual) is combined with BAND_FLOOR_MM, the band's model error: the paper
taken as Lambertian and uniform, at the rig file's radius and seen through poses good to a fraction of a pixel (on 19 of the blind study's captures
without a moved LED or an effect that bends the band, LED 6's components read up to 0.77 mm, LED 9's up to
0.45; a sample radius 0.5 mm off gave 0.66) - the pooled held-out gain exceeds GAIN_THRESHOLD and
the folds agree. Premise, stated: the reference capture was lit by the LEDs where the lamp calibration puts
them (it is the calibration's capture); what the band measures is the LEDs' move since.

Use (:func:`apply_band_evidence`): a significant band names ``led_position_error`` with the band's
offsets (:func:`glossrig.core.diagnose.witness.take_witness_test`, ``direct``: the LEDs that light
the band light the sample; the rows' test with the offsets held is recorded, not required); a band
that shows no offset refutes a BRDF-space ``led_position_error`` more than BOUND_Z combined standard
errors away.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy.stats import chi2, norm

from glossrig.core.diagnose.catalogue import GAIN_THRESHOLD, TEST_Z, CauseResult, consistent_folds
from glossrig.core.diagnose.witness import BOUND_Z, brdf_cause, pair_rates, refute, single_leds, take_witness_test

BAND_FLOOR_MM = 1.0   # the band's model error per offset component, mm (module docstring)
BAND_Z = TEST_Z       # an LED's offset must lie as far from 0 as BAND_Z standard errors of one component:
#: sqrt of chi^2 (3 components) at the two-sided BAND_Z-sigma tail
BAND_Z3 = math.sqrt(float(chi2.isf(2 * norm.sf(BAND_Z), 3)))
FIT_CHI2 = 2.0        # the fit's robust normalised residual must stay below this (a moved LED's pattern)
MIN_COS = 0.15        # band pixels lit at least this steeply (cos theta_in) under the LED
ALBEDO_CUT = 0.5      # pixels below this fraction of the band's median albedo: a printed marker
EDGE_MM = 1.0         # band pixels this close to the band's upper or lower edge are left out
#: frame- and pixel-space causes that bend the band's shading between the captures (module docstring)
BENDING_SENSOR = ("black_level_offset", "sensor_nonlinearity", "shutter_error", "channel_response")


def band_bound(n_leds: int) -> float:
    """The bound of no move on the LEDs' offsets together: chi^2 with 3 x ``n_leds`` degrees of
    freedom at the two-sided BAND_Z-sigma tail (module docstring, "Test")."""
    return float(chi2.isf(2 * norm.sf(BAND_Z), 3 * n_leds))


def band_moved(per_led: dict) -> tuple[bool, str]:
    """Whether the band's offsets show moved LEDs (module docstring, "Test"): one LED's beyond BAND_Z3
    (sqrt chi^2, 3 components) or all LEDs' together beyond :func:`band_bound`; and what was found."""
    z = [float(p["z"]) for p in per_led.values()]
    total, bound = float(np.sum(np.square(z))), band_bound(len(z))
    if max(z) > BAND_Z3:
        return True, f"an LED's offset beyond the {BAND_Z:g}-sigma bound of no move ({max(z):.2f} > {BAND_Z3:.2f})"
    if total > bound:
        return True, (f"the {len(z)} LEDs' offsets together beyond the {BAND_Z:g}-sigma bound of no move (sum of "
                      f"chi^2 {total:.1f} > {bound:.1f}, {3 * len(z)} components)")
    return False, (f"every LED's offset within the {BAND_Z:g}-sigma bound of no move (sqrt chi^2, 3 components, "
                   f"{BAND_Z3:.2f}), and all together (sum of chi^2 {total:.1f} <= {bound:.1f}, {3 * len(z)} "
                   "components)")


def _irradiance(P, X, N):
    d = np.asarray(P, float)[None, :] - X
    d2 = np.sum(d * d, axis=1)
    return np.maximum(np.sum(d * N, axis=1), 1e-9) / np.sqrt(d2) / d2


def band_points(geom, camera: tuple, rig, size):
    """The band's pixels seen at one rotation: full-image (u, v) and each pixel's point and normal
    (holder frame) on the marker band's cylinder, through the calibrated poses."""
    from glossrig.core.calibration.markers import cylinder_marker_radius
    from glossrig.core.extraction.cylinder import intersect_cylinder, undistorted_rays

    K, dist = camera
    w, h = size
    rb, cm = cylinder_marker_radius(rig), rig.cylinder_markers
    lo, hi = cm.band_bottom + EDGE_MM, cm.band_top - EDGE_MM
    C = -geom.R_hold.T @ geom.t_hold
    o = geom.R_cyl.T @ (C - geom.t_cyl)

    def cast(u, v):
        d = (undistorted_rays(K, dist, u, v) @ geom.R_hold) @ geom.R_cyl
        return intersect_cylinder(o, d, rb, lo, hi)
    # a coarse grid finds the band's box, then every pixel in it is cast
    gv, gu = np.mgrid[0:h:4, 0:w:4]
    _, ok = cast(gu.ravel().astype(float), gv.ravel().astype(float))
    if not ok.any():
        return None
    x0, x1 = max(0, int(gu.ravel()[ok].min()) - 4), min(w, int(gu.ravel()[ok].max()) + 5)
    y0, y1 = max(0, int(gv.ravel()[ok].min()) - 4), min(h, int(gv.ravel()[ok].max()) + 5)
    x0, y0 = x0 - x0 % 2, y0 - y0 % 2
    vv, uu = np.mgrid[y0:y1, x0:x1]
    p, ok = cast(uu.ravel().astype(float), vv.ravel().astype(float))
    n = p[ok] * np.array([1.0, 0.0, 1.0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return {"box": (x0, y0, x1, y1), "u": uu.ravel()[ok], "v": vv.ravel()[ok],
            "X": p[ok] @ geom.R_cyl.T + geom.t_cyl, "N": n @ geom.R_cyl.T}


def band_rates(sample_dir, reference_dir, sample_geometry: dict, camera: tuple,
               image_size: tuple[int, int]) -> list[dict]:
    """Both captures' HDR rates over the marker band, per (rotation, LED), in images of ``image_size``
    (width, height; the sample capture's): units with the band pixels'
    ``X``, ``N`` (:func:`band_points`, the sample capture's poses), CFA ``colour``, rates ``rs``, ``rr`` and
    variances ``vs``, ``vr`` where both are valid."""
    from glossrig.core.calibration.demosaic import channel_index
    from glossrig.core.capture import load_manifest
    from glossrig.core.rig import load_rig

    ms, mr = load_manifest(Path(sample_dir)), load_manifest(Path(reference_dir))
    rig_s, rig_r = load_rig(ms.folder / "rig.toml"), load_rig(mr.folder / "rig.toml")
    units = []
    for rot, g in sorted(sample_geometry.items()):
        leds = single_leds(ms, rot)
        if not leds:
            continue
        bp = band_points(g, camera, rig_s, image_size)
        if bp is None:
            continue
        box = bp["box"]
        i, j = bp["v"] - box[1], bp["u"] - box[0]
        for led in leds:
            rates = pair_rates(ms, mr, rig_s, rig_r, rot, led, box)
            if rates is None:
                continue
            rs, vs, rr, vr, cfa = rates
            a, b, c, d = rs[i, j], rr[i, j], vs[i, j], vr[i, j]
            ok = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0) & np.isfinite(c) & np.isfinite(d)
            units.append({"rotation": float(rot), "led": int(led), "X": bp["X"][ok], "N": bp["N"][ok],
                          "colour": channel_index(rs.shape, cfa)[i, j][ok].astype(int),
                          "rs": a[ok].astype(float), "rr": b[ok].astype(float), "vs": c[ok].astype(float),
                          "vr": d[ok].astype(float)})
    return units


def _fit(y, sd, colour, X, N, P, rows):
    """The offset (3,) and colour offsets fitted on ``rows``, the offset's covariance and the robust
    normalised residual's scale."""
    from scipy.optimize import least_squares

    e0 = _irradiance(P, X[rows], N[rows])
    yy, ss, cc = y[rows], sd[rows], colour[rows]

    def res(p):
        return (yy - p[3 + cc] - np.log(_irradiance(P + p[:3], X[rows], N[rows]) / e0)) / ss
    r = least_squares(res, np.zeros(6), loss="soft_l1", f_scale=3.0, x_scale=np.array([1.0, 1.0, 1.0, 0.01, 0.01, 0.01]))
    scale = 1.4826 * float(np.median(np.abs(r.fun)))
    J = r.jac
    cov = np.linalg.pinv(J.T @ J) * max(scale, 1.0) ** 2
    return r.x, cov[:3, :3], scale


def _chi2(y, sd, colour, X, N, P, rows, x, a):
    """Chi^2 of ``rows`` with offset ``x`` and the colour offsets solved on them (``a``: None) or given."""
    r = y[rows] - np.log(_irradiance(P + x, X[rows], N[rows]) / _irradiance(P, X[rows], N[rows]))
    w = 1.0 / sd[rows] ** 2
    c = colour[rows]
    if a is None:
        a = np.array([np.sum((w * r)[c == k]) / max(np.sum(w[c == k]), 1e-30) for k in range(3)])
    z = (r - a[c]) / sd[rows]
    z = np.clip(z, -5.0, 5.0)                  # a marker edge or a hot pixel weighs no more than 5 sigma
    return float(np.sum(z ** 2))


def band_evidence(units: list[dict], lamps: dict, bent_by: list[str] | None = None) -> dict | None:
    """The LEDs' moves the band measures (module docstring): per LED ``offset_mm`` (3,) and ``se_mm``,
    the RMS ``magnitude`` (per axis, over the LEDs), held-out ``gain`` and ``fold_gains``, the fit's
    ``chi2_scale``, ``significant`` (``why_not`` where not). None where no band was seen; ``bent_by``:
    the causes found that bend the band's shading (then not read)."""
    if not units:
        return None
    if bent_by:
        return {"significant": False, "why_not": "the band's shading is bent by " + ", ".join(bent_by)
                + " found in this capture: not read for LED positions", "per_led": {}, "magnitude": float("nan"),
                "se": float("nan"), "gain": 0.0, "fold_gains": []}
    per_led: dict[int, dict] = {}
    fold_gains: list[float] = []
    chi0, chi1, worst_scale = 0.0, 0.0, 0.0
    for un in units:
        led = un["led"]
        if led not in lamps:
            continue
        P = np.asarray(lamps[led], float)
        X, N = un["X"], un["N"]
        e0 = _irradiance(P, X, N)
        cos_in = np.sum((P[None, :] - X) * N, axis=1) / np.linalg.norm(P[None, :] - X, axis=1)
        alb = un["rr"] / e0
        keep = cos_in > MIN_COS
        for k in range(3):
            m = keep & (un["colour"] == k)
            if m.sum() > 10:
                keep &= ~((un["colour"] == k) & (alb < ALBEDO_CUT * np.median(alb[m])))
        if keep.sum() < 200:
            continue
        y = np.log(un["rs"] / un["rr"])
        sd = np.sqrt(un["vs"] / un["rs"] ** 2 + un["vr"] / un["rr"] ** 2)
        rows = np.flatnonzero(keep)
        x, cov, scale = _fit(y, sd, un["colour"], X, N, P, rows)
        x = x[:3]
        # held out: around the circumference, the halves by the angle of each point about the axis
        ang = np.arctan2(N[rows, 0], N[rows, 2])
        cut = np.median(ang)
        halves = (rows[ang <= cut], rows[ang > cut])
        for tr, te in ((halves[0], halves[1]), (halves[1], halves[0])):
            xt = _fit(y, sd, un["colour"], X, N, P, tr)[0][:3]
            c0 = _chi2(y, sd, un["colour"], X, N, P, te, np.zeros(3), None)
            c1 = _chi2(y, sd, un["colour"], X, N, P, te, xt, None)
            chi0, chi1 = chi0 + c0, chi1 + c1
            fold_gains.append((c0 - c1) / c0 if c0 > 0 else 0.0)
        se = np.sqrt(np.maximum(np.diag(cov), 0.0))
        # the offset's distance from 0 in its combined standard errors (three components: chi^2 with 3 dof)
        z = float(np.sqrt(np.sum((x / np.hypot(se, BAND_FLOOR_MM)) ** 2)))
        per_led[led] = {"offset_mm": [float(v) for v in x], "se_mm": [float(v) for v in se],
                        "z": z, "pixels": int(len(rows)), "chi2_scale": float(scale)}
        worst_scale = max(worst_scale, scale)
    if not per_led:
        return None
    offs = np.array([p["offset_mm"] for p in per_led.values()])
    ses = np.array([np.hypot(p["se_mm"], BAND_FLOOR_MM) for p in per_led.values()])
    mag = float(np.sqrt(np.mean(offs ** 2)))
    # the RMS's standard error, to first order (each component's combined standard error)
    se_mag = float(np.sqrt(np.sum((offs * ses) ** 2)) / (offs.size * max(mag, 1e-9)))
    gain = (chi0 - chi1) / chi0 if chi0 > 0 else 0.0
    ev: dict = {"per_led": {str(k): v for k, v in per_led.items()}, "magnitude": mag, "se": se_mag, "gain": gain,
          "fold_gains": fold_gains, "chi2_scale": worst_scale, "significant": False, "why_not": None}
    if worst_scale > FIT_CHI2:
        ev["why_not"] = (f"the ratio is no moved LED's pattern: its residual is {worst_scale:.1f} times the noise "
                         "(another change of the light between the captures)")
        return ev
    moved, found = band_moved(ev["per_led"])
    if not moved:
        ev["why_not"] = found
    elif not (gain > GAIN_THRESHOLD and consistent_folds(fold_gains)):
        ev["why_not"] = "held-out gain not above the threshold in the folds"
    else:
        ev["significant"] = True
        ev["moved"] = found
    return ev


def bending_causes(causes: list[CauseResult], vig: dict | None, emission: dict | None) -> list[str]:
    """The causes found in a capture that bend the band's shading (module docstring): an eligible sensor
    response cause (frames), an eligible BRDF-space stray light, vignetting or LED emission (named
    through their own witnesses: the frames' dark pixels, the white patch), or a significant patch
    signature of vignetting or emission."""
    bending = BENDING_SENSOR + ("stray_light", "vignetting", "led_emission")
    out = [c.name for c in causes if c.name in bending and c.eligible]
    for name, ev in (("vignetting", vig), ("led_emission", emission)):
        if ev is not None and ev.get("significant") and name not in out:
            out.append(name)
    return out


def apply_band_evidence(m, causes: list[CauseResult], ev: dict | None) -> None:
    """Judge the BRDF-space ``led_position_error`` by the marker band (module docstring), in place;
    ``m``: the model the cause was fitted on (:func:`glossrig.core.diagnose.catalogue.model_of`)."""
    from glossrig.core.diagnose.geometry import Geometry

    c = brdf_cause(causes, "led_position_error")
    if c is None or ev is None:
        return
    mag_b = float(c.magnitude) if c.magnitude is not None else float("nan")
    c.params.update({"offset_band_mm": {k: p["offset_mm"] for k, p in ev["per_led"].items()},
                     "band": {k: ev[k] for k in ("magnitude", "se", "gain", "fold_gains", "significant", "why_not")}})
    if ev["significant"]:
        geo = Geometry(m)
        # an LED the band gave no estimate for (too few band pixels it lights well) stays where the lamp
        # calibration puts it, and is said so
        offsets = {k: np.asarray(ev["per_led"][str(k)]["offset_mm"], float) if str(k) in ev["per_led"]
                   else np.zeros(3) for k in geo.leds}
        unseen = [k for k in geo.leds if str(k) not in ev["per_led"]]

        def test():
            return geo.held_test(offsets=offsets)
        note = ("marker-band signature: the white band on the cylinder, the same paper in the sample and reference "
                "captures, is shaded between them as by LEDs moved by "
                + "; ".join(f"LED {k}: ({', '.join(f'{v:+.2g}' for v in p['offset_mm'])}) mm"
                            for k, p in ev["per_led"].items())
                + f" (held-out gain {ev['gain']:.1%}; no material acts there; free BRDF-space fit: RMS {mag_b:.3g} mm)"
                + (f"; LED(s) {', '.join(map(str, unseen))} not measured on the band, held at the lamp calibration's"
                   if unseen else ""))
        extra = {"offset_mm": {k: p["offset_mm"] for k, p in ev["per_led"].items()}}
        if take_witness_test(c, m, ev, "rms_mm", ev["magnitude"], None, extra, note, "marker band", test=test,
                             direct=True):
            return
    if (c.significant and np.isfinite(mag_b) and not ev["significant"] and ev["per_led"]
            and ev.get("chi2_scale", 0.0) <= FIT_CHI2
            and not band_moved(ev["per_led"])[0]
            and abs(mag_b - ev["magnitude"]) > BOUND_Z * ev["se"]):
        refute(c, f"the marker band refutes it: seen in both captures it shows the LEDs where they were (RMS offset "
                  f"{ev['magnitude']:.2g} +- {ev['se']:.2g} mm), the BRDF-space fit needs {mag_b:.3g} mm")
