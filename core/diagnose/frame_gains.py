"""The gain of every frame of an LED's exposure sequence, and the LED-drift test on them
(thesis 4.3.3, fig. 4.12; issue 14).

An LED's output changes from frame to frame: fast (jitter, which the pipeline's neighbour
correction removes, thesis eq. 4.32-4.38) and slowly (drift, thesis fig. 4.12). Both multiply
every pixel of a frame alike, so the raw series of an LED is

    DN_ep - black = r_p t_e g_e

with one rate r_p per pixel and one gain g_e per frame (:func:`frame_gains`, fitted by
weighted least squares with the EMVA 1288 variances of :class:`.frames.FrameSet`; the gains
are known up to one common factor, fixed at an information-weighted mean of 1). Their
covariance is the inverse of the Gauss-Newton information with the rates *profiled out*
(the Schur complement of the rates' block): a pixel seen in a few frames only tells the
gains of those frames relative to each other, and treating the rates as known understated
the slope's standard error three-fold on synthetic null stacks (a null chi^2 of 17 with 2
degrees of freedom; with the Schur complement the mean over the 12 null stacks of tests/test_frame_gains.py is 2.1).

**The drift test** (:func:`drift_test`). Drift is a slow trend of the gains in capture
time: per LED, ``g_e = alpha (1 + a tau_e)`` with tau_e the frame's time (minutes) from the
middle of its sequence (beside the shutter term below), fitted by generalised least squares
with covariance ``cov(g) + s^2 I``. ``s`` is the frame-to-frame jitter, one value for the rig's LEDs
(they are of one kind), estimated from the data by the method of moments: the pooled
generalised chi^2 of the trend fits equals its degrees of freedom (s = 0 when photon noise
alone explains the scatter, as on an ideal twin capture). The statistic is the Wald statistic
of the LEDs' slopes (with their covariance: they share the shutter term), chi^2 with one
degree of freedom per LED when no LED drifts; drift
is significant when it exceeds that distribution's upper tail at the same 4-sigma level as the
marker band's test (:data:`TAIL`, :mod:`.marker_band`): a false-alarm rate of 6.3e-5 a capture
under the noise model.

Why not the held-out gain of the frame space (:mod:`.frames`): its base model has no frame
gains, so a slow drift is scored against every pixel's photon noise, and each pixel's rate,
fitted over the part of the sequence where the pixel is neither dark nor clipped, takes up
most of it. Measured on the eight-LED blind study (validation/diagnose/blind_study_8led.md at
42aabcc): drifts of 0.0056-0.0083 /min gained 0.018-0.089 % held out, under the frame
threshold of 0.13 % for eight slopes. And the frame-to-frame jitter of a real LED (0.5 %,
the twin's ``led_jitter``) is structure that held-out score does not expect. On the gains the
drift is a trend in a short series whose scatter the test measures: on synthetic stacks with a
drift of 0.006 /min the statistic of "no LED drifts at all" is 36-49 against a bound of 19.3 (two
LEDs, six seeds), and with 0.5 % jitter and no drift it stays at 0.8-3.8 (measured before the rig's
own drift joined the null, below, which lowers both).

**The rig's own drift.** A healthy rig's LEDs drift too (thesis fig. 4.12; the pipeline's
neighbour correction and patch normalisation are there to remove it): the twin simulates it by
default, 1 % over periods of 20-60 min (the rig file's ``[leds]`` figures, :mod:`glossrig.core.led_fluctuations`),
an RMS slope of 0.0013 /min. On a few LEDs it is lost in the photon noise and the jitter; on many it is not: on
the rgl study's anisotropic GGX capture (16 LED sequences, thesis fluctuations, no other effect)
the statistic of "no LED drifts" was 68.8 against a bound of 47.2, the slopes within 2.6 standard
errors of the drift the twin recorded. So the test asks whether the LEDs drift *more than the
rig's own*: the slopes are taken as drawn around zero with that RMS, which adds its square to
each slope's variance (a random effect), and the statistic is chi^2(L) when they drift as a
healthy rig does. On that capture it is 37.6; on the rgl study's ten captures 10-38 against
47.2 (validation/diagnose/rgl_study.md). On the eight-LED blind study's drift trials (--ideal
captures, drifts of 2.3-3.7 % amplitude, the study's 3000 pixels per LED) it is 38-64 against
32.9 (all three named, as before). What is lost: a drift a few times the rig's own on two LEDs
(the two-LED blind study's drift trials: 2.8-10.5 against 19.3, where trial 25 was named before).

**Shutter.** An exposure-time error delta is a frame gain too, ``1 + delta / t_e``, the same for
every LED (it is the camera's), largest at the shortest exposures. Fitted alone, a trend in time
takes part of it (measured on the two-LED blind study's shutter trials: statistics of 8.8-14.7
against 19.3 with the shutter error fitted as jitter): the trend fit carries one shutter term
``t_min / t_e`` shared by the LEDs, so a drift is a trend that differs from LED to LED and
follows time, not exposure. Its standard error covers the truth: over 400 synthetic stacks with a
shutter error of 2e-5 - 6e-5 s (tests/test_frame_gains.py), z = (estimate - truth) / stderr has mean
-0.03 and SD 1.02. On twin captures it may be somewhat small: the two-LED blind study's six shutter
trials (raws rewritten, :mod:`glossrig.twin.rewrite_raw`) read z = -2.3 to +1.4, RMS 1.5 (chi^2 13.1
on 6 degrees, p = 0.04) - not traced. (The rewrite used to round to the nearest integer, which left
the darkest pixels of the shortest frames without the effect - 17 % of a 2e-5 s error missing on a
matte crop; it rounds stochastically now. That was not what made those six scatter: with the old
rounding they read -2.4 to +1.1.)

Other sensor causes bend the gains too (a black offset, a compression); on top of them
(:mod:`.conditional`) the test runs on the frames with their terms undone (:func:`linearised`).

**What neither an LED nor the shutter does** (:func:`camera_structure`). An LED's drift differs
from LED to LED and follows capture time; a shutter error is ``delta / t_e``. A camera effect
outside the catalogue that follows the exposure setting - a gain step at the long exposures (a
long-exposure mode of the camera), a step half-way through every sequence, a response error at
low signal - bends every LED's gains alike at each exposure time, and a linear trend per LED takes
enough of it to pass the drift test: measured on a matte twin capture's sample crop (two LEDs), a
3 % gain on every exposure of 1 s or longer read a drift statistic of 57.2 against 19.3, a 3 % step
half-way through each sequence 42.6, and either was named ``led_drift``. So the gains are also
fitted with a free gain per exposure time shared by the LEDs on top of the trends and the shutter
term, the jitter by moments on that fullest model (the trend fit's own jitter takes up a step's
misfit: 0.78 % for that 3 % step, against 0.09 % on the full model); the drop of chi^2 is tested
against chi^2 with one degree per added direction at the same 4-sigma tail. Where it is
significant, the gains carry structure common to every LED at each exposure time that the trends
and the shutter term do not describe: neither the drift nor the shutter error is named - it is their
check (:func:`camera_check`, :attr:`.catalogue.CauseResult.check`), taken again on top of any selected
sensor cause (:mod:`.conditional`) - and the structure is an "unexplained" entry along ``exposure_s``
(:mod:`.unexplained`, reported as the common gain's profile over the exposure times). On that
capture the statistic read 161-1762 for those effects (1 % and 3 % steps; bound 48.9-50.5) and
7.9 with none; on synthetic stacks (tests/test_frame_gains.py) with a drift, a drift on both LEDs
alike, jitter or a shutter error, 2.6-35.4 against 45.5-47.2. A black offset or a compression makes
it too (1061-1970 on synthetic stacks with an 8 DN offset): on top of such a cause the test runs
on the frames with its terms undone, like the others.

**Sensor causes and the jitter** (:func:`sensor_check`). A black offset, a compression and a
per-channel response are scored by the held-out gain of :mod:`.frames`, whose base model has no
frame gains; an LED's frame-to-frame jitter is structure it does not expect, and a compression
can take part of it up. Measured on the synthetic stacks of tests/test_diagnose.py (two LEDs,
rates up to 2e6 DN/s, no sensor effect): with 0.5 % jitter ``sensor_nonlinearity`` was named on
1 of 52 seeds (300-351), with 1 % on 4 of 40 (400-439), before this check; with it on none. A gain per frame cannot mimic what these
causes do - an offset is added, a compression bends the bright pixels of a frame more than its
dark ones - so each must also pass a check on the gains model: undo the cause's terms at its own
estimate (:func:`linearised`), refit the gains, and compare the drop of the weighted misfit
(:func:`gains_misfit`; over the misfit per degree of freedom where that exceeds 1, a
quasi-likelihood scale for a noise model that is off) with chi^2 with one degree per parameter.
The estimate comes from the other model, so the drop is at most the likelihood ratio's maximum
over the parameters, chi^2(k) when there is no effect: the check is conservative. It is a second
test of a cause the held-out gain already found, at the 2-sigma level (:data:`CHECK_TAIL`): on those
stacks the five jitter-made namings dropped the misfit by -19 to -8 (the compression made the gains
model worse), a compression of 0.01 - the blind study's smallest - by 9-25 (four seeds, no jitter)
and 15-32 (0.5 % jitter), where a 4-sigma bound (16) would have lost one of each four.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2, norm

from glossrig.core.diagnose.catalogue import CHECK_Z, TEST_Z
from glossrig.core.led_fluctuations import drift_slope_rms_per_min

#: the upper tail at which a test's chi^2 is significant: the two-sided TEST_Z-sigma tail (6.3e-5)
TAIL = float(2 * norm.sf(TEST_Z))
#: the upper tail of the sensor causes' check (:func:`sensor_check`): the two-sided CHECK_Z-sigma tail (4.6 %)
CHECK_TAIL = float(2 * norm.sf(CHECK_Z))
MIN_FRAMES = 4          # an LED with fewer frames that any pixel sees unclipped has no trend to test
#: the scale degeneracy (gains x k, rates / k) is given this variance along the constant
#: direction in the trend fit: the trend's free intercept takes it, whatever its size
_FREE = 1.0


def frame_gains(Z, T, W, M, iters: int = 20) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gains of the frames of one LED: ``Z`` (n_exp, P) signal above black, ``T`` exposure
    times (n_exp, P), ``W`` weights (1 / variance), ``M`` the frames each pixel is used in.
    Gauss-Newton on the gains with the rates profiled out (module docstring). Returns the
    gains (n_exp,) of the frames any pixel sees (``seen``), their covariance, and ``seen``."""
    WM = np.where(M, W, 0.0)
    seen = np.sum(WM, axis=1) > 0
    Z, T, WM = Z[seen], T[seen], WM[seen]
    g = np.ones(len(Z))
    cov = np.zeros((len(Z), len(Z)))
    for _ in range(iters):
        G = T * g[:, None]
        c = np.sum(WM * G * G, axis=0)
        keep = c > 0
        r = np.where(keep, np.sum(WM * G * Z, axis=0) / np.where(keep, c, 1.0), 0.0)
        X = T * r[None, :]
        score = np.sum(WM * (Z - X * g[:, None]) * X, axis=1)
        B = (WM * X * G)[:, keep]
        info = np.diag(np.sum(WM * X * X, axis=1)) - (B / c[keep]) @ B.T
        cov = np.linalg.pinv(info, rcond=1e-10, hermitian=True)
        step = cov @ score
        g = g + step
        if np.max(np.abs(step)) < 1e-10:
            break
    info_w = np.sum(WM * (T * r[None, :]) ** 2, axis=1)
    k = float(np.sum(info_w * g) / np.sum(info_w))
    return g / k, cov / k ** 2, seen


def gains_misfit(Z, T, W, M, g, seen) -> tuple[float, int]:
    """The weighted sum of squares of the frames about ``rate_p t_e g_e`` (the rates refitted at the
    gains ``g`` of :func:`frame_gains` over the frames ``seen``, :func:`.frames._fit_rates`) and its
    degrees of freedom: the observations less one rate per pixel and the gains (less the common factor)."""
    from glossrig.core.diagnose.frames import _fit_rates

    WM = np.where(M, W, 0.0)[seen]
    Z, G = Z[seen], T[seen] * g[:, None]
    r = _fit_rates(Z, T[seen], None, None, gain=g[:, None], WM=WM)
    n_rates = int(np.sum(np.any(WM > 0, axis=0)))
    return float(np.sum(WM * (Z - r[None, :] * G) ** 2)), int(np.sum(WM > 0)) - n_rates - (len(g) - 1)


def linearised(fs, i: int, offset=0.0, gain=None, c=0.0) -> tuple[np.ndarray, np.ndarray]:
    """LED ``i``'s signal with a selected model's terms undone - a black offset subtracted, a
    compression ``x (1 - c x / range)`` inverted, a per-frame gain (shutter error) divided out -
    and the weights carried through (the variance of x is the DN variance over (dz/dx)^2, then over
    the gain squared). The terms are :func:`.frames._linear_pred`'s."""
    z = fs.Z[i] - offset
    W = 1.0 / fs.V[i]
    c = np.asarray(c, float)
    if np.any(c != 0.0):
        # the root of x - c x^2 / range = z near x = z, in the form without cancellation (exact at c = 0,
        # where (range / 2c) (1 - sqrt(...)) loses every digit)
        x = 2.0 * z / (1.0 + np.sqrt(np.maximum(1.0 - 4.0 * c * z / fs.range, 1e-6)))
        W = W * (1.0 - 2.0 * c * x / fs.range) ** 2
        z = x
    if gain is not None:
        z = z / gain
        W = W * gain ** 2
    return z, W


def _trend(gs, covs, taus, inv_t, s2: float):
    """GLS fit of every LED's gains at jitter variance ``s2``: per LED an intercept and a slope in
    capture time, and one shutter term (``t_min / t_e``) shared by the LEDs (module docstring,
    "Shutter"); the LEDs' gains are independent of each other. Returns the slopes relative to
    their intercepts, their covariance, (the shutter coefficient, its standard error, the mean
    intercept it is relative to), and the pooled generalised chi^2 with its degrees of freedom."""
    L = len(gs)
    npar = 2 * L + 1
    N = np.zeros((npar, npar))
    rhs = np.zeros(npar)
    blocks = []
    for k, (g, cv, tau, it) in enumerate(zip(gs, covs, taus, inv_t)):
        n = len(g)
        Si = np.linalg.inv(cv + (s2 + 1e-14) * np.eye(n) + _FREE * np.ones((n, n)))
        A = np.zeros((n, npar))
        A[:, 2 * k], A[:, 2 * k + 1], A[:, -1] = 1.0, tau, it
        N += A.T @ Si @ A
        rhs += A.T @ Si @ g
        blocks.append((g, A, Si))
    C = np.linalg.pinv(N, hermitian=True)
    b = C @ rhs
    chi = float(sum((g - A @ b) @ Si @ (g - A @ b) for g, A, Si in blocks))
    dof = sum(len(g) for g in gs) - npar
    alpha = b[0:-1:2]
    slopes = b[1:-1:2] / alpha
    idx = np.arange(1, 2 * L, 2)
    cov = C[np.ix_(idx, idx)] / np.outer(alpha, alpha)
    return slopes, cov, (float(b[-1]), float(np.sqrt(C[-1, -1])), float(np.mean(alpha))), chi, dof


@dataclass
class GainSeries:
    """The frame gains' fit of a capture (:func:`gain_series`): per LED sequence (``leds``: the labels of
    :class:`.frames.FrameSet`, the LED's id, with its rotation where there are several) its slope in capture
    time (relative, 1/min) with their covariance; the shutter error (s) the gains show with its standard
    error; the jitter (relative RMS per frame) the fit measured."""

    leds: list[str]
    slopes: np.ndarray
    cov: np.ndarray
    shutter_s: float
    shutter_se_s: float
    jitter: float
    #: the weighted sum of squares of the frames about the gains model (:func:`gains_misfit`, summed over
    #: the LEDs) and its degrees of freedom: what :func:`sensor_check` compares
    chi2: float = float("nan")
    dof: int = 0
    #: the RMS slope (1/min) a healthy LED of the capture's rig drifts by: its rig file's
    #: (:meth:`glossrig.core.rig.Lighting.drift_slope_rms_per_min`), what :func:`drift_test` takes as its null
    baseline_per_min: float = drift_slope_rms_per_min()
    #: gain structure common to the LEDs at each exposure time beyond the trends and the shutter term
    #: (:func:`camera_structure`); None where not fitted
    camera: dict | None = None


def gain_series(fs, terms=None, camera: bool = True) -> GainSeries | None:
    """Every LED's frame gains (:func:`frame_gains`) and their joint fit (module docstring): a trend
    in capture time per LED, a shutter term shared by the LEDs, the jitter by the method of moments.
    ``terms(i) -> dict`` (offset / gain / c of :func:`.frames._linear_pred`): the selected causes'
    terms to undo first (:func:`linearised`); None: the frames as they are. ``camera``: fit the camera
    structure too (:func:`camera_structure`, which the drift and shutter tests read; a series only the
    sensor check compares, :func:`sensor_check`, need not). None when no LED has
    :data:`MIN_FRAMES` frames that any pixel sees."""
    gs, covs, taus, inv_t, leds, t_e = [], [], [], [], [], []
    ssr, dof = 0.0, 0
    t_min = float(min(np.min(t) for t in fs.T))
    for i in range(len(fs.Z)):
        z, W = linearised(fs, i, **(terms(i) if terms is not None else {}))
        g, cov, seen = frame_gains(z, fs.T[i], W, fs.ok[i])
        if seen.sum() < MIN_FRAMES:
            continue
        s_i, d_i = gains_misfit(z, fs.T[i], W, fs.ok[i], g, seen)
        ssr, dof = ssr + s_i, dof + d_i
        gs.append(g)
        covs.append(cov)
        taus.append(fs.tau[i][seen, 0])
        inv_t.append(t_min / fs.T[i][seen, 0])
        t_e.append(fs.T[i][seen, 0])
        leds.append(fs.label[i])
    if not gs:
        return None
    fit = _trend(gs, covs, taus, inv_t, 0.0)
    s2 = 0.0
    if fit[3] > fit[4]:
        s2 = _jitter_by_moments(lambda v: _trend(gs, covs, taus, inv_t, v)[3], fit[4], 60)
        fit = _trend(gs, covs, taus, inv_t, s2)
    slopes, cov, (d, d_se, alpha), _, _ = fit
    b = fs.fd.drift_rms_per_min
    return GainSeries(leds, slopes, cov, d / alpha * t_min, d_se / alpha * t_min, float(np.sqrt(s2)), ssr, dof, b,
                      camera_structure(gs, covs, taus, inv_t, t_e, b) if camera else None)


def _jitter_by_moments(chi_of, dof: float, steps: int) -> float:
    """Method of moments: the jitter variance at which a fit's pooled generalised chi^2 (``chi_of(s2)``,
    falling as s2 grows) equals its degrees of freedom; bisection on a log scale up to 20 % jitter."""
    lo, hi = 1e-12, 0.04
    for _ in range(steps):
        mid = float(np.sqrt(lo * hi))
        if chi_of(mid) > dof:
            lo = mid
        else:
            hi = mid
    return hi


class _CommonGainsFit:
    """GLS of the LEDs' gains (:func:`camera_structure`): per LED an intercept and a trend in capture time, a
    shutter term shared by the LEDs and (``common``) a gain per exposure time shared by them; covariance
    cov(g) + s2 I (jitter) + b^2 tau tau^T (the rig's own drift as a random slope). Each LED's covariance
    but the jitter is diagonalised once, so a fit at another jitter costs a few small products."""

    def __init__(self, gs, covs, taus, inv_t, t_e, b: float):
        self.keys = np.unique(np.concatenate(t_e))
        L = len(gs)
        self.n_trend = 2 * L + 1
        self.leds = []
        for k, (g, cv, tau, it, te) in enumerate(zip(gs, covs, taus, inv_t, t_e)):
            n = len(g)
            w, Q = np.linalg.eigh(cv + _FREE * np.ones((n, n)) + b ** 2 * np.outer(tau, tau))
            A = np.zeros((n, self.n_trend + self.keys.size))
            A[:, 2 * k], A[:, 2 * k + 1], A[:, 2 * L] = 1.0, tau, it
            A[np.arange(n), self.n_trend + np.searchsorted(self.keys, te)] = 1.0
            self.leds.append((g, Q, w, A, np.diag(cv)))
        self.n = int(sum(len(g) for g in gs))

    def fit(self, s2: float, common: bool):
        """chi^2, the normal matrix, and per LED its residual with the diagonal of its covariance."""
        m = self.n_trend + (self.keys.size if common else 0)
        N, rhs, parts = np.zeros((m, m)), np.zeros(m), []
        for g, Q, w, A, d in self.leds:
            Si = (Q / (w + s2 + 1e-14)) @ Q.T
            A = A[:, :m]
            N += A.T @ Si @ A
            rhs += A.T @ Si @ g
            parts.append((g, A, Si, d + s2))
        beta = np.linalg.pinv(N, rcond=1e-10, hermitian=True) @ rhs
        res = [(g - A @ beta, v) for g, A, _, v in parts]
        chi = float(sum(r @ Si @ r for (r, _), (_, _, Si, _) in zip(res, parts)))
        return chi, N, res


def _largest_step(prof: np.ndarray, se: np.ndarray) -> float:
    """The effect of the camera structure: the change of the common gain between adjacent exposure times
    where it is most significant (largest |change| / its standard error). Not the profile's spread: the
    trends and the shutter term, fitted beside a step, bend the few-photon shortest exposures' residual
    by several of their large standard errors (measured: -11 % at 1/4000 s beside a 3 % step at 1 s, whose
    jump reads 2.5 %)."""
    if prof.size < 2:
        return 0.0
    d = np.diff(prof)
    z = np.abs(d) / np.sqrt(se[1:] ** 2 + se[:-1] ** 2)
    return float(abs(d[int(np.argmax(z))]))


def camera_structure(gs, covs, taus, inv_t, t_e, b: float) -> dict | None:
    """The test of the module docstring ("What neither an LED nor the shutter does"): the chi^2 drop when a
    gain per exposure time shared by the LEDs joins their trends and the shutter term, the jitter by
    moments on that full model; with the profile of the trends' residual over the exposure times (the
    LEDs' weighted mean per exposure time, relative gain, with standard errors from the diagonal of the
    gains' covariance) and its most significant step between adjacent exposure times as the effect
    (:func:`_largest_step`). None when the
    shared gains add no direction (one LED, or one exposure time)."""
    f = _CommonGainsFit(gs, covs, taus, inv_t, t_e, b)
    chi_full, N_full, _ = f.fit(0.0, True)
    r_full = int(np.linalg.matrix_rank(N_full, hermitian=True))
    s2 = 0.0
    if chi_full > f.n - r_full:
        # the jitter by moments on the fullest model
        s2 = _jitter_by_moments(lambda v: f.fit(v, True)[0], f.n - r_full, 40)
        chi_full = f.fit(s2, True)[0]
    chi_trends, N_trends, res = f.fit(s2, False)
    dof = r_full - int(np.linalg.matrix_rank(N_trends, hermitian=True))
    if dof < 1:
        return None
    stat = chi_trends - chi_full
    bound = float(chi2.isf(TAIL, dof))
    keys = f.keys
    num, den = np.zeros(keys.size), np.zeros(keys.size)
    for (r, v), te in zip(res, t_e):
        j = np.searchsorted(keys, te)
        np.add.at(num, j, r / v)
        np.add.at(den, j, 1.0 / v)
    prof = num / den
    prof_se = 1.0 / np.sqrt(den)
    return {"chi2": float(stat), "dof": int(dof), "bound": bound, "tail": TAIL, "significant": bool(stat > bound),
            "jitter": float(np.sqrt(s2)), "exposure_s": [float(x) for x in keys], "gain": [float(x) for x in prof],
            "gain_stderr": [float(x) for x in prof_se],
            "effect": _largest_step(prof, prof_se),
            "rule": "a gain per exposure time shared by the LEDs on top of their trends and the shutter term (GLS, "
                    "jitter by moments on that model, the rig's own drift as a random slope): chi^2 drop against "
                    "chi^2 with one degree per added direction at the 4-sigma tail"}


def drift_test(gsr: GainSeries | None, baseline: float | None = None) -> dict | None:
    """The drift test of the module docstring on a capture's frame gains (:func:`gain_series`): the
    LEDs' slopes in capture time, their Wald chi^2 against its bound, the jitter. ``baseline``: the
    RMS slope (1/min) a healthy rig's LEDs drift by (module docstring, "The rig's own drift"); None:
    the series' own (``baseline_per_min``: its capture's rig file's); 0: "no LED drifts at all". None
    without a series."""
    if gsr is None:
        return None
    b = gsr.baseline_per_min if baseline is None else float(baseline)
    se = np.sqrt(np.diag(gsr.cov))
    # Wald statistic of "no LED drifts more than the rig's own": the slopes share the shutter term, so their
    # covariance is used whole, and each LED's own drift adds b^2 to its slope's variance
    stat = float(gsr.slopes @ np.linalg.solve(gsr.cov + b ** 2 * np.eye(len(gsr.slopes)), gsr.slopes))
    bound = float(chi2.isf(TAIL, len(gsr.slopes)))
    return {"slope_per_min": {k: float(a) for k, a in zip(gsr.leds, gsr.slopes)},
            "stderr_per_min": {k: float(e) for k, e in zip(gsr.leds, se)},
            "jitter": gsr.jitter, "shutter_term_s": gsr.shutter_s, "shutter_term_stderr_s": gsr.shutter_se_s,
            "baseline_per_min": b,
            "chi2": stat, "dof": len(gsr.slopes), "bound": bound, "tail": TAIL,
            "passed": bool(stat > bound), "camera": gsr.camera,
            "rule": "per LED the frame gains' trend in capture time, beside a shutter term common to the LEDs (GLS, "
                    "rates profiled out, jitter by moments); Wald chi^2 of the slopes, each with the rig's own "
                    "drift (baseline_per_min RMS) added to its variance, against chi^2 with one degree per LED at "
                    "the 4-sigma tail"}


def camera_check(test: dict | None) -> dict | None:
    """The check of a frame-gain cause (LED drift, shutter error; :attr:`.catalogue.CauseResult.check`): the
    gains its test was taken on carry no structure common to the LEDs per exposure time beyond the trends
    and the shutter term (``test["camera"]``, :func:`camera_structure`); where they do, a camera effect
    outside the catalogue bends them and the cause is not named (module docstring). None without one."""
    cam = None if test is None else test.get("camera")
    if cam is None:
        return None
    return {"passed": not cam["significant"], "chi2": cam["chi2"], "dof": cam["dof"], "bound": cam["bound"],
            "tail": cam["tail"], "rule": "no gain common to the LEDs per exposure time beyond their trends and the "
                                         "shutter term (frame_gains.camera_structure) at the 4-sigma tail"}


def shutter_test(gsr: GainSeries | None) -> dict | None:
    """The shutter test (module docstring, "Shutter"): the shutter term of the frame gains' fit
    (:func:`gain_series`), beside every LED's trend, against its standard error - (delta / se)^2
    against chi^2 with one degree of freedom at the 4-sigma tail. None without a series."""
    if gsr is None:
        return None
    stat = (gsr.shutter_s / gsr.shutter_se_s) ** 2 if gsr.shutter_se_s > 0 else 0.0
    bound = float(chi2.isf(TAIL, 1))
    return {"delta_s": gsr.shutter_s, "stderr_s": gsr.shutter_se_s, "jitter": gsr.jitter, "chi2": float(stat),
            "dof": 1, "bound": bound, "tail": TAIL, "passed": bool(stat > bound), "camera": gsr.camera,
            "rule": "the frame gains' shutter term t_min / t_e shared by the LEDs, beside every LED's trend in "
                    "capture time (GLS, rates profiled out, jitter by moments); (delta / se)^2 against chi^2 with "
                    "one degree at the 4-sigma tail"}


def sensor_check(base: GainSeries | None, ext: GainSeries | None, k: int) -> dict | None:
    """The check of a sensor cause (module docstring, "Sensor causes and the jitter"): the drop of the
    gains model's chi^2 when the cause's terms are undone at its estimate - ``base``: :func:`gain_series`
    of the frames as they are, ``ext``: of the frames with the terms undone - over the misfit per degree
    of freedom left (when above 1), against chi^2 with ``k`` (the cause's parameters) degrees of freedom
    at :data:`CHECK_TAIL`. None without a series."""
    if base is None or ext is None or ext.dof <= 0:
        return None
    phi = max(1.0, ext.chi2 / ext.dof)
    stat = (base.chi2 - ext.chi2) / phi
    bound = float(chi2.isf(CHECK_TAIL, k))
    return {"chi2": float(stat), "dof": k, "bound": bound, "tail": CHECK_TAIL, "misfit_per_dof": float(phi),
            "passed": bool(stat > bound),
            "rule": "the cause's terms at its estimate undone, the frames refitted with a free gain per frame: the "
                    "drop of chi^2 (over the misfit per degree of freedom, when above 1) against chi^2 with one "
                    "degree per parameter at the 2-sigma tail"}


#: the causes tested on the frame gains, by name, each a function of :func:`gain_series`'s fit: the
#: conditional step (:mod:`.conditional`) takes the same test again on the fit with the selected causes undone
TESTS = {"led_drift": drift_test, "shutter_error": shutter_test}
#: the key of the frame structure (:func:`glossrig.core.diagnose.frames.frame_stage`) holding the camera
#: structure (:func:`camera_structure`), binned by log10 exposure time like the other frame variables
CAMERA_KEY = "gain common to the LEDs (relative), by exposure_s (log10)"
#: sensor causes whose terms bend the gains themselves: where one is named the camera structure is not judged
BENDS_GAINS = ("black_level_offset", "sensor_nonlinearity", "channel_response")


def camera_entry(causes) -> dict | None:
    """The camera structure of the frames as they are (:func:`camera_structure`, as the drift cause's test
    among ``causes`` reports it) as a frame structure entry: its profile over log10 exposure time (``x``,
    ``mean``) and its test; not significant (``judged`` False) where a sensor cause that bends the gains
    itself (BENDS_GAINS) is named - its terms, not a camera effect, then make it. None without one."""
    drift = next((r for r in causes if r.name == "led_drift"), None)
    c = drift.test.get("camera") if drift is not None and drift.test is not None else None
    if c is None:
        return None
    named = [r.name for r in causes if r.name in BENDS_GAINS and r.eligible]
    return {"x": [float(np.log10(t)) for t in c["exposure_s"]], "mean": c["gain"], "n": [1] * len(c["gain"]),
            "chi2": c["chi2"], "dof": c["dof"], "bound": c["bound"], "effect": c["effect"],
            "significant": bool(c["significant"] and not named), "judged": not named,
            "note": (f"not judged: {', '.join(named)} is named, whose terms bend the gains" if named else c["rule"])}
