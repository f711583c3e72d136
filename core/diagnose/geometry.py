"""Rig-geometry causes in BRDF space: the LED emission pattern, LED position errors and a
sample radius error, each a parameterised extension of the forward model that
re-evaluates every row's geometry (issue 7).

The measured BRDF of a row is ``f = (albedo / pi) S / R`` (thesis eq. 4.78) with S the
sample's patch-normalised value and R the reference's at the same directions
(:func:`glossrig.core.extraction.extract.diffuse_normalize`). When the sample capture's rig
differs from the one the reference and the calibrations describe, the light reaching
a surface point changes by the ratio of irradiances ``E'(p) / E(p)``, the patch
normalisation divides by the same ratio at the white patch, and the lobe is seen at
the true angles instead of the assumed ones:

    y = [rho_d / pi + rho_s L(angles')] * (E'(p) / E(p)) / (E'(patch) / E(patch)),
    E = I(direction) cos(theta_in) / d^2

(:meth:`Geometry.evaluate`). Angles, points and normals come from
:mod:`glossrig.core.extraction.cylinder` / :mod:`glossrig.core.models.angles`, the pipeline's own
geometry. This describes a sample capture whose rig changed after the reference and
lamp calibration were taken (the blind study's set-up). A change shared by the
reference capture cancels in S / R except through the angles.

Per-LED parameters cannot be predicted on a held-out LED, so those causes are fitted
on one half of the sample's pixel rows and scored on the other (two spatial folds;
the thesis rig's image has the cylinder axis along the pixel columns, so the halves
are the two sides of the cylinder around its circumference), the global radius by
leaving one LED out. Identifiability: the held-out
error along the scale of the fitted parameter vector (0 = base model, 1 = fit) must
not be flat.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from glossrig.core.models.angles import normalize
from glossrig.core.extraction.cylinder import SurfaceSamples, sample_angles, surface_samples
from glossrig.core.calibration.markers import holder_marker_corners
from glossrig.core.rig import load_rig

from glossrig.core.diagnose.catalogue import (GAIN_THRESHOLD, HUBER_C, BrdfModel, CauseResult, RobustScore,
                                              _scalar_cause, deviance, following_fit, one_value, one_value_per_led,
                                              on_bound, not_one_value, ON_BOUND,
                                              weighted_solve)
from glossrig.core.diagnose.error_model import huber_sigma, misfit_features

FIT_ROWS = 6_000          # training rows used by the non-linear fits (held-out scoring uses all)
UP = np.array([0.0, 1.0, 0.0])


class Geometry:
    """The rows' geometry, re-evaluated under perturbed rig parameters."""

    def __init__(self, m: BrdfModel):
        d = m.data
        self.m = m
        tab = d.table.iloc[m.rows]
        rig = load_rig(d.measured.rig_path)
        self.radius, self.height = rig.cylinder_radius, rig.sample_height
        self.pts = tab[["x", "y", "z"]].to_numpy(float)
        self.nrm = tab[["nx", "ny", "nz"]].to_numpy(float)
        self.uv = (tab["u"].to_numpy(float) + 0.5, tab["v"].to_numpy(float) + 0.5)   # Bayer block centres
        self.led = tab["led"].to_numpy(int)
        self.rot = tab["rotation"].to_numpy(float)
        self.leds = sorted(int(x) for x in np.unique(self.led))
        self.lamps = {k: np.asarray(d.lamps[k], float) for k in self.leds}
        self.geo = d.measured.geometry
        corners = holder_marker_corners(rig, inner=True)
        self.patch = corners.mean(axis=0)
        n = normalize(np.cross(corners[1] - corners[0], corners[2] - corners[0]))
        cam = next(iter(self.geo.values())).surface.camera_centre
        self.patch_n = n if float(n @ (cam - self.patch)) > 0 else -n
        self.E0 = self._irradiance(self.lamps_of(self.led), self.pts, self.nrm)
        self._radius_cache: dict = {}

    def lamps_of(self, led, offsets=None):
        P = np.array([self.lamps[int(k)] for k in led]) if np.ndim(led) else self.lamps[int(led)]
        if offsets is not None:
            P = P + (np.array([offsets[int(k)] for k in led]) if np.ndim(led) else offsets[int(led)])
        return P

    @staticmethod
    def _irradiance(P, pts, nrm):
        w = P - pts
        d2 = np.sum(w * w, axis=-1)
        return np.maximum(np.sum(w * nrm, axis=-1) / np.sqrt(d2), 1e-4) / d2

    @staticmethod
    def emission(P, pts, n, tilt):
        """cos^n of the angle between (point - LED) and the LED's axis: the nominal axis points
        from the LED at the cylinder axis (horizontally), tilted by ``tilt`` = (up, side) rad."""
        P = np.asarray(P, float)
        a0 = normalize(-np.array([P[0], 0.0, P[2]]))
        side = np.cross(a0, UP)
        a = normalize(a0 + tilt[0] * UP + tilt[1] * side)
        c = np.clip(normalize(np.asarray(pts, float) - P) @ a, 1e-6, 1.0)
        return c ** n

    def surface(self, rows, dr):
        """Points and normals of ``rows`` on a cylinder of radius + dr (same poses); rows whose
        ray misses the changed cylinder keep their nominal point."""
        pts, nrm = self.pts[rows].copy(), self.nrm[rows].copy()
        if dr == 0:
            return pts, nrm
        K, dist = self.m.data.camera
        for rot in np.unique(self.rot[rows]):
            g = self.geo[rot]
            sel = np.nonzero(self.rot[rows] == rot)[0]
            u, v = self.uv[0][rows][sel], self.uv[1][rows][sel]
            s = surface_samples(K, dist, self.m.data.image_size, g.R_hold, g.t_hold, g.R_cyl, g.t_cyl,
                                self.radius + dr, self.height, pixels=(u, v))
            key = np.round(u * 4) * 1e6 + np.round(v * 4)
            skey = np.round(np.asarray(s.u) * 4) * 1e6 + np.round(np.asarray(s.v) * 4)
            order = np.argsort(skey)
            pos = np.clip(np.searchsorted(skey[order], key), 0, max(len(skey) - 1, 0))
            hit = (skey[order][pos] == key) if len(skey) else np.zeros(len(key), bool)
            j = order[pos[hit]]
            pts[sel[hit]] = s.points[j]
            nrm[sel[hit]] = s.normals[j]
        return pts, nrm

    def held_test(self, **perturbation):
        """The BRDF rows with a geometry change measured outside them held fixed (``perturbation``: the
        keywords of :meth:`evaluate`), the lobe re-evaluated at the changed angles and scored as the
        BRDF-space geometry causes are fitted, with the sigma that follows the lobe (a model without the
        lobe's slope: its own sigma): :func:`~glossrig.core.diagnose.catalogue.fixed_made_test`'s four
        results. The witnesses of the sample radius and the LED positions test the rows so."""
        from glossrig.core.diagnose.catalogue import fixed_made_test

        m = self.m
        one = m.diffuse()
        L, F, dL = self.evaluate(np.arange(len(m.rows)), **perturbation)
        if "dL" not in m.cols:
            return fixed_made_test(m, ([one, m.cols["L"]], None), ([one, L], F))
        return fixed_made_test(m, ([one, m.cols["L"]], None, m.cols["dL"]), ([one, L], F, dL))

    def evaluate(self, rows, offsets=None, dr=0.0, em=None):
        """(L, F, dL) of ``rows``: the lobe at the perturbed angles, the irradiance factor and the lobe's
        slope along theta_h there (the error model's slope feature: a cause that moves the lobe is scored
        with the sigma that follows it, :meth:`glossrig.core.diagnose.catalogue.BrdfModel.follow`).
        ``offsets``: LED id -> (3,) mm; ``dr``: radius change, mm; ``em``: (n, {LED: tilt})."""
        pts, nrm = self.surface(rows, dr)
        L = np.empty(len(rows))
        F = np.empty(len(rows))
        dL = np.empty(len(rows))
        for led in np.unique(self.led[rows]):
            for rot in np.unique(self.rot[rows]):
                sel = np.nonzero((self.led[rows] == led) & (self.rot[rows] == rot))[0]
                if not len(sel):
                    continue
                g = self.geo[rot].surface
                P = self.lamps_of(led, offsets)
                s = SurfaceSamples(self.uv[0][rows][sel], self.uv[1][rows][sel], pts[sel], nrm[sel],
                                   g.camera_centre, g.axis)
                a = sample_angles(s, P, rot)
                L[sel] = self.m.lobe_at(a)
                dL[sel] = self.m.lobe_slope(a)
                E = self._irradiance(P, pts[sel], nrm[sel])
                Ep = self._irradiance(P, self.patch, self.patch_n) / self._irradiance(self.lamps[led], self.patch,
                                                                                       self.patch_n)
                if em is not None:
                    n, tilt = em
                    E = E * self.emission(P, pts[sel], n, tilt[led])
                    Ep = Ep * self.emission(P, self.patch[None], n, tilt[led])[0]
                F[sel] = E / self.E0[rows][sel] / Ep
        return L, F, dL


def per_led_folds(m: BrdfModel) -> list[tuple[np.ndarray, np.ndarray]]:
    """The folds of a cause with per-LED parameters (no held-out LED can be predicted by them): leave one
    sample rotation out where the capture has several - an LED's position and emission are the rig's and do
    not turn with the sample, while a material's departure that per-LED parameters could take up does (on
    the rgl study's anisotropic Beckmann conductor, rotations 0 and 90 degrees, LED offsets of 1.8 mm RMS
    gained 10 % on top of the Beckmann lobe between the two halves of the pixel rows) - else the two halves
    of the sample's pixel rows (:meth:`BrdfModel.halves`)."""
    rot = m.cols["rotation"]
    rots = np.unique(rot)
    if len(rots) >= 2:
        return [(rot != r, rot == r) for r in rots]
    return m.halves()


def _vector_cause(geo: Geometry, name, doc, unpack, base, x0, lo, hi, magnitude, params_of, unit,
                  owners) -> CauseResult:
    """A cause with a parameter vector (some per LED): fitted on one half of the sample's pixel
    rows by variable projection (rho_d, rho_s linear), scored on the other half. ``owners``: per
    parameter, the LED whose rows alone it changes (None: every row)."""
    m = geo.m
    c = m.cols
    rng = np.random.default_rng(0)
    base_res = ext_res = 0.0
    gains, fits, fold_errors = [], [], []
    scales = np.linspace(0.0, 2.0, 5)
    prof = np.zeros(len(scales))
    n_all = 0

    D = m.diffuse()
    allrows = np.arange(len(c["y"]))
    v0 = m.misfit["v0"]

    def predict(x, train):
        """The cause at parameters ``x`` with rho_d, rho_s (and a conditioned model's flexible material
        columns) solved on the ``train`` rows with the sigma that follows the model
        (:func:`~glossrig.core.diagnose.catalogue.following_fit`): (prediction, sigma) for every row."""
        L, F, dL = geo.evaluate(allrows, **unpack(x))
        _, pr, sig = following_fit(m, [D, L], dL, train, factor=F)
        return pr, sig

    def score(x, train, test):
        pr, sig = predict(x, train)
        return deviance((c["y"] - pr)[test], sig[test], m.sigma_reference()[test])

    def fit(train_idx):
        train = np.zeros(len(allrows), bool)
        train[train_idx] = True
        sub = train_idx if len(train_idx) <= FIT_ROWS else np.sort(rng.choice(train_idx, FIT_ROWS, False))
        y, sig0 = c["y"][sub], c["sigma"][sub]
        flex = m.flexible_columns(train)[sub] if m.flexible else np.zeros((len(sub), 0))
        groups = {k: np.flatnonzero(geo.led[sub] == k) for k in geo.leds}
        last = {}  # the last evaluated x and its (L, F, dL), for the Jacobian

        def resid(L, F, dL):
            # the deviance as a sum of squares: the normalised residuals with the sigma that follows the model
            # (rho_d, rho_s and the flexible columns solved with the base's sigma), and per row
            # sqrt(log(sigma^2 / v0) + 1), whose squares sum to sum(log sigma^2) plus a constant
            X = np.column_stack([D[sub], L, flex]) * F[:, None]
            coef, _ = weighted_solve(X, y, sig0, 2)
            pr = X @ coef
            mis = m.misfit
            rs = mis.get("rho_s", 1.0)                # the lobe's size stays the base's (BrdfModel.follow)
            sig = np.sqrt(mis["v0"][sub] + misfit_features(pr, rs * L * F, rs * dL * F) @ mis["k"])
            r = y - pr
            return np.concatenate([r / huber_sigma(sig, r, HUBER_C), np.sqrt(np.log(sig ** 2 / v0[sub]) + 1.0)])

        def fun(x):
            last["x"], last["LF"] = np.array(x, float), geo.evaluate(sub, **unpack(x))
            return resid(*last["LF"])

        def jac(x):
            # forward differences (step 1e-3 max(1, |x|), as least_squares' diff_step=1e-3), each column
            # re-evaluating the geometry of its own LED's rows only (a per-LED parameter moves nothing
            # else; rho_d and rho_s are re-solved over all rows, so the column is the exact difference)
            L0, F0, S0 = last["LF"] if np.array_equal(last.get("x"), x) else geo.evaluate(sub, **unpack(x))
            r0 = resid(L0, F0, S0)
            J = np.empty((len(r0), len(x)))
            for j in range(len(x)):
                h = 1e-3 * max(1.0, abs(x[j]))
                h = -h if x[j] + h > hi[j] else h
                xj = np.array(x, float)
                xj[j] += h
                if owners[j] is None:
                    L, F, S = geo.evaluate(sub, **unpack(xj))
                else:
                    rows = groups[owners[j]]
                    L, F, S = L0.copy(), F0.copy(), S0.copy()
                    L[rows], F[rows], S[rows] = geo.evaluate(sub[rows], **unpack(xj))
                J[:, j] = (resid(L, F, S) - r0) / h
            return J

        return least_squares(fun, x0, jac=jac, bounds=(lo, hi), x_scale=np.maximum(hi - lo, 1e-9) / 20,
                             max_nfev=30 * len(x0)).x

    robust = RobustScore()
    for train, test in per_led_folds(m):
        x = fit(allrows[train])
        fits.append(x)
        e0, e1 = score(base, train, test), score(x, train, test)
        robust.add(c["y"], predict(base, train)[0], predict(x, train)[0], test)
        for j, sc in enumerate(scales):
            prof[j] += score(base + sc * (x - base), train, test) * test.sum()
        base_res += e0 * test.sum()
        ext_res += e1 * test.sum()
        n_all += test.sum()
        gains.append((e0 - e1) / e0)
        fold_errors.append(e1)
    xa = fit(allrows)
    spread = np.ptp(np.array(fits), axis=0) / 2
    profile = {"grid": scales.tolist(), "error": (prof / n_all).tolist(), "along": "scale of the fitted parameters"}
    r = CauseResult(name, "brdf", doc, dict(params_of(xa), unit=unit, fold_estimates=[params_of(f) for f in fits]),
                    params_of(spread), ext_res / n_all, base_res / n_all, gains, len(x0), profile=profile,
                    magnitude=magnitude(xa), prediction=predict(xa, np.ones(len(allrows), bool))[0],
                    fold_errors=fold_errors, robust=robust.result())
    e = np.asarray(profile["error"])
    if (e.max() - e.min()) / max(e.min(), 1e-12) < GAIN_THRESHOLD:
        r.identifiable = False
        r.note = ("held-out error varies by less than 2 % along the fitted parameters (scale 0-2): "
                  "the data cannot tell this cause apart")
    else:
        r.note = (("split: leave one sample rotation out" if len(np.unique(c["rotation"])) >= 2 else
                   "split: the two halves of the sample's pixel rows") + " (per-LED parameters); stderr = fold spread")
        # the folds' agreement judged on the effect, not on the parameters: per-LED offsets along a direction
        # the data barely constrain (towards the sample: only the irradiance's scale changes, which rho_d and
        # rho_s take) scatter between the halves, up to the bounds, while the effect they describe agrees
        allr = np.ones(len(allrows), bool)
        p0 = predict(base, allr)[0]
        effects = [predict(f, allr)[0] / np.maximum(p0, 1e-12) - 1.0 for f in fits]
        # the fit on all rows, though, must lie inside the range the physics is searched over: per-LED
        # parameters of a real material's departure run to the bounds (on the rgl study's acrylic_felt_green
        # and chm_mint captures, 9 and 16 of the 24 LED offsets of the pooled fit at +-15 mm, RMS 10-13 mm,
        # against a lamp calibration good to 2 mm; held-out gains 55-57 % - a departure in theta_d, which on
        # the cylinder rig each LED sees over its own narrow range, taken up LED by LED). A fold's fit may
        # reach a bound along a direction half the rows barely constrain (the blind study's hidden 1.3 mm
        # offsets on sample_2_6: one fold's offset towards the sample at -15 mm, the pooled fit's largest 2.8 mm)
        if on_bound(xa, lo, hi, base):
            not_one_value(r, ON_BOUND + " (the fit on all rows)")
        else:
            one_value(r, effects, np.mean(effects, axis=0), -np.inf, np.inf, np.zeros(len(allrows)))
    return r


#: the causes of :func:`geometry_causes`, in its order
GEOMETRY_CAUSES = ("led_position_error", "led_emission", "sample_radius_error")


def geometry_causes(m: BrdfModel, log=None, only=GEOMETRY_CAUSES) -> list[CauseResult]:
    """LED position error, LED emission and sample radius error (those of ``only``); ``log``
    (callable(CauseResult)) is called as each finishes (progress)."""
    say = log or (lambda r: None)
    geo = Geometry(m)
    leds = geo.leds
    nl = len(leds)
    out = []

    # ---- LED position error: 3 offsets per LED
    doc = ("LED position error (thesis 4.1.5: hand-mounted holders): each LED sits off the position the lamp "
           "calibration gives by an offset (dx, dy, dz). The lobe is seen at other angles (wi changes by ~offset/d "
           "rad, d ~ 300 mm), and the irradiance cos(theta_in)/d^2 on the sample and on the white patch change by "
           "different amounts: a per-LED gradient over the sample. Magnitude: RMS of the fitted offsets per axis (mm).")
    off = lambda x: {"offsets": {k: x[3 * i:3 * i + 3] for i, k in enumerate(leds)}}
    if "led_position_error" in only:
        out.append(_vector_cause(
            geo, "led_position_error", doc, off, np.zeros(3 * nl), np.zeros(3 * nl), np.full(3 * nl, -15.0),
            np.full(3 * nl, 15.0), lambda x: float(np.sqrt(np.mean(np.square(x)))),
            lambda x: {"offset_mm": {str(k): [float(v) for v in x[3 * i:3 * i + 3]] for i, k in enumerate(leds)}},
            "mm (per LED, holder frame)", [k for k in leds for _ in range(3)]))
        say(out[-1])

    # ---- LED emission pattern: cos^n about a tilted axis
    doc = ("LED emission pattern (thesis 4.1.3, fig. 4.2): the radiant intensity left after the diffuser falls as "
           "cos^n of the angle to the LED's optical axis, the axis tilted from the cylinder axis by a small "
           "(up, side) angle per LED. The sample spans +-6 degrees seen from an LED, the white patch sits elsewhere, "
           "so the patch normalisation leaves a smooth per-LED factor: quadratic in the angle (n) with a linear "
           "part (n x tilt). Independent of the lobe and of the image position, unlike vignetting.")
    em = lambda x: {"em": (x[0], {k: x[1 + 2 * i:3 + 2 * i] for i, k in enumerate(leds)})}
    x0 = np.concatenate([[20.0], np.zeros(2 * nl)])
    if "led_emission" in only:
        out.append(_vector_cause(
            geo, "led_emission", doc, em, np.zeros(1 + 2 * nl), x0, np.concatenate([[0.0], np.full(2 * nl, -0.15)]),
            np.concatenate([[400.0], np.full(2 * nl, 0.15)]), lambda x: float(x[0]),
            lambda x: {"n": float(x[0]), "tilt_deg": {str(k): [float(math.degrees(v)) for v in x[1 + 2 * i:3 + 2 * i]]
                                                      for i, k in enumerate(leds)}},
            "cos exponent n; axis tilt (up, side) degrees", [None] + [k for k in leds for _ in range(2)]))
        say(out[-1])

    # ---- sample radius error: one global scalar (leave one LED out)
    doc = ("Sample radius error (thesis 4.1.4: paper and sample thickness): the wrapped sample's radius differs from "
           "the rig file's by dr. Every pixel then sees another point of the surface with another normal, so the "
           "angles and the irradiance change; the calibrated poses are kept. A shift of the normal by ~dr/r "
           "times the distance from the silhouette: small except near the sample's edges.")
    one = m.diffuse()
    allrows = np.arange(len(m.rows))
    cache = {}

    def make_r(dr):
        # on a 0.002-mm lattice, so that the folds' searches share the re-evaluated geometry (speed)
        key = round(float(dr) / 0.002) * 0.002
        if key not in cache:
            cache[key] = geo.evaluate(allrows, dr=key)
        L, F, dL = cache[key]
        return [one, L], F, dL

    if "sample_radius_error" in only:
        out.append(_scalar_cause(m, "sample_radius_error", doc, make_r, (-3.0, 3.0), "dr_mm", "mm", grid_n=13))
        one_value_per_led(out[-1], m, make_r, (-3.0, 3.0), "dr_mm", 0.0)
        say(out[-1])
    return out
