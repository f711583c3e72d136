"""Stray light's frame-space signature (issue 14, items 3 and 5): what the dark pixels of each
LED's frames say about the BRDF-space ``stray_light`` cause.

Physics. Stray light (thesis 4.1.5; the twin's ``stray_radiance``) is light scattered by the box
and board: an additive, uniform radiance ``L_s = s I / (pi D^2)`` on every pixel of the frame while
an LED is on (D the LED's distance from the cylinder axis), background and holder included. So

(a) **upper bound**: every other contribution to a pixel is >= 0, so no pixel reads less than the
    veil. The mean rate of the frame's darkest pixels bounds the veil from above (within its noise):
    a BRDF-space fit whose s exceeds that bound by more than the uncertainties is physically
    refuted. This is what separates a material that rises toward grazing incidence - a measured
    BRDF need not be reciprocal there (acrylic_felt_green: f(wo, wi) / f(wi, wo) - 1 = -23 to -79 %
    at theta_in 81-90 deg), so no reciprocal material term can take the rise - from stray light,
    which BRDF space cannot do;
(b) **signature**: the pixels that see nothing lit directly rise under each LED by the same s
    times that LED's ``I / D^2``. A positive dark-pixel signal is a signature no material can
    produce; where the BRDF data agree with the veil the frames measured (the BRDF model with the
    veil of that s held fixed - no parameter of it fitted to the BRDF rows - beats the base model
    on every LED's rows),
    ``stray_light`` is named even where its free BRDF-space fit on top of the best material model
    (:func:`glossrig.core.diagnose.catalogue.instrument_bases`) gains too little - the flexible
    model's reciprocal grazing term takes up the symmetric part of its 1 / cos theta_in rise.

Measurement (:func:`dark_veil`, in the frame-space stage on the crops diagnose already reads).
Per LED and CFA colour, the dark pixels are chosen on one half of the exposures (even / odd index,
the frame space's folds): each pixel's rate ``sum z / sum t`` over its unclipped exposures of that
half (z = DN - stated black), and the pixels within DARK_NOISE_Z of their own noise above the
DARK_QUANTILE quantile of the colour's rates; the veil is measured on the other half, where their
noise is independent of the choice (choosing and measuring on the same frames would bias it low):
the mean z of those pixels at each exposure where they are unclipped, fitted by ``b + V t``
(weighted least squares, EMVA 1288 variances) - b takes a black-level error, which adds DN and not
DN/s. The halves' V are averaged. The veil is expressed in the sample's patch-normalised units
(divided by the white patch's rate per colour, as extraction does, thesis eq. 4.49-4.50); its
standard error counts the fit's and the patch mean's.

Conversion to s (:func:`frame_evidence`), by the pipeline's own calibration: at a BRDF row the
sample value over the measured BRDF, ``S_c / f_c``, is the patch-normalised reading of the
reference white (divided by its BRDF, the reference's own when ``--reference-brdf`` renormalised
the table, albedo / pi otherwise) at that geometry, ``cos theta_in k I / (P d^2)``. So the veil
per unit s, ``k I / (pi D^2 P)``, is ``g / (pi D^2)`` with ``g = median(S_c d^2 / (f_c cos theta_in))``
over the LED's rows, and ``s = pi D^2 v / ((1 - v) g)`` (the veil lights the white patch too: the
patch-normalised veil is ``V / (P + V)``) - the same s as the BRDF-space term
``s d^2 / (pi D^2 cos theta_in)`` (:func:`glossrig.core.diagnose.catalogue.stray_extra`).
"""
from __future__ import annotations

import math

import numpy as np

from glossrig.core.diagnose.catalogue import CauseResult, chi2, fixed_term_test, stray_extra
from glossrig.core.diagnose.data import LUMA, FrameData

DARK_QUANTILE = 0.01     # the dark pixels' reference level: this quantile of a colour's rates in the crop
DARK_NOISE_Z = 3.0       # ... and the pixels within this many of their own sigma above it are "dark"
MIN_DARK = 30            # fewer dark pixels of a colour: no measurement there
MIN_UNCLIPPED = 0.9      # an exposure enters the veil fit when this fraction of the dark pixels is unclipped
SIGNATURE_Z = 5.0        # the pooled frame-space s must exceed this many standard errors to be a signature
BOUND_Z = 3.0            # a BRDF-space s above the frames' bound by this many standard errors is refuted


def _half_rates(z, varz, t, ok, use):
    """Per pixel: rate ``sum z / sum t`` over the unclipped exposures in ``use`` and its variance
    (``varz``: each frame's variance, EMVA 1288)."""
    m = ok & use[:, None, None]
    T = np.sum(np.where(m, t[:, None, None], 0.0), axis=0)
    num = np.sum(np.where(m, z, 0.0), axis=0)
    var = np.sum(np.where(m, varz, 0.0), axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(T > 0, num / T, np.nan), np.where(T > 0, var / T ** 2, np.nan)


def _veil_fit(z, t, ok, fd: FrameData, dark, use):
    """``b + V t`` fitted to the dark pixels' mean z at the exposures in ``use``: (V, se, b) or None."""
    rows = []
    n = int(dark.sum())
    for e in np.nonzero(use)[0]:
        okd = ok[e][dark]
        if okd.mean() < MIN_UNCLIPPED:
            continue
        ze = z[e][dark][okd]
        rows.append((t[e], float(ze.mean()), float(np.mean(fd.variance(ze))) / max(okd.sum(), 1)))
    if len(rows) < 2 or len({r[0] for r in rows}) < 2 or n == 0:
        return None
    tt, mm, vv = (np.array(x) for x in zip(*rows))
    X = np.stack([np.ones_like(tt), tt], axis=1) / np.sqrt(vv)[:, None]
    y = mm / np.sqrt(vv)
    cov = np.linalg.pinv(X.T @ X)
    coef = cov @ X.T @ y
    return float(coef[1]), float(math.sqrt(max(cov[1, 1], 0.0))), float(coef[0])


def dark_veil(fd: FrameData, geometry: dict) -> list[dict]:
    """The veil under each LED (module docstring): one entry per LED frame set, with per colour
    (R, G, B) the veil in patch-normalised units (``veil``, ``veil_se``), in DN/s (``veil_dn_s``),
    the fitted DN offset (``offset_dn``), the patch rate (``patch_dn_s``) and the dark pixels'
    count (``n_dark``); a colour without enough dark pixels or exposures is None.
    ``geometry``: rotation -> the measurement's geometry (its ``patch_mask`` in the crop)."""
    from glossrig.core.diagnose.frames import channel_white, unclipped

    out = []
    for lf in fd.leds:
        z = lf.dn - lf.black[None].astype(np.float32)
        t = np.asarray(lf.exposure_s, float)
        ok = unclipped(lf.dn, channel_white(lf, fd.white)[None])
        col = lf.colours()
        patch = np.asarray(geometry[lf.rotation].patch_mask, bool) if lf.rotation in geometry else None
        idx = np.arange(len(t))
        halves = [idx % 2 == p for p in (0, 1)]
        varz = fd.variance(z)
        sel = [_half_rates(z, varz, t, ok, h) for h in halves]
        rate_all, _ = _half_rates(z, varz, t, ok, np.ones(len(t), bool))
        ent: dict = {"led": int(lf.led), "rotation": float(lf.rotation), "veil": [], "veil_se": [],
                     "veil_dn_s": [], "offset_dn": [], "patch_dn_s": [], "n_dark": []}
        for c in range(3):
            cc = col == c
            pr = rate_all[cc & patch] if patch is not None and patch.shape == cc.shape else np.array([])
            pr = pr[np.isfinite(pr)]
            p_rate = float(pr.mean()) if pr.size else float("nan")
            # the patch mean's standard error from its pixels' scatter (non-uniform lighting counts too:
            # an upper estimate)
            p_rel = float(pr.std(ddof=1) / math.sqrt(pr.size) / p_rate) if pr.size > 1 and p_rate > 0 else 0.0
            fits = []
            n_dark = 0
            for p in (0, 1):
                r, v = sel[p]
                good = cc & np.isfinite(r)
                if patch is not None and patch.shape == cc.shape:
                    good &= ~patch
                if good.sum() < MIN_DARK:
                    continue
                floor = float(np.quantile(r[good], DARK_QUANTILE))
                dark = good & (r <= floor + DARK_NOISE_Z * np.sqrt(v))
                if dark.sum() < MIN_DARK:
                    continue
                f = _veil_fit(z, t, ok, fd, dark, halves[1 - p])
                if f is not None:
                    fits.append(f)
                    n_dark += int(dark.sum())
            if not fits or not (p_rate > 0):
                for k in ("veil", "veil_se", "veil_dn_s", "offset_dn"):
                    ent[k].append(None)
                ent["patch_dn_s"].append(p_rate if np.isfinite(p_rate) else None)
                ent["n_dark"].append(n_dark)
                continue
            V = float(np.mean([f[0] for f in fits]))
            se = float(math.sqrt(sum(f[1] ** 2 for f in fits)) / len(fits))
            ent["veil"].append(V / p_rate)
            ent["veil_se"].append(math.hypot(se, V * p_rel) / p_rate)
            ent["veil_dn_s"].append(V)
            ent["offset_dn"].append(float(np.mean([f[2] for f in fits])))
            ent["patch_dn_s"].append(p_rate)
            ent["n_dark"].append(n_dark)
        out.append(ent)
    return out


def frame_evidence(veil: list[dict] | None, table, lamps: dict) -> dict | None:
    """The frames' s (module docstring): per LED frame set ``s = pi D^2 v / ((1 - v) g)`` per colour, combined
    with the Rec. 709 weights of the colours measured, and pooled over the LED frame sets (mean;
    standard error from the noise and, with two or more, from their spread). ``spread``: the
    median relative half-width (16-84 %) of the per-row conversion g - how far the ideal point-source
    geometry the BRDF-space term assumes departs from what the reference saw. None without a veil
    measurement."""
    if not veil:
        return None
    units = []
    for e in veil:
        rows = table[(table.led == e["led"]) & (table.rotation == e["rotation"])]
        if rows.empty or e["led"] not in lamps:
            continue
        lamp = np.asarray(lamps[e["led"]], float)
        pts = rows[["x", "y", "z"]].to_numpy(float)
        d2 = np.sum((lamp - pts) ** 2, axis=1)
        D2 = float(np.sum(lamp ** 2))
        cos = np.maximum(rows["cos_in"].to_numpy(float), 0.05)
        s_c, se_c, w_c, rel = [], [], [], []
        for k, c in enumerate("rgb"):
            v, vse = e["veil"][k], e["veil_se"][k]
            if v is None or f"S_{c}" not in rows:
                continue
            with np.errstate(invalid="ignore", divide="ignore"):
                g = rows[f"S_{c}"].to_numpy(float) * d2 / (rows[c].to_numpy(float) * cos)
            g = g[np.isfinite(g) & (g > 0)]
            if g.size < 10:
                continue
            gm = float(np.median(g))
            q16, q84 = np.percentile(g, [16, 84])
            # the veil lights the white patch too, so the patch-normalised veil is V / (P + V) = v:
            # V / P = v / (1 - v)
            s_c.append(math.pi * D2 * v / ((1 - v) * gm))
            se_c.append(math.pi * D2 * vse / ((1 - v) ** 2 * gm))
            w_c.append(LUMA[k])
            rel.append(float((q84 - q16) / 2 / gm))
        if not s_c:
            continue
        w = np.array(w_c) / np.sum(w_c)
        units.append({"led": e["led"], "rotation": e["rotation"], "s": float(w @ np.array(s_c)),
                      "se": float(math.sqrt(np.sum((w * np.array(se_c)) ** 2))), "spread": float(np.median(rel)),
                      "n_dark": int(sum(x for x in e["n_dark"] if x))})
    if not units:
        return None
    s = np.array([u["s"] for u in units])
    se_noise = float(math.sqrt(sum(u["se"] ** 2 for u in units)) / len(units))
    se_spread = float(np.std(s, ddof=1) / math.sqrt(len(s))) if len(s) > 1 else 0.0
    return {"s": float(s.mean()), "se": float(math.hypot(se_noise, se_spread)), "se_noise": se_noise,
            "spread": float(np.median([u["spread"] for u in units])), "units": units,
            "unit": "fraction of the LED's direct irradiance (as the BRDF-space stray_light cause's s)"}


def fixed_veil_test(m, s: float) -> tuple[float, float, list, np.ndarray, list]:
    """The BRDF model with the veil of the frames' ``s`` held fixed (``s`` times
    :func:`~glossrig.core.diagnose.catalogue.stray_extra`) against the base model, rho_d and rho_s
    re-solved for each. The veil's size comes from the frames, not from these rows, so no parameter
    of it is fitted to them and the comparison is made on all rows: (base error, error, gains on each
    LED's rows, prediction on all rows, held-out fold gains). The held-out folds (rho_d, rho_s solved
    on the other LEDs) are kept for the record only: with a lobe that misfits the material (a real
    material, two LEDs) the carried-over rho_d, rho_s decide them - measured on ilm_l3_37_matte with
    s = 0.009 hidden and recovered by the frames to 0.1 %: held-out fold gains +13 % and -39 %."""
    c = m.cols
    off = s * stray_extra(m)
    one = np.full_like(c["L"], 1 / np.pi)
    basis = [one, c["L"]]
    held = []
    for train, test in m.folds():
        _, p0, _ = m.solve_linear(basis, train)
        _, p1, _ = m.solve_linear(basis, train, offset=off)
        e0, e1 = chi2((c["y"] - p0)[test], c["sigma"][test]), chi2((c["y"] - p1)[test], c["sigma"][test])
        held.append((e0 - e1) / e0)
    return (*fixed_term_test(m, basis, offset=off), held)


def apply_frame_evidence(m, causes: list[CauseResult], ev: dict | None) -> None:
    """Judge the BRDF-space ``stray_light`` cause by the frames (module docstring), in place.

    * the frames' s is above SIGNATURE_Z standard errors: the cause is re-tested with the veil of
      that s held fixed (:func:`fixed_veil_test`) and, where the BRDF data agree with it (by the
      usual rule on that test, with no failed LED allowed: a lower error on every LED's rows, the pooled gain above the
      threshold), it takes that test's result and s (the free BRDF-space s is kept as ``s_brdf``)
      and carries ``frame_signature``. (Twin captures without
      stray light read s ~ 2e-6 there, 1000 times below the catalogue's smallest stray light: such a
      veil is no signature because the BRDF data do not gain from it);
    * otherwise, where the BRDF-space s exceeds the frames' bound ``s_frames (1 + spread)`` by more than
      BOUND_Z combined standard errors: ``refuted`` (not significant), with what the frames show.
    """
    c = next((x for x in causes if x.name == "stray_light" and x.space == "brdf"), None)
    if c is None or ev is None:
        return
    s_b = float(c.params.get("s", float("nan")))
    se_b = float(c.stderr.get("s", 0.0) or 0.0)
    c.params.update({"s_frames": ev["s"], "s_frames_se": ev["se"], "s_frames_spread": ev["spread"],
                     "frames": [{k: u[k] for k in ("led", "rotation", "s", "se", "n_dark")} for u in ev["units"]]})
    if ev["s"] > SIGNATURE_Z * ev["se"]:
        e0, e1, gains, pred, held = fixed_veil_test(m, ev["s"])
        fixed = CauseResult(c.name, c.space, c.doc, {}, {}, e1, e0, gains, c.n_extra_params)
        c.params["fixed_veil_heldout_fold_gains"] = held
        # every LED's rows, not the sign test of catalogue.consistent_folds: that tolerates a held-out LED the
        # fit must extrapolate to, while this test fits nothing of the veil and scores every LED in-sample
        if fixed.significant and all(g > 0 for g in gains):
            c.params.update({"s_brdf": s_b, "s": ev["s"], "fixed_by": "frames"})
            c.stderr["s"] = ev["se"]
            c.base_error, c.error, c.fold_gains, c.prediction, c.magnitude = e0, e1, gains, pred, ev["s"]
            # the free fit's held-out robust score does not describe the fixed veil (scored on every LED's rows)
            c.params["free_fit_robust"], c.robust = c.robust, None
            c.frame_signature = True
            c.note = (f"frame-space signature: the pixels that see nothing read a veil of s = {ev['s']:.3g} +- "
                      f"{ev['se']:.2g} under every LED (no material lights them); the BRDF data agree: with s held "
                      f"at that value (no parameter fitted to them) their error drops on every LED's rows (free "
                      f"BRDF-space fit: s = {s_b:.3g})")
            return
        c.params["fixed_veil_gain"] = fixed.gain
    bound = ev["s"] * (1 + ev["spread"]) + BOUND_Z * math.hypot(ev["se"], se_b)
    if s_b > bound:
        c.refuted = (f"the frames refute it: the darkest off-sample pixels read a veil of at most s = "
                     f"{ev['s']:.2g} +- {ev['se']:.2g} (a uniform veil lights every pixel), the BRDF-space fit "
                     f"needs s = {s_b:.3g}: what rises toward grazing incidence in the BRDF data is no veil")
        c.note = (c.note + "; " if c.note else "") + c.refuted
